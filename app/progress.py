"""A long command's progress on standard error: on a terminal, a bar with the share done and the
time left, redrawn at most REDRAW_S apart; elsewhere (a log file, CI, a pipe), a plain line every
LINE_EVERY_S seconds, so a script's log shows the command is alive without filling up (and a
command shorter than that writes nothing)."""

from __future__ import annotations

import sys
import time
from typing import TextIO

BAR_WIDTH = 30
REDRAW_S = 0.1
LINE_EVERY_S = 5.0


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}" if seconds >= 3600 \
        else f"{seconds // 60}:{seconds % 60:02d}"


class Progress:
    """`progress(fraction, detail)` from the work; `close()` (or the with block's end) when done."""

    def __init__(self, label: str, stream: TextIO | None = None, terminal: bool | None = None) -> None:
        self.label = label
        self.stream = stream or sys.stderr
        self.terminal = self.stream.isatty() if terminal is None else terminal
        self.started = time.monotonic()
        # a terminal shows the bar at once; a log's first line comes after LINE_EVERY_S (a short
        # command writes nothing there)
        self._shown = -float("inf") if self.terminal else self.started
        self._drawn = False

    def text(self, fraction: float, detail: str = "", now: float | None = None) -> str:
        fraction = min(max(fraction, 0.0), 1.0)
        elapsed = (time.monotonic() if now is None else now) - self.started
        left = f"{_clock(elapsed * (1 - fraction) / fraction)} left" if fraction > 0.005 else "time left unknown"
        extra = f", {detail}" if detail else ""
        if self.terminal:
            filled = int(round(BAR_WIDTH * fraction))
            return f"{self.label} [{'#' * filled}{'.' * (BAR_WIDTH - filled)}] {100 * fraction:5.1f} % {left}{extra}"
        return f"{self.label}: {100 * fraction:.1f} % after {_clock(elapsed)}, {left}{extra}"

    def __call__(self, fraction: float, detail: str = "") -> None:
        now = time.monotonic()
        if now - self._shown < (REDRAW_S if self.terminal else LINE_EVERY_S):
            return
        self._shown = now
        if self.terminal:
            self.stream.write("\r\033[K" + self.text(fraction, detail, now))
            self._drawn = True
        else:
            self.stream.write(self.text(fraction, detail, now) + "\n")
        self.stream.flush()

    def close(self) -> None:
        if self._drawn:
            self.stream.write("\n")
            self.stream.flush()
            self._drawn = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
