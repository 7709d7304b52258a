"""`photopft bench tidal`: the population's quiet breathing read as optical maps with noise."""

from __future__ import annotations

import numpy as np

from benchmarks.tidal import readings
from app.cli import main


def test_the_rate_read_between_mid_inspirations_keeps_the_noise_free_curves():
    """Six of the population's subjects, 20 mL of noise a map: the rate as read now stays within
    0.5/min of the noise-free curve's where the rate read between end-expiratory minima (as it was)
    reads it faster on average."""
    rows = readings(6, 1, [0.020], draws=3)
    assert len(rows) == 18
    now = np.array([r.optical[1] - r.truth[1] for r in rows])
    before = np.array([r.between_minima[1] - r.between_minima[0] for r in rows])
    assert np.all(np.abs(now) <= 0.5) and abs(np.mean(now)) < 0.1
    assert np.mean(before) > 0.1


def test_the_bench_prints_its_table_and_refuses_bad_arguments_in_one_line(capsys):
    assert main(["bench", "tidal", "--subjects", "2", "--draws", "1", "--noise-ml", "0,10", "--no-write"]) == 0
    out = capsys.readouterr().out
    assert "| 10 mL | 2 |" in out and "RR between minima (before)" in out
    for bad in (["--noise-ml", "abc"], ["--noise-ml", "-5"], ["--subjects", "0"]):
        assert main(["bench", "tidal", *bad, "--no-write"]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--" in err[0]
