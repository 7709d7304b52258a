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

from core.limits import Refusal
from core.volume.maps import REGIONS

MOUTHPIECE_OFF = "mouthpiece-off"  # the event that ends the subject's calibration through the flow sensor
# a calibration whose residual is over this share of the flow sensor's range over the segment is refused
MAX_RESIDUAL_SHARE = 0.05
# a regional gain over this is no surface the cameras see moving with the breath: the fit leans on noise
MAX_REGION_GAIN = 6.0
MIN_SEGMENT_S = 20.0  # quiet breathing and a slow VC take longer; less tells too little
MIN_RANGE_L = 1.0  # the segment must swing this much (a slow VC does; quiet breathing alone does not)
LEAVE_OUT_PARTS = 5  # the segment's parts each predicted from a fit on the others
# the fewest maps a fit takes (at most four gains, an offset and a trend): a rig at 110 frames/s makes 22
# a second, the simulated rig on a busy machine one or two
MIN_FIT_MAPS = 30
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
    """Litres = sum of gains x regional signals (signals of one group share a gain: GROUPINGS), plus
    curvature_per_l x the square of the signals' plain sum (0 unless a curved fit was chosen: CURVED).
    residual_l: rms of the fit over the segment; range_l: the flow sensor's over it; expected_error: the
    rms of the segment's parts' excursion errors predicted from fits on the other parts, as a share of
    range_l (0.02 = 2 %)."""

    gains: dict[str, float]
    segment_s: tuple[float, float]
    residual_l: float
    range_l: float
    expected_error: float
    refused: Refusal | None = None
    samples: int = 0
    curvature_per_l: float = 0.0
    # fit_t_s, fit_l: the fitted curve over the segment, to show; grouping: the GROUPINGS key chosen
    extra: dict = field(default_factory=dict)

    def volume_l(self, signals: dict[str, np.ndarray]) -> np.ndarray:
        linear = sum(g * np.asarray(signals[name], dtype=float) for name, g in self.gains.items())
        if not self.curvature_per_l:
            return linear
        return linear + self.curvature_per_l * sum(np.asarray(signals[name], dtype=float) for name in self.gains) ** 2

    def label(self) -> str:
        return f"optical, calibrated on the subject (residual {1000 * self.residual_l:.0f} mL)"

    @classmethod
    def refused_for(cls, code: str, reason: str, names: tuple[str, ...] = (),
                    segment_s: tuple[float, float] = (0.0, 0.0)) -> SubjectCalibration:
        """A calibration that gave no fit: its gains NaN, why, and what the operator should do (REDO)."""
        return cls({n: float("nan") for n in names}, segment_s, float("nan"), float("nan"), float("nan"),
                   refused=Refusal(code, reason, REDO))


# Maps further apart than this (a step or an arm left them out: core/volume/steps.py) start a new stretch
# with its own offset in the fit: the optical signal's level across such a gap is not known (a mesh
# body read 0.35 L higher after a 36 mm step sideways; docs/history/volume-log.md, "Steps").
MAX_BRIDGE_S = 0.3


def stretches(t_s: np.ndarray) -> np.ndarray:
    """Each map's stretch number: maps more than MAX_BRIDGE_S apart (or three of the maps' usual
    intervals, where they are sparser) begin a new stretch."""
    steps = np.diff(np.asarray(t_s, dtype=float))
    if not len(steps):
        return np.zeros(len(t_s), dtype=int)
    bridge = max(MAX_BRIDGE_S, 3.0 * float(np.median(steps)))
    return np.r_[0, np.cumsum(steps > bridge)].astype(int)


def _design(t_s: np.ndarray, signals: np.ndarray) -> np.ndarray:
    """The signals, an offset for each stretch (stretches) and one linear trend."""
    centred = t_s - t_s.mean()
    stretch = stretches(t_s)
    offsets = (stretch[:, None] == np.unique(stretch)[None, :]).astype(float)
    return np.column_stack([signals, offsets, centred])


