"""Pulmonary function values of a session from a volume curve (optical or flow sensor).

The protocol's events cut the curve: tidal breathing, slow vital capacity (`vc-start` ...
`maneuver-end`) and forced expirations (`forced-start` ... `maneuver-end`). Volumes are litres
(BTPS), positive = inhaled.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.signal import find_peaks

from core.analysis.fitted_curve import smoothed_on_grid
from core.analysis.spirometry import (ForcedValues, SessionGrade, cough_not_judged, forced_values, grade_session,
                                     start_not_judged)
from core.runs import runs
from core.volume.noise import curve_noise_l

ANALYSIS_RATE_HZ = 200.0

# The least tidal volume of a breath, raised where the curve's noise makes breaths that size (docs/constants.md)
MIN_TIDAL_FLOOR_L = 0.02
BREATH_OVER_NOISE = 4.0


def least_tidal_l(stretches: list[tuple[np.ndarray, np.ndarray]]) -> float:
    """The least tidal volume a breath of these stretches may have: MIN_TIDAL_FLOOR_L, or
    BREATH_OVER_NOISE times the stretches' noise (curve_noise_l, their samples as recorded) where
    that is more."""
    noise = [curve_noise_l(v) for _, v in stretches]
    noise = [n for n in noise if np.isfinite(n)]
    return max(MIN_TIDAL_FLOOR_L, BREATH_OVER_NOISE * float(np.median(noise))) if noise else MIN_TIDAL_FLOOR_L


@dataclass
class TidalValues:
    breaths: int
    tidal_volume_l: float
    respiratory_rate_bpm: float
    minute_ventilation_lpm: float
    inspiratory_time_s: float
    expiratory_time_s: float
    ie_ratio: float  # inspiratory over expiratory time
    tptef_te: float  # time to peak tidal expiratory flow over expiratory time
    ie50: float  # inspiratory over expiratory flow at half the tidal volume
    end_expiratory_level_l: float
    sighs: int = 0  # breaths of twice the median tidal volume or more, left out of the values above


# Slow VC (ATS/ERS 2005, lung volumes): the exhalation ends on a plateau, and the two largest
# acceptable VCs agree within 150 mL; the largest acceptable VC is reported.
VC_PLATEAU_L = 0.050  # under this in the last second of the slow exhalation
VC_REPEATABILITY_L = 0.150


@dataclass
class VitalCapacity:
    vc_l: float
    ic_l: float
    erv_l: float
    irv_l: float
    exhalation_end_l: float = 0.0  # volume exhaled in the last second before the lowest point
    start_s: float = float("nan")

    @property
    def plateau(self) -> bool:
        return self.exhalation_end_l < VC_PLATEAU_L

    @property
    def acceptable(self) -> bool:
        return self.plateau

    @property
    def problems(self) -> list[str]:
        if self.plateau:
            return []
        return [f"ended too early: {1000 * self.exhalation_end_l:.0f} mL in the last second of the exhalation "
                f"(a plateau is under {1000 * VC_PLATEAU_L:.0f} mL)"]


def vc_repeatability_l(manoeuvres: list[VitalCapacity]) -> float:
    """The difference between the two largest acceptable VCs (NaN with fewer than two)."""
    values = sorted((m.vc_l for m in manoeuvres if m.acceptable), reverse=True)
    return values[0] - values[1] if len(values) >= 2 else float("nan")


@dataclass
class SessionValues:
    tidal: TidalValues | None = None
    vital_capacity: VitalCapacity | None = None  # the largest acceptable slow VC (else the largest)
    vc_manoeuvres: list[VitalCapacity] = field(default_factory=list)
    forced: SessionGrade | None = None
    problems: list[str] = field(default_factory=list)
    # exhaled volume (L) of each forced manoeuvre, sampled at ANALYSIS_RATE_HZ from the blow's
    # start (its ForcedValues.time_zero_s is on this clock), in the order of forced.manoeuvres
    forced_curves: list[np.ndarray] = field(default_factory=list)
    # why the curve's samples are too far apart for a peak flow (MAX_PEF_SAMPLE_INTERVAL_S), else None
    pef_refused: str | None = None
    # the operator's mark (s) of every forced blow on the curve that was not rejected, read or left out
    forced_marks_s: list[float] = field(default_factory=list)

    def parameters(self) -> dict[str, float | str | int]:
        """Flat values for the results file's /parameters attributes."""
        out: dict[str, float | str | int] = {}
        if self.tidal is not None:
            t = self.tidal
            out.update(TV_l=t.tidal_volume_l, RR_bpm=t.respiratory_rate_bpm, VE_lpm=t.minute_ventilation_lpm,
                       Ti_s=t.inspiratory_time_s, Te_s=t.expiratory_time_s, IE_ratio=t.ie_ratio,
                       tPTEF_tE=t.tptef_te, IE50=t.ie50, breaths=t.breaths, sighs=t.sighs)
        if self.vital_capacity is not None:
            v = self.vital_capacity
            out.update(VC_l=v.vc_l, IC_l=v.ic_l, ERV_l=v.erv_l, IRV_l=v.irv_l, VC_manoeuvres=len(self.vc_manoeuvres),
                       VC_acceptable=sum(m.acceptable for m in self.vc_manoeuvres))
            spread = vc_repeatability_l(self.vc_manoeuvres)
            if np.isfinite(spread):
                out["VC_repeatability_l"] = spread
        if self.forced is not None:
            f = self.forced
            out.update(FVC_l=f.fvc_l, FEV1_l=f.fev1_l, FEF2575_lps=f.fef2575_lps, **forced_proportions(f))
            if not self.pef_refused:
                out["PEF_lps"] = f.pef_lps
            usable = [m for m in f.manoeuvres if m.fev1_usable] or f.manoeuvres
            fev6 = [m.fev6_l for m in usable]
            out.update(FEV6_l=max(fev6), FEV075_l=max(m.fev075_l for m in usable),
                       FET_s=float(max(m.fet_s for m in usable)))
        return out


