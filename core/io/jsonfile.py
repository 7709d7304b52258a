"""Reading the project's JSON files (calibration profiles) with errors that name the file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable, TypeVar

T = TypeVar("T")


def read_json_object(path: Path, error: type[Exception], what: str = "file") -> dict[str, Any]:
    """The JSON object in `path`; `error` with a message naming the file when it is missing or not an object."""
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise error(f"cannot read {what} {path}: {exc}") from exc
    except json.JSONDecodeError as exc:
        raise error(f"{path} is not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise error(f"{path}: expected a JSON object, found {type(data).__name__}")
    return data


def load_checked(path: Path, load: Callable[[Path], T], error: type[Exception]) -> T:
    """`load(path)`, with a field of the wrong type or shape (a traceback in the loader) turned into
    `error` naming the file."""
    try:
        return load(path)
    except error:
        raise
    except (TypeError, ValueError, IndexError, AttributeError, KeyError) as exc:
        raise error(f"{path}: a field has the wrong type or shape ({exc})") from exc
