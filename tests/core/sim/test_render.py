"""The renderer against the image formation model, computed independently here."""

from __future__ import annotations

import numpy as np
import pytest

from core.rig import thesis_head
from core.sim.render import CameraModel
from core.sim.scene import Digitiser, HeightFieldScene, SpherePlacement, SphereScene
from core.sim.surfaces import BodyGrid, build_height_field

QUIET = CameraModel(noise=False)


def _board(tilt_x=0.2, tilt_y=-0.1, albedo=0.7, modes=None):
    grid = BodyGrid.covering(400.0, -320.0, 320.0, 1.0)
    x, y = grid.coordinates()
    h = 10.0 + x * tilt_x + y * tilt_y
    return grid, build_height_field(grid, h, np.full_like(x, albedo), modes)


def test_plane_under_one_light_equals_the_formula():
    tx, ty, albedo, z_mid = 0.2, -0.1, 0.7, 2010.0
    _, board = _board(tx, ty, albedo)
    head = thesis_head("front", scale=0.1)
    scene = HeightFieldScene({"front": board}, z_mid, 4000.0)
    digitiser = Digitiser(QUIET, 12)
    light = 2
    frame, maps = scene.render(head, 0.0, light, np.uint64(0), digitiser, want_maps=True)

    gain, ambient_e, _, _, dn_per_e, _ = digitiser.args()
    rows, cols = np.meshgrid(np.arange(3, head.height, 7), np.arange(5, head.width, 9), indexing="ij")
    u = (cols - head.cx) / head.fx
    v = (rows - head.cy) / head.fy
    z = (z_mid - 10.0) / (1.0 + u * tx + v * ty)  # Z = z_mid - h(X, Y) along the ray (u, v, 1) Z
    normal = np.array([-tx, -ty, -1.0]) / np.linalg.norm([-tx, -ty, -1.0])
    point = np.stack([u * z, v * z, z], axis=-1)
    to_light = head.light_positions_mm[light] - point
    r2 = np.sum(to_light**2, axis=-1)
    cos = np.clip(to_light @ normal / np.sqrt(r2), 0, None)
    expected = np.round((gain * albedo * cos / r2 + ambient_e * albedo) * dn_per_e)

    on = np.isfinite(maps.depth_mm[rows, cols])  # the board ends short of the image corners
    assert on.mean() > 0.9
    rows, cols, z, expected = rows[on], cols[on], z[on], expected[on]
    np.testing.assert_allclose(maps.depth_mm[rows, cols], z, rtol=1e-6)
    np.testing.assert_allclose(maps.normals[rows, cols], np.broadcast_to(normal, z.shape + (3,)), atol=1e-5)
    assert np.max(np.abs(frame[rows, cols].astype(float) - expected)) <= 1.0
    dark, _ = scene.render(head, 0.0, -1, np.uint64(0), digitiser)
    np.testing.assert_allclose(dark[rows, cols], np.round(ambient_e * albedo * dn_per_e), atol=1)


def test_truth_volume_of_an_analytic_deformation_equals_its_closed_form():
    sigma, peak_mm = 60.0, 5.0
    grid = BodyGrid.covering(400.0, -320.0, 320.0, 1.0)
    x, y = grid.coordinates()
    bump = np.exp(-(x**2 + (y - 20) ** 2) / (2 * sigma**2))
    _, board = _board(0.0, 0.0, modes={"bump": bump})
    closed_form_l = peak_mm * 2 * np.pi * sigma**2 * 1e-6
    scene = HeightFieldScene({"front": board}, 2010.0, 4000.0, mode_amplitudes=lambda t: np.array([peak_mm * t]))
    assert scene.truth_volume_l(np.array([1.0]))[0] == pytest.approx(closed_form_l, rel=0.005)

    # The rendered surfaces sweep the same volume: integrate the depth change over the pixel footprints.
    head = thesis_head("front", scale=0.25)
    digitiser = Digitiser(QUIET, 12)
    _, rest = scene.render(head, 0.0, 0, np.uint64(0), digitiser, want_maps=True)
    _, moved = scene.render(head, 1.0, 0, np.uint64(0), digitiser, want_maps=True)
    footprint = (rest.depth_mm / head.fx) * (rest.depth_mm / head.fy)
    swept = np.nansum((rest.depth_mm - moved.depth_mm) * footprint) * 1e-6
    assert swept == pytest.approx(closed_form_l, rel=0.005)


