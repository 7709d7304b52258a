"""photopft bench sides: the two heads' distance from their trunk widths through a forced blow."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.sides import READS, BlowSides, sides_table

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


def _blow(body: str, blow: str, front_l: float, back_l: float, moved_mm: float) -> BlowSides:
    true = {"front": 1.0, "back": 0.5}
    at_true = {"front": front_l, "back": back_l}
    at_widths = {"front": front_l * 1.1, "back": back_l}
    return BlowSides("parametric", body, blow, 2.0, true,
                     {"true": (2000.0, 2001.0), "reconstructed": (2000.0, 2000.0 + moved_mm)},
                     {READS[0]: true, READS[1]: at_true, READS[2]: at_widths})


def test_each_blow_s_error_and_the_scatter_a_calibration_on_the_subject_cannot_take_out():
    rows = [_blow("random-1000", "blow 1", 1.0, 0.5, 4.0), _blow("random-1000", "blow 2", 0.85, 0.5, 8.0),
            _blow("random-1001", "blow 1", 1.3, 0.5, -2.0), _blow("random-1001", "blow 2", 1.15, 0.5, -6.0)]
    # over the blow's true volume change (2 L), not the heads' levelled change: a head may see little of it
    assert rows[1].error(READS[0]) == 0.0 and rows[1].error(READS[1]) == pytest.approx(-0.075)
    assert rows[1].error(READS[2]) == pytest.approx((0.935 + 0.5 - 1.5) / 2.0)
    assert rows[0].moved_mm("true") == pytest.approx(1.0) and rows[3].moved_mm("reconstructed") == pytest.approx(-6.0)
    text = sides_table(rows)
    assert "| parametric | random-1000 | blow 2 | 2.00 | 1.000, 0.500 | +1.0 | +8.0 | +0.0 % | -7.5 % | -3.2 % |" in text
    summary = next(line for line in text.splitlines() if line.startswith("- parametric"))
    # each body's two blows lie 3.75 % either side of its own mean: 7.5 % apart, both bodies alike
    errors = 100 * np.array([0.0, -0.075, 0.15, 0.075])
    assert f"true distance: {errors.mean():+.1f} % (sd {errors.std():.1f}), about each body's mean sd 3.8 %" \
        in summary
    assert "moved +1.0 mm (sd 0.0) on true maps, +1.0 mm (sd 5.4) on reconstructed ones" in summary


def test_the_bench_reads_both_populations_blows_end_to_end(capsys):
    from app.cli import main

    assert main(["bench", "sides", "--subjects", "1", "--scale", "0.1", "--no-write"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith(("| parametric", "| mesh"))]
    assert len(rows) >= 4 and {r.split(" | ")[0] for r in rows} == {"| parametric", "| mesh"}
    for row in rows:
        cells = row.strip("| ").split(" | ")
        moved = [float(c) for c in cells[5:7]]
        assert all(np.isfinite(moved)) and all(abs(m) < 100 for m in moved), row  # mm at 2 m: never a metre off
    parametric = next(line for line in out.splitlines() if line.startswith("- parametric"))
    at_true = float(parametric.split("; true distance: ")[1].split(" %")[0])
    assert -30 < at_true < 10, parametric  # the reconstruction keeps most of the levelled change at the true distance
