"""Progress of long commands: a bar with the time left on a terminal, a line every few seconds elsewhere."""

from __future__ import annotations

import io

from app import progress as progress_module
from app.progress import Progress


def test_a_terminal_gets_a_bar_with_the_time_left():
    out = io.StringIO()
    bar = Progress("processing s.h5", out, terminal=True)
    bar.started -= 30.0  # 30 s in, a quarter done: 1:30 left
    bar(0.25, "front 10")
    bar.close()
    text = out.getvalue()
    assert text.startswith("\r\033[K") and text.endswith("\n")
    assert "processing s.h5 [########......................]  25.0 % 1:30 left, front 10" in text


def test_a_log_gets_a_line_every_few_seconds(monkeypatch):
    now = [1000.0]
    monkeypatch.setattr(progress_module.time, "monotonic", lambda: now[0])
    out = io.StringIO()
    bar = Progress("simulating s.h5", out, terminal=False)
    for step in range(1, 101):  # 100 updates over 20 s
        now[0] += 0.2
        bar(step / 100)
    bar.close()
    lines = out.getvalue().splitlines()
    assert 3 <= len(lines) <= 4 and "\r" not in out.getvalue()
    assert lines[0] == "simulating s.h5: 25.0 % after 0:05, 0:15 left"
