"""The subject's own calibration: litres from the optical signals through the flow sensor.

Two heads cannot see the trunk's flanks, and how much of a breath they move differs from body to
body, so no scale fitted to one body family holds on another. As respiratory inductance
plethysmographs do, the session opens with the subject breathing through the flow sensor while both
heads run (quiet breathing and one slow VC); the flow sensor's volume (BTPS, drift removed) is
fitted by least squares on the regional optical signals (each head's chest and abdomen) over that
segment, and the cameras alone give the litres once the mouthpiece is off.

The fit's trend and offset are nuisances (the two signals' slow drifts and arbitrary zeros); only
the regional gains carry over to the rest of the session. How well they carry is measured on the
segment itself: each of its parts is predicted from a fit on the others (`expected_error`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import lsq_linear

from core.volume.maps import REGIONS

MOUTHPIECE_OFF = "mouthpiece-off"
# a calibration whose residual is over this share of the flow sensor's range over the segment is refused
MAX_RESIDUAL_SHARE = 0.05
# a regional gain over this is no surface the cameras see moving with the breath: the fit leans on noise
MAX_REGION_GAIN = 6.0
MIN_SEGMENT_S = 20.0  # quiet breathing and a slow VC take longer; less tells too little
MIN_RANGE_L = 1.0  # the segment must swing this much (a slow VC does; quiet breathing alone does not)
LEAVE_OUT_PARTS = 5  # the segment's parts each predicted from a fit on the others
CHEST = ("upper left", "upper right")
ABDOMEN = ("lower left", "lower right")


def regional_signals(head_regions: dict[str, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Each head's chest and abdomen (litres on the maps' times): `<head> chest`, `<head> abdomen`."""
    out = {}
    for name, quadrants in head_regions.items():
        if set(REGIONS) <= set(quadrants):
            out[f"{name} chest"] = sum(np.asarray(quadrants[r], dtype=float) for r in CHEST)
            out[f"{name} abdomen"] = sum(np.asarray(quadrants[r], dtype=float) for r in ABDOMEN)
    return out


def calibration_segment(events: list[tuple[float, str]], flow_end_s: float) -> tuple[float, float] | None:
    """(start, end) in seconds of the session's calibration through the flow sensor: up to
    `mouthpiece-off`; without it (a flow sensor over the whole session), up to the end of the first
    slow VC. None where the flow sensor does not cover one."""
    ordered = sorted(events)
    off = next((t for t, label in ordered if label == MOUTHPIECE_OFF), None)
    if off is None:
        start = next((t for t, label in ordered if label == "vc-start"), None)
        if start is None:
            return None
        off = next((t for t, label in ordered if label == "maneuver-end" and t > start), None)
        if off is None:
            return None
    end = min(off, flow_end_s)
    return (0.0, end) if end >= MIN_SEGMENT_S else None


@dataclass
class SubjectCalibration:
    """Litres = sum of gains x regional signals. residual_l: rms of the fit over the segment;
    range_l: the flow sensor's over it; expected_error: the rms of the parts' relative excursion errors
    predicted from fits on the other parts (a share, 0.02 = 2 %)."""

    gains: dict[str, float]
    segment_s: tuple[float, float]
    residual_l: float
    range_l: float
    expected_error: float
    refused: str | None = None
    samples: int = 0
    extra: dict = field(default_factory=dict)  # fit_t_s, fit_l: the fitted curve over the segment, to show

    def volume_l(self, signals: dict[str, np.ndarray]) -> np.ndarray:
        return sum(g * np.asarray(signals[name], dtype=float) for name, g in self.gains.items())

    def label(self) -> str:
        return f"optical, calibrated on the subject (residual {1000 * self.residual_l:.0f} mL)"


def _design(t_s: np.ndarray, signals: np.ndarray) -> np.ndarray:
    centred = t_s - t_s.mean()
    return np.column_stack([signals, np.ones_like(t_s), centred])


def _fit(t_s: np.ndarray, signals: np.ndarray, flow_l: np.ndarray) -> np.ndarray:
    """Gains (non-negative) then offset and trend, least squares."""
    k = signals.shape[1]
    lower = np.r_[np.zeros(k), -np.inf, -np.inf]
    upper = np.full(k + 2, np.inf)
    return lsq_linear(_design(t_s, signals), flow_l, bounds=(lower, upper), method="bvls").x


