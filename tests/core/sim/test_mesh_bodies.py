"""The test population: MakeHuman's CC0 body mesh shaped by its macro targets, breathing by two
displacement modes, ray-cast by a renderer that shares only the image formation with the
height-field one. Read from ../shared/data/makehuman; nothing copied."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from core.sim.makehuman import (Macros, MeshDataError, age_parameter, closed_volume_mm3,
                                load_mesh_data, mesh_body, target_weights, triangles)
from core.sim.mesh_breathing import (VolumePolynomial, amplitudes_for, at_rest, breathing_modes, chest_share_curve,
                                     trunk_frame)


@pytest.fixture(scope="module")
def mesh_data(shared_data):
    return load_mesh_data(str(shared_data / "makehuman"))


def test_missing_data_is_named_in_one_line(tmp_path):
    with pytest.raises(MeshDataError, match=r"body.npz: the MakeHuman body mesh is not there"):
        load_mesh_data(str(tmp_path))


def test_macro_weights_partition_as_makehuman_combines_them():
    m = Macros(gender=0.3, age=age_parameter(40.0), muscle=0.7, weight=0.2, height=0.8)
    w = target_weights(m)
    universal = sum(v for k, v in w.items() if k.startswith("universal-"))
    ethnic = sum(v for k, v in w.items() if k.split("-")[0] in ("african", "asian", "caucasian"))
    assert universal == pytest.approx(1.0) and ethnic == pytest.approx(1.0)
    heights = sum(v for k, v in w.items() if k.startswith("height/"))
    assert heights == pytest.approx(2 * 0.8 - 1.0)  # maxheight at 2h - 1 of every body term
    assert age_parameter(11.0) == pytest.approx(0.1875) and age_parameter(25.0) == 0.5


def test_a_closed_mesh_volume_is_exact_on_a_box():
    corners = np.array([[x, y, z] for x in (0, 2.0) for y in (0, 3.0) for z in (0, 5.0)])
    # faces counter-clockwise seen from outside
    quads = np.array([[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]])
    assert closed_volume_mm3(corners, triangles(quads)) == pytest.approx(30.0)


def test_the_population_is_plausible_reproducible_and_various(mesh_data):
    bodies = [mesh_body(seed, mesh_data) for seed in range(30)]
    assert mesh_body(4, mesh_data) == mesh_body(4, mesh_data) and mesh_body(4, mesh_data) != mesh_body(5, mesh_data)
    adults = [b for b in bodies if b.age_years >= 18]
    assert all(140 <= b.height_cm <= 210 and 15 <= b.bmi <= 30 for b in adults), [(b.height_cm, b.bmi) for b in adults]
    assert {b.sex for b in bodies} == {"male", "female"}
    assert any(b.age_years < 18 for b in bodies) and any(b.age_years >= 65 for b in bodies)
    children = [b for b in bodies if b.age_years < 12]
    assert all(b.height_cm < 165 for b in children)
    assert json.loads(bodies[0].as_json())["kind"] == "makehuman mesh"


def test_breathing_moves_the_trunk_out_and_nothing_else(mesh_data):
    body = mesh_body(3, mesh_data)
    verts = body.vertices_mm(mesh_data)
    modes = breathing_modes(verts, mesh_data, body)
    frame = trunk_frame(verts, mesh_data)
    assert frame.crotch_y < frame.xiphoid_y < frame.top_y
    rib = modes[0]
    assert np.abs(modes[:, mesh_data.arm_weight > 0.9]).max() < 1e-9  # the arms stay
    assert np.abs(modes[:, verts[:, 1] > frame.top_y + 50]).max() < 1e-9  # the head stays
    sides = (mesh_data.trunk_weight > 0.9) & (np.abs(verts[:, 0]) > 100) & (np.abs(verts[:, 1] - frame.xiphoid_y) < 40)
    assert np.all(np.sign(rib[sides, 0]) == np.sign(verts[sides, 0]))  # bucket handle: the sides move out
    front, back, _ = frame.at(verts[:, 1])
    spine = (np.abs(verts[:, 2] - back) < 5) & (np.abs(verts[:, 0]) < 30)
    sternum = (np.abs(verts[:, 2] - front) < 5) & (np.abs(verts[:, 0]) < 30) & (np.abs(verts[:, 1] - frame.xiphoid_y) < 30)
    assert np.abs(rib[spine]).max() < 0.1 and rib[sternum, 2].min() > 0.8  # pump handle: the sternum forward


def test_the_volume_polynomial_is_the_mesh_volume_and_amplitudes_hit_their_targets(mesh_data):
    body = mesh_body(6, mesh_data)
    verts = body.vertices_mm(mesh_data)
    tris = triangles(mesh_data.quads)
    modes = breathing_modes(verts, mesh_data, body)
    poly = VolumePolynomial.fit(verts, tris, modes)
    rest = closed_volume_mm3(verts, tris)
    rng = np.random.default_rng(0)
    for a, b in rng.uniform(-60, 60, (5, 2)):
        exact = closed_volume_mm3(verts + a * modes[0] + b * modes[1], tris) - rest
        assert poly(np.array(a), np.array(b)) == pytest.approx(exact, rel=1e-7, abs=1.0)
    rib, abdomen = np.array([2.5e6, -0.3e6]), np.array([1.5e6, -0.2e6])
    amps = amplitudes_for(poly, rib, abdomen)
    assert poly(amps[:, 0], amps[:, 1]) == pytest.approx(rib + abdomen, rel=1e-9)
    assert amps[0, 0] / amps[0, 1] == pytest.approx((rib[0] / poly.linear_mm3[0]) / (abdomen[0] / poly.linear_mm3[1]))


def test_the_rib_cage_share_follows_the_manoeuvre():
    t = np.arange(0, 30, 0.01)
    events = [(0.0, "tidal-start"), (10.0, "vc-start"), (18.0, "maneuver-end"), (22.0, "forced-start"),
              (28.0, "maneuver-end")]
    share = chest_share_curve(t, events, {"tidal": 0.3, "vc": 0.6, "forced": 0.7})
    at = lambda s: share[int(s * 100)]  # noqa: E731
    assert at(5) == pytest.approx(0.3) and at(14) == pytest.approx(0.6) and at(25) == pytest.approx(0.7)
    assert at(20) == pytest.approx(0.3) and 0.3 < at(10.0) < 0.6  # blended over a second


def test_a_blows_share_changes_where_the_lung_volume_is_at_rest():
    """The forced manoeuvre's share holds from its inspiration's start to its recovery's end, so the
    compartments do not trade volume at TLC (where the blow's event is) or at RV (where it ends)."""
    t = np.arange(0, 20, 0.01)
    # as core/sim/breathing.py's forced: a 1.6 s inspiration and a 0.4 s hold before the blow's event
    lung = np.interp(t, [0, 6, 7.6, 8, 12, 13.5, 20], [0.0, 0.0, 3.0, 3.0, -1.0, 0.0, 0.0])
    events = [(0.0, "tidal-start"), (8.0, "forced-start"), (12.0, "maneuver-end")]
    moved = at_rest(t, lung, events)
    assert 5.0 <= moved[1][0] <= 6.0 and 13.5 <= moved[2][0] <= 15.0
    share = chest_share_curve(t, moved, {"tidal": 0.3, "vc": 0.6, "forced": 0.7})
    inspiration_to_recovery = (t >= 6.6) & (t <= 13.0)
    assert np.ptp(share[inspiration_to_recovery]) < 1e-12 and share[800] == pytest.approx(0.7)
    top = (t >= 7.6) & (t <= 8.0)  # the inspiration held at TLC, the blow's start
    naive = chest_share_curve(t, events, {"tidal": 0.3, "vc": 0.6, "forced": 0.7}) * lung
    assert np.ptp(naive[top]) > 0.5  # what the blow's own times did: a litre's trade at TLC


def _plane_mesh(z_mid: float, tilt_x_deg: float, tilt_y_deg: float, step: float = 20.0):
    """The board of core.sim.shapes.plane as triangles in the front camera's frame, wound to face it."""
    xs, ys = np.arange(-340.0, 341.0, step), np.arange(-250.0, 251.0, step)
    x, y = np.meshgrid(xs, ys)
    z = z_mid - (10.0 + x * np.tan(np.radians(tilt_x_deg)) + y * np.tan(np.radians(tilt_y_deg)))
    verts = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    nx = len(xs)
    quads = np.array([[i * nx + j, i * nx + j + 1, (i + 1) * nx + j + 1, (i + 1) * nx + j]
                      for i in range(len(ys) - 1) for j in range(nx - 1)])
    a, b, c = verts[quads[0, :3]]
    if np.dot(np.cross(b - a, c - a), a) > 0:  # facing away: reverse the winding
        quads = quads[:, ::-1].copy()
    return verts, quads


def test_the_two_renderers_agree_on_a_tilted_board():
    """The mesh ray-caster and the height-field renderer draw the same board, noise off: the same
    grey levels, depth and normals inside it (they share only the image formation)."""
    from dataclasses import replace

    from core.rig import thesis_rig
    from core.sim import shapes
    from core.sim.mesh_render import distortion_margin_px, rasterise, shade, vertex_normals
    from core.sim.render import CameraModel, camera_rays, pack_lights
    from core.sim.scene import Digitiser, HeightFieldScene

    head = replace(thesis_rig(0.1).heads["front"], dist_coeffs=np.array([-0.08, 0, 0, 0, 0]))
    z_mid = 2100.0
    board = HeightFieldScene(shapes.plane(2.0, albedo=0.5), z_mid, 4000.0)
    digitiser = Digitiser(CameraModel(noise=False).binned(10.0), 12)
    expected, maps = board.render(head, 0.0, 2, np.uint64(1), digitiser, want_maps=True)
    verts, quads = _plane_mesh(z_mid, 10.0, 5.0)
    tris = np.ascontiguousarray(np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]))
    normals = np.empty_like(verts)
    vertex_normals(verts, quads, normals)
    u, v = camera_rays(head)
    depth, tri_id, bary = np.empty(head.shape), np.empty(head.shape, np.int64), np.empty(head.shape + (2,))
    rasterise(verts, tris, u, v, head.fx, head.fy, head.cx, head.cy, distortion_margin_px(u, v, head.fx, head.fy,
              head.cx, head.cy), depth, tri_id, bary)
    out = np.empty(head.shape, head.frame_dtype)
    depth_out, normal_out = np.empty(head.shape), np.empty(head.shape + (3,))
    shade(out, depth, tri_id, bary, tris, normals, u, v, np.ones(head.shape), 0.5, 0.0, 1.0, pack_lights(head)[2],
          True, *digitiser.args(), np.uint64(1), True, depth_out, normal_out)
    inside = np.isfinite(maps.depth_mm) & (tri_id >= 0)
    inside[:3], inside[-3:], inside[:, :3], inside[:, -3:] = False, False, False, False
    assert inside.mean() > 0.5
    assert np.abs(depth_out - maps.depth_mm)[inside].max() < 1e-3
    assert np.abs(normal_out - maps.normals)[inside].max() < 1e-6
    assert np.abs(out.astype(int) - expected.astype(int))[inside].max() <= 1