def test_specular_highlight_sits_where_the_normal_bisects_view_and_light():
    head = thesis_head("front", scale=0.5)
    scene = SphereScene(75.0, [SpherePlacement(0.0, np.array([60.0, -40.0, 2100.0]))], 4300.0, albedo=0.05,
                        specular=1.5, shininess=4000.0)
    digitiser = Digitiser(QUIET, 12)
    for light in range(4):
        frame, maps = scene.render(head, 0.0, light, np.uint64(0), digitiser, want_maps=True)
        u = (np.arange(head.width) - head.cx) / head.fx
        v = (np.arange(head.height) - head.cy) / head.fy
        point = np.stack(np.broadcast_arrays(u[None] * maps.depth_mm, v[:, None] * maps.depth_mm, maps.depth_mm), -1)
        to_light = head.light_positions_mm[light] - point
        half = to_light / np.linalg.norm(to_light, axis=-1, keepdims=True) - point / np.linalg.norm(
            point, axis=-1, keepdims=True)
        alignment = np.nan_to_num(np.sum(maps.normals * half, -1) / np.linalg.norm(half, axis=-1), nan=-1)
        mirror = np.unravel_index(np.argmax(alignment), alignment.shape)
        brightest = np.unravel_index(np.argmax(frame), frame.shape)
        assert np.hypot(*np.subtract(mirror, brightest)) <= 1.0, (light, mirror, brightest)


