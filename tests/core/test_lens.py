"""The lens undone: a distorted, vignetted camera's cycles reconstruct as the pinhole camera's."""

from __future__ import annotations

from dataclasses import replace

import h5py
import numpy as np
import pytest

from core.reconstruction.lens import LensCorrection
from core.pipeline.process import process_session
from core.rig import thesis_head
from core.sim.breathing import Sway
from core.sim.render import CameraModel
from core.sim.scene import Digitiser, SpherePlacement, SphereScene
from core.sim.simulate import SimConfig, simulate


def test_the_correction_puts_a_sphere_where_the_pinhole_camera_sees_it_evenly_lit():
    pinhole = thesis_head("front", scale=0.5)
    lens = replace(pinhole, dist_coeffs=np.array([-0.3, 0.0, 0.0, 0.0, 0.0]), vignetting=0.25)
    camera = CameraModel(noise=False, ambient_level=0.5, background_level=0.0)
    scene = SphereScene(12.0, [SpherePlacement(0.0, np.array([380.0, -270.0, 2000.0]))], 4000.0, albedo=0.8)

    def seen(head):
        frame, _ = scene.render(head, 0.0, -1, np.uint64(0), Digitiser(camera, 16))
        return np.repeat(frame[None].astype(np.float64), 4, axis=0)

    corrected, _, _ = LensCorrection(lens).correct(seen(lens), np.zeros((4,) + lens.shape, bool), None)
    expected = seen(pinhole)

    def centre(image):
        rows, cols = np.nonzero(image > 0.5 * image.max())
        return np.array([cols.mean(), rows.mean()])

    assert np.linalg.norm(centre(seen(lens)[0]) - centre(expected[0])) > 4.0
    assert np.linalg.norm(centre(corrected[0]) - centre(expected[0])) < 0.5
    assert corrected[0].max() == pytest.approx(expected[0].max(), rel=0.03)  # the corner's light given back


def test_a_distorted_vignetted_rig_measures_the_distance_of_the_pinhole_rig(tmp_path):
    distances = {}
    for name, lens in (("pinhole", {}), ("lens", {"lens_k1": -0.15, "vignetting": 0.25})):
        session, results = tmp_path / f"{name}.h5", tmp_path / f"{name}-r.h5"
        simulate(session, SimConfig(scene="plane", protocol="static", seconds=4 * 5 / 110, scale=0.15,
                                    heads=("front",), sway=Sway(0, 0, 0), **lens))
        process_session(session, results, workers=1)
        with h5py.File(results) as f:
            distances[name] = float(np.median(f["heads/front/distance_mm"][:]))
    assert distances["lens"] == pytest.approx(distances["pinhole"], abs=3.0)
