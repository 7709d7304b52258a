"""`photopft bench process`: the command a user runs, timed end to end, as a ratio to real time."""

from __future__ import annotations

import re

from app.cli import main


def test_process_bench_times_the_whole_command_per_worker_count(capsys):
    assert main(["bench", "process", "--seconds", "0.3", "--scale", "0.05", "--workers", "1,2", "--no-write"]) == 0
    out = capsys.readouterr().out
    rows = re.findall(r"^\| (\d) \| (binned|every pixel) \| ([\d.]+) s \| (\d+) \| ([\d.]+) \| ([\d.]+) \|$", out,
                      flags=re.M)
    assert [(r[0], r[1]) for r in rows] == [("1", "binned"), ("2", "binned"), ("2", "every pixel")]
    assert all(int(r[3]) > 0 and float(r[5]) > 0 for r in rows)
    assert rows[0][3] == rows[1][3] == rows[2][3]  # the same maps, whatever the workers and the binning