def forced_proportions(f: SessionGrade) -> dict[str, float | str | int]:
    """FEV1/FVC and the blows' grades, and how many blows were graded without their start or a cough
    their curve could not tell (start_not_judged, cough_not_judged)."""
    return dict(FEV1_FVC=f.fev1_fvc, grade=f.grade, grade_FEV1=f.fev1_grade, grade_FVC=f.fvc_grade,
                acceptable_FEV1=f.acceptable_fev1, acceptable_FVC=f.acceptable_fvc, manoeuvres=len(f.manoeuvres),
                starts_not_judged=sum(not m.bev_judged for m in f.manoeuvres),
                coughs_not_judged=sum(not m.cough_judged for m in f.manoeuvres))


def grade_caveat(parameters: dict) -> str:
    """What a session's grade was given without, in words ('' for nothing): the blows whose start the
    maps were too far apart to judge, and those whose cough check the maps' noise could not."""
    parts = []
    if starts := int(parameters.get("starts_not_judged", 0)):
        parts.append(f"the start of {starts} of {parameters['manoeuvres']} blows not judged (maps too far apart)")
    if coughs := int(parameters.get("coughs_not_judged", 0)):
        parts.append(f"a cough found in {coughs} not judged (the maps' noise could make one)")
    return "; ".join(parts)


# The widest sample interval a curve's PEF is given from, and a blow's start judged on: one map a light
# cycle (docs/constants.md)
MAX_PEF_SAMPLE_INTERVAL_S = 0.05


# A manoeuvre is read across a gap of maps up to this, left out beyond (docs/constants.md)
MAX_BRIDGED_GAP_S = 0.15
# A forced blow's peak flow lies within this of its top (the 61 waveforms of ../shared/data/spirometry-
# waveforms: 0.03-0.57 s after 0.5 % of the volume is out, median 0.09 s); a map missing there takes
# the peak flow with it
PEAK_FLOW_WITHIN_S = 0.6


# The maps at every frame (`process`, /peak_flow_volume) reach this far either side of where the curve
# of one map a cycle falls fastest in a forced blow: its steepest step lies within a step or two of the
# peak flow, and the flow of a good blow rises to its peak in 20-100 ms and falls from it over longer
PEAK_FLOW_REACH_S = 0.3
# The peak flow read on the maps at every frame lies at least this far inside their span, or the
# span missed it (peak_flow_of_frames)
PEAK_FLOW_MARGIN_S = 0.05


def peak_flow_spans_s(t_s: np.ndarray, volume_l: np.ndarray, events: list[tuple[float, str]],
                      ) -> list[tuple[float, float]]:
    """Where each forced blow's peak flow is (events on the curve's clock, s): PEAK_FLOW_REACH_S either
    side of the curve's steepest fall from one finite sample to the next, from 2 s before the
    operator's `forced-start` to the manoeuvre's end (the stretch analyse_volume reads the blow in)."""
    t, v = np.asarray(t_s, dtype=float), np.asarray(volume_l, dtype=float)
    good = np.isfinite(v)
    t, v = t[good], v[good]
    spans = []
    for a, b in _windows(sorted(events), "forced-start", float(t[-1]) if len(t) else 0.0)[0]:
        inside = np.nonzero((t >= a - 2.0) & (t <= b))[0]
        if len(inside) < 2:
            continue
        falls = -np.diff(v[inside]) / np.diff(t[inside])
        k = inside[int(np.argmax(falls))]
        steepest = 0.5 * (t[k] + t[k + 1])
        spans.append((steepest - PEAK_FLOW_REACH_S, steepest + PEAK_FLOW_REACH_S))
    return spans


def short_gaps(t_s: np.ndarray, volume_l: np.ndarray, max_gap_s: float) -> np.ndarray:
    """The non-finite samples of a curve that lie in a gap of at most max_gap_s between finite
    neighbours (a mask); those at either end, or in a longer gap, are not."""
    bad = ~np.isfinite(volume_l)
    out = np.zeros(len(bad), dtype=bool)
    if not bad.any():
        return out
    for first, end in runs(bad):
        if first > 0 and end < len(bad) and t_s[end] - t_s[first - 1] <= max_gap_s:
            out[first:end] = True
    return out


# A slow VC is read inside one stretch between maps left out only where its highest and lowest volumes
# are at least this far from the stretch's gaps (a slow manoeuvre does not turn inside a gap of half a
# second, a step's, and come back), and no sample outside the stretch lies beyond them by more than
# this share of its range (a level's jump across a step is smaller) (docs/constants.md)
VC_EXTREME_FROM_GAP_S = 1.0
VC_OUTSIDE_SHARE = 0.10


