"""The thesis' calibrations: the flow sensor (eq. 5.4) and the volume regression (eqs 5.1-5.3).

Flow: steady flows from a reference flowmeter against the mean ADC reading of each,
flow (L/s) = C1 * adc + C0 by least squares (thesis: C1 = 0.002085, C0 = -4.007).
Volume: phi = (X^T X)^-1 X^T pv with X = [gradient volume, number of valid pixels, distance] per
sample and pv the flow-sensor volume, fitted on training sessions; the optical volume is then
X phi. Kept beside the metric volume as the thesis' method and a comparison.

Profiles are JSON files with their provenance (created, sessions used, fit quality), checked on
load: a wrong field or an impossible fit is refused with a message that names it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.io.jsonfile import load_checked, read_json_object
from core.io.outputs import write_text_atomic

FLOW_FORMAT = "photopft-flow-calibration"
VOLUME_FORMAT = "photopft-volume-calibration"


class CalibrationProfileError(ValueError):
    """A calibration that cannot be trusted or read; the message names the field or the fit."""


@dataclass
class FlowCalibration:
    gain_lps: float  # C1, L/s per count
    offset_lps: float  # C0, L/s
    r_squared: float
    residuals_lps: list[float]
    range_lps: tuple[float, float]
    points: int
    created: str = ""
    sources: list[str] = field(default_factory=list)

    def flow_lps(self, adc: np.ndarray) -> np.ndarray:
        return self.gain_lps * np.asarray(adc, dtype=float) + self.offset_lps

    def to_json(self) -> dict[str, Any]:
        return {"format": FLOW_FORMAT, "format_version": 1, "created": self.created, "sources": self.sources,
                "gain_lps": self.gain_lps, "offset_lps": self.offset_lps, "r_squared": self.r_squared,
                "residuals_lps": self.residuals_lps, "range_lps": list(self.range_lps), "points": self.points}


def fit_flow(adc_means: np.ndarray, reference_lps: np.ndarray, min_r_squared: float = 0.995,
             created: str = "", sources: list[str] | None = None) -> FlowCalibration:
    """Least-squares line through (mean ADC, reference flow) pairs of steady flows (eq. 5.4)."""
    adc = np.asarray(adc_means, dtype=float)
    flow = np.asarray(reference_lps, dtype=float)
    if adc.shape != flow.shape or adc.ndim != 1:
        raise CalibrationProfileError("ADC means and reference flows must be two lists of the same length")
    if len(adc) < 3:
        raise CalibrationProfileError(f"a flow calibration needs three or more steady flows, got {len(adc)}")
    if not (np.all(np.isfinite(adc)) and np.all(np.isfinite(flow))):
        raise CalibrationProfileError("ADC means and reference flows must be finite numbers")
    if np.ptp(flow) < 0.5:
        raise CalibrationProfileError(f"the reference flows span {np.ptp(flow):.2f} L/s: cover the working range "
                                      "(for example -4 to +4 L/s, and 0)")
    gain, offset = np.polyfit(adc, flow, 1)
    predicted = gain * adc + offset
    residuals = flow - predicted
    total = float(np.sum((flow - flow.mean()) ** 2))
    r_squared = 1.0 - float(np.sum(residuals**2)) / total
    if not gain > 0:
        raise CalibrationProfileError(f"the fitted gain {gain:.6g} L/s per count is not positive: are the "
                                      "reference flows and readings paired in the same order and sign?")
    if r_squared < min_r_squared:
        raise CalibrationProfileError(f"the flows do not lie on a line: R^2 = {r_squared:.4f} (below "
                                      f"{min_r_squared}); largest residual {np.max(np.abs(residuals)):.3f} L/s")
    return FlowCalibration(float(gain), float(offset), r_squared, [round(float(r), 6) for r in residuals],
                           (float(flow.min()), float(flow.max())), len(adc), created, sources or [])


@dataclass
class VolumeCalibration:
    phi: np.ndarray  # coefficients of [gradient volume, pixels, distance]
    r_squared: float
    correlation: float
    samples: int
    created: str = ""
    sessions: list[str] = field(default_factory=list)

    def volume_l(self, features: np.ndarray) -> np.ndarray:
        return np.asarray(features, dtype=float) @ self.phi

    def to_json(self) -> dict[str, Any]:
        return {"format": VOLUME_FORMAT, "format_version": 1, "created": self.created, "sessions": self.sessions,
                "features": ["gradient_volume", "valid_pixels", "distance_mm"], "phi": self.phi.tolist(),
                "r_squared": self.r_squared, "correlation": self.correlation, "samples": self.samples}


def regression_features(read, heads: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """(the first head's map times, the regression's features at them): X = [gradient volume summed
    over the heads, valid pixels summed, mean distance] (eq. 5.1). `read(head, name)` gives a head's
    per-map series; the same features for training (calibrate volume) and prediction (process)."""
    t = read(heads[0], "timestamp_ns")

    def at(name: str) -> list[np.ndarray]:
        return [np.interp(t, read(h, "timestamp_ns"), read(h, name)) for h in heads]

    return t, np.column_stack([sum(at("gradient_volume")), sum(at("valid_pixels")), np.mean(at("distance_mm"), axis=0)])


def fit_volume(features: np.ndarray, volume_l: np.ndarray, created: str = "",
               sessions: list[str] | None = None, min_correlation: float = 0.8) -> VolumeCalibration:
    """phi = (X^T X)^-1 X^T pv (eq. 5.3); X (N, 3) = [gradient volume, valid pixels, distance]."""
    x = np.asarray(features, dtype=float)
    pv = np.asarray(volume_l, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) != len(pv):
        raise CalibrationProfileError("the volume regression needs N x 3 features and N volumes")
    keep = np.all(np.isfinite(x), axis=1) & np.isfinite(pv)
    x, pv = x[keep], pv[keep]
    if len(pv) < 10:
        raise CalibrationProfileError(f"too few samples for the volume regression: {len(pv)}")
    if np.linalg.matrix_rank(x) < 3:
        raise CalibrationProfileError("the features do not vary independently (rank < 3): train on sessions with "
                                      "breathing, at more than one distance")
    phi = np.linalg.solve(x.T @ x, x.T @ pv)
    fitted = x @ phi
    r_squared = 1.0 - float(np.sum((pv - fitted) ** 2) / np.sum((pv - pv.mean()) ** 2))
    correlation = float(np.corrcoef(fitted, pv)[0, 1])
    if correlation < min_correlation:
        raise CalibrationProfileError(f"the regression explains too little: r = {correlation:.3f} "
                                      f"(below {min_correlation})")
    return VolumeCalibration(phi, r_squared, correlation, len(pv), created, sessions or [])


def save_profile(profile: FlowCalibration | VolumeCalibration, path: str | os.PathLike) -> None:
    write_text_atomic(path, json.dumps(profile.to_json(), indent=2) + "\n")


def _number(data: dict, key: str, path: Path) -> float:
    if key not in data:
        raise CalibrationProfileError(f"{path}: missing field {key!r}")
    value = data[key]
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not np.isfinite(value):
        raise CalibrationProfileError(f"{path}: field {key!r} must be a finite number, found {value!r}")
    return float(value)


def load_profile(path: str | os.PathLike) -> FlowCalibration | VolumeCalibration:
    return load_checked(Path(path), _load_profile, CalibrationProfileError)


def _load_profile(path: Path) -> FlowCalibration | VolumeCalibration:
    data = read_json_object(path, CalibrationProfileError, "calibration profile")
    kind = data.get("format")
    if kind not in (FLOW_FORMAT, VOLUME_FORMAT):
        raise CalibrationProfileError(f"{path}: 'format' must be {FLOW_FORMAT!r} or {VOLUME_FORMAT!r}, found {kind!r}")
    if data.get("format_version") != 1:
        raise CalibrationProfileError(f"{path}: format_version {data.get('format_version')!r}, this reader knows 1")
    if kind == FLOW_FORMAT:
        gain, offset = _number(data, "gain_lps", path), _number(data, "offset_lps", path)
        r2 = _number(data, "r_squared", path)
        if not gain > 0:
            raise CalibrationProfileError(f"{path}: gain_lps {gain} must be positive")
        if not 0.0 <= r2 <= 1.0:
            raise CalibrationProfileError(f"{path}: r_squared {r2} is impossible")
        span = data.get("range_lps", [0.0, 0.0])
        return FlowCalibration(gain, offset, r2, list(data.get("residuals_lps", [])), (float(span[0]), float(span[1])),
                               int(data.get("points", 0)), str(data.get("created", "")), list(data.get("sources", [])))
    phi = np.asarray(data.get("phi", []), dtype=float)
    if phi.shape != (3,) or not np.all(np.isfinite(phi)):
        raise CalibrationProfileError(f"{path}: field 'phi' must be three finite numbers, found {data.get('phi')!r}")
    r = _number(data, "correlation", path)
    if not -1.0 <= r <= 1.0:
        raise CalibrationProfileError(f"{path}: correlation {r} is impossible")
    return VolumeCalibration(phi, _number(data, "r_squared", path), r, int(data.get("samples", 0)),
                             str(data.get("created", "")), list(data.get("sessions", [])))
