"""Volume building blocks: the cap above the silhouette plane, and distances from two silhouettes."""

from __future__ import annotations

import numpy as np
import pytest

from core.rig import thesis_head
from core.volume import cap_measure, gradient_volume_correlations, rescaled_cap, two_head_distances


def _dome(head, distance_mm: float, height_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Depth of a paraboloid cap of `height_mm` over a 400 x 300 mm ellipse whose rim lies at distance_mm."""
    u = (np.arange(head.width) - head.cx) / head.fx
    v = (np.arange(head.height) - head.cy) / head.fy
    x, y = u[None, :] * distance_mm, v[:, None] * distance_mm
    r2 = (x / 200.0) ** 2 + (y / 150.0) ** 2
    mask = r2 < 1.0
    return np.where(mask, distance_mm - height_mm * (1 - r2), np.nan), mask


def test_cap_volume_against_an_independent_sum_and_a_rigid_shift():
    head = thesis_head("front", scale=0.5)
    depth, mask = _dome(head, 2000.0, 80.0)
    cap = cap_measure(depth, mask, head)
    # computed here independently: the rim plane is at 2000 mm; trunk rows are >= 60 % of the widest
    widths = mask.sum(axis=1)
    rows = widths >= 0.6 * widths.max()
    region = mask & rows[:, None]
    z = depth[region]
    expected_l = float(np.sum((2000.0 - z) * (z / head.fx) * (z / head.fy))) * 1e-6
    assert cap.volume_l == pytest.approx(expected_l, rel=0.02)
    assert cap.side_depth_mm == pytest.approx(2000.0, abs=2.0)
    shifted = cap_measure(depth + 40.0, mask, head)  # the same body 40 mm further away, same pixels
    assert shifted.side_depth_mm == pytest.approx(cap.side_depth_mm + 40.0, abs=0.5)
    assert shifted.volume_l == pytest.approx(cap.volume_l * (2040.0 / 2000.0) ** 2, rel=0.01)
    flat = cap_measure(np.where(mask, 1950.0, np.nan), mask, head)
    assert abs(flat.volume_l) < 1e-6 and flat.side_depth_mm == pytest.approx(1950.0)


def test_two_silhouettes_and_a_baseline_give_both_distances():
    baseline, d_front = 4230.0, 1990.0
    width_mm = 600.0
    f = 845.0
    w_front, w_back = width_mm * f / d_front, width_mm * f / (baseline - d_front)
    front, back = two_head_distances(np.array([w_front]), np.array([w_back]), baseline)
    assert front[0] == pytest.approx(d_front, abs=1e-6) and back[0] == pytest.approx(baseline - d_front, abs=1e-6)


def test_rescaling_a_cap_follows_the_cube_of_the_scale():
    assert rescaled_cap(np.array([2.0]), np.array([2000.0]), np.array([2100.0]))[0] == pytest.approx(2.0 * 1.05**3)


def test_gradient_volume_correlations_per_head_and_combined():
    t_ref = np.linspace(0.0, 20.0, 2001)
    volume = np.sin(2 * np.pi * t_ref / 4.0)
    t_front, t_back = np.linspace(0.5, 19.5, 191), np.linspace(0.55, 19.55, 191)
    r = gradient_volume_correlations({"front": (t_front, 3.0 + 2.0 * np.sin(2 * np.pi * t_front / 4.0)),
                                      "back": (t_back, -np.sin(2 * np.pi * t_back / 4.0))}, t_ref, volume)
    assert r["front"] == pytest.approx(1.0, abs=1e-6) and r["back"] == pytest.approx(-1.0, abs=1e-3)
    same = gradient_volume_correlations({"front": (t_front, np.sin(2 * np.pi * t_front / 4.0)),
                                         "back": (t_back, np.sin(2 * np.pi * t_back / 4.0))}, t_ref, volume)
    assert same["combined"] == pytest.approx(1.0, abs=1e-3)
