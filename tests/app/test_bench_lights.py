"""`photopft bench lights`: the light calibration of rigs as built, against their truth."""

from __future__ import annotations

import numpy as np

from benchmarks.lights import lights_table, run_rig
from benchmarks.population import draw_subjects


def test_a_rig_is_calibrated_from_its_spheres_and_compared_with_the_lights_as_built(tmp_path):
    subject = draw_subjects(1, 1, [])[0]
    row = run_rig(subject, 0.1, str(tmp_path))
    # every LED as built lies exactly led_offset_mm from the drawing: the truth read is the rig's
    for offsets in row["built_offset_mm"].values():
        np.testing.assert_allclose(offsets, subject.led_offset_mm, rtol=1e-9)
    for label in ("specular", "specular+matte"):
        assert "failed" not in row[label], row[label]
        for errors in row[label].values():
            assert len(errors["position_mm"]) == 4 and np.all(np.isfinite(errors["position_mm"]))
    for head, errors in row["specular+matte"].items():  # the matte sphere gives the axes, if not the positions
        assert "axis_deg" in errors and "the matte sphere" in row["specular+matte refined on"][head]
    assert not list(tmp_path.iterdir())  # the sphere sessions are not left behind
    text = lights_table([row], 0.1, 1, row["seconds"], 1)
    assert "| 0 |" in text and "LEDs within 5 mm" in text