def vc_between_gaps(t_s: np.ndarray, volume_l: np.ndarray) -> np.ndarray | None:
    """The samples (a mask) of the stretch between non-finite samples that holds a whole slow VC, or None.

    A level that jumps across a gap (a step's, docs/volume.md) must not enter the VC, so it is read
    inside one stretch: the one of the largest range, taken only where its highest and lowest volumes
    are at least VC_EXTREME_FROM_GAP_S from a gap (the window's own ends are no gap) and no sample
    outside it lies more than VC_OUTSIDE_SHARE of its range beyond them (else the VC's full
    inspiration or expiration is elsewhere: the stretch holds breaths and half the manoeuvre)."""
    finite = np.isfinite(volume_l)
    best, best_range = None, -1.0
    for first, end in runs(finite):
        if end - first < MIN_MANOEUVRE_SAMPLES:
            continue
        span = volume_l[first:end]
        if float(np.ptp(span)) > best_range:
            best, best_range = (first, end), float(np.ptp(span))
    if best is None:
        return None
    first, end = best
    t = t_s[first:end]
    extremes = t[[int(np.argmax(volume_l[first:end])), int(np.argmin(volume_l[first:end]))]]
    if first > 0 and np.any(extremes - t[0] < VC_EXTREME_FROM_GAP_S):
        return None
    if end < len(t_s) and np.any(t[-1] - extremes < VC_EXTREME_FROM_GAP_S):
        return None
    out = np.zeros(len(t_s), dtype=bool)
    out[first:end] = True
    elsewhere = volume_l[finite & ~out]
    high, low = float(np.max(volume_l[out])), float(np.min(volume_l[out]))
    margin = VC_OUTSIDE_SHARE * (high - low)
    if len(elsewhere) and (elsewhere.max() > high + margin or elsewhere.min() < low - margin):
        return None
    return out


def resample(t_s: np.ndarray, volume_l: np.ndarray, rate_hz: float = ANALYSIS_RATE_HZ) -> tuple[np.ndarray, np.ndarray]:
    """A volume curve on an even grid at rate_hz, straight between its samples. A shape-preserving cubic
    (PCHIP) was tried for the optical curve's peak flow (one map a light cycle): on error-free curves it
    brought the standard waveforms' PEF within 10 % on 92 % of them against 78 %, but on measured optical
    curves it followed their noise: 4 of 7 blows within 10 % or 0.30 L/s against 5 of 7 (docs/history/volume-log.md,
    "Peak flow")."""
    grid = np.arange(t_s[0], t_s[-1], 1.0 / rate_hz)
    return grid, np.interp(grid, t_s, volume_l)


def _breaths(t_s: np.ndarray, volume_l: np.ndarray, min_breath_s: float, min_tidal_l: float):
    """(t, smoothed volume, flow, pairs of consecutive end-expiratory minima) of one stretch."""
    t, v = resample(t_s, volume_l)
    if len(t) < 2 * min_breath_s * ANALYSIS_RATE_HZ:
        return t, v, v, []
    width = max(1, int(0.15 * ANALYSIS_RATE_HZ))
    pad = np.pad(v, width, mode="edge")
    smooth = np.convolve(pad, np.ones(width) / width, mode="same")[width:-width]
    # The stretch's own ends count as minima when the volume rises from (or falls to) them.
    minima, _ = find_peaks(-np.pad(smooth, 1, constant_values=np.inf), distance=int(min_breath_s * ANALYSIS_RATE_HZ),
                           prominence=min_tidal_l)
    minima = _without_wiggles(smooth, np.clip(minima - 1, 0, len(smooth) - 1))
    flow = np.gradient(smooth, 1.0 / ANALYSIS_RATE_HZ)
    return t, smooth, flow, list(zip(minima[:-1], minima[1:]))


# A "breath" under half the median in volume and in time is a wiggle on an expiration, merged with its
# neighbour (three or more breaths only; docs/benchmarks.md, constants).
WIGGLE_FRACTION = 0.5


def _breath_peak(smooth: np.ndarray, a: int, b: int) -> tuple[int, float]:
    """The end of inspiration of the breath between minima a and b (its sample) and its tidal
    volume, the peak over the mean of the two minima."""
    peak = a + int(np.argmax(smooth[a:b]))
    return peak, float(smooth[peak] - 0.5 * (smooth[a] + smooth[b]))


def _without_wiggles(smooth: np.ndarray, minima: np.ndarray) -> np.ndarray:
    minima = list(minima)
    while len(minima) >= 4:
        pairs = list(zip(minima[:-1], minima[1:]))
        peaks, vt = map(np.array, zip(*(_breath_peak(smooth, a, b) for a, b in pairs)))
        ti, te = peaks - np.array(minima[:-1]), np.array(minima[1:]) - peaks
        k = int(np.argmin(vt))
        short = ti[k] < WIGGLE_FRACTION * np.median(ti) or te[k] < WIGGLE_FRACTION * np.median(te)
        if not (vt[k] < WIGGLE_FRACTION * np.median(vt) and short):
            break
        a, b = pairs[k]
        minima.remove(a if smooth[a] > smooth[b] else b)
    return np.array(minima, dtype=int)


# Quiet breathing expires longer than it inspires: a "breath" with Te under 0.3 Ti is the rise into a
# manoeuvre, not a breath (docs/benchmarks.md, constants).
MIN_EXPIRATION_PER_INSPIRATION = 0.3
# A breath starts and ends near one end-expiratory level: minima further apart than half the
# breath's volume are a stretch cut mid-breath (a window opening during an inspiration), not a breath.
MAX_LEVEL_CHANGE_OF_TIDAL = 0.5


Breath = tuple[float, float, float, float, float, float, float, float, float, float]
# A breath's end inspiration and end expirations are read on a parabola fitted over this share of its
# inspiratory time either side: the largest (smallest) sample there is the noise's on an optical curve,
# +18 mL of tidal volume at 25 mL of noise a map (`photopft bench tidal`, docs/benchmarks.md)
EXTREME_FIT_SHARE_OF_TI = 0.2


