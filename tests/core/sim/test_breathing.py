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


def test_blows_follow_a_standard_waveform_scaled_to_the_subject(shared_data):
    from core.sim.breathing import standard_curve
    from core.analysis.spirometry import forced_values, read_waveform

    failures = []
    for path in sorted((shared_data / "spirometry-waveforms" / "ISO26782").glob("*.wf")):
        standard = read_waveform(path)
        expected = forced_values(standard.volume_l, standard.rate_hz)
        curve = standard_curve(standard.volume_l, standard.rate_hz)
        subject = Subject(sex="female", age_years=11, height_cm=145)  # a child: the standard shrinks to her lungs
        wave = protocol_waveform(subject, "forced", None, 3, [ForcedBlow(standard=curve)])
        start = next(t for t, label in wave.events if label == "forced-start")
        end = next(t for t, label in wave.events if label == "maneuver-end")
        exhaled = wave.at(start) - wave.volume_l[int(start * RATE_HZ): int(end * RATE_HZ)]
        got = forced_values(exhaled, RATE_HZ)
        if abs(got.fvc_l - subject.fvc) > 0.005 * subject.fvc:
            failures.append(f"{path.name} FVC {got.fvc_l:.3f} against the subject's {subject.fvc:.3f}")
        if abs(got.fev1_l / got.fvc_l - expected.fev1_l / expected.fvc_l) > 0.01:
            failures.append(f"{path.name} FEV1/FVC {got.fev1_l / got.fvc_l:.3f} against the standard's "
                            f"{expected.fev1_l / expected.fvc_l:.3f}")
    assert not failures, failures


def test_irregular_breathing_varies_and_sighs():
    from scipy.signal import find_peaks

    from core.sim.breathing import tidal

    subject = Subject(rate_variability=0.15, sigh_every=6, tidal_volume_l=0.5)
    volume = tidal(subject, 240.0, np.random.default_rng(1))
    peaks, _ = find_peaks(volume, distance=int(1.5 * RATE_HZ), prominence=0.1)
    sizes, periods = volume[peaks], np.diff(peaks) / RATE_HZ
    assert sizes.max() > 1.8 * np.median(sizes)  # sighs
    assert 0.1 < periods.std() / periods.mean() < 0.4  # an irregular rate
    regular = tidal(Subject(tidal_volume_l=0.5), 240.0, np.random.default_rng(1))
    assert regular.max() < 1.5 * 0.5


@pytest.mark.parametrize("rate_bpm", [10.0, 14.0, 20.0])
def test_the_clinical_protocol_breathes_as_many_quiet_breaths_as_the_guided_session_asks(rate_bpm):
    """Once the mouthpiece is off, the guided session's tidal page goes on until MIN_TIDAL_BREATHS
    breaths are read; the simulated clinical protocol gives the analysis as many (10 s alone held 2-3
    at 12-18 /min)."""
    from core.analysis.protocol_feedback import MIN_TIDAL_BREATHS
    from core.analysis.values import analyse_volume

    wave = protocol_waveform(Subject(respiratory_rate_bpm=rate_bpm), "clinical", None, seed=4)
    off = next(t for t, label in wave.events if label == "mouthpiece-off")
    t = np.arange(len(wave.volume_l)) / RATE_HZ
    after = t >= off
    values = analyse_volume(t[after], wave.volume_l[after], [e for e in wave.events if e[0] >= off])
    assert values.tidal.breaths >= MIN_TIDAL_BREATHS
    assert values.tidal.respiratory_rate_bpm == pytest.approx(rate_bpm, rel=0.15)
