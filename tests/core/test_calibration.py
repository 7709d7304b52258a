"""The thesis' flow and volume calibrations: fits on known data, refusals, profiles read back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from core.calibration.spirometer import (CalibrationProfileError, FlowCalibration, fit_flow, fit_volume, load_profile,
                              save_profile)


def test_flow_fit_recovers_the_thesis_sensor(tmp_path):
    rng = np.random.default_rng(0)
    flows = np.array([-4.0, -2.0, -1.0, 0.0, 1.0, 2.0, 4.0])
    adc = (flows + 4.007) / 0.002085 + rng.normal(0, 0.3, len(flows))
    fit = fit_flow(adc, flows)
    assert fit.gain_lps == pytest.approx(0.002085, rel=1e-3) and fit.offset_lps == pytest.approx(-4.007, abs=2e-3)
    assert fit.r_squared > 0.9999 and fit.range_lps == (-4.0, 4.0) and len(fit.residuals_lps) == 7
    save_profile(fit, tmp_path / "flow.json")
    again = load_profile(tmp_path / "flow.json")
    assert isinstance(again, FlowCalibration) and again.gain_lps == pytest.approx(fit.gain_lps)


@pytest.mark.parametrize("adc, flows, message", [
    ([1, 2], [0, 1], "three or more"),
    ([100, 200, 300], [0.0, 0.1, 0.2], "span"),
    ([300, 200, 100], [-2.0, 0.0, 2.0], "not positive"),
    ([100, 200, 300, 400], [-2.0, 2.0, -1.0, 1.0], "do not lie on a line"),
])
def test_impossible_flow_fits_are_refused(adc, flows, message):
    with pytest.raises(CalibrationProfileError, match=message):
        fit_flow(adc, flows)


def test_volume_regression_eq_5_3():
    rng = np.random.default_rng(1)
    n = 400
    gv = 0.8 + 0.05 * np.sin(np.linspace(0, 20, n))
    pixels = 45000 + rng.normal(0, 300, n)
    distance = 2000 + rng.normal(0, 20, n)
    phi = np.array([30.0, -2e-4, 1e-3])
    x = np.column_stack([gv, pixels, distance])
    fit = fit_volume(x, x @ phi + rng.normal(0, 0.01, n))
    np.testing.assert_allclose(fit.phi, phi, rtol=0.05)
    assert fit.correlation > 0.99
    with pytest.raises(CalibrationProfileError, match="rank"):
        fit_volume(np.column_stack([gv, gv, gv]), gv)


def test_profiles_with_wrong_fields_are_refused(tmp_path):
    path = tmp_path / "p.json"
    for content, message in (({"format": "photopft-flow-calibration", "format_version": 1, "gain_lps": -1.0,
                               "offset_lps": 0.0, "r_squared": 0.99}, "must be positive"),
                             ({"format": "photopft-flow-calibration", "format_version": 1, "gain_lps": 0.002,
                               "offset_lps": "x", "r_squared": 0.99}, "'offset_lps' must be a finite number"),
                             ({"format": "photopft-volume-calibration", "format_version": 1, "phi": [1, 2],
                               "r_squared": 0.9, "correlation": 0.9}, "'phi' must be three"),
                             ({"format": "something"}, "'format' must be")):
        path.write_text(json.dumps(content))
        with pytest.raises(CalibrationProfileError, match=message):
            load_profile(path)
