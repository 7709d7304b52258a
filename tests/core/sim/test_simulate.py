"""Whole simulated sessions: determinism, geometry of the torso, truth against the flow sensor."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from core.io.session import SessionFile, validate_session
from core.sim.breathing import Subject, Sway
from core.volume.flow_sensor import btps_factor
from core.sim.simulate import SimConfig, simulate


def _frames(path):
    with h5py.File(path) as f:
        return {h: f[f"heads/{h}/frames"][:] for h in f["heads"]}


def test_same_seed_same_session_other_seed_other_noise(tmp_path):
    config = SimConfig(protocol="tidal", seconds=0.2, scale=0.08, seed=5)
    simulate(tmp_path / "a.h5", config)
    simulate(tmp_path / "b.h5", config)
    simulate(tmp_path / "c.h5", SimConfig(protocol="tidal", seconds=0.2, scale=0.08, seed=6))
    a, b, c = (_frames(tmp_path / n) for n in ("a.h5", "b.h5", "c.h5"))
    for head in a:
        np.testing.assert_array_equal(a[head], b[head])
        assert not np.array_equal(a[head], c[head])
    with h5py.File(tmp_path / "a.h5") as fa, h5py.File(tmp_path / "b.h5") as fb:
        np.testing.assert_array_equal(fa["flow/adc"][:], fb["flow/adc"][:])
        np.testing.assert_array_equal(fa["truth/volume_l"][:], fb["truth/volume_l"][:])


def test_noise_seed_draws_other_noise_on_the_same_scene(tmp_path):
    config = SimConfig(protocol="tidal", seconds=0.2, scale=0.08, seed=5)
    simulate(tmp_path / "a.h5", config)
    simulate(tmp_path / "n.h5", SimConfig(protocol="tidal", seconds=0.2, scale=0.08, seed=5, noise_seed=77))
    a, n = _frames(tmp_path / "a.h5"), _frames(tmp_path / "n.h5")
    with SessionFile(tmp_path / "a.h5") as fa, SessionFile(tmp_path / "n.h5") as fn:
        np.testing.assert_array_equal(fa.truth()["front/depth_mm"][0], fn.truth()["front/depth_mm"][0])
        np.testing.assert_array_equal(fa.rig.heads["front"].light_positions_mm, fn.rig.heads["front"].light_positions_mm)
    for head in a:
        difference = a[head].astype(np.int32) - n[head].astype(np.int32)
        assert np.count_nonzero(difference) > 0.3 * difference.size  # other noise (the dark background often rounds alike)
        assert abs(difference.mean()) < 0.1  # and nothing else: zero on average


def test_torso_is_an_adult_trunk_seen_from_the_front(tmp_path):
    path = tmp_path / "t.h5"
    simulate(path, SimConfig(protocol="static", seconds=0.1, scale=0.25, sway=Sway(0, 0, 0), truth_maps_at=[4]))
    with SessionFile(path) as s:
        head = s.rig.heads["front"]
        depth = s.truth()["front/depth_mm"][0]
        normals = s.truth()["front/normals"][0]
    footprint = depth / head.fx
    rows = np.where(np.isfinite(depth).sum(axis=1) > 0)[0]
    widest = max(np.nansum(footprint[r][np.isfinite(depth[r])]) for r in rows)
    assert 560 < widest < 700, widest  # shoulder to shoulder
    centre = depth[head.height // 2, head.width // 2]
    assert centre == pytest.approx(2000.0, abs=40)  # distance to the surface on the axis
    assert np.nanmax(depth) - np.nanmin(depth) > 80  # a body, not a board
    assert np.nanmean(np.abs(normals[..., 0])) > 0.15  # curved across


def test_truth_volume_is_what_the_surfaces_sweep_and_the_flow_sensor_carries_it(tmp_path):
    path = tmp_path / "vc.h5"
    subject = Subject()
    simulate(path, SimConfig(protocol="vc", scale=0.08, seed=2, subject=subject, sway=Sway(0, 0, 0),
                             truth_maps_at=[4, 5 * 300 + 4]))
    with SessionFile(path) as s:
        truth = s.truth()
        volume = truth["volume_l"][:]
        t_truth = truth["timestamp_ns"][:]
        adc, t_flow = s.flow_samples()
        flow = s.flow
        attrs = flow.attrs
        depth = truth["front/depth_mm"][:], truth["back/depth_mm"][:]
        heads = s.rig.heads
    vc = volume.max() - volume.min()
    assert vc == pytest.approx(subject.inspiratory_capacity + subject.expiratory_reserve, rel=0.01)
    btps = btps_factor(attrs["room_temperature_c"], attrs["room_pressure_hpa"], attrs["room_humidity_pct"])
    flow_lps = (flow.gain_lps * adc + flow.offset_lps) * btps
    sensor_volume = np.cumsum(flow_lps) / flow.sample_rate_hz
    sensor_volume_at_truth = np.interp(t_truth, t_flow, sensor_volume)
    assert np.max(np.abs(sensor_volume_at_truth - volume)) < 0.03 * vc
    # The depth maps the cameras see hold most of the swept volume (the sides are out of view).
    k = 1
    frame_t = (5 * 300 + 4) / 110.0
    expected = np.interp(frame_t, (t_truth - t_truth[0]) / 1e9, volume)
    seen = 0.0
    for name, d in zip(("front", "back"), depth):
        h = heads[name]
        seen += np.nansum((d[0] - d[k]) * (d[0] / h.fx) * (d[0] / h.fy)) * 1e-6
    assert abs(expected) > 1.0 and 0.8 < seen / expected <= 1.01


def test_lost_frames_leave_gaps_not_shifts(tmp_path):
    path = tmp_path / "drop.h5"
    simulate(path, SimConfig(protocol="tidal", seconds=0.5, scale=0.05, drop_rate=0.1, seed=4))
    assert validate_session(path) == []
    with SessionFile(path) as s:
        ids = s.frame_id("front").astype(int)
        assert s.lost_frames("front") > 0
        np.testing.assert_array_equal(s.light_index("front"), np.array(s.rig.sequence)[ids % 5])


def test_sphere_calibration_session(tmp_path):
    path = tmp_path / "sph.h5"
    simulate(path, SimConfig(scene="specular-sphere", scale=0.1, placements=5, heads=("front",)))
    assert validate_session(path) == []
    with SessionFile(path) as s:
        assert s.kind == "sphere-calibration" and s.subject is None and s.flow is None
        assert s.attrs["sphere_finish"] == "specular" and s.attrs["sphere_radius_mm"] == 75.0
        assert [label for _, label in s.events()] == ["placement"] * 5
        assert s.heads == ["front"]


@pytest.mark.parametrize("scene", ["plane", "vase", "relief", "sphere", "matte-sphere"])
def test_every_scene_renders_and_validates(tmp_path, scene):
    path = tmp_path / f"{scene}.h5"
    simulate(path, SimConfig(scene=scene, scale=0.05, seconds=0.1, placements=2))
    assert validate_session(path) == []
    with SessionFile(path) as s:
        lit = s.frames("front")[0].astype(float)
        dark = s.frames("front")[4].astype(float)
        assert lit.max() > dark.max() + 100
