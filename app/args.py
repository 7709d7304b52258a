"""Command-line argument types shared by every verb: numbers are finite, outputs may be forced."""

from __future__ import annotations

import argparse
import math


def finite(text: str) -> float:
    """A command-line number: nan and inf are refused."""
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from exc
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _positive(kind):
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from exc
        if not math.isfinite(value) or value <= 0:
            raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text}")
        return value

    return parse


positive = _positive(float)
positive_count = _positive(int)


def add_force(p: argparse.ArgumentParser) -> None:
    p.add_argument("--force", action="store_true",
                   help="replace an existing output (never an input or a recorded session)")


# The simulator's worlds by name (core/sim/simulate.py, WORLDS; a test keeps the two the same), here
# so that building the parser does not import the simulator
WORLD_NAMES = ("ideal", "clinic", "clinic-polarised", "clinic-widening")
