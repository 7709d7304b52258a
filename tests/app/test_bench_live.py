"""`photopft bench live`: the live view's metric volume against the simulated subject's truth, as the
window runs it (a short run at a small scale; the figures in docs/benchmarks.md come from 60 s)."""

from __future__ import annotations

import pytest

from benchmarks.live import run_live_bench
from core.analysis.optical_litres import POPULATION_GAIN


@pytest.mark.slow
def test_the_live_volume_follows_the_true_volume():
    text, figures = run_live_bench(14.0, 0.1)
    # measured at 14 s, scale 0.1: r 0.93, slope 1.05
    # the live curve is the optical estimate, the plain volume times the population's gain
    assert figures["samples"] >= 20 and figures["r"] > 0.75 and 0.75 < figures["slope"] / POPULATION_GAIN < 1.3
    assert "| samples | per second | r | slope |" in text