def _fitted_extreme(curve: np.ndarray, i: int, half_width: int, sign: int) -> float:
    """The extreme (sign +1 a maximum, -1 a minimum) of the parabola fitted to curve[i - half_width :
    i + half_width + 1] where it lies inside that window, else the parabola's value at i."""
    lo, hi = max(0, i - half_width), min(len(curve), i + half_width + 1)
    x = np.arange(lo, hi) - i
    c = np.polyfit(x, curve[lo:hi], 2)
    if sign * c[0] < 0:
        vertex = -c[1] / (2 * c[0])
        if x[0] <= vertex <= x[-1]:
            return float(np.polyval(c, vertex))
    return float(np.polyval(c, 0.0))


def _one_breath(t: np.ndarray, smooth: np.ndarray, flow: np.ndarray, a: int, b: int,
                min_tidal_l: float) -> Breath | None:
    """(VT, Ti, Te, tPTEF/tE, IE50, end-expiratory level, end-inspiration time, end-expiration time,
    start time, mid-inspiration time) of the breath between minima a and b."""
    peak, vt = _breath_peak(smooth, a, b)
    if vt < min_tidal_l or peak in (a, b):
        return None
    ti, te = t[peak] - t[a], t[b] - t[peak]
    if te < MIN_EXPIRATION_PER_INSPIRATION * ti:  # a rise cut off by the stretch's end, not a breath
        return None
    if abs(smooth[a] - smooth[b]) > MAX_LEVEL_CHANGE_OF_TIDAL * vt:
        return None
    half_width = max(2, int(EXTREME_FIT_SHARE_OF_TI * ti * ANALYSIS_RATE_HZ))
    level, top = _fitted_extreme(smooth, a, half_width, -1), _fitted_extreme(smooth, peak, half_width, +1)
    vt = top - 0.5 * (level + _fitted_extreme(smooth, b, half_width, -1))
    tptef = int(np.argmin(flow[peak:b])) / ANALYSIS_RATE_HZ / te
    half = 0.5 * (level + top)  # the inspiration's middle, on the levels fitted (not the noisiest sample)
    i_half = a + int(np.argmin(np.abs(smooth[a:peak] - half)))
    e_half = peak + int(np.argmin(np.abs(smooth[peak:b] - half)))
    ie50 = flow[i_half] / -flow[e_half] if flow[e_half] < 0 else float("nan")
    return vt, ti, te, tptef, ie50, level, t[peak], t[b], t[a], t[i_half]


def tidal_breaths(stretches: list[tuple[np.ndarray, np.ndarray]], min_breath_s: float = 1.2,
                  min_tidal_l: float | None = None) -> list[Breath]:
    """Every breath of the stretches: (VT, Ti, Te, tPTEF/tE, IE50, end-expiratory level,
    end-inspiration time, end-expiration time, start time, mid-inspiration time). min_tidal_l: the
    least tidal volume of a breath (default: least_tidal_l of the stretches)."""
    if min_tidal_l is None:
        min_tidal_l = least_tidal_l(stretches)
    breaths = []
    for t_s, volume_l in stretches:
        t, smooth, flow, pairs = _breaths(t_s, volume_l, min_breath_s, min_tidal_l)
        breaths += [b for b in (_one_breath(t, smooth, flow, a, z, min_tidal_l) for a, z in pairs) if b is not None]
    return breaths


