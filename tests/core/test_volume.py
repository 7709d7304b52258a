"""Volume building blocks: distances from two silhouettes, gradient-volume correlations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from core.volume.maps import gradient_volume_correlations, two_head_distances


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
    from core.volume.maps import rim_depths

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
    from core.volume.maps import rim_side_mm

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
    from core.volume.maps import rim_model

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


def _hemi_ellipsoid(head, semi_axes_px=(120.0, 100.0), depth_mm=100.0):
    """A trunk-like relief with flanks that turn to grazing at its silhouette: Z = 2000 - d sqrt(1 - r^2)."""
    rows, cols = np.mgrid[0:head.height, 0:head.width]
    r2 = ((cols - head.cx) / semi_axes_px[0]) ** 2 + ((rows - head.cy) / semi_axes_px[1]) ** 2
    mask = r2 < 1.0
    return np.where(mask, 2000.0 - depth_mm * np.sqrt(np.clip(1.0 - r2, 0, None)), np.nan), mask


def test_the_rim_level_sees_through_the_ribs_widening_on_steep_flanks():
    """Depths that move, edge by edge, as the hinge and the sideways stretch have them, plus one common
    shift: the level follows the shift alone. The hinge alone takes the flanks' widening for a shift."""
    from dataclasses import replace
    from core.rig import thesis_head
    from core.volume.maps import rim_model

    head = thesis_head("front", scale=0.25)
    depth, mask = _hemi_ellipsoid(head)
    model = rim_model(depth, mask, head, band_px=12)
    assert model.sideways
    rng = np.random.default_rng(3)
    moved = depth.copy()
    for e, row in enumerate(model.rows):
        used = model.cols[e] >= 0
        moved[row, model.cols[e][used]] += (-rng.uniform(0.02, 0.08) * model.regressor[e][used]
                                            - rng.uniform(0.005, 0.02) * model.lateral[e][used])
    moved += 1.7
    assert model.level(moved, mask) - model.level(depth, mask) == pytest.approx(1.7, abs=1e-6)
    hinge_only = replace(model, sideways=False)
    assert abs(hinge_only.level(moved, mask) - hinge_only.level(depth, mask) - 1.7) > 0.5


def test_a_parabolic_relief_cannot_tell_widening_from_a_shift():
    """On a paraboloid the hinge's profile, the stretch's and a constant are one and the same across
    each row: the stretch is left out of the level rather than leave it undetermined."""
    from core.rig import thesis_head
    from core.volume.maps import rim_model

    head = thesis_head("front", scale=0.25)
    rows, cols = np.mgrid[0:head.height, 0:head.width]
    r2 = ((cols - head.cx) / 120.0) ** 2 + ((rows - head.cy) / 100.0) ** 2
    mask = r2 < 1.0
    depth = np.where(mask, 2000.0 - 80.0 * (1.0 - r2), np.nan)
    assert not rim_model(depth, mask, head, band_px=12).sideways
    assert rim_model(*_hemi_ellipsoid(head), head, band_px=12).sideways


def test_the_trunk_width_stays_when_the_flanks_lose_their_outermost_pixels():
    """A trunk of circular cross-section (150 mm radius, axis vertical at 2000 mm, centred on the
    view): the circle through each row's outermost pixels places its sides, so losing one or two
    of them (a flank steepening past the integrator's grazing limit as the chest fills) leaves its
    width; the silhouette's own width drops by the pixels lost."""
    from core.rig import thesis_head
    from core.volume.maps import trunk_width_px

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


def _rendered_trunk(head, shift_mm=(0.0, 0.0, 0.0), radius=250.0, distance=2000.0):
    """Depth and mask of a trunk seen by `head`: a vertical cylinder of circular cross-section below
    rounded shoulders (Y = -200 + X^2 / 500 mm) with a neck of 60 mm radius above them, cut off by
    the image's bottom edge, moved by shift_mm (X, Y, Z)."""
    dx, dy, dz = shift_mm
    v, u = np.mgrid[0:head.height, 0:head.width].astype(float)
    x, y = (u - head.cx) / head.fx, (v - head.cy) / head.fy
    depth = np.full(u.shape, np.nan)
    for r, part in ((radius, "trunk"), (60.0, "neck")):
        # nearest meeting of the ray (x Z, y Z, Z) with the cylinder (X - dx)^2 + (Z - centre)^2 = r^2
        centre = distance + dz
        a, b, c = x * x + 1.0, -2.0 * (x * dx + centre), dx * dx + centre * centre - r * r
        disc = b * b - 4 * a * c
        z = np.where(disc >= 0, (-b - np.sqrt(np.clip(disc, 0, None))) / (2 * a), np.nan)
        shoulder = -200.0 + (x * z - dx) ** 2 / 500.0 + dy
        below = y * z >= shoulder
        depth = np.where(np.isnan(depth) & np.isfinite(z) & (below if part == "trunk" else ~below), z, depth)
    return depth, np.isfinite(depth)