def test_a_mesh_body_session_holds_its_truth(tmp_path, shared_data):
    """`simulate --body mesh:N`: both heads see the trunk at the distance asked, the flow sensor
    measures the mesh's own volume change, and the body's measures are the subject's."""
    from core.sim.bodies import body_named
    from core.sim.breathing import Sway
    from core.sim.simulate import SimConfig, simulate
    from core.io.session import SessionFile

    body = body_named("mesh:2")
    path = tmp_path / "mesh.h5"
    summary = simulate(path, SimConfig(body=body, protocol="tidal", seconds=3.0, scale=0.1, seed=2,
                                       truth_maps_at=[4], distance_mm=1900.0,
                                       sway=Sway(0.0, 0.0, 0.0)))
    assert summary.truth_volume_range_l[1] - summary.truth_volume_range_l[0] > 0.2
    with SessionFile(path) as s:
        assert s.subject.height_cm == pytest.approx(body.height_cm) and s.subject.sex == body.sex
    with h5py.File(path, "r") as f:
        truth = f["truth"]
        t = truth["timestamp_ns"][:] / 1e9
        volume, flow = truth["volume_l"][:], truth["flow_lps"][:]
        integrated = np.concatenate([[0.0], np.cumsum(0.5 * (flow[1:] + flow[:-1]) * np.diff(t))])
        assert np.abs(integrated - (volume - volume[0])).max() < 0.01
        assert json.loads(truth.attrs["body"])["kind"] == "makehuman mesh"
        front = truth["front/depth_mm"][0]
        h, w = front.shape
        assert abs(float(front[h // 2, w // 2]) - 1900.0) < 15.0  # the axis meets the trunk at the xiphoid
        assert np.isfinite(truth["back/depth_mm"][0][h // 2, w // 2])
