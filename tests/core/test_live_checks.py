"""The live view's checks on the optical volume (core/reconstruction/live_checks.py): what they
judge by and for how long."""

from __future__ import annotations

import numpy as np

from core.reconstruction.live_checks import LOOK_INTERVAL_S, REFERENCE_WINDOW_S, WINDOW_S, LiveOpticalChecks
from core.reconstruction.process import MAX_SHEEN
from core.volume.metric import MAX_REFERENCE_DISAGREEMENT, MIN_REFERENCE_SWING_L
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
    assert checks.checked and "head front" in checks.refusal()
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
    assert checks.checked and "bent" in checks.refusal()  # the sum tilts by 1.2 MAX_SIDES_TILT
    checks.add_profile("back", 0.2 + 2 * LOOK_INTERVAL_S, _profile(-0.6 * MAX_SIDES_TILT, 1000.0))
    assert "bent" in checks.refusal()  # too far from the front's newest: not paired
    for t in (0.3, 0.4):
        checks.add_profile("front", 0.2 + 2 * LOOK_INTERVAL_S + t, _profile(0.6 * MAX_SIDES_TILT, 2000.0))
    assert checks.refusal() is None  # the median of three pairs: two of them untilted


def test_sides_that_move_with_the_breathing_are_refused_over_the_last_breaths():
    """The live volume referred to the trunk's sides against the same referred to the top of the view,
    as `process` compares them (MetricVolume.refusal), over the last REFERENCE_WINDOW_S."""
    checks = LiveOpticalChecks(["front", "back"])
    t = np.arange(0.0, REFERENCE_WINDOW_S, 0.2)
    breath = 0.5 * np.sin(2 * np.pi * t / 4.0)
    for when, side in zip(t, breath):  # the sides' level took 40 % of the breath away
        checks.add_volumes(float(when), side, side / 0.6)
    assert checks.checked and "top of the view" in checks.refusal()
    assert f"{100 * (1 + MAX_REFERENCE_DISAGREEMENT):.0f} %" in checks.refusal()
    for when, side in zip(t + REFERENCE_WINDOW_S + 1.0, breath):  # the patient held the arms away
        checks.add_volumes(float(when), side, 1.02 * side)
    assert checks.checked and checks.refusal() is None
    shallow = LiveOpticalChecks(["front", "back"])
    for when, side in zip(t, 0.4 * MIN_REFERENCE_SWING_L * np.sin(2 * np.pi * t / 4.0)):
        shallow.add_volumes(float(when), side, side / 0.6)
    assert not shallow.checked and shallow.refusal() is None  # too little breathing to tell


def test_silhouettes_that_widen_with_the_breathing_withhold_values_over_the_last_breaths():
    """The two heads' silhouettes against the live volume, as `process` weighs them (flank_refusal):
    a trunk of 0.12 m^2 in view whose silhouettes grow 1.5 % a litre moves its unseen flanks by about
    11 % of the breath; one whose silhouettes keep their width is not refused, whatever sway does to
    each head's alone (it leaves their mean)."""
    from core.volume.metric import MAX_FLANK_SHARE, flank_share

    t = np.arange(0.0, REFERENCE_WINDOW_S, 0.2)
    breath = 0.5 * np.sin(2 * np.pi * t / 4.0)
    noise = 0.001 * np.random.default_rng(2).standard_normal(len(t))
    area_mm2 = 120_000.0
    checks = LiveOpticalChecks(["front", "back"])
    for when, volume, n in zip(t, breath, noise):
        checks.add_volumes(float(when), volume, volume, (0.015 * volume + n, area_mm2))
    assert flank_share(0.015, area_mm2) > 3 * MAX_FLANK_SHARE
    # a breath of 1 L would lose about 106 mL: the tidal volume goes too, as `process` withholds it
    assert "silhouette widens by 1.5 % per litre" in checks.refusal() and "neither camera sees" in checks.refusal()
    assert checks.refusal().startswith("no tidal volume, rate, VC") and "of its 9" in checks.refusal()
    assert checks.withheld() is None
    steady = LiveOpticalChecks(["front", "back"])
    for when, volume, n in zip(t, breath, noise):
        steady.add_volumes(float(when), volume, volume, (n, area_mm2))
    assert steady.checked and steady.refusal() is None and steady.withheld() is None
    # 0.7 % a litre: 5 % of the volume in the flanks, 25 mL of a 0.5 L breath; the tidal volume and
    # rate stay and the curve is not refused, VC, FVC, FEV1 and PEF would be withheld
    some = LiveOpticalChecks(["front", "back"])
    for when, volume, n in zip(t, breath / 2, noise):
        some.add_volumes(float(when), volume, volume, (0.007 * volume + n, area_mm2))
    assert some.refusal() is None
    assert some.withheld().startswith("VC, FVC, FEV1 and PEF would not be given: "
                                      "the trunk's silhouette widens by 0.7 %")
