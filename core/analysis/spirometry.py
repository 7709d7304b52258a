"""Forced spirometry per the ATS/ERS 2019 standard (Graham et al., AJRCCM 200:e70).

A manoeuvre is the exhaled volume (litres, rising during the blow) against time, sampled
evenly. Values are measured from back-extrapolated time zero; quality follows the 2019
acceptability, usability, repeatability and grading rules.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

PEF_WINDOW_S = 0.08  # ATS/ERS: the steepest slope for back-extrapolation over an 80 ms window
PLATEAU_L = 0.025  # end of forced expiration: less than this in the last second
# The exhalation ends where the volume first comes within this of its largest value: the sensor's
# noise on a flat end (a closed glottis, a held breath) then cannot move the end later and make the
# last second look like a plateau.
END_OF_EXHALATION_L = 0.001
REPEATABILITY_L = 0.150
COUGH_REBOUND_OF_PEF = 0.2  # flow rising again after PEF by this fraction of PEF, in the first second
COUGH = "cough or glottic closure in the first second"


@dataclass
class ForcedValues:
    """One forced expiration."""

    fvc_l: float
    fev1_l: float
    fev075_l: float
    fev6_l: float  # the volume 6 s after time zero; a blow over by then has exhaled its FVC
    pef_lps: float
    fef2575_lps: float
    fet_s: float
    bev_l: float  # back-extrapolated volume
    time_zero_s: float
    plateau_l: float  # volume exhaled in the last second
    cough_in_first_second: bool
    eofe: bool = False  # end of forced expiration reached (set with the other manoeuvres in mind)
    # the curve's flow noise over one sample step (sqrt(2) sigma / step) over its PEF; 0 for a curve
    # whose noise is not weighed (a flow sensor's)
    pef_noise_ratio: float = 0.0
    # the step (s) between the samples PEF was read on, where not the curve's own: an optical blow's
    # maps at every frame (core/analysis/values.py, analyse_volume's peak_flow_volume)
    pef_step_s: float = float("nan")
    pef_smoothing_s: float = float("nan")  # the Gaussian's sigma those samples were smoothed over first
    # the median step (s) of the curve's own samples through the blow, where its noise was weighed
    samples_step_s: float = float("nan")
    # False where the curve's noise could have made the cough the check found (cough_not_judged)
    cough_judged: bool = True
    # False where the samples were too far apart to place time zero (start_not_judged)
    bev_judged: bool = True
    mark_s: float = float("nan")  # the operator's mark of the blow on the session's clock, where known
    problems: list[str] = field(default_factory=list)

    @property
    def fev1_fvc(self) -> float:
        return self.fev1_l / self.fvc_l if self.fvc_l > 0 else float("nan")

    @property
    def bev_limit_l(self) -> float:
        return max(0.05 * self.fvc_l, 0.100)

    @property
    def bev_ok(self) -> bool:
        """The start is not hesitant: the back-extrapolated volume within its limit, or not judged."""
        return self.bev_l <= self.bev_limit_l or not self.bev_judged

    @property
    def fev1_acceptable(self) -> bool:
        return self.bev_ok and not self.cough_in_first_second

    @property
    def fvc_acceptable(self) -> bool:
        return self.fev1_acceptable and self.eofe

    @property
    def fev1_usable(self) -> bool:
        return self.bev_ok

    @property
    def fvc_usable(self) -> bool:
        return self.bev_ok


MIN_BLOW_L = 0.1  # below this there is no blow to grade (a small child's FVC is about 1 L)


def end_of_exhalation(exhaled_l: np.ndarray) -> int:
    """Index of the end of the exhalation: the first sample within END_OF_EXHALATION_L of the
    largest exhaled volume."""
    exhaled_l = np.asarray(exhaled_l, dtype=float)
    return int(np.argmax(exhaled_l >= exhaled_l.max() - END_OF_EXHALATION_L))


def _at(t: np.ndarray, values: np.ndarray, when: float) -> float:
    return float(np.interp(when, t, values))


def forced_values(volume_l: np.ndarray, rate_hz: float) -> ForcedValues:
    """Values of one forced expiration from its exhaled volume-time curve."""
    v = np.asarray(volume_l, dtype=float)
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"the sample rate must be a positive number, found {rate_hz}")
    if v.ndim != 1 or len(v) < int(rate_hz):
        raise ValueError(f"the curve lasts {len(v) / rate_hz:.2f} s: FEV1 needs at least one second of volume "
                         "samples")
    if not np.all(np.isfinite(v)):
        raise ValueError("the curve holds non-finite samples (NaN or infinity)")
    v = v - v[0]
    if v.max() < MIN_BLOW_L:
        raise ValueError(f"no forced expiration: the exhaled volume never exceeds {max(v.max(), 0.0):.3f} L "
                         f"(an empty blow is not graded)")
    t = np.arange(len(v)) / rate_hz
    flow = np.gradient(v, 1.0 / rate_hz)
    # Back extrapolation: the tangent at the steepest part of the curve (over 80 ms, ATS/ERS).
    n = max(1, int(round(PEF_WINDOW_S * rate_hz)))
    slopes = (v[n:] - v[:-n]) / (n / rate_hz)
    k = int(np.argmax(slopes))
    slope = float(slopes[k])
    t_mid = t[k] + n / (2 * rate_hz)
    v_mid = 0.5 * (v[k] + v[k + n])
    time_zero = t_mid - v_mid / slope
    bev = _at(t, v, time_zero) if time_zero > 0 else 0.0
    fvc = float(v.max())
    end_index = end_of_exhalation(v)
    t_end = t[end_index]
    fet = t_end - time_zero
    last = t >= t_end - 1.0
    plateau = float(fvc - _at(t, v, max(t_end - 1.0, 0.0))) if last.any() else fvc
    fev1 = _at(t, v, time_zero + 1.0)
    fev075 = _at(t, v, time_zero + 0.75)
    fev6 = _at(t, v, time_zero + 6.0) if time_zero + 6.0 <= t[-1] else fvc
    t25 = float(np.interp(0.25 * fvc, np.maximum.accumulate(v), t))
    t75 = float(np.interp(0.75 * fvc, np.maximum.accumulate(v), t))
    fef2575 = 0.5 * fvc / (t75 - t25) if t75 > t25 else float("nan")
    pef = float(flow.max())
    first = (t >= time_zero + 0.05) & (t <= time_zero + 1.0) & (t > t[int(np.argmax(flow))])
    cough = False
    if first.any():
        # A cough or glottic closure in the first second: after the peak, flow only falls in a good
        # blow; here it falls to a tenth of the peak and comes back above a third of it, or it
        # comes back up by a fifth of the peak after falling (a cough that does not stop the flow).
        f = flow[first]
        low = np.nonzero(f < 0.1 * pef)[0]
        stopped = bool(len(low) and np.any(f[low[0]:] > 0.3 * pef))
        rebound = float(np.max(f - np.minimum.accumulate(f)))
        cough = stopped or rebound > COUGH_REBOUND_OF_PEF * pef
    values = ForcedValues(fvc, fev1, fev075, fev6, pef, fef2575, fet, bev, time_zero, plateau, cough)
    values.eofe = plateau < PLATEAU_L or fet >= 15.0
    if not values.bev_ok:
        values.problems.append(hesitant_start(values))
    if cough:
        values.problems.append(COUGH)
    if not values.eofe:
        values.problems.append(f"no plateau: {plateau:.3f} L in the last second, FET {fet:.1f} s (early stop?)")
    return values


def cough_not_judged(values: ForcedValues, noise_ratio: float, limit: float) -> None:
    """Take back a cough the curve's noise could have made: where one sample step's flow noise is
    over `limit` of the peak flow (`noise_ratio`, as a PEF within 10 % needs it), a rebound of
    COUGH_REBOUND_OF_PEF of the peak is not told from the noise. The blow is then graded on its other
    criteria and says so; the operator, who watched it, rejects a blow that was coughed."""
    if not values.cough_in_first_second or not noise_ratio > limit:
        return
    values.cough_in_first_second, values.cough_judged = False, False
    values.problems = [p for p in values.problems if p != COUGH] + [
        f"cough in the first second not judged: the flow's noise is {100 * noise_ratio:.0f} % of its peak "
        f"(at most {100 * limit:.0f} %)"]


def hesitant_start(values: ForcedValues) -> str:
    return (f"back-extrapolated volume {values.bev_l:.3f} L over the limit {values.bev_limit_l:.3f} L "
            "(hesitant start)")


def start_not_judged(values: ForcedValues, step_s: float, max_step_s: float) -> None:
    """Leave the start unjudged where the samples are over `max_step_s` apart: joined by straight lines
    (or a smooth fit) across the steepest part, they flatten it, and time zero and the back-extrapolated
    volume read from it move by more than the limit's margin (docs/constants.md). The blow is then
    graded on its other criteria and says so; the operator, who watched it, rejects a hesitant start."""
    if not step_s > max_step_s:
        return
    values.problems = [p for p in values.problems if p != hesitant_start(values)] + [
        f"start not judged: a map every {1000 * step_s:.0f} ms, at least one every {1000 * max_step_s:.0f} ms "
        "needed to place time zero"]
    values.bev_judged = False


@dataclass
class SessionGrade:
    manoeuvres: list[ForcedValues]
    fev1_grade: str
    fvc_grade: str
    fev1_l: float
    fvc_l: float
    fev1_fvc: float
    fef2575_lps: float
    pef_lps: float
    fev1_repeatability_l: float
    fvc_repeatability_l: float
    acceptable_fev1: int
    acceptable_fvc: int
    pef_noise_ratio: float = 0.0  # that of the blow PEF is taken from
    pef_step_s: float = float("nan")  # that blow's (ForcedValues.pef_step_s)

    @property
    def grade(self) -> str:
        """The worse of the FEV1 and FVC grades."""
        order = "ABCDEUF"
        return max(self.fev1_grade, self.fvc_grade, key=order.index)


def repeatability_tolerance_l(largest_l: float, age_years: float | None = None) -> float:
    """ATS/ERS 2019: the two largest values within 0.150 L; at age 6 or under, within 0.100 L or
    10 % of the largest, whichever is greater."""
    if age_years is not None and age_years <= 6:
        return max(0.100, 0.10 * largest_l)
    return REPEATABILITY_L


def _grade(values: list[float], usable: int, age_years: float | None) -> tuple[str, float]:
    """ATS/ERS 2019 grade from the acceptable values and the count of usable ones."""
    values = sorted(values, reverse=True)
    if not values:
        return ("U" if usable else "F"), float("nan")
    if len(values) == 1:
        return "E", float("nan")
    spread = values[0] - values[1]
    tolerance = repeatability_tolerance_l(values[0], age_years)
    if len(values) >= 3 and spread <= tolerance:
        return "A", spread
    if spread <= tolerance:
        return "B", spread
    if spread <= tolerance + 0.050:
        return "C", spread
    if spread <= tolerance + 0.100:
        return "D", spread
    return "E", spread


def grade_session(manoeuvres: list[ForcedValues], age_years: float | None = None) -> SessionGrade:
    """Acceptability with the other blows in mind, repeatability, grades, and the values reported.

    The end of forced expiration is also reached when the FVC is within the repeatability
    tolerance of, or greater than, the largest FVC before it. The largest FEV1 and the largest FVC
    are reported (each from any acceptable blow, else usable ones); FEF25-75 and PEF come from the
    acceptable blow with the largest FEV1 + FVC.
    """
    if not manoeuvres:
        raise ValueError("no forced expirations to grade")
    largest = None  # the largest FVC before the manoeuvre: the first has none to be within
    for m in manoeuvres:
        if not m.eofe and largest is not None and m.fvc_l >= largest - repeatability_tolerance_l(largest, age_years):
            m.eofe = True
            m.problems = [p for p in m.problems if not p.startswith("no plateau")]
        largest = m.fvc_l if largest is None else max(largest, m.fvc_l)
    fev1_ok = [m for m in manoeuvres if m.fev1_acceptable]
    fvc_ok = [m for m in manoeuvres if m.fvc_acceptable]
    fev1_grade, fev1_spread = _grade([m.fev1_l for m in fev1_ok], sum(m.fev1_usable for m in manoeuvres), age_years)
    fvc_grade, fvc_spread = _grade([m.fvc_l for m in fvc_ok], sum(m.fvc_usable for m in manoeuvres), age_years)
    fev1_from = fev1_ok or [m for m in manoeuvres if m.fev1_usable] or manoeuvres
    fvc_from = fvc_ok or [m for m in manoeuvres if m.fvc_usable] or manoeuvres
    fev1 = max(m.fev1_l for m in fev1_from)
    fvc = max(m.fvc_l for m in fvc_from)
    best = max(fvc_ok or fev1_ok or manoeuvres, key=lambda m: m.fev1_l + m.fvc_l)
    return SessionGrade(manoeuvres, fev1_grade, fvc_grade, fev1, fvc, fev1 / fvc, best.fef2575_lps, best.pef_lps,
                        fev1_spread, fvc_spread, len(fev1_ok), len(fvc_ok), best.pef_noise_ratio,
                        best.pef_step_s)


@dataclass
class Waveform:
    """A spirometer test waveform file (`.wf`)."""

    group: str
    name: str
    kind: str  # VT: volume-time (L); FT: flow-time (L/s)
    rate_hz: float
    samples: np.ndarray
    expected: dict[str, float]

    @property
    def volume_l(self) -> np.ndarray:
        if self.kind == "VT":
            return self.samples
        return np.concatenate([[0.0], np.cumsum(0.5 * (self.samples[1:] + self.samples[:-1])) / self.rate_hz])


def read_waveform(path: str | os.PathLike) -> Waveform:
    """Parse a `.wf` file ([Header], [Parameters], [Data]; an optional trailing 0x1A byte)."""
    path = Path(path)
    try:
        text = path.read_bytes().replace(b"\x1a", b"").decode("latin-1")
    except OSError as exc:
        raise ValueError(f"cannot read waveform {path}: {exc}") from exc
    section = None
    header: dict[str, str] = {}
    expected: dict[str, float] = {}
    data: list[float] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("[") and line.endswith("]"):
            section = line[1:-1].strip().lower()
            continue
        if section in ("header", "parameters"):
            if "=" not in line:
                raise ValueError(f"{path}:{number}: expected KEY=VALUE in [{section}], found {line!r}")
            key, value = (part.strip() for part in line.split("=", 1))
            if section == "header":
                header[key.lower()] = value
            else:
                expected[key.upper()] = _wf_number(value, f"{path}:{number}: parameter {key}")
        elif section == "data":
            data.append(_wf_number(line, f"{path}:{number}: data sample"))
    if "freq" not in header:
        raise ValueError(f"{path}: [Header] has no Freq")
    rate = _wf_number(header["freq"], f"{path}: [Header] Freq")
    if not rate > 0:
        raise ValueError(f"{path}: [Header] Freq must be a positive sample rate, found {header['freq']!r}")
    zoom = _wf_number(header["fzoom"], f"{path}: [Header] fZoom") if "fzoom" in header else 1.0
    if not zoom > 0:
        raise ValueError(f"{path}: [Header] fZoom must be a positive scale factor, found {header['fzoom']!r}")
    kind = header.get("type", "VT").upper()
    if kind not in ("VT", "FT"):
        raise ValueError(f"{path}: Type {kind!r} is neither VT (volume-time) nor FT (flow-time)")
    if len(data) < 10:
        raise ValueError(f"{path}: [Data] holds {len(data)} samples")
    # ISO 23747 files store samples as integers to be multiplied by fZoom
    return Waveform(header.get("group", ""), header.get("name", path.stem), kind, rate,
                    zoom * np.asarray(data), expected)


def _wf_number(text: str, where: str) -> float:
    """A number of a .wf file: a decimal comma is read as a point; NaN and infinity are refused."""
    try:
        value = float(text.strip().replace(",", "."))
    except ValueError as exc:
        raise ValueError(f"{where} is not a number: {text!r}") from exc
    if not np.isfinite(value):
        raise ValueError(f"{where} must be a finite number, found {text!r}")
    return value