def test_inverse_square_falloff_with_distance():
    head = thesis_head("front", scale=0.1)
    digitiser = Digitiser(QUIET, 16)
    _, board = _board(0.0, 0.0, 0.8)
    centre = (head.height // 2, head.width // 2)
    values = []
    for z in (1810.0, 2210.0):
        frame, _ = HeightFieldScene({"front": board}, z, 5000.0).render(head, 0.0, 0, np.uint64(0), digitiser)
        values.append(float(frame[centre]))
    gain, ambient_e, _, _, dn_per_e, _ = digitiser.args()
    ambient = ambient_e * 0.8 * dn_per_e

    def lit(z):
        ray = np.array([(centre[1] - head.cx) / head.fx, (centre[0] - head.cy) / head.fy, 1.0])
        d = head.light_positions_mm[0] - ray * (z - 10.0)
        r = np.linalg.norm(d)
        return gain * 0.8 * (-d[2] / r) / r**2 * dn_per_e

    assert values[0] - ambient == pytest.approx(lit(1810.0), abs=1.0)
    assert values[1] - ambient == pytest.approx(lit(2210.0), abs=1.0)
    assert values[0] / values[1] > 1.3  # nearer is brighter


def test_noise_has_the_shot_and_read_variance():
    head = thesis_head("front", scale=0.25)
    camera = CameraModel(ambient_level=0.0)
    digitiser = Digitiser(camera, 16)
    _, board = _board(0.0, 0.0, 0.8)
    scene = HeightFieldScene({"front": board}, 2010.0, 5000.0)
    a, _ = scene.render(head, 0.0, 0, np.uint64(1000), digitiser)
    b, _ = scene.render(head, 0.0, 0, np.uint64(10_000_000), digitiser)
    quiet, _ = scene.render(head, 0.0, 0, np.uint64(0), Digitiser(CameraModel(ambient_level=0.0, noise=False), 16))
    centre = (slice(100, 150), slice(150, 200))
    e_per_dn = 1 / digitiser.dn_per_e
    signal_e = quiet[centre].astype(float).mean() * e_per_dn
    measured = np.var((a[centre].astype(float) - b[centre].astype(float)) * e_per_dn) / 2
    assert measured == pytest.approx(signal_e + camera.read_noise_e**2, rel=0.1)


def test_binned_pixels_have_the_grey_levels_of_one_and_half_its_noise():
    """Scale 0.5 reads 2 x 2 pixels as one: four times the electrons, the same grey level, half the noise."""
    _, board = _board(0.0, 0.0, albedo=0.7)
    scene = HeightFieldScene({"front": board}, 2010.0, 4000.0)
    camera = CameraModel()
    binned = camera.binned(2.0)
    assert binned.full_well_e == pytest.approx(4 * camera.full_well_e)
    assert binned.read_noise_e == pytest.approx(2 * camera.read_noise_e)
    head = thesis_head("front", scale=0.2)
    spread = {}
    for name, model in (("one", camera), ("binned", binned)):
        frames = [scene.render(head, 0.0, 1, np.uint64(k * head.width * head.height), Digitiser(model, 12))[0]
                  for k in range(8)]
        stack = np.stack(frames).astype(float)[:, 60:140, 80:200]
        spread[name] = (stack.mean(), stack.std(axis=0).mean())
    assert spread["binned"][0] == pytest.approx(spread["one"][0], rel=0.01)
    assert spread["binned"][1] / spread["one"][1] == pytest.approx(0.5, abs=0.07)
    with pytest.raises(ValueError, match="positive"):
        camera.binned(0.0)


def test_steep_flanks_are_rendered_up_to_the_silhouette():
    """A flat-topped dome with steep sides (a superellipsoid of revolution): every pixel whose ray
    meets the surface where it is tilted less than 75 degrees is rendered, at the depth of the ray's
    first meeting with the analytic surface (found here by a fine march)."""
    radius_mm, top_mm, exponent, z_mid = 250.0, 120.0, 2.4, 2000.0
    grid = BodyGrid.covering(300.0, -300.0, 300.0, 0.5)
    x, y = grid.coordinates()

    def dome(r):
        s = np.clip(r / radius_mm, 0.0, 1.0)
        return np.where(r < radius_mm, top_mm * (1.0 - s**exponent) ** (1.0 / exponent), np.nan)

    surface = build_height_field(grid, dome(np.hypot(x, y)), np.full_like(x, 0.7))
    head = thesis_head("front", scale=0.25)
    _, maps = HeightFieldScene({"front": surface}, z_mid, 4000.0).render(head, 0.0, 0, np.uint64(0),
                                                                         Digitiser(QUIET, 12), want_maps=True)
    row = int(round(head.cy))
    u = (np.arange(head.width) - head.cx) / head.fx
    v = (row - head.cy) / head.fy
    z = np.arange(z_mid - top_mm - 1.0, z_mid, 0.005)
    gap = z[:, None] - z_mid + dome(np.hypot(z[:, None] * u, z[:, None] * v))  # < 0 in front of the surface
    crossed = np.nan_to_num(gap, nan=-1.0) >= 0.0
    met = crossed.any(axis=0)
    first = z[np.argmax(crossed, axis=0)]
    r_hit = np.hypot(first * u, first * v) / radius_mm
    slope = top_mm / radius_mm * r_hit ** (exponent - 1) * (1 - np.minimum(r_hit, 1 - 1e-9) ** exponent) ** (
        1 / exponent - 1)
    gentle = met & (np.degrees(np.arctan(slope)) < 75.0)
    flank = gentle & (np.degrees(np.arctan(slope)) > 45.0)
    assert flank.sum() >= 6  # the steep flank is in the test
    rendered = maps.depth_mm[row]
    assert np.isfinite(rendered[gentle]).all()
    np.testing.assert_allclose(rendered[gentle], first[gentle], atol=0.05)
    assert not np.isfinite(rendered[~met]).any()


def test_the_modes_summed_on_the_grid_render_the_surface_summed_per_ray():
    """breathing_surface sums the breathing modes once a frame; the renderer's own sum of each mode's
    interpolation along every ray (both linear) gives the same depths and grey levels."""
    from core.sim.render import STRETCH_COLUMNS, pack_lights, render_height_field

    x, _ = BodyGrid.covering(400.0, -320.0, 320.0, 1.0).coordinates()
    grid, board = _board(0.1, 0.05, modes={"bump": np.exp(-x**2 / 8000.0), "tilt": 0.01 * x})
    amps = np.array([4.0, -2.5])
    scene = HeightFieldScene({"front": board}, 2010.0, 4000.0, mode_amplitudes=lambda t: amps)
    head = thesis_head("front", scale=0.25)
    digitiser = Digitiser(QUIET, 12)
    frame, maps = scene.render(head, 0.0, 1, np.uint64(0), digitiser, want_maps=True)
    u, v, vignette = scene._optics.of(head)
    per_ray = np.empty(head.shape, dtype=head.frame_dtype)
    depth, normals = np.empty(head.shape), np.empty((*head.shape, 3))
    render_height_field(per_ray, np.full(head.shape, np.nan), u, v, vignette, board.fields, grid.x0, grid.y0, grid.step,
                        amps, 1.0, 0.0, 0.0, 2010.0, board.front_mm(amps), board.specular, board.shininess,
                        pack_lights(head)[1], True, *digitiser.args(), np.uint64(0), True, depth, normals,
                        np.zeros((0, STRETCH_COLUMNS)))
    assert np.isfinite(maps.depth_mm).sum() > 1000
    np.testing.assert_allclose(maps.depth_mm, depth, atol=1e-6, equal_nan=True)
    np.testing.assert_allclose(maps.normals, normals, atol=1e-9, equal_nan=True)
    assert np.abs(frame.astype(int) - per_ray.astype(int)).max() <= 1
