"""The live view's checks on the optical volume (core/pipeline/live_checks.py): what they
judge by and for how long."""

from __future__ import annotations

import numpy as np

from core.pipeline.live_checks import LOOK_INTERVAL_S, WINDOW_S, LiveOpticalChecks
from core.pipeline.quality import MAX_SHEEN
from core.volume.sides import MAX_SIDES_TILT


def _profile(tilt: float, offset_mm: float) -> tuple[np.ndarray, np.ndarray]:
    height = np.arange(-200.0, 201.0, 10.0)
    return height, offset_mm + tilt * height


def test_a_look_is_due_once_a_look_interval_and_again_after_a_replay_moved_back():
    checks = LiveOpticalChecks(["front", "back"])
    assert checks.due("front", 10.0) and not checks.due("front", 10.0 + 0.5 * LOOK_INTERVAL_S)
    assert checks.due("back", 10.1)  # each head its own
    assert checks.due("front", 10.0 + LOOK_INTERVAL_S)
    assert checks.due("front", 2.0)  # time ran backwards: a replay was moved


def test_the_checks_judge_by_the_last_window_only():
    checks = LiveOpticalChecks(["front", "back"])
    assert not checks.checked and checks.refusal() is None
    checks.add_sheen("front", 0.0, 3 * MAX_SHEEN)
    assert checks.checked and "head front" in str(checks.refusal())
    for t in np.arange(1.0, WINDOW_S + 2.0):
        checks.add_sheen("front", float(t), 0.2 * MAX_SHEEN)
    assert checks.refusal() is None  # the glossy look has left the window and the median is matte
    checks.clear()
    assert not checks.checked


def test_bent_maps_are_paired_across_the_heads_and_refused():
    checks = LiveOpticalChecks(["front", "back"])
    checks.add_profile("front", 0.0, _profile(0.6 * MAX_SIDES_TILT, 2000.0))
    assert not checks.checked  # one head alone: nothing to compare
    checks.add_profile("back", 0.1, _profile(0.6 * MAX_SIDES_TILT, 1000.0))
    assert checks.checked and "bent" in str(checks.refusal())  # the sum tilts by 1.2 MAX_SIDES_TILT
    checks.add_profile("back", 0.2 + 2 * LOOK_INTERVAL_S, _profile(-0.6 * MAX_SIDES_TILT, 1000.0))
    assert "bent" in str(checks.refusal())  # too far from the front's newest: not paired
    for t in (0.3, 0.4):
        checks.add_profile("front", 0.2 + 2 * LOOK_INTERVAL_S + t, _profile(0.6 * MAX_SIDES_TILT, 2000.0))
    assert checks.refusal() is None  # the median of three pairs: two of them untilted
