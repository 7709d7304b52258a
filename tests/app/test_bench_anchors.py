"""photopft bench anchors: each reference of a map's displacement read on whole processed sessions."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.anchors import BOTH, HEADS, SIGNALS, anchors_table, fit_to_truth, read_anchors

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")


def test_a_read_s_slope_residual_and_map_to_map_part():
    t = np.arange(400) / 20.0
    truth = 0.5 * np.sin(2 * np.pi * t / 4.0)
    sway = 0.1 * np.sin(2 * np.pi * t / 23.0)  # slow: it stays in the residual, not in the map-to-map part
    noise = np.random.default_rng(1).normal(0.0, 0.02, t.size)
    slope, residual, map_to_map = fit_to_truth(truth, 0.8 * truth + 0.3 + sway + noise)
    assert slope == pytest.approx(0.8, abs=0.01)
    assert residual == pytest.approx(np.sqrt(np.mean((sway - sway.mean() + noise) ** 2)), rel=0.05)
    assert map_to_map == pytest.approx(0.02, rel=0.1)
    assert np.isnan(fit_to_truth(truth[:9], truth[:9])[0])  # too few maps


def _sums(t_ns: np.ndarray, visible_l: np.ndarray, shift_mm: np.ndarray, level_error_mm: np.ndarray,
          neck_mm: np.ndarray) -> dict:
    """Stored sums of a head whose trunk (area 0.25 m2) gains visible_l while the whole map shifts by shift_mm
    (towards the head: negative); its level misses the shift by level_error_mm."""
    area = 250000.0
    displaced = -visible_l * 1e6 + shift_mm * area
    reference = np.full(len(t_ns), 5e7)
    current = reference + displaced - (shift_mm + level_error_mm) * area
    columns = lambda x: np.column_stack([x] * 5)  # four quadrants and "all" alike: only "all" is read
    return {"parts": ["upper left", "upper right", "lower left", "lower right", "all"], "timestamp_ns": t_ns,
            "reference": columns(reference), "current": columns(current), "areas": columns(np.full(len(t_ns), area)),
            "displaced": columns(displaced), "neck_mm": neck_mm}


def test_the_three_reads_of_stored_sums_and_the_maps_without_a_neck():
    t = np.arange(400) / 20.0  # whole periods of each, so that none takes a share of another
    t_ns = (t * 1e9).astype(np.int64)
    truth = 0.4 * np.sin(2 * np.pi * t / 4.0)
    sway_mm = 3.0 * np.sin(2 * np.pi * t / 10.0)
    level_error = 0.1 * np.sin(2 * np.pi * t / 0.5)  # the level's own noise
    neck = sway_mm.copy()
    neck[[3, 4]] = np.nan
    stored = {"front": _sums(t_ns, 0.6 * truth, sway_mm, level_error, neck),
              "back": _sums(t_ns + 10_000_000, 0.2 * truth, -sway_mm, level_error, -sway_mm)}
    slope, residual, map_to_map, no_neck, maps = read_anchors(stored, t_ns, truth)
    assert maps == 400 and no_neck == {"front": 2, "back": 0}
    assert slope["less the neck"]["front"] == pytest.approx(0.6, abs=1e-3) and residual["less the neck"]["front"] < 1e-3
    assert residual["levelled"]["front"] == pytest.approx(0.025 * np.sqrt(0.5), rel=0.05)  # 0.1 mm over 0.25 m2
    assert residual["plain"]["front"] == pytest.approx(0.75 * np.sqrt(0.5), rel=0.1)  # the sway, 3 mm over 0.25 m2
    # summed, the sway along the axis cancels between the heads, and the back's maps come on the front's times
    assert slope["plain"][BOTH] == pytest.approx(0.8, abs=0.02) and residual["plain"][BOTH] < 0.02
    text = anchors_table([_row(slope, residual, map_to_map, no_neck, maps)])
    assert "| parametric | random-1000 | less the neck | 0.60, 0.20, 0.80 |" in text
    assert "| 2, 0 (400) |" in text and text.splitlines()[-1].startswith("- parametric (1 subjects): levelled:")


def _row(slope, residual, map_to_map, no_neck, maps):
    from benchmarks.anchors import AnchorRow

    return AnchorRow("parametric", "random-1000", slope, residual, map_to_map, no_neck, maps, 1.0)


def test_both_populations_end_to_end(capsys):
    from app.cli import main

    assert main(["bench", "anchors", "--subjects", "1", "--scale", "0.1", "--seconds", "6", "--no-write"]) == 0
    rows = [line.strip("| ").split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith(("| parametric", "| mesh"))]
    assert [(r[0], r[2]) for r in rows] == [(p, s) for p in ("parametric", "mesh") for s in SIGNALS]
    for population in ("parametric", "mesh"):
        read = {r[2]: [float(x) for x in r[4].split(", ")] for r in rows if r[0] == population}
        # unreferred, each head's map is where the two heads' widths put it: its sway and their error, millimetres
        # over a trunk, where the neck or the level take most of them out
        for k in range(len(HEADS)):
            assert read["plain"][k] > 2 * max(read["less the neck"][k], read["levelled"][k]), (population, read)