def tidal_stretches(t_s: np.ndarray, volume_l: np.ndarray,
                    events: list[tuple[float, str]]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The curve's stretches of quiet breathing (see tidal_windows), each cut where the curve has no
    value for longer than MAX_BRIDGED_GAP_S (optical maps left out: core/pipeline/quality.py): a
    breath is read only where it was measured, and read across a map missing here and there as the
    manoeuvres are, without the missing samples."""
    out = []
    finite = np.isfinite(volume_l)
    read = finite | short_gaps(t_s, volume_l, MAX_BRIDGED_GAP_S)
    for a, b in tidal_windows(sorted(events), float(t_s[-1])):
        inside = (t_s >= a) & (t_s <= b) & read
        edges = np.flatnonzero(np.diff(np.concatenate(([0], inside.astype(np.int8), [0]))))
        for start, stop in zip(edges[::2], edges[1::2]):
            kept = finite[start:stop]
            if kept.sum() > 10:
                out.append((t_s[start:stop][kept], volume_l[start:stop][kept]))
    return out


# A sigh is a breath of at least twice the median tidal volume (Bendixen et al. 1964; the usual
# definition in tidal breathing analysis): it is counted, and left out of the tidal values.
SIGH_OF_MEDIAN = 2.0


def breath_period_s(breaths: list[Breath]) -> float:
    """The breaths' mean period: the mean interval from one breath's mid-inspiration to the next's,
    over breaths that follow one another (the mean of Ti + Te where none do). An end-expiratory pause
    is flat, and its minimum falls anywhere in it with a noisy curve's noise; at a stretch's ends it
    can only move inwards, which shortened the breaths between minima: +0.15/min with 10 mL of noise
    a sample on the population's tidal breathing (`photopft bench tidal`). An inspiration's middle is
    where the volume changes fastest."""
    periods = [b[9] - a[9] for a, b in zip(breaths[:-1], breaths[1:]) if b[8] == a[7]]
    return float(np.mean(periods)) if periods else float(np.mean([b[1] + b[2] for b in breaths]))


def tidal_values(stretches: list[tuple[np.ndarray, np.ndarray]], min_breath_s: float = 1.2,
                 min_tidal_l: float | None = None) -> TidalValues | None:
    """Breaths between consecutive end-expiratory minima, pooled over stretches of quiet breathing,
    sighs left out; None with fewer than two breaths. The rate is the breaths' mean period
    (breath_period_s)."""
    return tidal_values_of(tidal_breaths(stretches, min_breath_s, min_tidal_l))


def quiet_breaths(breaths: list[Breath]) -> list[Breath]:
    """The breaths without the sighs (three breaths or more: a sigh needs a median to stand out from)."""
    if len(breaths) < 3:
        return breaths
    median = float(np.median([b[0] for b in breaths]))
    return [b for b in breaths if b[0] < SIGH_OF_MEDIAN * median]


def tidal_values_of(breaths: list[Breath]) -> TidalValues | None:
    """tidal_values of breaths already found (tidal_breaths)."""
    quiet = quiet_breaths(breaths)
    if len(quiet) < 2:
        return None
    vt, ti, te, tptef, ie50, levels = (np.array(column) for column in list(zip(*quiet))[:6])
    tv = float(np.mean(vt))
    rr = 60.0 / breath_period_s(quiet)
    return TidalValues(len(quiet), tv, rr, tv * rr, float(np.mean(ti)), float(np.mean(te)),
                       float(np.mean(ti) / np.mean(te)), float(np.mean(tptef)), float(np.nanmean(ie50)),
                       float(np.mean(levels)), len(breaths) - len(quiet))


def _windows(events: list[tuple[float, str]], start_label: str,
             end_s: float) -> tuple[list[tuple[float, float]], list[float]]:
    """(start, end) of each manoeuvre that ended within the recording; the starts of those that did not."""
    out, unfinished = [], []
    for k, (t, label) in enumerate(events):
        if label != start_label:
            continue
        end = next((t2 for t2, l2 in events[k + 1:] if l2 == "maneuver-end"), None)
        if end is None or end > end_s:
            unfinished.append(t)
        elif not _rejected(events, end):
            out.append((t, end))
    return out, unfinished


MANOEUVRE_STARTS = ("tidal-start", "vc-start", "forced-start")
# Fewest volume samples a slow VC or a forced expiration's lead-in is read from, and a blow from its top
MIN_MANOEUVRE_SAMPLES = 10
MIN_BLOW_SAMPLES = 20
# A blow whose top is the first map after a gap is read when it has exhaled less than this (the least
# back-extrapolated volume any blow is allowed) over the next HELD_SEEN_S: the breath was still held
HELD_EXHALED_L = 0.100
HELD_SEEN_S = 0.1


def too_few_samples(what: str, at_s: float, samples: int, span_s: float, needed: int = MIN_MANOEUVRE_SAMPLES,
                    where: str = "") -> str:
    """Why a manoeuvre was not read: the volume came too sparsely (a slow stream of maps, or maps left out)."""
    place = f" {where}" if where else ""
    return (f"{what} at {at_s:.1f} s: {samples} volume sample(s) in its {span_s:.1f} s{place}, at least {needed} "
            "needed; the maps came too slowly or were left out")


def _rejected(events: list[tuple[float, str]], end: float) -> bool:
    """The operator rejected the manoeuvre that ended at `end` (a `maneuver-rejected` event after
    its end and before the next manoeuvre starts): it is left out, as if it had not been done."""
    for t, label in events:
        if t < end:
            continue
        if label in MANOEUVRE_STARTS:
            return False
        if label == "maneuver-rejected":
            return True
    return False


def tidal_windows(events: list[tuple[float, str]], end_s: float) -> list[tuple[float, float]]:
    """Stretches of quiet breathing: from `tidal-start`, and between a manoeuvre's end (plus 3 s
    of recovery) and the next manoeuvre; where two overlap (a `tidal-start` after a manoeuvre's
    recovery, as the clinical protocol's `mouthpiece-off` has it), their union, so that no breath is
    read twice."""
    windows = []
    ordered = sorted(events)
    starts = [t for t, label in ordered if label in ("vc-start", "forced-start")]
    for t, label in ordered:
        if label == "tidal-start":
            stop = next((t2 for t2, l2 in ordered if t2 > t and l2 in ("maneuver-end", "vc-start", "forced-start")),
                        end_s)
            windows.append((t, stop))
        elif label == "maneuver-end":
            stop = next((s for s in starts if s >= t), end_s)
            if stop - (t + 3.0) > 4.0:
                windows.append((t + 3.0, stop))
    out: list[tuple[float, float]] = []
    for a, b in sorted(windows):
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    return out


def analyse_volume(t_s: np.ndarray, volume_l: np.ndarray, events: list[tuple[float, str]],
                   age_years: float | None = None, fitted: bool = False,
                   peak_flow_volume: tuple[np.ndarray, np.ndarray] | None = None) -> SessionValues:
    """Tidal values, slow VC and graded forced expirations of one session's volume curve.

    fitted: read each slow VC and forced expiration from a smoothing spline through its samples
    (core.analysis.fitted_curve), for an optical volume, one noisy sample a light cycle; a flow
    sensor's curve is read straight. peak_flow_volume: (times in s, litres) of the same volume at
    every frame through each forced blow's peak flow (a results file's /peak_flow_volume): a fitted
    blow whose peak flow it holds takes its PEF from it (peak_flow_of_frames); a fitted curve that is
    itself one map a frame is read so too."""
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(volume_l, dtype=float)
    if fitted and peak_flow_volume is None and len(t) > 1 and float(np.median(np.diff(t))) <= MAX_FRAME_STEP_S:
        peak_flow_volume = (t, v)
    result = SessionValues()
    start_s, end_s = float(t[0]), float(t[-1])
    ordered = sorted(events)
    result.tidal = tidal_values(tidal_stretches(t, v, ordered))
    if result.tidal is None:
        result.problems.append("no stretch of tidal breathing with two or more breaths")
    frc = result.tidal.end_expiratory_level_l if result.tidal is not None else 0.0
    vc_windows, vc_unfinished = _windows(ordered, "vc-start", end_s)
    result.problems += [f"slow VC from {t:.1f} s not finished before the recording ended: left out"
                        for t in vc_unfinished]
    # the manoeuvres read across a map missing here and there (short_gaps), never across a longer gap
    bridged = short_gaps(t, v, MAX_BRIDGED_GAP_S)
    missing_t = t[bridged]
    t, v = t[~bridged], v[~bridged]

    def note_missing(what: str, at_s: float, first_s: float, last_s: float) -> None:
        count = int(np.count_nonzero((missing_t >= first_s) & (missing_t <= last_s)))
        if count:
            result.problems.append(f"{what} at {at_s:.1f} s: {count} map(s) missing, read across (gaps of at most "
                                   f"{1000 * MAX_BRIDGED_GAP_S:.0f} ms)")

    for a, b in vc_windows:
        if a < start_s:  # before this curve begins (the live volume after the subject's calibration)
            continue
        inside = (t >= a) & (t <= b + 0.5)
        if inside.sum() < MIN_MANOEUVRE_SAMPLES:
            result.problems.append(too_few_samples("slow VC", a, int(inside.sum()), b + 0.5 - a))
            continue
        note_missing("slow VC", a, a, b + 0.5)
        if not np.all(np.isfinite(v[inside])):
            run = vc_between_gaps(t[inside], v[inside])
            if run is None:
                result.problems.append(f"slow VC at {a:.1f} s: the curve holds non-finite samples (NaN or infinity: "
                                       "e.g. optical maps left out where an arm hid the trunk's sides or the subject "
                                       "stepped) between its highest and lowest volume: left out")
                continue
            first, last = float(t[inside][run][0]), float(t[inside][run][-1])
            result.problems.append(f"slow VC at {a:.1f} s: read from {first:.1f} to {last:.1f} s, between maps left "
                                   "out (not read across them)")
            inside = inside & (t >= first) & (t <= last)
        ti, vi = smoothed_on_grid(t[inside], v[inside], ANALYSIS_RATE_HZ) if fitted else (t[inside], v[inside])
        i_low = int(np.argmin(vi))
        top, bottom = float(vi.max()), float(vi[i_low])
        ic, erv = top - frc, frc - bottom
        tv = result.tidal.tidal_volume_l if result.tidal is not None else float("nan")
        last_second = float(np.interp(ti[i_low] - 1.0, ti, vi)) - bottom
        result.vc_manoeuvres.append(VitalCapacity(top - bottom, ic, erv, ic - tv, last_second, a))
    if result.vc_manoeuvres:
        acceptable = [m for m in result.vc_manoeuvres if m.acceptable]
        result.vital_capacity = max(acceptable or result.vc_manoeuvres, key=lambda m: m.vc_l)
    blows: list[ForcedValues] = []
    peak_missing: list[float] = []  # the blows with a map missing where their peak flow is
    forced_windows, forced_unfinished = _windows(ordered, "forced-start", end_s)
    finite, index = np.isfinite(v), np.arange(len(t))  # the curve as the blows read it, gaps and all
    result.problems += [f"forced expiration from {t:.1f} s not finished before the recording ended: left out"
                        for t in forced_unfinished]
    result.forced_marks_s = sorted([a for a, _ in forced_windows] + forced_unfinished)
    result.forced_marks_s = [a for a in result.forced_marks_s if a >= start_s]
    for a, b in forced_windows:
        # The blow starts from the full inspiration (TLC): the highest volume from just before the
        # operator's mark (marked at the blow) to the manoeuvre's end (marked at the inspiration).
        if a < start_s:
            continue
        # Across a longer gap the level is not kept (a step moved it by up to 0.16 L: docs/volume.md): the
        # blow is read between the last such gap before the mark and the first after it
        gaps = index[~finite & (t >= a - 2.0) & (t <= b + 0.5)]
        after_gap = 0
        if (t[gaps] < a).any():  # the first finite sample after the last gap that starts before the mark
            later = index[finite & (index > gaps[t[gaps] < a].max())]
            after_gap = int(later[0]) if len(later) else len(t)
        cut_at = gaps[gaps > after_gap]
        before = (t >= a - 2.0) & (t <= b) & (index >= after_gap) & (index < (cut_at[0] if len(cut_at) else len(t)))
        if before.sum() < MIN_MANOEUVRE_SAMPLES:
            result.problems.append(too_few_samples("forced expiration", a, int(before.sum()), b + 2.0 - a))
            continue
        i_top = int(index[before][np.argmax(v[before])])
        if i_top == after_gap and after_gap > 0 and float(
                v[i_top] - np.interp(t[i_top] + HELD_SEEN_S, t[before], v[before])) >= HELD_EXHALED_L:
            result.problems.append(f"forced expiration at {a:.1f} s: the blow was under way when the maps came back "
                                   "after a gap: its start is not seen, left out")
            continue
        stop = float(t[cut_at[0] - 1]) if len(cut_at) else min(b + 0.5, end_s)
        blow = (t >= t[i_top]) & (t <= stop)
        if blow.sum() < MIN_BLOW_SAMPLES:
            result.problems.append(too_few_samples("forced expiration", a, int(blow.sum()), stop - t[i_top],
                                                   MIN_BLOW_SAMPLES, "after its full inspiration"))
            continue
        note_missing("forced expiration", a, a - 2.0, b + 0.5)
        missing_near_peak = bool(np.any((missing_t >= t[i_top]) & (missing_t <= t[i_top] + PEAK_FLOW_WITHIN_S)))
        if fitted:
            # The top, too, is read on the fitted curve: the largest sample is the noise's largest.
            tw, vw = smoothed_on_grid(t[before | blow], v[before | blow], ANALYSIS_RATE_HZ)
            i_fitted_top = int(np.argmax(np.where(tw <= b, vw, -np.inf)))
            vb = vw[i_fitted_top:]
        else:
            vb = resample(t[blow], v[blow])[1]
        exhaled = vb[0] - vb
        i_low = int(np.argmax(exhaled))
        try:
            m = forced_values(exhaled[: i_low + 1], ANALYSIS_RATE_HZ)
        except ValueError as exc:
            result.problems.append(f"forced expiration at {a:.1f} s: {exc}")
            continue
        if len(cut_at):
            if m.time_zero_s + 1.0 > (len(exhaled) - 1) / ANALYSIS_RATE_HZ:
                result.problems.append(f"forced expiration at {a:.1f} s: maps are missing from {stop:.1f} s, less "
                                       "than a second after its time zero (before FEV1): left out")
                continue
            result.problems.append(f"forced expiration at {a:.1f} s: read to {stop:.1f} s, where maps are missing "
                                   f"for longer than {1000 * MAX_BRIDGED_GAP_S:.0f} ms (not read across)")
        if fitted:
            fitted_pef_lps = m.pef_lps
            _peak_flow_read_straight(m, t[blow], v[blow])
            cough_not_judged(m, m.pef_noise_ratio, MAX_PEF_NOISE_RATIO)  # the cough is read on the maps' curve
            start_not_judged(m, m.samples_step_s, MAX_PEF_SAMPLE_INTERVAL_S)
        drawn, frames = exhaled[: i_low + 1], None
        if fitted and peak_flow_volume is not None:
            frames = peak_flow_of_frames(m, *peak_flow_volume, float(tw[i_fitted_top]), stop, fitted_pef_lps)
            if frames is not None:
                drawn = drawn_through_frames(drawn, float(tw[i_fitted_top]), *frames)
        if missing_near_peak and frames is None:  # maps at every frame that hold the peak need no other
            peak_missing.append(a)
        m.mark_s = a
        blows.append(m)
        result.forced_curves.append(drawn)
    if blows:
        result.forced = grade_session(blows, age_years)
        step = result.forced.pef_step_s
        if not np.isfinite(step):
            step = float(np.median(np.diff(t)))
        noise_limit = pef_noise_limit(step)
        if step > MAX_PEF_SAMPLE_INTERVAL_S:
            result.pef_refused = (f"PEF not given: the volume has a sample every {1000 * step:.0f} ms, and a peak "
                                  f"flow needs one at least every {1000 * MAX_PEF_SAMPLE_INTERVAL_S:.0f} ms (an "
                                  "optical map every light cycle)")
            result.problems.append(result.pef_refused)
        elif peak_missing:
            result.pef_refused = (f"PEF not given: a map is missing within {1000 * PEAK_FLOW_WITHIN_S:.0f} ms of "
                                  f"the top of the blow at {peak_missing[0]:.1f} s, where the peak flow is")
            result.problems.append(result.pef_refused)
        elif result.forced.pef_noise_ratio > noise_limit:
            result.pef_refused = (f"PEF not given: the optical volume's noise from map to map is "
                                  f"{100 * result.forced.pef_noise_ratio:.0f} % of the peak flow (a PEF within "
                                  f"10 % needs at most {100 * noise_limit:.0f} % at a map every "
                                  f"{1000 * step:.0f} ms)")
            result.problems.append(result.pef_refused)
    return result


# The most one step's flow noise may be of the PEF, a map a cycle, for the PEF to be given (docs/constants.md)
MAX_PEF_NOISE_RATIO = 0.05


def pef_noise_limit(step_s: float) -> float:
    """The most one step's flow noise may be of the PEF for it to be given, on samples step_s apart."""
    return MAX_PEF_NOISE_RATIO_FRAMES if step_s <= MAX_FRAME_STEP_S else MAX_PEF_NOISE_RATIO