def test_the_body_frame_follows_a_trunk_moving_by_fractions_of_a_pixel():
    """The rendered trunk moved up and down by 0.2 mm steps (1/12 px at 2000 mm): the body frame's
    vertical shift follows the move in proportion, on a straight line within 0.08 px, with a slope
    fy / Z for a Z between the outline's depths (the shoulders' top on the front of the trunk at
    1750 mm, the sides at 2000 mm), where the middle of the first and last trunk rows, a whole-pixel
    feature, moves by half-pixel steps. Moved along the axis, the frame's scale is the distance's
    ratio and its sideways shift the sideways move's."""
    from core.rig import thesis_head
    from core.volume.maps import BodySilhouette, row_widths_px, trunk_width_px

    head = thesis_head("front", scale=0.25)
    depth, valid = _rendered_trunk(head)
    widths = row_widths_px(depth, valid, head)
    silhouette = BodySilhouette(valid, widths, head)
    reference_width = trunk_width_px(depth, valid, head, widths)
    moves_mm = np.arange(-3.0, 3.01, 0.2)
    shifts_px = []
    for dy in moves_mm:
        moved, moved_valid = _rendered_trunk(head, (0.0, dy, 0.0))
        moved_widths = row_widths_px(moved, moved_valid, head)
        frame = silhouette.frame(moved_valid, moved_widths, trunk_width_px(moved, moved_valid, head, moved_widths)
                                 / reference_width)
        shifts_px.append(frame.shift_v_px)
        assert frame.shift_u_px == pytest.approx(0.0, abs=0.05) and frame.scale == pytest.approx(1.0, abs=3e-4)
    slope, intercept = np.polyfit(moves_mm, shifts_px, 1)
    assert head.fy / 2000.0 < slope < head.fy / 1750.0
    assert np.max(np.abs(np.array(shifts_px) - (slope * moves_mm + intercept))) < 0.08
    for dz in (-40.0, 40.0):
        moved, moved_valid = _rendered_trunk(head, (20.0, 0.0, dz))
        moved_widths = row_widths_px(moved, moved_valid, head)
        frame = silhouette.frame(moved_valid, moved_widths, trunk_width_px(moved, moved_valid, head, moved_widths)
                                 / reference_width)
        assert frame.scale == pytest.approx(2000.0 / (2000.0 + dz), abs=1e-3)
        assert frame.shift_u_px == pytest.approx(head.fx * 20.0 / (2000.0 + dz), abs=0.3)


def test_the_body_aligned_displacement_of_a_swaying_rigid_trunk_is_nil():
    """The same rigid trunk 30 mm farther and 10 mm to the side: after the body frame and the level of
    the sides, the trunk moved by about a millimetre (median 0.9 mm: one similarity cannot carry a
    rounded trunk's front and its sides, at different depths, exactly; the outermost pixels' depth,
    used before, left 12 mm)."""
    from core.rig import thesis_head
    from core.volume.maps import body_aligned_displacement

    head = thesis_head("front", scale=0.25)
    depth_b, mask_b = _rendered_trunk(head)
    depth_a, mask_a = _rendered_trunk(head, (10.0, 0.0, 30.0))
    displacement = body_aligned_displacement(depth_a, mask_a, depth_b, mask_b, head)
    inner = ndimage.binary_erosion(mask_b, iterations=4)
    assert np.nanmedian(np.abs(displacement[inner])) < 1.5


def _cylinder_map(head, axis_mm: float, radius_mm: float = 150.0, lost_px: int = 2):
    """A vertical cylinder's depth map (axis axis_mm away) with the outermost lost_px of each side
    left out, as the reconstruction leaves them: (depth, valid, silhouette)."""
    u = (np.arange(head.width) - head.cx) / head.fx  # x / z of each column's ray
    a = 1.0 + u ** 2  # the ray x = u z meets x^2 + (z - Z0)^2 = R^2 at the smaller root
    disc = axis_mm ** 2 - a * (axis_mm ** 2 - radius_mm ** 2)
    z_row = np.where(disc >= 0, (axis_mm - np.sqrt(np.maximum(disc, 0.0))) / a, np.nan)
    depth = np.tile(z_row, (head.height, 1))
    depth[:10] = np.nan  # rows without the subject
    silhouette = np.isfinite(depth)
    valid = silhouette & ~ndimage.binary_dilation(~silhouette, structure=np.ones((1, 2 * lost_px + 1)))
    return depth, valid, silhouette



