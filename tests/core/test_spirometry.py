"""Spirometry: the standard test waveforms, hand-computed curves, ATS/ERS 2019 criteria, GLI."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from core.analysis.reference import ReferenceUnavailable, reference
from core.sim.breathing import ForcedBlow, forced_expiration_curve
from core.analysis.spirometry import forced_values, grade_session, read_waveform, repeatability_tolerance_l


def _within(got, expected, relative, absolute):
    return abs(got - expected) <= max(relative * abs(expected), absolute)


def _waveform_rows(shared_data):
    folder = shared_data / "spirometry-waveforms"
    with open(folder / "reference_values.csv") as fh:
        return [(folder / row["file"], row) for row in csv.DictReader(fh)]


def test_every_standard_waveform(shared_data):
    failures = []
    rows = _waveform_rows(shared_data)
    assert len(rows) >= 61
    for path, row in rows:
        wave = read_waveform(path)
        v = forced_values(wave.volume_l, wave.rate_hz)
        checks = [("FVC", v.fvc_l, row["FVC_L"], 0.03, 0.050), ("FEV1", v.fev1_l, row["FEV1_L"], 0.03, 0.050),
                  ("FEV6", v.fev6_l, row["FEV6_L"], 0.03, 0.050),
                  ("FEF25-75", v.fef2575_lps, row["FEF2575_Lps"], 0.05, 0.200)]
        if row["group"] == "ISO26782":
            checks.append(("PEF", v.pef_lps, row["PEF_Lps"], 0.10, 0.30))
        for name, got, expected, rel, ab in checks:
            if expected == "":
                continue
            if got is None or not _within(got, float(expected), rel, ab):
                failures.append(f"{path.name} {name}: {got} against {expected}")
    assert not failures, failures


def test_waveform_file_errors(tmp_path):
    bad = tmp_path / "bad.wf"
    bad.write_text("[Header]\nType=VT\n[Data]\n0.0\n")
    with pytest.raises(ValueError, match="no Freq"):
        read_waveform(bad)
    bad.write_text("[Header]\nFreq=100\n[Data]\n" + "0.1\n" * 20 + "oops\n")
    with pytest.raises(ValueError, match="bad.wf:24: data sample is not a number"):
        read_waveform(bad)


def test_values_of_a_hand_computed_curve():
    """A linear rise of flow to 6 L/s, 0.2 s at 6 L/s, then exponential emptying: every value by hand."""
    rate = 1000.0
    t = np.arange(0, 8.0, 1 / rate)
    fvc, rise, hold = 5.0, 0.1, 0.2
    v_rise = 6.0 * rise / 2  # 0.3 L
    v_hold = v_rise + 6.0 * hold  # 1.5 L at t = 0.3 s
    tau = (fvc - v_hold) / 6.0  # flow stays continuous at 6 L/s
    v = np.where(t < rise, 6.0 * t**2 / (2 * rise), v_rise + 6.0 * (t - rise))
    v = np.where(t >= rise + hold, fvc - (fvc - v_hold) * np.exp(-(t - rise - hold) / tau), v)
    values = forced_values(v, rate)
    t0 = rise - v_rise / 6.0  # the tangent along the constant-flow segment reaches zero here: 0.05 s
    assert values.time_zero_s == pytest.approx(t0, abs=0.002)
    assert values.bev_l == pytest.approx(6.0 * t0**2 / (2 * rise), abs=0.002)
    expected_fev1 = fvc - (fvc - v_hold) * np.exp(-(t0 + 1.0 - rise - hold) / tau)
    assert values.fev1_l == pytest.approx(expected_fev1, abs=0.002)
    assert values.fev075_l == pytest.approx(fvc - (fvc - v_hold) * np.exp(-(t0 + 0.75 - rise - hold) / tau), abs=0.002)
    assert values.fvc_l == pytest.approx(fvc, abs=0.001)
    assert values.pef_lps == pytest.approx(6.0, rel=0.01)
    t25 = rise + (0.25 * fvc - v_rise) / 6.0  # 1.25 L: on the constant-flow segment
    t75 = rise + hold - tau * np.log((fvc - 0.75 * fvc) / (fvc - v_hold))
    assert values.fef2575_lps == pytest.approx(0.5 * fvc / (t75 - t25), rel=0.005)


def _blow(fvc=4.9, fev1=4.1, pef=9.6, **kwargs):
    return forced_values(forced_expiration_curve(fvc, fev1, pef, ForcedBlow(**kwargs), 6.0), 1000.0)


def test_ats_ers_2019_criteria_on_constructed_curves():
    slow = _blow(rise_time_s=0.4)
    assert not slow.bev_ok and not slow.fev1_acceptable
    early = _blow(stop_after_s=1.0)
    assert not early.eofe and early.fev1_acceptable and not early.fvc_acceptable
    cough = _blow(cough_at_s=0.4)
    assert cough.cough_in_first_second and not cough.fev1_acceptable
    good = _blow()
    assert good.bev_ok and good.eofe and not good.cough_in_first_second
    session = grade_session([_blow(), _blow(effort=0.98), _blow(effort=1.01)], age_years=30)
    assert session.fev1_grade == "A" and session.fvc_grade == "A" and session.grade == "A"
    assert session.acceptable_fvc == 3


def test_sensor_noise_after_an_early_stop_does_not_make_a_plateau():
    """A blow stopped after 2 s (a closed glottis), then flat with a sensor's noise (0.3 mL): the
    noise's largest value comes seconds after the stop; the exhalation still ends at the stop, so
    the last second is the blow's, not the flat, and it is no plateau."""
    exhaled = forced_expiration_curve(4.9, 4.1, 9.6, ForcedBlow(stop_after_s=2.0), 6.0)
    noisy = exhaled + 0.0003 * np.random.default_rng(3).standard_normal(len(exhaled))
    for curve in (exhaled, noisy):
        values = forced_values(curve, 1000.0)
        assert not values.eofe and values.fet_s < 2.0
        assert values.plateau_l > 0.1