def pef_not_given(m: ForcedValues) -> str | None:
    """Why one blow's PEF is not given, in a few words (the rule the session's PEF is refused by, on the
    samples it was read on); None where it is given. A flow sensor's blow (no noise weighed) always is."""
    step = m.pef_step_s if np.isfinite(m.pef_step_s) else m.samples_step_s
    if not np.isfinite(step):
        return None
    if step > MAX_PEF_SAMPLE_INTERVAL_S:
        return f"a map every {1000 * step:.0f} ms, at least one every {1000 * MAX_PEF_SAMPLE_INTERVAL_S:.0f} ms needed"
    limit = pef_noise_limit(step)
    if not m.pef_noise_ratio <= limit:
        return f"the noise from map to map is {100 * m.pef_noise_ratio:.0f} % of the peak flow (at most {100 * limit:.0f} %)"
    return None


def _peak_flow_read_straight(m: ForcedValues, t_s: np.ndarray, volume_l: np.ndarray) -> None:
    """Give a fitted blow the PEF of its samples read straight, and the noise ratio it is judged by.

    The fit rounds a sharp peak: on the standard waveforms sampled one map a cycle, the peak flow read
    straight was within 10 % more often in every band of noise under 15 % (docs/volume.md). The ratio is taken on
    the fitted PEF, which the noise does not raise."""
    straight = resample(t_s, volume_l)[1]
    exhaled = straight[0] - straight
    peak = int(np.argmax(exhaled))
    m.pef_noise_ratio = pef_noise_ratio(t_s, volume_l, m.pef_lps)
    m.samples_step_s = float(np.median(np.diff(t_s))) if len(t_s) > 1 else float("nan")
    if peak >= 1:
        m.pef_lps = float(np.gradient(exhaled[: peak + 1], 1.0 / ANALYSIS_RATE_HZ).max())


