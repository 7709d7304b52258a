"""Breathing waveforms: manoeuvres hit the values they were asked for."""

from __future__ import annotations

import numpy as np
import pytest

from core.sim.breathing import RATE_HZ, ForcedBlow, Subject, Sway, forced_expiration_curve, protocol_waveform


def _bet_fev1(volume):
    """FEV1 at back-extrapolated time zero, computed plainly here (tangent at peak flow)."""
    flow = np.gradient(volume) * RATE_HZ
    k = int(np.argmax(flow))
    t = np.arange(len(volume)) / RATE_HZ
    t0 = t[k] - volume[k] / flow[k]
    return float(np.interp(t0 + 1.0, t, volume)), float(np.interp(t0, t, volume))


@pytest.mark.parametrize("fvc, fev1, pef", [(4.9, 4.1, 9.6), (3.2, 1.6, 4.0), (2.5, 2.2, 6.5)])
def test_forced_curve_delivers_fvc_fev1_pef(fvc, fev1, pef):
    v = forced_expiration_curve(fvc, fev1, pef, ForcedBlow(), duration_s=6.0 if fev1 / fvc >= 0.7 else 10.0)
    flow = np.gradient(v) * RATE_HZ
    assert v[-1] == pytest.approx(fvc, abs=0.03)
    assert v[-1] - v[-int(RATE_HZ)] < 0.025  # a plateau in the last second
    assert _bet_fev1(v)[0] == pytest.approx(fev1, abs=0.02)
    assert flow.max() == pytest.approx(pef, rel=0.01)


def test_imperfect_blows():
    good = forced_expiration_curve(4.9, 4.1, 9.6, ForcedBlow())
    slow = forced_expiration_curve(4.9, 4.1, 9.6, ForcedBlow(rise_time_s=0.4))
    early = forced_expiration_curve(4.9, 4.1, 9.6, ForcedBlow(stop_after_s=1.2))
    cough = forced_expiration_curve(4.9, 4.1, 9.6, ForcedBlow(cough_at_s=0.4))
    assert _bet_fev1(slow)[1] > max(0.05 * 4.9, 0.100) > _bet_fev1(good)[1]  # back-extrapolated volume
    assert early[-1] < 4.9 - 0.3 and np.all(np.diff(early[int(1.2 * RATE_HZ):]) == 0)
    flow = np.gradient(cough) * RATE_HZ
    assert np.all(np.abs(flow[int(0.41 * RATE_HZ):int(0.47 * RATE_HZ)]) < 1e-9)


def test_full_protocol_levels_and_events():
    subject = Subject()
    w = protocol_waveform(subject, "full", None, seed=0)
    labels = [label for _, label in w.events]
    assert labels.count("forced-start") == 3 and "vc-start" in labels and labels[0] == "tidal-start"
    assert w.volume_l.max() == pytest.approx(subject.inspiratory_capacity, rel=1e-3)
    assert w.volume_l.min() < -subject.expiratory_reserve + 0.01
    assert 50 < w.duration_s < 60  # three blows fit the README's 60 s session
    assert protocol_waveform(subject, "full", 20.0, seed=0).duration_s == pytest.approx(20.0)


def test_sway_bounds():
    s = Sway(50.0, 15.0, 3.0, seed=2).at(np.linspace(0, 120, 5000))
    assert np.abs(s[:, 2]).max() <= 50.0 and np.abs(s[:, 2]).max() > 20.0
    assert np.abs(s[:, 0]).max() <= 15.0


def test_subject_validation():
    with pytest.raises(ValueError, match="height_cm"):
        Subject(height_cm=20)
