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


def test_the_side_of_a_round_trunk_lies_beyond_its_silhouette_where_the_surface_turns_parallel():
    """A circular cross-section 150 mm in radius at 2000 mm: the camera sees it up to the tangent
    ray; the circle through the outermost pixels puts the side (X = 150 mm) within 0.05 mm."""
    from core.volume import rim_side_mm

    radius, centre, fx = 150.0, 2000.0, 844.6
    for offset_px in (0.0, 0.3, 0.6, 0.9):
        u = (np.arange(40) - offset_px)[::-1] / fx + 0.05  # outermost ray first
        # nearest meeting of the ray (u Z, Z) with the circle X^2 + (Z - centre)^2 = radius^2
        a, b, c = u * u + 1.0, -2.0 * centre, centre**2 - radius**2
        disc = b * b - 4 * a * c
        hit = disc >= 0
        z = (-b - np.sqrt(disc[hit])) / (2 * a[hit])
        lateral, ray = u[hit] * z, u[hit]
        gap, _ = rim_side_mm(lateral, z, ray)
        assert gap == pytest.approx(radius - lateral[0], abs=0.05)


def test_the_rim_level_of_a_breathing_band_is_its_common_intercept():
    """Depths that move, edge by edge, in proportion to the regressor plus one common shift: the
    level of the moved map less the level of the first is the shift."""
    from core.rig import thesis_head
    from core.volume import rim_model

    head = thesis_head("front", scale=0.25)
    rows, cols = np.mgrid[0:head.height, 0:head.width]
    r2 = ((cols - head.cx) / 120.0) ** 2 + ((rows - head.cy) / 100.0) ** 2
    mask = r2 < 1.0
    depth = np.where(mask, 2000.0 - 100.0 * np.sqrt(np.clip(1.0 - r2, 0, None)), np.nan)
    model = rim_model(depth, mask, head, band_px=12)
    assert len(model.rows) > 100
    rng = np.random.default_rng(2)
    moved = depth.copy()
    for e, row in enumerate(model.rows):
        used = model.cols[e] >= 0
        moved[row, model.cols[e][used]] += -rng.uniform(0.02, 0.08) * model.regressor[e][used]
    moved += 1.7
    assert model.level(moved, mask) - model.level(depth, mask) == pytest.approx(1.7, abs=1e-9)


def test_the_trunk_width_stays_when_the_flanks_lose_their_outermost_pixels():
    """A trunk of circular cross-section (150 mm radius, axis vertical at 2000 mm, centred on the
    view): the circle through each row's outermost pixels places its sides, so losing one or two
    of them (a flank steepening past the integrator's grazing limit as the chest fills) leaves its
    width; the silhouette's own width drops by the pixels lost."""
    from core.rig import thesis_head
    from core.volume import trunk_width_px

    head = thesis_head("front", scale=0.25)
    radius, centre = 150.0, 2000.0
    u = (np.arange(head.width) - head.cx) / head.fx
    a, b, c = u * u + 1.0, -2.0 * centre, centre**2 - radius**2
    disc = b * b - 4 * a * c
    row_depth = np.where(disc >= 0, (-b - np.sqrt(np.clip(disc, 0, None))) / (2 * a), np.nan)
    depth = np.tile(row_depth, (head.height, 1))
    full = np.isfinite(depth)
    sides_px = 2 * head.fx * radius / centre  # the widest points, X = +-radius at Z = centre

    def without_outermost(mask, n):
        out = mask.copy()
        for r in range(mask.shape[0]):
            cols = np.nonzero(mask[r])[0]
            out[r, cols[:n]] = out[r, cols[len(cols) - n:]] = False
        return out

    widths = [trunk_width_px(depth, without_outermost(full, n), head) for n in (0, 1, 2)]
    assert widths == pytest.approx([sides_px] * 3, abs=0.1)
    silhouettes = [without_outermost(full, n)[0].sum() for n in (0, 1, 2)]
    assert silhouettes[0] - silhouettes[2] == 4