# A curve sampled at most this far apart is one of maps at every frame (9.1 ms at 110 frames/s), whose
# PEF is judged by MAX_PEF_NOISE_RATIO_FRAMES
MAX_FRAME_STEP_S = 0.02
# The same bar at a map every frame (docs/constants.md)
MAX_PEF_NOISE_RATIO_FRAMES = 0.05
# Smoothings (sigma, s) tried in turn on a blow's maps at every frame before its PEF is read (docs/constants.md)
PEAK_FLOW_SIGMAS_S = (0.0, 0.005, 0.01, 0.015, 0.02)


def flow_noise_gain(sigma_steps: float) -> float:
    """The flow noise of one step of a curve Gaussian-smoothed over sigma_steps samples (truncated at 4
    sigma, as scipy's), per unit of the curve's white noise and over the step: sqrt(sum of the squared
    differences of the kernel's neighbouring weights); sqrt(2) unsmoothed."""
    if sigma_steps <= 0:
        return float(np.sqrt(2.0))
    reach = int(4.0 * sigma_steps + 0.5)
    weights = np.exp(-0.5 * (np.arange(-reach, reach + 1) / sigma_steps) ** 2)
    weights /= weights.sum()
    return float(np.sqrt(np.sum(np.diff(np.r_[0.0, weights, 0.0]) ** 2)))


