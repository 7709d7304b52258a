"""The 3 L syringe check (core/calibration/syringe.py): strokes found in and out, each within 3 %, and a
flow line 5 % off found out."""

from __future__ import annotations

import numpy as np
import pytest

from app.gui.syringe_check import SimulatedSyringe, check_from_samples
from core.calibration.syringe import SyringeCheck, Stroke, syringe_strokes


def test_three_strokes_in_and_out_through_the_simulated_sensor_pass_with_the_true_line():
    syringe = SimulatedSyringe()
    adc, stamps = syringe.stop()
    check = check_from_samples(adc, stamps, syringe.model.gain_lps, syringe.model.offset_lps)
    assert len(check.strokes) == 6 and check.passed, check.verdict()
    assert [s.volume_l > 0 for s in check.strokes] == [True, False] * 3
    assert all(abs(abs(s.volume_l) - 3.0) < 0.03 for s in check.strokes)
    assert check.verdict().startswith("passed: 6 strokes")


def test_a_flow_line_five_percent_off_fails():
    syringe = SimulatedSyringe()
    adc, stamps = syringe.stop()
    check = check_from_samples(adc, stamps, 1.05 * syringe.model.gain_lps, 1.05 * syringe.model.offset_lps)
    assert not check.passed and "FAILED" in check.verdict()
    assert all(0.04 < s.error() < 0.06 for s in check.strokes)


def test_too_few_strokes_is_no_verdict():
    t = np.arange(0, 4, 0.001)
    flow = np.where(t < 2, np.sin(np.pi * t / 2) * np.pi / 4 * 3.0, 0.0)
    strokes = syringe_strokes(t, flow)
    assert len(strokes) == 1 and strokes[0].volume_l == pytest.approx(3.0, abs=0.01)
    check = SyringeCheck(strokes)
    assert not check.passed and "3 needed" in check.verdict()
    assert SyringeCheck([Stroke(0, 1, 3.2, 5.0)] * 3).verdict().startswith("FAILED")
