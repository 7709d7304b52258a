"""The metric optical volume: litres from the height maps of one or both heads, without a training step.

Each head's maps are compared with its first map in the body's own frame (core/volume/maps.py,
DisplacementTracker): the current map is resampled so its trunk lies on the reference's
(BodySilhouette: widths between the trunk's sides on the same body rows, the blurred silhouettes'
shift), both are referred to the level the trunk has at its sides (so a rigid shift along
the axis is not breathing), and the displacement of every pixel, weighted by its metric footprint
(Z / fx)(Z / fy), adds up to the volume the trunk gained on that head's side.

The depth map's absolute scale is the weak point: the surface's relief above its sides (10-25 L per
head for an adult, the neck and shoulders included) scales with it, so a map 1 % too far reads
0.1-0.25 L too much. The
scale of every map is therefore set from a distance that does not follow breathing:
- two heads: the trunk's widths between its sides and the baseline (D_f / D_b = W_b / W_f,
  D_f + D_b = baseline; lateral expansion widens both alike), smoothed over WIDTH_SMOOTHING_S;
- one head: the depth of the sides in the maps themselves, smoothed over SIDE_SMOOTHING_S.
The level each map is referred to is fitted over the whole session where it agrees with each map's
own (session_shifts, level_agreement): each map's own carries the band's noise many times over.
Measured limits on simulated subjects: docs/volume.md.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from scipy import ndimage

from core.volume.noise import curve_noise_l
from core.rig import Head
from core.volume.steps import StepWatch
from core.volume.maps import (REGIONS, DisplacementSums, DisplacementTracker, head_volume_l, maps_within,
                              metric_head_volume_l, row_widths_px, smooth_in_time, trunk_width_px,
                              two_head_distances)

# Sigma (s) the two heads' distances are smoothed over: short enough to follow sway (docs/constants.md)
WIDTH_SMOOTHING_S = 0.3
# The live view's distances follow the two heads' widths with an exponential time constant of this (s):
# causal, and on one map at a time, so smoothed longer
LIVE_WIDTH_TIME_CONSTANT_S = 1.0
LIVE_REFERENCE_MAPS = 200  # the maps whose median gives the live view the reference's trunk width
SIDE_SMOOTHING_S = 3.0
# No series of the maps is smoothed across a longer gap between them: a step's (docs/constants.md)
MAX_SMOOTHED_GAP_S = 0.15
VOLUME_SMOOTHING_S = 0.03  # the maps' own noise; a forced expiration's volume curve has little above 5 Hz
# A head's map scale this far from 1: the two views' trunk sides are not the same (docs/volume.md).
MAX_SCALE_MISMATCH = 0.08
# The most map-to-map noise (L, robust rms) a curve may carry and give values (docs/constants.md)
MAX_MAP_NOISE_L = 0.05
# A map over JUMP_L off the median of its JUMP_WINDOW_S has jumped (docs/constants.md)
JUMP_WINDOW_S = 0.4
JUMP_L = 0.1
MAX_JUMP_SHARE = 0.01
# A map whose trunk is this much wider than its rows' median ratio to the reference says has an arm
# taken into its outline on some rows, and is left out (docs/constants.md)
MAX_OUTLINE_EXCESS = 0.03
# An arm only widens the outline: the trunk's own width is read on the narrower maps, this percentile
# of them, so an arm in up to three quarters of the maps is still found
OUTLINE_REFERENCE_PERCENTILE = 25.0


def arm_in_outline(outline_excess: np.ndarray) -> np.ndarray:
    """Per map (or for one), whether an arm was taken into the trunk's outline: its excess width
    (HeadDisplacements.outline_excess) over MAX_OUTLINE_EXCESS. Such a map's trunk sides, and the level
    they give, are the arm's on those rows. A map without the excess measured (NaN) counts as clear."""
    return np.asarray(outline_excess, dtype=float) > MAX_OUTLINE_EXCESS


