"""The tidal volumes of a calibrated optical curve read with the subject's quiet-breathing gain."""

import numpy as np
import pytest

from core.analysis.quiet_breathing import MAX_QUIET_BREATHING_FACTOR, quiet_breathing_gain, with_quiet_breathing_gain
from core.analysis.values import analyse_volume
from core.sim.breathing import RATE_HZ, Subject, protocol_waveform
from core.volume.subject_calibration import MOUTHPIECE_OFF


def _clinical(quiet_share: float, noise_l: float = 0.0, seed: int = 3):
    """The clinical protocol's lung volume (the flow sensor's, up to mouthpiece-off) and an optical curve
    one map a light cycle that shows quiet breathing `quiet_share` times as large as the slow VC and blows
    (each quiet breath's excursion above its end-expiratory level scaled), with white noise."""
    waveform = protocol_waveform(Subject(), "clinical", None, seed)
    t = np.arange(len(waveform.volume_l)) / RATE_HZ
    v = waveform.volume_l
    events = sorted(waveform.events)
    manoeuvres = [(a, next(b for b, lb in events if b > a and lb == "maneuver-end"))
                  for a, label in events if label in ("vc-start", "forced-start")]
    in_manoeuvre = np.zeros(len(t), dtype=bool)
    for a, b in manoeuvres:
        in_manoeuvre |= (t >= a) & (t <= b + 3.0)
    level = np.min(v[~in_manoeuvre])
    shown = np.where(in_manoeuvre, v, level + quiet_share * (v - level))
    maps_t = np.arange(0, t[-1], 1 / 22.0)
    rng = np.random.default_rng(seed)
    optical = np.interp(maps_t, t, shown) + rng.normal(0, noise_l, len(maps_t))
    off = next(a for a, label in events if label == MOUTHPIECE_OFF)
    flow = t <= off
    return (t[flow][::10], v[flow][::10]), (maps_t, optical), (t, v), events


def test_the_tidal_volume_is_read_with_the_gain_of_the_calibrations_quiet_breathing():
    """A curve whose quiet breaths read 1.17 times their litres while its slow VC reads true (mesh 101002's
    calibrated curve: 1.17 and 0.98): its TV, 17 % high as read, comes within 1 % of the lungs' with the
    gain the flow sensor gives over the calibration's quiet breathing; the VC and the times do not move."""
    flow, optical, lungs, events = _clinical(1.17)
    truth = analyse_volume(*lungs, events)
    read = analyse_volume(*optical, events, fitted=True)
    assert read.tidal.tidal_volume_l == pytest.approx(1.17 * truth.tidal.tidal_volume_l, rel=0.02)
    gain = quiet_breathing_gain(*flow, *optical, events)
    assert gain is not None and gain.factor == pytest.approx(1 / 1.17, rel=0.01) and gain.breaths >= 4
    given = with_quiet_breathing_gain(read, gain)
    assert given.tidal.tidal_volume_l == pytest.approx(truth.tidal.tidal_volume_l, rel=0.01)
    assert given.tidal.minute_ventilation_lpm == pytest.approx(truth.tidal.minute_ventilation_lpm, rel=0.02)
    assert given.tidal.respiratory_rate_bpm == read.tidal.respiratory_rate_bpm
    assert given.vital_capacity.vc_l == read.vital_capacity.vc_l
    assert any(f"quiet-breathing gain (x{gain.factor:.2f}, from {gain.breaths} breaths" in p for p in given.problems)


def test_noise_that_swells_the_read_tidal_volume_is_taken_out_with_it():
    """25 mL of noise a map lets the analysis read a 0.5 L breath larger; the same reading over the
    calibration's breaths puts the gain where the later breaths read true within 5 %."""
    flow, optical, lungs, events = _clinical(1.0, noise_l=0.025, seed=5)
    truth = analyse_volume(*lungs, events).tidal.tidal_volume_l
    read = analyse_volume(*optical, events, fitted=True)
    given = with_quiet_breathing_gain(read, quiet_breathing_gain(*flow, *optical, events))
    assert abs(given.tidal.tidal_volume_l / truth - 1) < 0.05


def test_a_curve_that_does_not_measure_quiet_breathing_gives_no_tidal_values():
    """Quiet breaths read twice their litres during the calibration: the tidal values are withheld with
    the reason, the rest given."""
    flow, optical, lungs, events = _clinical(2.0)
    gain = quiet_breathing_gain(*flow, *optical, events)
    assert gain.factor < 1 / MAX_QUIET_BREATHING_FACTOR and not gain.plausible
    given = with_quiet_breathing_gain(analyse_volume(*optical, events, fitted=True), gain)
    assert given.tidal is None and given.vital_capacity is not None
    assert any("tidal values not given" in p and "2.00 times" in p for p in given.problems)


def test_no_gain_without_a_calibration_through_the_flow_sensor():
    """A flow sensor over 10 s only (no calibration segment) or without two breaths: no gain, values unchanged."""
    flow, optical, lungs, events = _clinical(1.17)
    short = flow[0] <= 10.0
    assert quiet_breathing_gain(flow[0][short], flow[1][short], *optical, events) is None
    assert quiet_breathing_gain(np.zeros(0), np.zeros(0), *optical, events) is None
    read = analyse_volume(*optical, events, fitted=True)
    assert with_quiet_breathing_gain(read, None) is read
