"""The log file in the user's state folder: full detail of what went wrong, for support."""

from __future__ import annotations

import logging
from logging.handlers import RotatingFileHandler
from pathlib import Path

from app.paths import state_dir


def log_file(name: str = "photopft.log") -> Path:
    return state_dir() / name


def log_to_file(path: Path) -> Path:
    """Send this process's log records (INFO and up) to `path`, rotated at 5 MB, three kept."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = RotatingFileHandler(path, maxBytes=5_000_000, backupCount=3, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(threadName)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    return path