def peak_flow_of_frames(m: ForcedValues, t_s: np.ndarray, volume_l: np.ndarray, top_s: float, end_s: float,
                        fitted_pef_lps: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Give a fitted blow (its top and the end it is read to, s) the PEF of its maps at every frame, where
    they hold its peak flow (at least PEAK_FLOW_MARGIN_S inside their span), are all there (no step over
    MAX_FRAME_STEP_S) and at least 10: read straight on them smoothed with the first of PEAK_FLOW_SIGMAS_S
    whose flow noise (flow_noise_gain times their noise, curve_noise_l, over the step) is at most
    MAX_PEF_NOISE_RATIO_FRAMES of the fitted PEF, else with the last; that ratio, the step and the
    smoothing go with it. Returns the curve it was read on (s on an even grid at ANALYSIS_RATE_HZ,
    litres); else None, and the blow keeps what it had."""
    t, v = np.asarray(t_s, dtype=float), np.asarray(volume_l, dtype=float)
    inside = (t >= top_s) & (t <= end_s)
    t, v = t[inside], v[inside]
    if len(t) < 10 or not np.isfinite(v).all() or np.diff(t).max() > MAX_FRAME_STEP_S:
        return None
    step = float(np.median(np.diff(t)))
    noise_l = curve_noise_l(v)
    for sigma_s in PEAK_FLOW_SIGMAS_S:
        ratio = noise_l * flow_noise_gain(sigma_s / step) / step / fitted_pef_lps if fitted_pef_lps > 0 else np.inf
        if ratio <= MAX_PEF_NOISE_RATIO_FRAMES:
            break
    smoothed = ndimage.gaussian_filter1d(v, sigma_s / step, mode="nearest") if sigma_s > 0 else v
    grid, straight = resample(t, smoothed)
    flow = -np.gradient(straight, 1.0 / ANALYSIS_RATE_HZ)
    peak = int(np.argmax(flow))
    missed_before = t[0] > top_s + MAX_FRAME_STEP_S and grid[peak] < t[0] + PEAK_FLOW_MARGIN_S
    missed_after = t[-1] < end_s - MAX_FRAME_STEP_S and grid[peak] > t[-1] - PEAK_FLOW_MARGIN_S
    if missed_before or missed_after:
        return None
    m.pef_lps = float(flow[peak])
    m.pef_noise_ratio = float(ratio)
    m.pef_step_s = step
    m.pef_smoothing_s = float(sigma_s)
    return grid, straight


def drawn_through_frames(exhaled_l: np.ndarray, start_s: float, frames_t_s: np.ndarray,
                         frames_volume_l: np.ndarray) -> np.ndarray:
    """A fitted blow's exhaled volume (at ANALYSIS_RATE_HZ from start_s) drawn through the maps at every
    frame its PEF was read on (peak_flow_of_frames' curve), so that its flow-volume loop peaks at the PEF
    given: inside their span the maps' exhaled volume, moved onto the fitted curve at both ends of the
    span by an offset straight between them (the two differ by the noise the fit takes out)."""
    t = start_s + np.arange(len(exhaled_l)) / ANALYSIS_RATE_HZ
    inside = (t >= frames_t_s[0]) & (t <= frames_t_s[-1])
    if inside.sum() < 2:
        return exhaled_l
    frames = -np.interp(t[inside], frames_t_s, frames_volume_l)  # exhaled, up to the constant the offset sets
    first, last = np.nonzero(inside)[0][[0, -1]]
    offset_first, offset_last = exhaled_l[first] - frames[0], exhaled_l[last] - frames[-1]
    share = (t[inside] - t[first]) / max(t[last] - t[first], 1e-12)
    out = np.array(exhaled_l, dtype=float)
    out[inside] = frames + offset_first + share * (offset_last - offset_first)
    return out


def pef_noise_ratio(t_s: np.ndarray, volume_l: np.ndarray, pef_lps: float) -> float:
    """The flow noise of one sample step (sqrt(2) times the curve's noise, curve_noise_l, over the
    median step) over a peak flow; infinite for a peak flow of 0 or less."""
    noise_lps = np.sqrt(2.0) * curve_noise_l(volume_l) / float(np.median(np.diff(t_s)))
    return float(noise_lps / pef_lps) if pef_lps > 0 else float("inf")