def _fit(t_s: np.ndarray, signals: np.ndarray, flow_l: np.ndarray, gains: int | None = None) -> np.ndarray:
    """The first `gains` columns' coefficients (non-negative; default: every signal's), the other signals'
    (a curvature: either sign), then each stretch's offset and the trend, least squares."""
    design = _design(t_s, signals)
    k = signals.shape[1] if gains is None else gains
    lower = np.r_[np.zeros(k), np.full(design.shape[1] - k, -np.inf)]
    upper = np.full(design.shape[1], np.inf)
    return lsq_linear(design, flow_l, bounds=(lower, upper), method="bvls").x


# Groupings of the regional signals, simplest first; more gains only where they predict better (docs/constants.md)
GROUPINGS = {"one gain": lambda name: "all", "chest and abdomen": lambda name: name.split()[-1],
             "each head": lambda name: name.split()[0], "each region": lambda name: name}
SELECTION_MARGIN = 0.9
# Each grouping is tried straight and curved: with a term in the square of the signals' plain sum. The
# level at the trunk's sides moves more per litre near TLC than below it on a trunk that widens, so the
# signal keeps 0.53 of the first half litre of a VC and 0.66 of 3.5 L (docs/volume.md, "Curved").
CURVED = ", curved"


def fit_subject_calibration(map_t_s: np.ndarray, signals: dict[str, np.ndarray], flow_t_s: np.ndarray,
                            flow_volume_l: np.ndarray, segment_s: tuple[float, float],
                            groupings: tuple[str, ...] = tuple(GROUPINGS), curved: bool = True) -> SubjectCalibration:
    """The least squares of the flow sensor's volume on the regional signals over `segment_s` (times in
    seconds on one clock), in the grouping of `groupings` (GROUPINGS' names, simplest first), straight or,
    with `curved`, with a curvature (CURVED), that predicts the segment's parts left out of the fit best;
    a curve that would not rise with the signals over the segment is not taken. Refused (the reason in
    `refused`) where the fit is poor."""
    names = list(signals)
    t = np.asarray(map_t_s, dtype=float)
    x = np.column_stack([np.asarray(signals[n], dtype=float) for n in names]) if names else np.zeros((len(t), 0))
    inside = (t >= segment_s[0]) & (t <= segment_s[1]) & np.isfinite(x).all(axis=1)
    flow_t = np.asarray(flow_t_s, dtype=float)
    inside &= (t >= flow_t[0]) & (t <= flow_t[-1]) if len(flow_t) else np.zeros(len(t), bool)
    empty = SubjectCalibration({n: float("nan") for n in names}, segment_s, float("nan"), float("nan"), float("nan"))
    if not names:
        return SubjectCalibration.refused_for("calibration-no-signal", "no regional optical signal to calibrate",
                                              segment_s=segment_s)
    if inside.sum() < MIN_FIT_MAPS:
        empty.refused = Refusal("calibration-few-maps", f"only {int(inside.sum())} maps with every region in "
                                f"view during the calibration (at least {MIN_FIT_MAPS}): the trunk hidden or the "
                                "maps too few", REDO)
        return empty
    t, x = t[inside], x[inside]
    y = np.interp(t, flow_t, np.asarray(flow_volume_l, dtype=float))
    range_l = float(np.ptp(y))
    plain_sum = x.sum(axis=1)
    square = plain_sum[:, None] ** 2
    chosen, tried = None, set()
    for grouping in groupings:
        group_of = GROUPINGS[grouping]
        groups = sorted({group_of(n) for n in names})
        members = np.array([[group_of(n) == g for g in groups] for n in names], dtype=float)  # names x groups
        if members.tobytes() in tried:  # one head: its chest and abdomen are its regions
            continue
        tried.add(members.tobytes())
        for bend in (False, True) if curved else (False,):
            columns = np.column_stack([x @ members, square]) if bend else x @ members
            if bend and not _rises(t, columns, y, len(groups), plain_sum):
                continue
            held_out, expected = _held_out(t, columns, y, range_l, len(groups))
            if chosen is None or held_out < SELECTION_MARGIN * chosen[4]:
                chosen = (grouping + (CURVED if bend else ""), members, groups, columns, held_out, expected)
    grouping, members, groups, columns, _, expected = chosen
    coefficients = _fit(t, columns, y, len(groups))
    fitted = _design(t, columns) @ coefficients
    residual = float(np.sqrt(np.mean((y - fitted) ** 2)))
    gains = {n: float(members[k] @ coefficients[:len(groups)]) for k, n in enumerate(names)}
    curvature = float(coefficients[len(groups)]) if columns.shape[1] > len(groups) else 0.0
    calibration = SubjectCalibration(gains, segment_s, residual, range_l, expected, samples=len(t),
                                     curvature_per_l=curvature,
                                     extra={"fit_t_s": t, "fit_l": fitted, "grouping": grouping})
    calibration.refused = calibration_refusal(calibration)
    return calibration