@pytest.mark.parametrize("scale", [0.15, 0.5])
def test_the_occluding_contour_is_found_where_the_map_lacks_the_silhouettes_outermost_pixels(scale):
    """A vertical cylinder (radius 150 mm, axis 2300 mm away): its contour lies at Z0 - R^2 / Z0.
    The map without the outermost 9 mm of each side (two pixels at scale 0.15, where the
    reconstruction solves no normal) still places it within 3 mm at either scale; the last pixel
    with a depth lies tens of mm nearer."""
    from core.rig import thesis_head
    from core.volume.maps import contour_depth_mm

    head = thesis_head("front", scale=scale)
    radius, axis_mm = 150.0, 2300.0
    depth, valid, silhouette = _cylinder_map(head, axis_mm, radius, lost_px=int(round(2 * scale / 0.15)))
    truth = axis_mm - radius ** 2 / axis_mm
    assert contour_depth_mm(depth, valid, silhouette, head) == pytest.approx(truth, abs=3.0)
    outermost = np.nanmax(np.where(valid, depth, np.nan))
    assert truth - outermost > 20.0


def test_the_body_frame_resampling_is_bilinear_on_the_valid_pixels():
    """BodyFrame.resampled (a numba kernel) against scipy's map_coordinates of the depth and of the
    valid pixels, the reference it replaced: the same pixels NaN, the same depths."""
    from core.volume.maps import BodyFrame
    from core.rig import thesis_head

    head = thesis_head(scale=0.25)
    rng = np.random.default_rng(2)
    depth = 2000.0 + 10.0 * rng.normal(size=head.shape)
    valid = np.zeros(head.shape, bool)
    valid[30:220, 60:300] = True
    valid[100:110, 100:105] = False
    v, u = np.mgrid[0:head.height, 0:head.width].astype(float)
    for frame in (BodyFrame(1.0, 0.0, 0.0), BodyFrame(1.013, 2.3, -1.7), BodyFrame(0.97, -40.2, 31.5),
                  BodyFrame(1.0, 3.5, 2.5)):
        for shown in (valid, np.ones(head.shape, bool)):
            at = [head.cy + (v - head.cy) * frame.scale + frame.shift_v_px,
                  head.cx + (u - head.cx) * frame.scale + frame.shift_u_px]
            z = ndimage.map_coordinates(np.where(shown, depth, 0.0), at, order=1, cval=0.0)
            weight = ndimage.map_coordinates(shown.astype(float), at, order=1, cval=0.0)
            expected = np.where(weight > 0.99, z / np.maximum(weight, 1e-9), np.nan)
            got = frame.resampled(depth, shown, head.shape, head)
            np.testing.assert_array_equal(np.isnan(got), np.isnan(expected))
            np.testing.assert_allclose(got, expected, atol=1e-9, equal_nan=True)


def test_the_two_heads_sides_agree_on_an_upright_trunk_and_not_on_a_bent_map():
    """A vertical cylinder seen from both heads: its contour's depths add up to the same sum at every
    height (tilt 0). The front map bent by 0.4 mm per mm of height, as a sheen bends it, tilts the
    sum by that much and the volume is refused; 0.1 is let through."""
    from core.rig import thesis_head
    from core.pipeline.quality import bend_refusal
    from core.volume.sides import MAX_SIDES_TILT, paired_tilts, side_profile_mm, sides_tilt

    front_head, back_head = thesis_head("front", scale=0.15), thesis_head("back", scale=0.15)
    baseline = 4000.0
    front = _cylinder_map(front_head, 2100.0)
    back = _cylinder_map(back_head, baseline - 2100.0)
    back_profile = side_profile_mm(*back, back_head)
    upright = sides_tilt(side_profile_mm(*front, front_head), back_profile)
    assert abs(upright) < 0.01
    rows = np.arange(front_head.height)[:, None]
    for bend in (0.1, 0.4):
        depth, valid, silhouette = front
        bent = depth * (1.0 + bend * (rows - front_head.cy) / front_head.fy)  # + bend * height
        tilt = sides_tilt(side_profile_mm(bent, valid, silhouette, front_head), back_profile)
        assert tilt == pytest.approx(bend, abs=0.02)
        refusal = bend_refusal(paired_tilts((np.array([0, 10]), [side_profile_mm(bent, valid, silhouette, front_head)] * 2),
                                            (np.array([5]), [back_profile])))
        assert (refusal is not None) == (bend > MAX_SIDES_TILT)
    assert refusal.code == "bent-maps" and "by 40 mm more for every 100 mm of its height" in refusal.reason
    short = (np.array([0.0, 100.0]), np.array([2000.0, 2000.0]))
    assert np.isnan(sides_tilt(short, short))  # less height in common than MIN_SIDES_SPAN_MM
    assert bend_refusal(np.array([np.nan])) is None