def jump_share(timestamp_ns: np.ndarray, volume_l: np.ndarray) -> tuple[float, float]:
    """(share of maps, largest jump in L) whose volume lies more than JUMP_L from the median of
    the maps within JUMP_WINDOW_S: a breath, even a forced one, moves the volume steadily one way
    over that time, so the median follows it, and a map off it by 100 mL has jumped."""
    t = np.asarray(timestamp_ns, dtype=float) / 1e9
    v = np.asarray(volume_l, dtype=float)
    good = np.isfinite(v)
    t, v = t[good], v[good]
    if len(v) < 5:
        return float("nan"), float("nan")
    off = np.abs(v - ndimage.median_filter(v, maps_within(t, JUMP_WINDOW_S), mode="nearest"))
    return float(np.mean(off > JUMP_L)), float(off.max())


@dataclass
class HeadDisplacements:
    timestamp_ns: np.ndarray
    sums: list[DisplacementSums]

    def series(self, key: str, region: str) -> np.ndarray:
        return np.array([getattr(s, key).get(region, np.nan) for s in self.sums], dtype=float)

    def series_of(self, key: str) -> np.ndarray:
        """A number each map's DisplacementSums carries (NaN where an older one lacks it)."""
        return np.array([getattr(s, key, np.nan) for s in self.sums], dtype=float)

    def of_maps(self, kept: np.ndarray) -> "HeadDisplacements":
        """These displacements on the maps `kept` (a mask over them) only."""
        return HeadDisplacements(self.timestamp_ns[kept], [s for s, k in zip(self.sums, kept) if k])

    @cached_property
    def session_shifts_mm(self) -> np.ndarray | None:
        """Each map's shift from the reference fitted over the session (session_shifts), or None."""
        return session_shifts(self.timestamp_ns, self.sums)

    @cached_property
    def _own_level_over_session_mm(self) -> np.ndarray:
        """Per map, how far its own level lies from the reference's plus the session's shift."""
        levels = np.array([s.levels_mm for s in self.sums], dtype=float).reshape(-1, 2)
        return levels[:, 1] - levels[:, 0] - self.session_shifts_mm

    def current(self, region: str, session_level: bool) -> np.ndarray:
        """The current maps' sums of a region, each referred to the reference's level plus its shift over the
        session (session_shifts_mm) with session_level and where there is one, else to its own level
        (RimModel.level)."""
        current = self.series("current", region)
        if not session_level or self.session_shifts_mm is None:
            return current
        return current + self._own_level_over_session_mm * self.series("areas", region)

    @property
    def body_shift_mm(self) -> np.ndarray:
        """(maps, 2) the body's in-plane shift since the reference (DisplacementSums.body_shift_mm)."""
        return np.array([s.body_shift_mm for s in self.sums], dtype=float).reshape(-1, 2)

    @property
    def side_mm(self) -> np.ndarray:
        return np.array([s.side_mm for s in self.sums], dtype=float)

    @cached_property
    def _mean_width_px(self) -> np.ndarray:
        return np.array([s.width_px for s in self.sums], dtype=float)

    @cached_property
    def _width_ratio(self) -> np.ndarray:
        return np.array([s.width_ratio for s in self.sums], dtype=float)

    @cached_property
    def _reference_width_each_map_px(self) -> np.ndarray:
        """Per map, its mean trunk width over its width_ratio: the reference's width as that map gives it."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return self._mean_width_px / self._width_ratio

    @property
    def width_px(self) -> np.ndarray:
        """Each map's trunk width (px) as the reference's width times the map's width_ratio: the median
        of its rows' ratios, which an arm joining the trunk on some rows does not move. The
        reference's width is the median over the maps of their mean width over their ratio, so an
        arm on the reference map itself moves none of them either. A map without a ratio keeps
        its mean width."""
        mean, ratio, per_map = self._mean_width_px, self._width_ratio, self._reference_width_each_map_px
        if not np.isfinite(per_map).any():
            return mean
        return np.where(np.isfinite(ratio), ratio * np.nanmedian(per_map), mean)

    @property
    def outline_excess(self) -> np.ndarray:
        """Per map, how much wider its trunk's mean width is than the median of its rows' ratios to the
        reference says (0 within the noise), against the narrower maps (OUTLINE_REFERENCE_PERCENTILE):
        an arm taken into the outline widens its own rows only, breathing and sway widen all of them
        alike. NaN without a ratio."""
        per_map = self._reference_width_each_map_px
        if not np.isfinite(per_map).any():
            return np.full(len(per_map), np.nan)
        return per_map / np.nanpercentile(per_map, OUTLINE_REFERENCE_PERCENTILE) - 1.0


@dataclass
class MetricVolume:
    timestamp_ns: np.ndarray  # the first head's map times
    volume_l: np.ndarray  # both heads, since the first map (positive = inhaled)
    heads: dict[str, np.ndarray]  # each head's part, on timestamp_ns
    regions: dict[str, np.ndarray]  # each trunk quadrant over the heads (REGIONS), on timestamp_ns
    side_distance_mm: dict[str, np.ndarray]  # the distance each head's sides were scaled to
    scale_from: str
    scale_mismatch: dict[str, float] = field(default_factory=dict)  # median |k - 1| of each head's maps
    # each head's level: "the session's" (session_shifts) or "each map's own" (RimModel.level)
    levels: dict[str, str] = field(default_factory=dict)
    # each head's trunk quadrants (REGIONS), on timestamp_ns: the regional signals the subject's
    # calibration weighs (core/volume/subject_calibration.py)
    head_regions: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def with_gaps(self, timestamp_ns: np.ndarray, maps_shown: dict[str, tuple[np.ndarray, np.ndarray]],
                  ) -> "MetricVolume":
        """This volume, made from some of the first head's maps, on all of them (`timestamp_ns`): NaN
        at a map left out, and at one whose nearest map in any head's (times, shown) was left out.
        What no map shows is not bridged: a curve straight across an arm's swing would hand the
        analysis a blow or a breath that was not measured."""
        t = np.asarray(timestamp_ns, dtype=np.int64)
        gap = ~np.isin(t, self.timestamp_ns)
        for times, shown in maps_shown.values():
            times = np.asarray(times, dtype=np.int64)
            after = np.clip(np.searchsorted(times, t), 1, len(times) - 1) if len(times) > 1 else np.zeros(len(t), int)
            nearest = after - (np.abs(t - times[after - 1]) < np.abs(times[after] - t)) if len(times) > 1 else after
            gap |= ~np.asarray(shown, dtype=bool)[nearest]
        at = np.searchsorted(self.timestamp_ns, t[~gap])

        def spread(values: np.ndarray) -> np.ndarray:
            out = np.full(len(t), np.nan)
            out[~gap] = np.asarray(values, dtype=float)[at]
            return out

        return replace(self, timestamp_ns=t, volume_l=spread(self.volume_l),
                       heads={n: spread(v) for n, v in self.heads.items()},
                       regions={r: spread(v) for r, v in self.regions.items()},
                       head_regions={n: {r: spread(v) for r, v in rs.items()} for n, rs in self.head_regions.items()},
                       side_distance_mm={n: on_maps_shown(v, maps_shown[n][1])
                                         for n, v in self.side_distance_mm.items()})


def on_maps_shown(values: np.ndarray, shown: np.ndarray) -> np.ndarray:
    """Values of the maps shown, on all the maps (NaN on the others)."""
    out = np.full(len(shown), np.nan)
    out[np.asarray(shown, dtype=bool)] = values
    return out


def side_targets(heads: dict[str, HeadDisplacements], baseline_mm: float | None) -> tuple[dict[str, np.ndarray], str]:
    """The distance each map's sides are scaled to, on each head's own times."""
    names = list(heads)
    if len(names) == 2 and baseline_mm:
        front, back = heads[names[0]], heads[names[1]]
        t = front.timestamp_ns.astype(float) / 1e9
        back_width = np.interp(t, back.timestamp_ns.astype(float) / 1e9, _bridged(back.width_px))
        d_front, _ = two_head_distances(_bridged(front.width_px), back_width, baseline_mm)
        d_front = smooth_in_time(t, d_front, WIDTH_SMOOTHING_S, MAX_SMOOTHED_GAP_S)
        d_back = np.interp(back.timestamp_ns.astype(float) / 1e9, t, baseline_mm - d_front)
        return {names[0]: d_front, names[1]: d_back}, "trunk widths and the baseline"
    return ({n: smooth_in_time(h.timestamp_ns.astype(float) / 1e9, h.side_mm, SIDE_SMOOTHING_S, MAX_SMOOTHED_GAP_S)
             for n, h in heads.items()}, "each head's side depth, smoothed")


def _bridged(x: np.ndarray) -> np.ndarray:
    good = np.isfinite(x)
    if not good.any():
        return x
    i = np.arange(len(x))
    return np.interp(i, i[good], x[good])


# The parts whose breathing the band's follows (session_shifts): the chest wall's two compartments,
# the rib cage and the abdomen (Konno and Mead), as the trunk's upper and lower halves
COMPARTMENTS = (("upper left", "upper right"), ("lower left", "lower right"))
MIN_SESSION_MAPS = 20  # fewer maps with a band leave each map's own level


def session_shifts(timestamp_ns: np.ndarray, sums: list[DisplacementSums]) -> np.ndarray | None:
    """Each map's shift along the axis from the reference (mm; NaN for a map without a band), fitted
    over the whole session; None with fewer than MIN_SESSION_MAPS maps that have a band.

    Each map's own level (RimModel.level) fits a hinge and a stretch amount for every edge of the band
    and one shift: unbiased, but the shift is what the amounts leave, a few per cent of the band's
    information, and it carries the band's noise many times over (a population body in the clinic
    world: 0.8 mm from map to map, about 50 mL on one head, and jumps; docs/volume.md). But an edge's
    breathing keeps its shape over a session: the band moves as the trunk beside it breathes, and the
    chest wall breathes with two compartments, rib cage and abdomen (Konno and Mead). So here each
    edge's hinge and stretch amounts are constant over the session, times the breathing of the two
    halves of the trunk (COMPARTMENTS: the footprint-weighted mean displacement of each half less the
    band's mean, which no shift moves), and each map keeps one unknown, its shift:
        y_ep(t) = s(t) + sum_k D_k(t) (a_ek h_ep + b_ek l_ep).
    The least squares over all maps and edges is solved exactly (session_fit), on the halves' breathing
    as steady_breathing gives it."""
    usable = [i for i, x in enumerate(sums) if x.band is not None and len(x.band) and np.isfinite(x.band).all()
              and np.isfinite(x.levels_mm).all()
              and all(np.isfinite(x.displaced.get(r, np.nan)) for part in COMPARTMENTS for r in part)
              and all(sum(x.areas.get(r, 0.0) for r in part) > 0 for part in COMPARTMENTS)]
    if len(usable) < MIN_SESSION_MAPS:
        return None
    stats = np.stack([sums[i].band for i in usable])  # T, edges, EDGE_STATISTICS
    with np.errstate(invalid="ignore", divide="ignore"):
        band_mean = stats[..., 1].sum(axis=1) / stats[..., 0].sum(axis=1)
        breathing = np.stack([sum(sums[i].displaced[r] for r in part) / sum(sums[i].areas[r] for r in part)
                              for i in usable for part in COMPARTMENTS]).reshape(len(usable), len(COMPARTMENTS))
    breathing -= band_mean[:, None]
    if not (np.isfinite(breathing).all() and np.isfinite(band_mean).all()):
        return None
    seconds = np.asarray(timestamp_ns, dtype=float)[usable] / 1e9
    shifts = session_fit(stats, steady_breathing(seconds, breathing))
    if shifts is None:
        return None
    out = np.full(len(sums), np.nan)
    out[usable] = shifts
    return out


# The halves' mean breathing despiked (a blow is not spread), their difference smoothed (docs/constants.md)
DESPIKE_WINDOW_S = 0.2
DESPIKE_MADS = 3.0
BREATHING_SMOOTHING_S = 0.1


def steady_breathing(seconds: np.ndarray, halves: np.ndarray) -> np.ndarray:
    """(maps, 2): the mean of the two halves' breathing (maps, 2) despiked (despiked), and their
    difference smoothed over BREATHING_SMOOTHING_S; the same span as the halves themselves."""
    mean = despiked(seconds, halves.mean(axis=1), DESPIKE_WINDOW_S, DESPIKE_MADS)
    difference = smooth_in_time(seconds, halves[:, 0] - halves[:, 1], BREATHING_SMOOTHING_S, MAX_SMOOTHED_GAP_S)
    return np.stack([mean, difference], axis=1)


def despiked(seconds: np.ndarray, values: np.ndarray, window_s: float, mads: float) -> np.ndarray:
    """A series with every value that lies more than `mads` robust deviations (1.4826 MAD over the
    series) from the median of the values within `window_s` replaced by that median (a Hampel filter);
    the others unchanged."""
    values = np.asarray(values, dtype=float)
    if len(values) < 3:
        return values.copy()
    median = ndimage.median_filter(values, maps_within(seconds, window_s), mode="nearest")
    deviation = np.abs(values - median)
    scale = 1.4826 * float(np.median(deviation))
    return np.where(deviation > mads * scale, median, values)


def session_fit(stats: np.ndarray, breathing: np.ndarray) -> np.ndarray | None:
    """The least squares of session_shifts on (maps, edges, EDGE_STATISTICS) sums and (maps,
    compartments) breathing: each map's shift, or None where it has no solution. Each edge's 2 K
    amounts are eliminated (their normal equations G a = r - B s), which leaves a maps x maps system
    for the shifts."""
    n, sy, sh, sl, syh, syl, shh, shl, sll = np.moveaxis(stats, 2, 0)
    maps, compartments = breathing.shape
    profile_sums, profile_y = (sh, sl), (syh, syl)
    profile_products = ((shh, shl), (shl, sll))
    pairs = [(k, a) for k in range(compartments) for a in range(2)]
    b = np.stack([breathing[:, k, None] * profile_sums[a] for k, a in pairs], axis=1).T  # edges, 2K, maps
    g = np.stack([np.stack([np.einsum("t,t,te->e", breathing[:, k], breathing[:, m], profile_products[a][c])
                            for m, c in pairs], axis=-1) for k, a in pairs], axis=1)  # edges, 2K, 2K
    r = np.stack([np.einsum("t,te->e", breathing[:, k], profile_y[a]) for k, a in pairs], axis=1)  # edges, 2K
    g_inverse = np.linalg.pinv(g)
    c = np.einsum("eij,ejt->eit", g_inverse, b)
    system = np.diag(n.sum(axis=1)) - b.reshape(-1, maps).T @ c.reshape(-1, maps)
    right = sy.sum(axis=1) - np.einsum("eit,ei->t", b, np.einsum("eij,ej->ei", g_inverse, r))
    try:
        return np.linalg.solve(system, right)
    except np.linalg.LinAlgError:
        return None


# The session's level only where each map's own fails and the two agree (docs/constants.md)
MAX_LEVEL_GAIN = 0.05
MAX_LEVEL_LAG_S = 0.1
GAIN_HUBER = 1.5  # residuals beyond this many robust sigmas weigh less (Huber)


def level_agreement(timestamp_ns: np.ndarray, session_l: np.ndarray, each_map_l: np.ndarray) -> tuple[float, float]:
    """(gain, lag in s) of a head's volume with each map's own level on the same volume with the
    session's level and its rate (robust least squares: each_map = gain (session - lag d/dt session) +
    offset); NaN where fewer than 10 maps have both."""
    t = np.asarray(timestamp_ns, dtype=float) / 1e9
    good = np.isfinite(session_l) & np.isfinite(each_map_l)
    if good.sum() < 10:
        return float("nan"), float("nan")
    t, x, y = t[good], np.asarray(session_l, float)[good], np.asarray(each_map_l, float)[good]
    design = np.column_stack([x, np.gradient(x, t), np.ones_like(x)])
    weight = np.ones_like(y)
    for _ in range(20):
        coefficients = np.linalg.lstsq(design * weight[:, None], y * weight, rcond=None)[0]
        residual = y - design @ coefficients
        sigma = 1.4826 * float(np.median(np.abs(residual))) + 1e-12
        weight = np.sqrt(np.minimum(1.0, GAIN_HUBER * sigma / np.maximum(np.abs(residual), 1e-12)))
    gain = float(coefficients[0])
    return gain, float(-coefficients[1] / gain) if gain else float("nan")


def metric_volume(heads: dict[str, HeadDisplacements], baseline_mm: float | None,
                  levels_of: dict[str, str] | None = None, smoothing_s: float = VOLUME_SMOOTHING_S) -> MetricVolume:
    """Both heads' volumes on the first head's times, their sum and the regions' sums. levels_of: each
    head's level as another volume of the same session chose it (MetricVolume.levels), instead of
    choosing here. smoothing_s: the sigma each head's volume is smoothed over in time (0: none)."""
    targets, scale_from = side_targets(heads, baseline_mm)
    t = next(iter(heads.values())).timestamp_ns
    per_head, head_regions = {}, {}
    mismatch, levels = {}, {}
    for name, h in heads.items():
        side, target = h.side_mm, targets[name]
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.abs(target / side - 1.0)
        mismatch[name] = float(np.nanmedian(ratio)) if np.isfinite(ratio).any() else float("nan")

        def on_t(values: np.ndarray) -> np.ndarray:
            return np.interp(t.astype(float), h.timestamp_ns.astype(float), _bridged(values))

        def volume(region: str, session_level: bool) -> np.ndarray:
            return metric_head_volume_l(h.series("reference", region), h.current(region, session_level), side, target)

        whole = volume("all", False)
        session_whole = volume("all", True) if h.session_shifts_mm is not None else None
        if session_whole is None:
            session = False
        elif levels_of is not None:
            session = levels_of.get(name) == "the session's"
        else:
            session = jump_share(h.timestamp_ns, whole)[0] > MAX_JUMP_SHARE or curve_noise_l(whole) > MAX_MAP_NOISE_L
            if session:
                gain, lag = level_agreement(h.timestamp_ns, session_whole, whole)
                session = abs(gain - 1.0) <= MAX_LEVEL_GAIN and abs(lag) <= MAX_LEVEL_LAG_S
        if session:
            whole = session_whole
        levels[name] = "the session's" if session else "each map's own"
        per_head[name] = on_t(whole)
        head_regions[name] = {r: on_t(volume(r, session)) for r in REGIONS}
    seconds = t.astype(float) / 1e9

    def smooth(values: np.ndarray) -> np.ndarray:
        return smooth_in_time(seconds, values, smoothing_s, MAX_SMOOTHED_GAP_S) if smoothing_s > 0 else values

    per_head = {name: smooth(v) for name, v in per_head.items()}
    volume = sum(per_head.values())
    head_regions = {n: {r: smooth(v) for r, v in rs.items()} for n, rs in head_regions.items()}
    regions = {r: sum(rs[r] for rs in head_regions.values()) for r in REGIONS}
    return MetricVolume(t, volume, per_head, regions, targets, scale_from, mismatch, levels, head_regions)



