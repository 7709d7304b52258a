"""What every bench shares: where the checkout, its docs and the reference data are, and how a table
is printed and written into its section of docs/benchmarks.md."""

from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

from app.args import finite


# The benches write their tables into the repository's docs/benchmarks.md: only from a source
# checkout (an installed or bundled application has no docs/ to write to, and reads nothing there)
CHECKOUT = Path(__file__).resolve().parents[1]
DOCS = CHECKOUT / "docs" / "benchmarks.md"
# The project's reference data, beside the checkout (never shipped with the application).
# ../shared beside the checkout, or where PHOTOPFT_SHARED says (as the tests read it)
SHARED = Path(os.environ.get("PHOTOPFT_SHARED", CHECKOUT.parent / "shared"))
DILIGENT_BEAR = SHARED / "data" / "diligent-integration" / "bear"


def in_checkout() -> bool:
    return (CHECKOUT / "pyproject.toml").is_file() and DOCS.parent.is_dir()


def write_section(name: str, text: str, path: Path = DOCS) -> None:
    """Replace (or add) the section between <!-- name --> markers in docs/benchmarks.md."""
    begin, end = f"<!-- {name} begin -->", f"<!-- {name} end -->"
    block = f"{begin}\n{text.rstrip()}\n{end}"
    current = path.read_text() if path.exists() else "# Benchmarks\n\nFigures measured by `photopft bench`.\n"
    if begin in current:
        current = re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: block, current, flags=re.S)
    else:
        current = current.rstrip() + "\n\n" + block + "\n"
    path.write_text(current)


def world_words(world: str) -> str:
    """What a named world of the simulator holds, for a bench's table."""
    from core.sim.simulate import WORLDS
    from core.sim.simulate import world_words as settings_words

    settings = WORLDS[world]
    if not settings:
        return "the rig as drawn: isotropic point LEDs, matte surfaces, a pinhole camera"
    return settings_words(settings)


def noises_ml(text: str) -> list[float]:
    """--noise-ml: comma-separated noises of a map, 0 mL or more."""
    from app.errors import UserError

    try:
        noise = [finite(n) for n in text.split(",")]
    except argparse.ArgumentTypeError as exc:
        raise UserError(f"--noise-ml: {exc}") from exc
    if any(n < 0 for n in noise):
        raise UserError(f"--noise-ml takes noises of 0 mL or more, not {text}")
    return noise


def publish(args: argparse.Namespace, section: str, heading: str, text: str) -> int:
    """Print a bench's table and, unless --no-write, put it in its section of docs/benchmarks.md."""
    print(text)
    if args.no_write:
        return 0
    if not in_checkout():
        print(f"not written: docs/benchmarks.md is written from a source checkout of photopft, and {CHECKOUT} "
              "is not one", file=sys.stderr)
        return 0
    write_section(section, f"## {heading}\n\n{text}\n")
    return 0
