"""The clinic's effects in the renderer against closed forms: an LED's cos^mu falloff about a
tilted axis on a plane, lens distortion against OpenCV's projectPoints, vignetting, mains flicker
and thermal drift."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from core.rig import thesis_head
from core.sim.render import CameraModel
from core.sim.scene import Digitiser, HeightFieldScene, SpherePlacement, SphereScene
from core.sim.simulate import Drift, SimConfig, as_built_heads, in_world
from core.rig import thesis_rig
from core.sim.surfaces import BodyGrid, build_height_field

QUIET = CameraModel(noise=False, ambient_level=0.0, background_level=0.0)


def _board(albedo: float = 0.7):
    grid = BodyGrid.covering(400.0, -320.0, 320.0, 1.0)
    x, y = grid.coordinates()
    return build_height_field(grid, np.full_like(x, 10.0), np.full_like(x, albedo))


def test_led_falloff_is_cos_mu_about_its_own_tilted_axis_on_a_plane():
    z_mid, albedo, light, mu = 2010.0, 0.7, 1, 2.6
    tilt = np.radians(9.0)
    axis = np.array([np.sin(tilt), -0.3 * np.sin(tilt), np.cos(tilt)])
    axis /= np.linalg.norm(axis)
    head = thesis_head("front", scale=0.1)
    head = replace(head, light_axis=np.tile(axis, (4, 1)), light_mu=np.full(4, mu))
    scene = HeightFieldScene({"front": _board(albedo)}, z_mid, 4000.0)
    digitiser = Digitiser(QUIET, 16)
    frame, _ = scene.render(head, 0.0, light, np.uint64(0), digitiser, want_maps=True)

    gain, _, _, _, dn_per_e, _ = digitiser.args()
    rows, cols = np.meshgrid(np.arange(3, head.height, 7), np.arange(5, head.width, 9), indexing="ij")
    u, v = (cols - head.cx) / head.fx, (rows - head.cy) / head.fy
    z = np.full(u.shape, z_mid - 10.0)
    point = np.stack([u * z, v * z, z], axis=-1)
    to_light = head.light_positions_mm[light] - point
    r = np.linalg.norm(to_light, axis=-1)
    cos_surface = -to_light[..., 2] / r  # the board faces the camera: normal (0, 0, -1)
    cos_led = np.sum(-to_light / r[..., None] * axis, axis=-1)  # from the LED towards the point, against its axis
    expected = np.round(gain * albedo * cos_surface * cos_led**mu / r**2 * dn_per_e)
    assert np.max(np.abs(frame[rows, cols] - expected)) <= 1.0
    isotropic, _ = scene.render(replace(head, light_axis=None, light_mu=None), 0.0, light, np.uint64(0), digitiser)
    ratio = frame[rows, cols] / isotropic[rows, cols]
    assert ratio.max() - ratio.min() > 0.01  # the falloff is there, and varies across the field


def test_lens_distortion_puts_a_sphere_where_opencv_projects_it():
    k1 = -0.3
    head = thesis_head("front", scale=0.5)
    head = replace(head, dist_coeffs=np.array([k1, 0.0, 0.0, 0.0, 0.0]))
    centre = np.array([380.0, -270.0, 2000.0])
    scene = SphereScene(12.0, [SpherePlacement(0.0, centre)], 4000.0, albedo=0.8, supersample=3)
    camera = replace(QUIET, ambient_level=0.5)  # evenly lit by the room: the disc's own centre, not its shading's
    frame, _ = scene.render(head, 0.0, -1, np.uint64(0), Digitiser(camera, 16))
    weights = frame.astype(float)
    rows, cols = np.nonzero(weights > 0)
    measured = np.array([np.average(cols, weights=weights[rows, cols]), np.average(rows, weights=weights[rows, cols])])
    projected, _ = cv2.projectPoints(centre[None], np.zeros(3), np.zeros(3), head.camera_matrix, head.dist_coeffs)
    pinhole = np.array([head.fx * centre[0] / centre[2] + head.cx, head.fy * centre[1] / centre[2] + head.cy])
    assert np.linalg.norm(projected.ravel() - pinhole) > 4.0  # the distortion is large enough to see
    assert np.linalg.norm(measured - projected.ravel()) < 0.5  # and the sphere sits where OpenCV puts it


def test_vignetting_darkens_the_corners_by_its_fraction():
    head = replace(thesis_head("front", scale=0.1), vignetting=0.2)
    camera = replace(QUIET, ambient_level=0.3)
    scene = HeightFieldScene({"front": _board(0.8)}, 1000.0, 4000.0)
    dark, _ = scene.render(head, 0.0, -1, np.uint64(0), Digitiser(camera, 16))
    centre = dark[head.height // 2, head.width // 2]
    # the board is flat and evenly lit by the room: only the lens makes the corners darker
    yy, xx = np.mgrid[0:head.height, 0:head.width]
    r2 = ((xx - head.cx) ** 2 + (yy - head.cy) ** 2) / (head.cx**2 + head.cy**2)
    on = np.isfinite(dark) & (dark > 0)
    np.testing.assert_allclose(dark[on], np.round(centre * (1 - 0.2 * r2[on]) / (1 - 0.2 * r2[head.height // 2,
                                                                                          head.width // 2])), atol=1.5)


def test_flicker_and_drift_follow_their_formulas():
    config = replace(SimConfig(seed=4), ambient_flicker=0.3, mains_hz=60.0, led_drift=0.02)
    drift = Drift(config)
    t = np.linspace(0, 1 / 120, 9)
    ambient = np.array([drift.ambient_at(ti) for ti in t])
    assert abs(ambient.max() - 1.3) < 0.02 and abs(ambient.min() - 0.7) < 0.02  # 120 Hz: one period in 1/120 s
    np.testing.assert_allclose(ambient[0], ambient[-1], atol=1e-9)
    head = thesis_head("front", scale=0.1)
    minutes = drift.relative_intensity(np.linspace(0, 1200, 2000))
    assert np.all(np.abs(minutes - 1) <= 0.02 + 1e-12) and np.all(minutes.max(0) - minutes.min(0) > 0.03)
    np.testing.assert_allclose(drift.head_at(head, 300.0).light_intensity,
                               head.light_intensity * drift.relative_intensity(np.array([300.0]))[0])


def test_the_clinic_builds_leds_off_the_drawing_tilted_and_anisotropic():
    config = in_world(SimConfig(seed=2, scale=0.1), "clinic")
    rig = thesis_rig(0.1)
    built = as_built_heads(rig, config)
    for name, head in built.items():
        drawn = rig.heads[name]
        offsets = np.linalg.norm(head.light_positions_mm - drawn.light_positions_mm, axis=1)
        np.testing.assert_allclose(offsets, config.led_offset_mm)
        tilts = np.degrees(np.arccos(head.light_axis[:, 2]))
        assert np.all(tilts <= config.led_tilt_deg + 1e-9) and tilts.max() > 1.0
        assert np.all((head.light_mu >= 1.0) & (head.light_mu <= 3.0))
        assert np.all(np.abs(head.light_intensity - 1) <= 0.1)
    again = as_built_heads(rig, replace(config, seed=99, rig_seed=2))
    np.testing.assert_array_equal(again["front"].light_positions_mm, built["front"].light_positions_mm)


def test_crossed_polarisers_cut_the_surface_reflection_to_their_extinction_and_dim_the_rest():
    """Behind crossed polarisers a glossy board's diffuse light is POLARISED_LED / 2 of what it was, its
    highlight (the surface reflection, which keeps the LED's polarisation) POLARISED_LED times the
    extinction; the sphere sessions are recorded without them."""
    from core.sim.simulate import (POLARISED_LED, POLARISER_EXTINCTION, polarised_camera, polarised_specular,
                                   sim_digitisers)

    head = thesis_head("front", scale=0.1)
    grid = BodyGrid.covering(400.0, -320.0, 320.0, 1.0)
    x, _ = grid.coordinates()

    def render(specular: float, camera: CameraModel) -> np.ndarray:
        board = build_height_field(grid, np.full_like(x, 10.0), np.full_like(x, 0.5), specular=specular,
                                   shininess=30.0)
        frame, _ = HeightFieldScene({"front": board}, 2010.0, 4000.0).render(head, 0.0, 0, np.uint64(0),
                                                                              Digitiser(camera, 16))
        return frame.astype(float)

    diffuse, glossy = render(0.0, QUIET), render(0.3, QUIET)
    behind = polarised_camera(QUIET)
    diffuse_p, glossy_p = render(0.0, behind), render(polarised_specular(0.3), behind)
    highlight = glossy - diffuse
    assert highlight.max() > 0.2 * diffuse.max()  # a highlight worth cutting
    np.testing.assert_allclose(diffuse_p, diffuse * POLARISED_LED / 2, atol=1.0)
    np.testing.assert_allclose(glossy_p - diffuse_p, highlight * POLARISED_LED * POLARISER_EXTINCTION, atol=1.5)
    rig = thesis_rig(0.1)
    config = in_world(SimConfig(scale=0.1), "clinic-polarised")
    assert sim_digitisers(config, rig)["front"].camera.white_level == QUIET.white_level * POLARISED_LED / 2
    assert sim_digitisers(replace(config, scene="specular-sphere"), rig)["front"].camera.white_level == QUIET.white_level