def test_grades_and_reported_values():
    a, b = _blow(), _blow(fvc=4.5, fev1=3.7, pef=8.8)
    grade = grade_session([a, b])
    assert grade.fev1_grade in "CDE" and grade.fev1_repeatability_l > 0.150
    assert grade.fev1_l == pytest.approx(max(a.fev1_l, b.fev1_l))
    unusable = grade_session([_blow(rise_time_s=0.4)])
    assert unusable.fev1_grade == "F"
    one = grade_session([_blow()])
    assert one.grade == "E"
    early = grade_session([_blow(), _blow(stop_after_s=1.0, effort=1.0)])
    assert early.acceptable_fvc == 1 and early.acceptable_fev1 == 2  # FEV1 from an early stop still counts


def test_gli_cross_check():
    """30-year-old male, 175 cm (the issue's cross-check)."""
    r = {p: reference(p, "male", 30, 175, "gli-2012") for p in ("FEV1", "FVC")}
    assert r["FEV1"].predicted == pytest.approx(4.334, abs=0.0015) and r["FEV1"].lln == pytest.approx(3.460, abs=0.0015)
    assert r["FVC"].predicted == pytest.approx(5.245, abs=0.0015) and r["FVC"].lln == pytest.approx(4.224, abs=0.0015)
    g = {p: reference(p, "male", 30, 175, "gli-global") for p in ("FEV1", "FVC")}
    assert g["FEV1"].predicted == pytest.approx(4.065, abs=0.0015) and g["FEV1"].lln == pytest.approx(3.161, abs=0.0015)
    assert g["FVC"].predicted == pytest.approx(4.871, abs=0.0015) and g["FVC"].lln == pytest.approx(3.793, abs=0.0015)
    assert g["FEV1"].zscore(g["FEV1"].lln) == pytest.approx(-1.645, abs=0.001)
    assert g["FEV1"].percent(g["FEV1"].predicted) == pytest.approx(100.0)


def test_reference_refuses_what_it_cannot_answer():
    with pytest.raises(ReferenceUnavailable, match="ages 3-95"):
        reference("FEV1", "male", 120, 175)
    with pytest.raises(ReferenceUnavailable, match="no equation for FEF2575"):
        reference("FEF2575", "male", 30, 175, "gli-global")
    with pytest.raises(ReferenceUnavailable, match="sex"):
        reference("FEV1", "other", 30, 175)


def test_young_children_have_their_own_repeatability_tolerance():
    """ATS/ERS 2019: at 6 years or under, within 0.100 L or 10 % of the largest value."""
    assert repeatability_tolerance_l(1.2, age_years=5) == pytest.approx(0.120)
    assert repeatability_tolerance_l(0.8, age_years=5) == pytest.approx(0.100)
    assert repeatability_tolerance_l(0.8, age_years=30) == pytest.approx(0.150)
    # two small blows 0.120 L apart: within an adult's 0.150 L, outside a child's 0.100 L (10 % is 0.080)
    blows = [_blow(fvc=0.80, fev1=0.74, pef=2.0), _blow(fvc=0.68, fev1=0.62, pef=1.9)]
    child, adult = grade_session(blows, age_years=5), grade_session(blows, age_years=30)
    assert child.fvc_repeatability_l == pytest.approx(0.120, abs=0.01)
    assert adult.fvc_grade == "B" and child.fvc_grade == "C"


def test_a_cough_that_only_slows_the_flow_is_caught():
    """Flow halved for 60 ms at 0.4 s, then back: no stop, but a rebound no good blow has."""
    volume = forced_expiration_curve(4.9, 4.1, 9.6, ForcedBlow(), 6.0)
    flow = np.gradient(volume, 1e-3)

    def with_dent(start: int) -> np.ndarray:
        dented = flow.copy()
        dented[start:start + 60] *= 0.5
        return np.concatenate([[0.0], np.cumsum(0.5 * (dented[1:] + dented[:-1])) * 1e-3])

    blow = forced_values(with_dent(400), 1000.0)
    assert blow.cough_in_first_second and not blow.fev1_acceptable
    assert not _blow().cough_in_first_second
    assert not forced_values(with_dent(2400), 1000.0).cough_in_first_second  # past the first second


def test_a_peak_flow_is_not_given_from_samples_too_far_apart():
    """FVC and FEV1 from a volume sampled every 91 ms (every other light cycle), but no PEF: the reason
    instead. Every 45 ms (each cycle) the PEF is there."""
    from core.analysis.values import analyse_volume

    events = [(1.0, "forced-start"), (9.0, "maneuver-end")]
    for step, given in ((1.0 / 11.0, False), (1.0 / 22.0, True)):
        t = np.arange(0.0, 10.0, step)
        volume = -4.0 * (1.0 - np.exp(-np.clip(t - 2.0, 0.0, None) / 0.5))
        values = analyse_volume(t, volume, events)
        parameters = values.parameters()
        assert parameters["FVC_l"] == pytest.approx(4.0, abs=0.05)
        assert ("PEF_lps" in parameters) == given
        assert any("PEF not given" in p for p in values.problems) != given