def fit_subject_calibration(map_t_s: np.ndarray, signals: dict[str, np.ndarray], flow_t_s: np.ndarray,
                            flow_volume_l: np.ndarray, segment_s: tuple[float, float]) -> SubjectCalibration:
    """The least squares of the flow sensor's volume on the regional signals over `segment_s`
    (times in seconds on one clock). Refused (the reason in `refused`) where the fit is poor."""
    names = list(signals)
    t = np.asarray(map_t_s, dtype=float)
    x = np.column_stack([np.asarray(signals[n], dtype=float) for n in names]) if names else np.zeros((len(t), 0))
    inside = (t >= segment_s[0]) & (t <= segment_s[1]) & np.isfinite(x).all(axis=1)
    flow_t = np.asarray(flow_t_s, dtype=float)
    inside &= (t >= flow_t[0]) & (t <= flow_t[-1]) if len(flow_t) else np.zeros(len(t), bool)
    empty = SubjectCalibration({n: float("nan") for n in names}, segment_s, float("nan"), float("nan"), float("nan"))
    if not names:
        empty.refused = "no regional optical signal to calibrate"
        return empty
    if inside.sum() < 10 * (len(names) + 2):
        empty.refused = f"only {int(inside.sum())} maps with every region in view during the calibration"
        return empty
    t, x = t[inside], x[inside]
    y = np.interp(t, flow_t, np.asarray(flow_volume_l, dtype=float))
    range_l = float(np.ptp(y))
    coefficients = _fit(t, x, y)
    residual = float(np.sqrt(np.mean((y - _design(t, x) @ coefficients) ** 2)))
    gains = {n: float(g) for n, g in zip(names, coefficients[:len(names)])}
    calibration = SubjectCalibration(gains, segment_s, residual, range_l, _expected_error(t, x, y), samples=len(t),
                                     extra={"fit_t_s": t, "fit_l": _design(t, x) @ coefficients})
    calibration.refused = calibration_refusal(calibration)
    return calibration


def _expected_error(t: np.ndarray, x: np.ndarray, y: np.ndarray) -> float:
    """The rms over LEAVE_OUT_PARTS contiguous parts of the segment of each part's excursion predicted
    from a fit on the others, relative to the flow sensor's excursion over that part."""
    edges = np.linspace(t[0], t[-1], LEAVE_OUT_PARTS + 1)
    errors = []
    for a, b in zip(edges[:-1], edges[1:]):
        held = (t >= a) & (t <= b)
        if held.sum() < 10 or (~held).sum() < 10 * (x.shape[1] + 2):
            continue
        gains = _fit(t[~held], x[~held], y[~held])[:x.shape[1]]
        predicted = x[held] @ gains
        swing = float(np.ptp(y[held]))
        if swing > 0:
            errors.append(np.ptp(predicted) / swing - 1.0)
    return float(np.sqrt(np.mean(np.square(errors)))) if errors else float("nan")


def calibration_refusal(calibration: SubjectCalibration) -> str | None:
    """Why the subject's calibration cannot be used, with what the operator should do; None if it can."""
    redo = "repeat the calibration: quiet breathing and one slow VC through the mouthpiece"
    if calibration.range_l < MIN_RANGE_L:
        return (f"the flow sensor's volume swings {calibration.range_l:.2f} L during the calibration (at least "
                f"{MIN_RANGE_L:.1f} L: a slow VC); {redo}")
    share = calibration.residual_l / calibration.range_l
    if share > MAX_RESIDUAL_SHARE:
        return (f"the optical signals follow the flow sensor within {100 * share:.1f} % of its range "
                f"(at most {100 * MAX_RESIDUAL_SHARE:.0f} %); {redo}")
    gains = np.array(list(calibration.gains.values()))
    if not np.any(gains > 0):
        return f"no region's signal follows the flow sensor's volume; {redo}"
    worst = max(calibration.gains, key=calibration.gains.get)
    if calibration.gains[worst] > MAX_REGION_GAIN:
        return (f"the {worst} signal would be weighed {calibration.gains[worst]:.1f} times (at most "
                f"{MAX_REGION_GAIN:.0f}): it moves too little to be measured; {redo}")
    return None