class LiveMetricVolume:
    """The metric volume map by map, for the live view: causal, so each map's scale comes from the
    trunk widths seen so far (two heads; the body frame's scale too, as `process` takes it from the
    heads' geometry) or the rim depth (one head), smoothed by an exponential average with the time
    constants above. Each head's maps come from one thread;
    `add` may be called from a thread per head."""

    def __init__(self, heads: dict[str, Head], baseline_mm: float | None) -> None:
        self._trackers = {name: DisplacementTracker(head) for name, head in heads.items()}
        self._names = list(heads)
        self._two_heads = len(heads) == 2 and bool(baseline_mm)
        self._baseline = baseline_mm
        self._lock = threading.Lock()
        self._width: dict[str, float] = {}
        # per head, each map's mean trunk width over its width_ratio: the reference's width as the maps
        # so far agree on it (HeadDisplacements.width_px, causally), the last LIVE_REFERENCE_MAPS of them
        self._reference_widths: dict[str, deque[float]] = {name: deque(maxlen=LIVE_REFERENCE_MAPS) for name in heads}
        self._robust_width: dict[str, float] = {}
        self._target: dict[str, tuple[float, float]] = {}  # head -> (time s, smoothed distance)
        self._k_reference: dict[str, float] = {}
        self._reference_side: dict[str, float] = {}
        self._volume = {name: 0.0 for name in heads}
        self._regions: dict[str, dict[str, float]] = {}  # each head's quadrants as its last map gave them
        self._geometric: dict[str, float] = {}  # each head's subject distance from the two heads' geometry
        self._steps = {name: StepWatch() for name in heads}  # a step's maps give no volume (core/volume/steps.py)

    def _smoothed(self, name: str, t_s: float, value: float, time_constant_s: float) -> float:
        if name in self._target:
            t_last, last = self._target[name]
            weight = 1.0 - np.exp(-max(t_s - t_last, 0.0) / time_constant_s)
            value = last + weight * (value - last)
        self._target[name] = (t_s, value)
        return value

    def geometric_distance_mm(self, name: str) -> float | None:
        """The head's subject distance (median depth) where the two heads' trunk widths and baseline put
        its last map (as core/pipeline/distance_pass.py's geometric_distances, causally); None before both heads
        have a trunk in view, and with one head."""
        with self._lock:
            return self._geometric.get(name)

    def add(self, name: str, t_s: float, depth_mm: np.ndarray, mask: np.ndarray,
            distance_mm: float | None = None, silhouette: np.ndarray | None = None) -> float:
        """Feed one head's map (and its median depth, for geometric_distance_mm; its silhouette, as
        DisplacementTracker.add takes it); the volume (L) both heads have seen since their first
        maps, or NaN while a head has no trunk in view yet."""
        tracker = self._trackers[name]
        target = frame_distance = row_widths = None
        if self._two_heads:
            # the body frame's scale from the two heads' geometry, as `process` has it: a head's maps
            # enter its tracker once the other head has a trunk width
            valid = mask & np.isfinite(depth_mm)
            row_widths = row_widths_px(depth_mm, valid, tracker.head)
            width = trunk_width_px(depth_mm, valid, tracker.head, row_widths)
            with self._lock:
                # the width the rows' median ratio gave the head's last map: an arm joining the trunk on
                # some rows does not move it (one map late, well inside LIVE_WIDTH_TIME_CONSTANT_S)
                width = self._robust_width.get(name, width)
                if np.isfinite(width):
                    self._width[name] = width
                if len(self._width) < 2 or name not in self._width:
                    return float("nan")
                front, back = self._names
                d_front, _ = two_head_distances(np.array([self._width[front]]), np.array([self._width[back]]),
                                                self._baseline)
                frame_distance = float(d_front[0]) if name == front else self._baseline - float(d_front[0])
                target = self._smoothed(name, t_s, frame_distance, LIVE_WIDTH_TIME_CONSTANT_S)
        sums = tracker.add(depth_mm, mask, silhouette, frame_distance, row_widths)
        with self._lock:
            arm = False
            if np.isfinite(sums.width_ratio) and np.isfinite(sums.width_px) and sums.width_ratio > 0:
                widths = self._reference_widths[name]
                each = sums.width_px / sums.width_ratio
                arm = bool(widths) and bool(arm_in_outline(each / float(np.median(widths)) - 1.0))
                if not arm:
                    widths.append(each)
                    self._robust_width[name] = sums.width_ratio * float(np.median(widths))
            # a step's maps, and a map with an arm in its outline (as `process` leaves them out), give no
            # volume: the other head's sum too, until they end
            if self._steps[name].moving(t_s, sums.body_shift_mm) or arm:
                self._volume[name] = float("nan")
                self._regions[name] = {r: float("nan") for r in REGIONS}
                return float("nan")
            if not np.isfinite(sums.side_mm) or "all" not in sums.reference:
                return float("nan")
            reference_side = self._reference_side.setdefault(name, sums.side_mm)  # the first is the reference
            if target is None:
                target = self._smoothed(name, t_s, sums.side_mm, SIDE_SMOOTHING_S)
            k = target / sums.side_mm
            if self._two_heads and distance_mm is not None and np.isfinite(distance_mm * k):
                self._geometric[name] = float(distance_mm * k)
            k_reference = self._k_reference.setdefault(name, target / reference_side)
            self._volume[name] = float(head_volume_l(sums.reference["all"], sums.current["all"], k_reference, k))
            self._regions[name] = {r: float(head_volume_l(sums.reference[r], sums.current[r], k_reference, k))
                                   for r in REGIONS if r in sums.reference and r in sums.current}
            return sum(self._volume.values()) if len(self._k_reference) == len(self._names) else float("nan")

    def head_regions(self) -> dict[str, dict[str, float]]:
        """Each head's trunk quadrants (L) as its last map gave them, once every head has one: what the
        subject's calibration weighs (core/volume/subject_calibration.py, regional_signals); {} before."""
        with self._lock:
            if len(self._regions) < len(self._names):
                return {}
            return {name: dict(quadrants) for name, quadrants in self._regions.items()}
