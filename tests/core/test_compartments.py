"""Compartment shares and the thoraco-abdominal phase angle against curves built with a known delay."""

from __future__ import annotations

import numpy as np
import pytest

from core.volume.compartments import compartment_shares, phase_angle_deg

PERIOD_S = 4.0


def _breathing(delay_s: float, seconds: float = 40.0):
    t = np.arange(0.0, seconds, 0.02)
    drift = 0.01 * t  # a slow drift, not breathing
    chest = 0.3 * np.sin(2 * np.pi * t / PERIOD_S) + drift
    abdomen = 0.2 * np.sin(2 * np.pi * (t - delay_s) / PERIOD_S) + drift
    return t, chest, abdomen


@pytest.mark.parametrize("delay_s, expected_deg", [(0.0, 0.0), (0.2, 18.0), (-0.3, -27.0), (2.0, 180.0)])
def test_phase_angle_is_the_abdomens_delay_over_the_breath(delay_s, expected_deg):
    t, chest, abdomen = _breathing(delay_s)
    angle = phase_angle_deg(t, chest, abdomen, [(2.0, 38.0)], PERIOD_S)
    assert abs(angle) == pytest.approx(abs(expected_deg), abs=1.5)
    if abs(expected_deg) < 180:
        assert np.sign(angle) == np.sign(expected_deg) or expected_deg == 0


def test_shares_of_in_phase_compartments_follow_their_amplitudes():
    t, chest, abdomen = _breathing(0.0)
    shares = compartment_shares(t, {"chest": chest, "abdomen": abdomen}, [(2.0, 20.0), (22.0, 38.0)])
    assert shares["chest"] == pytest.approx(0.6, abs=0.01) and shares["abdomen"] == pytest.approx(0.4, abs=0.01)


def test_no_quiet_breathing_gives_no_angle():
    t, chest, abdomen = _breathing(0.1)
    assert np.isnan(phase_angle_deg(t, chest, abdomen, [], PERIOD_S))
    assert compartment_shares(t, {"chest": chest}, [(100.0, 120.0)]) == {}
