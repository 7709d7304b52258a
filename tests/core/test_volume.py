"""Volume building blocks: distances from two silhouettes, gradient-volume correlations."""

from __future__ import annotations

import numpy as np
import pytest

from core.volume import gradient_volume_correlations, two_head_distances


def test_two_silhouettes_and_a_baseline_give_both_distances():
    baseline, d_front = 4230.0, 1990.0
    width_mm = 600.0
    f = 845.0
    w_front, w_back = width_mm * f / d_front, width_mm * f / (baseline - d_front)
    front, back = two_head_distances(np.array([w_front]), np.array([w_back]), baseline)
    assert front[0] == pytest.approx(d_front, abs=1e-6) and back[0] == pytest.approx(baseline - d_front, abs=1e-6)


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


def test_the_rim_is_extrapolated_past_the_noisy_outermost_pixels():
    """Depth falling linearly towards the silhouette, the two outermost pixels of every row thrown
    off (dim, grazing light): the rim is where the line through the rest meets the edge."""
    from core.volume import rim_depths

    rng = np.random.default_rng(5)
    mask = np.zeros((40, 60), bool)
    mask[5:35, 10:50] = True
    cols = np.arange(60)
    from_edge = np.minimum(cols - 10, 49 - cols).astype(float)
    depth = np.tile(2000.0 - 3.0 * from_edge, (40, 1))
    noisy = depth.copy()
    noisy[:, [10, 11, 48, 49]] += rng.normal(0, 20.0, (40, 4))
    rim, _ = rim_depths(noisy, noisy, mask, band_px=12)
    assert abs(rim - 2001.5) < 0.01  # 3 mm per pixel, half a pixel outside the edge
    with_them, _ = rim_depths(noisy, noisy, mask, band_px=12, skip_px=0)
    assert abs(with_them - 2001.5) > 0.1
