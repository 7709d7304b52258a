"""The simulated rig's true lights as a calibration profile: for benchmarks and tests only (the noise
floor), never at run time."""

from __future__ import annotations

import numpy as np

from core.calibration.rig_profile import HeadCalibration, RigCalibration
from core.io.session import SessionFile


def with_true_lights(session: SessionFile) -> RigCalibration:
    """A calibration profile holding the simulation's true lights (for benchmarks: the noise floor)."""
    truth = session.truth()
    heads = {}
    for name in session.heads:
        positions = np.asarray(truth[f"{name}/light_positions_mm"])
        intensity = (np.asarray(truth[f"{name}/light_intensity"]) if f"{name}/light_intensity" in truth
                     else np.ones(4))
        anisotropic = f"{name}/light_axis" in truth and f"{name}/light_mu" in truth  # the LEDs' falloff too
        heads[name] = HeadCalibration(positions, intensity, np.zeros((4, 3)), np.zeros(4), np.zeros((4, 3)),
                                      light_axis=np.asarray(truth[f"{name}/light_axis"]) if anisotropic else None,
                                      light_mu=np.asarray(truth[f"{name}/light_mu"]) if anisotropic else None)
    return RigCalibration("truth", [session.path.name], heads)
