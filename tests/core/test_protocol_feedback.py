"""What the patient-session wizard tells the operator after each manoeuvre, and when a
manoeuvre is done (core/analysis/protocol_feedback.py): the ATS/ERS rules outside the GUI."""

from __future__ import annotations

import numpy as np
import pytest

from core.analysis.values import analyse_volume
from core.analysis.protocol_feedback import (MAX_TIDAL_EXTENSION_S, TIDAL_EXTENSION_S, forced_feedback, tidal_extension_s,
                                    vc_feedback)
from core.sim.breathing import RATE_HZ, Subject, protocol_waveform


def _values():
    w = protocol_waveform(Subject(), "full", None, 1)  # tidal, one slow VC, three good blows
    return analyse_volume(np.arange(len(w.volume_l)) / RATE_HZ, w.volume_l, w.events, 40.0)


def test_three_good_blows_are_enough_and_one_vc_is_not():
    values = _values()
    forced = forced_feedback(values, 3, 40.0)
    assert forced.finished and "Grade A: enough blows" in forced.text
    vc = vc_feedback(values, 1, predicted_fvc_l=4.5)
    assert not vc.finished and "acceptable" in vc.text and "Another, please" in vc.text
    warned = vc_feedback(values, 1, predicted_fvc_l=12.0)
    assert "Far below the predicted FVC" in warned.text


def test_tidal_breathing_goes_on_while_breaths_are_too_few():
    assert tidal_extension_s(2, 0.0) == TIDAL_EXTENSION_S
    assert tidal_extension_s(5, 0.0) == 0.0
    assert tidal_extension_s(None, 0.0) == 0.0  # no flow sensor: counted when processed
    assert tidal_extension_s(2, MAX_TIDAL_EXTENSION_S) == 0.0


def test_a_blow_sampled_too_sparsely_says_why_it_was_not_read():
    """A renderer or a stream that falls behind gives a blow a few volume samples: the operator is told
    that, not an empty reason."""
    w = protocol_waveform(Subject(), "full", None, 1)
    t = np.arange(len(w.volume_l)) / RATE_HZ
    blows = [(at, label) for at, label in w.events if label == "forced-start"]
    sparse = np.ones(len(t), dtype=bool)
    for at, _ in blows:  # one sample every 0.5 s from 2 s before each blow to 8 s after
        near = (t >= at - 2.0) & (t <= at + 8.0)
        sparse[near] = np.isclose((t[near] - at) % 0.5, 0.0, atol=0.5 / RATE_HZ)
    values = analyse_volume(t[sparse], w.volume_l[sparse], w.events, 40.0)
    assert values.forced is None
    feedback = forced_feedback(values, 1, 40.0)
    assert "volume sample(s)" in feedback.text and "too slowly" in feedback.text and "()" not in feedback.text


def test_a_manoeuvre_before_the_curve_begins_is_not_a_problem_of_the_curve():
    """The live volume starts after the subject's calibration: the calibration's slow VC is not in it."""
    w = protocol_waveform(Subject(), "full", None, 1)
    t = np.arange(len(w.volume_l)) / RATE_HZ
    events = sorted(w.events)
    vc_start = next(at for at, label in events if label == "vc-start")
    vc_end = next(at for at, label in events if label == "maneuver-end" and at > vc_start)
    later = t > vc_end + 0.5 - 4.0 / RATE_HZ  # the curve begins with the VC's last few samples
    values = analyse_volume(t[later], w.volume_l[later], w.events, 40.0)
    assert not [p for p in values.problems if p.startswith("slow VC")]
    assert values.forced is not None and len(values.forced.manoeuvres) == 3


def test_each_blow_s_feedback_is_about_that_blow():
    """A loaded machine's maps lag the marks: when the operator ends blow 2, the curve may stop inside
    it. The feedback said "Blow 2" with blow 1's values; it says blow 2 is not read yet, and why. A blow
    left out before a good one does not take the good one's verdict either."""
    w = protocol_waveform(Subject(), "full", None, 1)
    t = np.arange(len(w.volume_l)) / RATE_HZ
    marks = sorted(at for at, label in w.events if label == "forced-start")
    ended = min(at for at, label in w.events if label == "maneuver-end" and at > marks[1])
    so_far = [(at, label) for at, label in w.events if at <= ended]  # the marks made when blow 2 ends
    lagging = t < marks[1] + 1.0  # the maps reach one second into blow 2
    values = analyse_volume(t[lagging], w.volume_l[lagging], so_far, 40.0)
    (first,) = values.forced.manoeuvres
    second = forced_feedback(values, 2, 40.0).text
    assert second.startswith("Blow 2: not analysable (forced expiration from") and "not finished" in second
    assert f"FVC {first.fvc_l:.2f} L" not in second
    sparse = np.ones(len(t), dtype=bool)
    near = (t >= marks[1] - 2.0) & (t <= marks[1] + 8.0)
    sparse[near] = np.isclose((t[near] - marks[1]) % 0.5, 0.0, atol=0.5 / RATE_HZ)  # blow 2 left out
    values = analyse_volume(t[sparse], w.volume_l[sparse], w.events, 40.0)
    assert len(values.forced.manoeuvres) == 2
    third = forced_feedback(values, 3, 40.0).text
    assert third.startswith("Blow 3: FVC") and f"FVC {values.forced.manoeuvres[1].fvc_l:.2f} L" in third


def test_a_blow_s_pef_is_given_only_where_the_maps_noise_allows():
    """The report's rule, per blow: a PEF read on maps a light cycle apart whose noise from map to map
    is over 5 % of it is not given, and the feedback says why instead of a number the noise made."""
    w = protocol_waveform(Subject(), "full", None, 1)
    every_cycle = np.arange(0, len(w.volume_l), 45)  # 45 ms: a map a light cycle at 110 frames/s
    t = every_cycle / RATE_HZ
    clean = analyse_volume(t, w.volume_l[every_cycle], w.events, 40.0, fitted=True)
    noisy = analyse_volume(t, w.volume_l[every_cycle] + np.random.default_rng(0).normal(0, 0.03, len(t)),
                           w.events, 40.0, fitted=True)
    given, refused = forced_feedback(clean, 1, 40.0).text, forced_feedback(noisy, 3, 40.0).text
    assert "L/s:" in given and "PEF not given" not in given
    last = noisy.forced.manoeuvres[-1]
    assert last.pef_noise_ratio > 0.05 and last.samples_step_s == pytest.approx(0.045, abs=0.001)
    assert f"PEF not given (the noise from map to map is {100 * last.pef_noise_ratio:.0f} % of the peak flow" in refused
    assert f"PEF {last.pef_lps:.1f} L/s" not in refused
