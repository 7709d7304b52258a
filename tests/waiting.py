"""Waiting in tests: on a condition, never for a set time (a busy machine stretches every set time)."""

from __future__ import annotations

import time
from typing import Callable

POLL_S = 0.02


def wait_until(condition: Callable[[], object], timeout_s: float, what: str = "the condition") -> None:
    """Return as soon as `condition()` is true; fail naming `what` if it is not within `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
        time.sleep(POLL_S)
