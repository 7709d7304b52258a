"""The LEDs' drift followed through a session (core/reconstruction/drift.py)."""

import numpy as np

from core.reconstruction.drift import light_gains_over_time


def test_a_drift_is_followed_through_noise_and_jumps_and_the_calibration_kept_at_the_median():
    """Readings every 0.5 s over 60 s with 0.4 % of noise and a few wild ones (an arm, a step): a light
    warming by 3.6 % and one by 1 % on a sine are followed within 0.25 %; a light that is 5 % off the
    calibration throughout reads 1 (what it is at the median stays the calibration's)."""
    t = np.arange(0.0, 60.0, 0.5)
    rng = np.random.default_rng(0)
    true = np.c_[1.0 + 0.0006 * t, 1.0 + 0.01 * np.sin(t / 20.0), np.full_like(t, 1.05), np.ones_like(t)]
    readings = true * (1.0 + 0.004 * rng.standard_normal(true.shape))
    readings[[10, 50, 90], 0] = [1.3, 0.7, 1.2]
    readings[::7, 1] = np.nan
    followed = light_gains_over_time(t, readings, t)
    expected = true / np.median(true, axis=0)
    assert np.abs(followed - expected).max() < 0.0025
    np.testing.assert_allclose(np.median(followed, axis=0), 1.0, atol=0.001)
    assert np.abs(followed[:, 2] - 1.0).max() < 0.0025
    at = np.array([0.25, 30.2, 59.9])  # between and beside the readings
    np.testing.assert_allclose(light_gains_over_time(t, readings, at)[:, 0], expected[[0, 60, 119], 0], atol=0.0025)


def test_too_few_readings_leave_the_intensities_as_calibrated():
    t = np.arange(4.0)
    readings = np.full((4, 4), np.nan)
    readings[:, 3] = 1.0
    np.testing.assert_array_equal(light_gains_over_time(t, readings, np.arange(10.0)), np.ones((10, 4)))