def _rises(t: np.ndarray, columns: np.ndarray, y: np.ndarray, gains: int, plain_sum: np.ndarray) -> bool:
    """Whether the curved fit (its last column the plain sum's square) rises with the plain sum over
    the whole span the segment's plain sum covers: its slope along the plain sum positive at both ends."""
    coefficients = _fit(t, columns, y, gains)
    straight = columns[:, :gains] @ coefficients[:gains]
    slope = float(np.polyfit(plain_sum, straight, 1)[0])
    curvature = float(coefficients[gains])
    return all(slope + 2.0 * curvature * end > 0 for end in (plain_sum.min(), plain_sum.max()))


def _held_out(t: np.ndarray, x: np.ndarray, y: np.ndarray, range_l: float,
              gains: int | None = None) -> tuple[float, float]:
    """Each of LEAVE_OUT_PARTS contiguous parts of the segment predicted from a fit on the others: (the rms
    of the predictions' errors about each part's own level, L; the rms of the parts' excursion errors as a
    share of the flow sensor's range over the segment, the expected error of a slow VC's worth)."""
    edges = np.linspace(t[0], t[-1], LEAVE_OUT_PARTS + 1)
    residuals, excursions = [], []
    for a, b in zip(edges[:-1], edges[1:]):
        held = (t >= a) & (t <= b)
        if held.sum() < 10 or (~held).sum() < MIN_FIT_MAPS:
            continue
        predicted = x[held] @ _fit(t[~held], x[~held], y[~held], gains)[:x.shape[1]]
        error = predicted - y[held]
        residuals.append(error - error.mean())
        excursions.append((np.ptp(predicted) - np.ptp(y[held])) / range_l)
    if not residuals:
        return float("nan"), float("nan")
    return float(np.sqrt(np.mean(np.square(np.concatenate(residuals))))), float(np.sqrt(np.mean(np.square(excursions))))


REDO = "repeat the calibration: quiet breathing and one slow VC through the mouthpiece"


def calibration_refusal(calibration: SubjectCalibration) -> Refusal | None:
    """Why the subject's calibration cannot be used, with what the operator should do; None if it can."""
    if calibration.range_l < MIN_RANGE_L:
        return Refusal("calibration-small-swing", f"the flow sensor's volume swings {calibration.range_l:.2f} L during "
                       f"the calibration (at least {MIN_RANGE_L:.1f} L: a slow VC)", REDO)
    share = calibration.residual_l / calibration.range_l
    if share > MAX_RESIDUAL_SHARE:
        return Refusal("calibration-poor-fit", f"the optical signals follow the flow sensor within {100 * share:.1f} % "
                       f"of its range (at most {100 * MAX_RESIDUAL_SHARE:.0f} %)", REDO)
    gains = np.array(list(calibration.gains.values()))
    if not np.any(gains > 0):
        return Refusal("calibration-no-follow", "no region's signal follows the flow sensor's volume", REDO)
    worst = max(calibration.gains, key=calibration.gains.get)
    if calibration.gains[worst] > MAX_REGION_GAIN:
        return Refusal("calibration-gain", f"the {worst} signal would be weighed {calibration.gains[worst]:.1f} times "
                       f"(at most {MAX_REGION_GAIN:.0f}): it moves too little to be measured", REDO)
    return None
