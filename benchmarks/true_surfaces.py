"""What the benches on true surfaces share (`bench visible`, `bench carry`, `bench sides`): a population
subject's clinical session as the simulator builds it, without rendering it, and the trunk of a map
rendered with its true depth and normals."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np


@dataclass(frozen=True)
class SubjectScene:
    config: Any  # core.sim.simulate.SimConfig
    rig: Any  # core.rig.Rig, at the scene's baseline
    scene: Any  # what renders the subject's frames and true maps at any time
    waveform: Any  # the session's breathing
    digitisers: dict  # each head's digitiser (core.sim.simulate.sim_digitisers)
    body: str  # the body's name as `simulate --body` takes it


def subject_scene(subject, scale: float, world: str, **changes) -> SubjectScene:
    """A subject of `bench population`'s draws in its clinical session (session_config), with `changes`
    made to its config (the world's sway or steps left out, say)."""
    from benchmarks.population import session_config
    from core.sim.simulate import build_scene, sim_digitisers, thesis_rig

    config = replace(session_config(subject, scale, world, "clinical", None), **changes)
    rig = thesis_rig(config.scale, tuple(config.heads), config.bit_depth, config.frame_rate_hz)
    scene, waveform = build_scene(config, rig)
    rig = replace(rig, baseline_mm=float(scene.baseline_mm))
    return SubjectScene(config, rig, scene, waveform, sim_digitisers(config, rig), subject.body_name)


def true_trunk(depth_mm: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(subject, trunk) of a true map: the pixels that show the subject, and its trunk among them
    (core/reconstruction/pipeline.py, trunk_mask)."""
    from core.reconstruction.pipeline import trunk_mask

    subject = np.isfinite(depth_mm) & np.isfinite(normals[..., 2])
    return subject, trunk_mask(subject, np.nan_to_num(normals))
