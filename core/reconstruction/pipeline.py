"""The Reconstructor: light cycles in, normals, metric depth, distance and gradient volume out.

The same object serves `photopft process` (offline, over a session file) and the live view
(over the capture stream), so what the operator saw is what the report says.

Per cycle (thesis Table 4.1, then past it):
1. subject mask from the summed signal; saturated or shadowed lights left out per pixel;
2. pseudo normals with the pseudo light vectors (distant-light photometric stereo, eq. 3.4-3.7);
3. distance from the diffused maxima regions (eq. 4.13, core/reconstruction/distance.py), the thesis' way;
4. metric depth: the pseudo normals integrated in perspective and scaled so that the depth at
   the regions' centres is the triangulated one;
5. per-pixel light vectors from that depth, with inverse-square falloff and the LEDs'
   relative intensities, normals solved again, integrated again; repeated until the depth
   settles (`iterations`).

Past the thesis (distance="photometric", the default): on a curved subject the diffused maxima
regions do not lie on the lines the thesis triangulates with, so their distance follows the
subject's shape more than its place (measured: about 1800 mm for a torso anywhere between 1800
and 2200 mm). Each iteration instead scales the integrated shape to the distance at which the
near-light model explains all four lights best (core/reconstruction/distance.py). With `track`, a
reconstructor remembers the last distance and only searches near it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from core.reconstruction.distance import DMR_THRESHOLD, MIN_FIT_PIXELS, DmrEstimate, PhotometricDistance, dmr_distance
from core.reconstruction.integrate import ROBUST_ITERATIONS, integrate_dct, integrate_masked, log_depth_gradients
from core.reconstruction.lens import LensCorrection, needs_correction
from core.reconstruction.photometric import distant_light_normals, gradients_from_normals, near_light_normals
from core.reconstruction.prefilter import noise_binning, prefilter_sigma_px, prefiltered
from core.reconstruction.reflectance import RedundancyFit, redundancy_fit
from core.rig import Head

NOMINAL_DISTANCE_MM = 2000.0
EDGE_GROWTH_PX = 3
DISTANCE_RESET = 0.05  # relative change of the distance from one cycle to the next that is not noise
MIN_SUBJECT_PIXELS = MIN_FIT_PIXELS  # fewer lit pixels than this: no subject in the cycle


@dataclass(frozen=True)
class ReconstructionSettings:
    method: str = "near"  # near: per-pixel lights (this project); distant: traditional photometric stereo
    integrator: str = "masked"  # masked: least squares on the subject; dct: faster, flattens (core/reconstruction/integrate.py)
    iterations: int = 2
    mask_fraction: float = 0.1  # subject: summed signal above this fraction of its 99th percentile
    # ... and its edge grown into what is above this fraction (None: eroded by a pixel instead)
    mask_edge_fraction: float | None = 0.03
    shadow_fraction: float = 0.02  # a light below this fraction of the subject's brightness counts as shadowed
    dmr_threshold: float = DMR_THRESHOLD
    max_depth_change_mm: float = 0.05  # stop iterating when the depth moves less than this (median)
    distance: str = "photometric"  # photometric (this project) or dmr (thesis eq. 4.13 only)
    track: bool = False  # search the distance near the previous cycle's (streams of one subject)
    distance_pixels: int = 250000  # pixels the photometric distance uses (its noise falls as 1/sqrt)
    # first cycle: fit the lights' relative intensities with the distance (for a rig whose LEDs have
    # drifted since their calibration; it costs accuracy on small subjects, docs/reconstruction.md)
    fit_intensity: bool = False
    # The distance of one cycle scatters by several mm (camera noise); each cycle's estimate is
    # averaged with the previous ones over about this many cycles (1: none; RunningDistance).
    distance_cycles: int = 5
    # Gaussian sigma (pixels) on the images before the normals are solved (core/reconstruction/prefilter.py);
    # None: chosen from the head's width (0 up to about 1000 px wide, 0.56 at 1400)
    prefilter_px: float | None = None

    def __post_init__(self) -> None:
        if self.distance not in ("photometric", "dmr"):
            raise ValueError(f"distance must be 'photometric' or 'dmr', got {self.distance!r}")
        if self.method not in ("near", "distant"):
            raise ValueError(f"method must be 'near' or 'distant', got {self.method!r}")
        if self.integrator not in ("dct", "masked"):
            raise ValueError(f"integrator must be 'dct' or 'masked', got {self.integrator!r}")


@dataclass
class HeadMap:
    normals: np.ndarray  # (H, W, 3), NaN off the mask
    depth_mm: np.ndarray  # (H, W), NaN off the mask
    albedo: np.ndarray
    mask: np.ndarray
    distance_mm: float  # median depth of the subject
    dmr: DmrEstimate
    gradient_volume: float
    iterations_done: int = 0
    extra: dict[str, float] = field(default_factory=dict)
    silhouette: np.ndarray | None = None  # the trunk's pixels, those without a normal or depth included


def default_pseudo_light_vectors(head: Head, distance_mm: float = NOMINAL_DISTANCE_MM) -> np.ndarray:
    """Unit vectors from the point on the optical axis at `distance_mm` towards each light."""
    d = head.light_positions_mm - np.array([0.0, 0.0, distance_mm])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def gradient_volume(normals: np.ndarray, mask: np.ndarray) -> float:
    """Thesis eq. 3.26 for one head: (1/k) sum(|p| + |q|) over the k valid pixels."""
    p, q = gradients_from_normals(normals)
    valid = mask & np.isfinite(p) & np.isfinite(q)
    k = int(valid.sum())
    return float(np.sum(np.abs(p[valid]) + np.abs(q[valid])) / k) if k else float("nan")


@dataclass
class RunningDistance:
    """A stream's distance: each cycle's estimate averaged with the previous ones, over about
    `cycles` of them (1: none). The first `cycles` estimates are averaged alike (their plain mean),
    then exponentially, each new one weighing 1 / cycles. A jump of more than DISTANCE_RESET (a new
    subject, a replay's start) starts the average again. A cycle without an estimate (NaN) reads
    NaN and leaves the average as it was."""
    cycles: int
    distance_mm: float | None = None
    averaged: int = 0  # estimates in the average since it last started

    def update(self, distance_mm: float) -> float:
        if not np.isfinite(distance_mm):
            return distance_mm
        previous = self.distance_mm
        if (previous is None or self.cycles <= 1
                or abs(distance_mm - previous) >= DISTANCE_RESET * previous):
            self.distance_mm, self.averaged = distance_mm, 1
        else:
            self.averaged += 1
            self.distance_mm = previous + (distance_mm - previous) / min(self.averaged, self.cycles)
        return self.distance_mm


def subject_mask(signal: np.ndarray, fraction: float, edge_fraction: float | None = None,
                 edge_px: int = EDGE_GROWTH_PX) -> np.ndarray:
    """The subject's pixels: summed signal above `fraction` of its 99th percentile, holes filled.

    Without edge_fraction, eroded by a pixel (mixed pixels at the silhouette). With it, grown
    instead by up to edge_px pixels into what is still above edge_fraction: the flanks of a
    torso, lit at grazing angles, are dim but their normals are good to the last pixel, and the
    metric volume is referred to the silhouette (core/volume/maps.py), so every pixel lost there is
    breathing lost."""
    total = np.sum(np.clip(signal, 0, None), axis=0)
    reference = np.percentile(total, 99)
    mask = ndimage.binary_fill_holes(total > fraction * reference)
    if edge_fraction is None:
        return ndimage.binary_erosion(mask, iterations=1)
    return ndimage.binary_dilation(mask, iterations=edge_px, mask=total > edge_fraction * reference)


def shadow_threshold(signal: np.ndarray, mask: np.ndarray, fraction: float) -> float:
    """The signal (lit minus dark) under which a light counts as shadowed at a pixel: `fraction` of the
    subject's brightness, the 99th percentile over `mask` of each pixel's brightest light. It follows
    the exposure, the LEDs' power, polarising filters and the skin's tone; a threshold of 1 % of full
    scale (41 DN at 12 bits; 0.02 of the brightness is 38 DN on the simulated subject at 2000 mm) put
    most of a dark-skinned trunk behind polarisers, at a fifth of the light, in shadow (docs/history/volume-log.md,
    "Skin the light model does not describe, and bent maps")."""
    if not mask.any():
        return float("inf")
    return float(fraction * np.percentile(np.max(signal[:, mask], axis=0), 99))


# A surface seen this near grazing (|n_z| of its distant-light normal below this) is an occluding
# contour: the trunk's sides, or an arm's edge where it lies beside the trunk
GRAZING_NZ = 0.35
# What lies beside the trunk is an arm when it spans at least this share of the trunk's rows (an
# arm hangs from the shoulder to below the waist)
ARM_SHARE_OF_TRUNK_ROWS = 0.25
# An arm held away may stay joined to the trunk on up to this share of its rows from its top (the armpit)
ARM_JOINED_SHARE = 0.25
# An occluding contour hides a side when at least this share of the row faces the camera beyond it, an
# arm's width: an arm held close leaves 0.16-0.18, a silhouette's edge pixels 0.01-0.03 (docs/constants.md)
MIN_BEYOND_CONTOUR_SHARE = 0.05


def trunk_mask(mask: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The trunk within a subject mask, without the arms.

    Arms are surfaces the integrator cannot tie to the trunk (their depth floats by its own
    constant: a head saw an arm held away 5-20 mm off, changing from map to map), no part of the
    breathing, and the volume's rules take the outer edges of a row for the trunk's sides. An arm
    held away is a run of pixels of its own beside the trunk on a row, up to where it meets the
    shoulder. So:
    1. on every row, the run through the silhouette's middle column;
    2. within those, the largest part that no near-grazing pixel (GRAZING_NZ, from `normals`)
       divides, with the grazing pixels nearer to it than to any part it was divided from (an
       occluding contour between arm and trunk);
    3. above where each side's arm leaves the trunk (its first row with background between them,
       within ARM_JOINED_SHARE of its rows; else its top row; then the first row with the whole arm
       beyond the trunk's side), nothing beyond the trunk's side there (the arm's top and the
       shoulder's tip over it, which one head may see joined to the trunk and the other not, and one
       map of a head but not the next).
    An arm held close, lying on the trunk's side with nothing between, stays."""
    if not mask.any():
        return mask
    # the middle of the largest connected part: a connected part has a pixel in every column it spans
    middle = int(np.median(np.nonzero(_largest_part(mask))[1]))
    runs, _ = ndimage.label(mask, structure=[[0, 0, 0], [1, 1, 1], [0, 0, 0]])
    through_middle = runs[:, middle]
    trunk = np.isin(runs, through_middle[through_middle > 0])
    facing = trunk & (np.abs(np.nan_to_num(normals[..., 2])) >= GRAZING_NZ)
    parts, n = ndimage.label(facing)
    if n > 1:
        rows, cols = ndimage.distance_transform_edt(~facing, return_distances=False, return_indices=True)
        trunk &= parts[rows, cols] == _largest_label(parts)
    trunk_rows = np.nonzero(trunk.any(axis=1))[0]
    for side in (slice(0, middle), slice(middle, None)):
        arms, found = ndimage.label(mask[:, side] & ~trunk[:, side])
        if not found:
            continue
        label = _largest_label(arms)
        arm_rows = np.nonzero((arms == label).any(axis=1))[0]
        if len(arm_rows) < ARM_SHARE_OF_TRUNK_ROWS * (trunk_rows[-1] - trunk_rows[0] + 1):
            continue  # no arm: a speck the mask left beside the trunk
        # where the arm leaves the trunk: its first row with background between the two (an arm held away
        # may still be joined to the trunk on its top rows, at the armpit); an arm held close, divided
        # from the trunk by an occluding contour only, leaves it at its top row
        left = side.start == 0
        upper = arm_rows[:int(np.ceil(ARM_JOINED_SHARE * len(arm_rows)))]
        top = next((int(r) for r in upper if _apart(mask[r, side], trunk[r, side], arms[r] == label, left)),
                   int(arm_rows[0]))
        # the trunk's side on the first row from there with the whole arm beyond it: the arm as the trunk
        # leaves it may begin with a contour's pixels on rows where the trunk still runs out along its top
        beside = next((int(r) for r in arm_rows if r >= top and _beyond(trunk[r, side], arms[r] == label, left)),
                      None)
        if beside is None:
            continue
        on_row = np.nonzero(trunk[beside, side])[0]
        if left:
            trunk[:beside, :on_row[0]] = False
        else:
            trunk[:beside, middle + on_row[-1] + 1:] = False
    return _largest_part(trunk)


def _apart(subject: np.ndarray, trunk: np.ndarray, arm: np.ndarray, left: bool) -> bool:
    """Whether on a row (one side's columns) background lies between the trunk and the arm."""
    trunk_cols, arm_cols = np.nonzero(trunk)[0], np.nonzero(arm)[0]
    if len(trunk_cols) == 0 or len(arm_cols) == 0:
        return False
    inner, outer = (arm_cols[-1], trunk_cols[0]) if left else (trunk_cols[-1], arm_cols[0])
    return bool(outer - inner > 1 and not subject[inner + 1:outer].all())


def _beyond(trunk: np.ndarray, arm: np.ndarray, left: bool) -> bool:
    """Whether on a row (one side's columns) the whole arm lies beyond the trunk's side."""
    trunk_cols, arm_cols = np.nonzero(trunk)[0], np.nonzero(arm)[0]
    if len(trunk_cols) == 0 or len(arm_cols) == 0:
        return False
    return bool(arm_cols[-1] < trunk_cols[0]) if left else bool(arm_cols[0] > trunk_cols[-1])


def _largest_label(labels: np.ndarray) -> int:
    """The label of the largest part in an ndimage.label image with at least one part."""
    return 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))


def _largest_part(flags: np.ndarray) -> np.ndarray:
    """The largest connected part of a mask (the mask itself when it has one part or none)."""
    parts, n = ndimage.label(flags)
    return flags if n <= 1 else parts == _largest_label(parts)


def occluded_side_share(mask: np.ndarray, normals: np.ndarray) -> float:
    """The share of the trunk's rows crossed by an occluding contour inside the silhouette: near-grazing
    normals (GRAZING_NZ) with at least MIN_BEYOND_CONTOUR_SHARE of the row's width facing the camera on
    either side of them. An arm held against the trunk puts one along most of its height (measured on
    simulated bodies: 0.5-0.8 of the rows with arms close, at most 0.02 without: folds under the
    breasts or belly run across rows, not down them). Where one runs, the trunk's sides the volume is
    referred to are hidden. A pixel or two facing the camera at the silhouette's very edge, outside a
    grazing one (a mesh body's facets, a map's noise there), is no arm."""
    rows = mask.any(axis=1)
    if not rows.any():
        return float("nan")
    grazing = mask & (np.abs(np.nan_to_num(normals[..., 2])) < GRAZING_NZ)
    facing = mask & ~grazing
    before = np.cumsum(facing, axis=1)
    after = before[:, -1:] - before
    first = np.argmax(facing, axis=1)
    last = mask.shape[1] - 1 - np.argmax(facing[:, ::-1], axis=1)
    least = np.maximum(MIN_BEYOND_CONTOUR_SHARE * (last - first + 1), 1)[:, None]  # the row's facing width
    hidden = grazing & (before >= least) & (after >= least)
    return float(np.sum(hidden.any(axis=1)) / np.sum(rows))


def side_out_of_view_share(mask: np.ndarray) -> float:
    """The share of the trunk's rows on which it reaches the image's left or right edge: there its
    side, which the volume is referred to, is out of view."""
    rows = mask.any(axis=1)
    if not rows.any():
        return float("nan")
    return float(np.sum(mask[:, 0] | mask[:, -1]) / np.sum(rows))


class HeadReconstructor:
    """Reconstructs one head's cycles. Holds the head's calibration and, between cycles, the
    stream's running distance (and the intensities fitted on its first cycle, when asked)."""

    def __init__(self, head: Head, pseudo_light_vectors: np.ndarray | None = None,
                 settings: ReconstructionSettings | None = None) -> None:
        self.head = head
        self.settings = settings or ReconstructionSettings()
        pseudo = default_pseudo_light_vectors(head) if pseudo_light_vectors is None else pseudo_light_vectors
        self.pseudo_light_vectors = np.asarray(pseudo, dtype=np.float64)
        u = (np.arange(head.width) - head.cx) / head.fx
        v = (np.arange(head.height) - head.cy) / head.fy
        self._rays = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((head.height, 1))), -1)
        # a wide head's normals from prefiltered images, its distance fit on bins of the same size
        # (core/reconstruction/prefilter.py): every pixel counts
        s = self.settings
        self._prefilter_px = prefilter_sigma_px(head.width) if s.prefilter_px is None else s.prefilter_px
        self._distance_binning = noise_binning(head.width)
        axis = head.light_axis if head.light_axis is not None else np.tile([0.0, 0.0, 1.0], (4, 1))
        mu = head.light_mu if head.light_mu is not None else np.zeros(4)
        self._axis = np.ascontiguousarray(axis, dtype=np.float64)
        self._mu = np.ascontiguousarray(mu, dtype=np.float64)
        self.running_distance = RunningDistance(self.settings.distance_cycles)
        self._lens = LensCorrection(head) if needs_correction(head) else None
        # the lights' relative intensities as fitted on the first cycle, as factors of the rig's
        # (PhotometricDistance.scale_and_intensity); None until then or when not fitted
        self.intensity_factors: np.ndarray | None = None
        # the last cycle's log-depth from its distant-light normals, where the next cycle's first
        # solve starts
        self._last_pseudo_log_depth: np.ndarray | None = None
        # the last cycle's final log-depth (near lights): the next cycle's lights are placed on it
        self._last_log_depth: np.ndarray | None = None

    @property
    def last_distance_mm(self) -> float | None:
        """The stream's distance after the last cycle that had one; None before any."""
        return self.running_distance.distance_mm

    def _no_subject(self) -> HeadMap:
        """A cycle without a subject: empty maps, no distance; the stream's running distance kept."""
        h = self.head
        return HeadMap(np.full(h.shape + (3,), np.nan), np.full(h.shape, np.nan), np.full(h.shape, np.nan),
                       np.zeros(h.shape, dtype=bool), float("nan"), DmrEstimate.none(), float("nan"))

    def _integrate(self, normals: np.ndarray, mask: np.ndarray, final: bool,
                   start: np.ndarray | None = None) -> np.ndarray:
        """Log-depth; the masked path's robust reweighting (core/reconstruction/integrate.py) only for a cycle's
        final depth: the iterations' depths only place the lights' vectors and the distance.
        `start`: the log-depth of the cycle's last iteration, or of the stream's last cycle."""
        h = self.head
        gu, gv = log_depth_gradients(normals, h.fx, h.fy, h.cx, h.cy)
        valid = mask & np.isfinite(gu) & np.isfinite(gv)
        if self.settings.integrator == "masked":
            return integrate_masked(gu, gv, valid, robust_iterations=ROBUST_ITERATIONS if final else 0,
                                    start=start)
        return np.where(valid, integrate_dct(np.where(valid, gu, 0.0), np.where(valid, gv, 0.0)), np.nan)

    @staticmethod
    def _anchor(log_depth: np.ndarray, dmr: DmrEstimate) -> float:
        """Scale of exp(log depth) that puts the regions' centres at their triangulated depths."""
        scales = []
        for (u, v), z in zip(dmr.centres_px, dmr.depths_mm):
            if not np.isfinite(z):
                continue
            value = ndimage.map_coordinates(log_depth, [[v], [u]], order=1, mode="nearest", cval=np.nan)[0]
            if np.isfinite(value):
                scales.append(z / np.exp(value))
        if scales:
            return float(np.mean(scales))
        median = np.nanmedian(log_depth)
        return NOMINAL_DISTANCE_MM / float(np.exp(median)) if np.isfinite(median) else NOMINAL_DISTANCE_MM

    def _scaled(self, log_depth: np.ndarray, dmr: DmrEstimate, problem: PhotometricDistance | None,
                guess_mm: float, search: str) -> tuple[np.ndarray, float]:
        """Depth from integrated log-depth: the DMR anchor, or the photometric distance searched
        widely (search="wide"), near the guess ("near"), or not at all ("keep")."""
        relative = np.exp(log_depth - np.nanmedian(log_depth))
        if problem is None:
            depth = self._anchor(log_depth, dmr) * np.exp(log_depth)
            return depth, float(np.nanmedian(depth))
        scale = guess_mm
        if search != "keep":
            span = (0.75, 1.35) if search == "wide" else (0.97, 1.03)
            scale = problem.scale(self._rays, relative, (guess_mm * span[0], guess_mm * span[1]),
                                  grid_points=9 if search == "wide" else 5)
            if not np.isfinite(scale):
                scale = guess_mm
        return scale * relative, float(scale)

    def reconstruct(self, signal: np.ndarray, saturated: np.ndarray | None = None,
                    dark: np.ndarray | None = None, distance_mm: float | None = None) -> HeadMap:
        """signal (4, H, W): each light's frame minus the dark frame; saturated (4, H, W) bool;
        dark (H, W), the dark frame, for the noise model of the distance search. distance_mm: the
        subject's median depth when it is known from elsewhere (the two heads' geometry,
        core/pipeline/process.py): the maps are scaled to it and no distance is searched or averaged."""
        h, s = self.head, self.settings
        signal, saturated, dark = self._as_pinhole(signal, saturated, dark)
        mask = subject_mask(signal, s.mask_fraction, s.mask_edge_fraction)
        if mask.sum() < MIN_SUBJECT_PIXELS:  # nobody in front of the head (dark, stepped away)
            return self._no_subject()
        # the normals from filtered images; the distance fit (its own noise model) from the raw ones
        solved, solved_saturated = prefiltered(signal, saturated, self._prefilter_px)
        pseudo_normals, albedo = distant_light_normals(solved, np.zeros(h.shape), self.pseudo_light_vectors)
        mask = trunk_mask(mask, pseudo_normals)
        if mask.sum() < MIN_SUBJECT_PIXELS:
            return self._no_subject()
        occluded = occluded_side_share(mask, pseudo_normals)
        pseudo_normals[~mask] = np.nan
        dmr = dmr_distance(pseudo_normals, mask, h.fx, h.fy, h.cx, h.cy, h.light_positions_mm,
                           self.pseudo_light_vectors, s.dmr_threshold)
        tracked = s.track and self.last_distance_mm is not None
        guess = self.last_distance_mm if tracked else (dmr.distance_mm if np.isfinite(dmr.distance_mm)
                                                       else NOMINAL_DISTANCE_MM)
        photometric = s.distance == "photometric" and s.method == "near" and distance_mm is None
        intensity = self._intensity()
        problem = (PhotometricDistance(signal, mask, h.light_positions_mm, intensity, dark,
                                       max_pixels=s.distance_pixels, binning=self._distance_binning,
                                       light_axis=self._axis, light_mu=self._mu)
                   if photometric else None)
        if distance_mm is not None:
            tracked = True

        def scaled(log_depth: np.ndarray, guess_mm: float, search: str) -> tuple[np.ndarray, float]:
            if distance_mm is not None:
                return distance_mm * np.exp(log_depth - np.nanmedian(log_depth)), float(distance_mm)
            return self._scaled(log_depth, dmr, problem, guess_mm, search)

        normals = pseudo_normals
        warm = s.method == "near" and tracked and self._last_log_depth is not None
        if warm:
            # a stream's cycle: the lights placed on the last cycle's surface, 45 ms (or a few cycles)
            # earlier, where the distant-light surface is a first guess for a cycle on its own
            log_depth = np.where(mask, self._last_log_depth, np.nan)
        else:
            log_depth = self._integrate(normals, mask, final=s.method != "near", start=self._last_pseudo_log_depth)
            self._last_pseudo_log_depth = log_depth
        depth, distance = scaled(log_depth, guess, "keep" if tracked else "wide")
        done = 0
        if s.method == "near":
            min_signal = shadow_threshold(signal, mask, s.shadow_fraction)
            normals = np.full(h.shape + (3,), np.nan)
            albedo = np.full(h.shape, np.nan)
            used = np.zeros(h.shape, dtype=np.int64)
            for done in range(1, s.iterations + 1):
                points = np.ascontiguousarray(self._rays * np.nan_to_num(depth, nan=distance)[..., None])
                near_light_normals(solved, points, h.light_positions_mm, intensity, self._axis, self._mu,
                                   solved_saturated, min_signal, normals, albedo, used)
                normals[~mask] = np.nan
                log_depth = self._integrate(normals, mask, final=False, start=log_depth)
                last = done == s.iterations
                searched = last or not tracked
                new_depth, distance = scaled(log_depth, distance, "near" if searched else "keep")
                change = np.nanmedian(np.abs(new_depth - depth))
                depth = new_depth
                if change < s.max_depth_change_mm:
                    if not searched:  # settled: one search near the tracked distance, then stop
                        depth, distance = scaled(log_depth, distance, "near")
                    break
            if s.integrator == "masked" and ROBUST_ITERATIONS > 0:
                log_depth = self._integrate(normals, mask, final=True, start=log_depth)
                depth, distance = scaled(log_depth, distance, "keep")
            self._last_log_depth = log_depth
        if problem is not None and s.fit_intensity and self.intensity_factors is None and np.isfinite(distance):
            scale, factors = problem.scale_and_intensity(self._rays, depth / distance, distance)
            if np.isfinite(scale):
                depth, distance = depth * (scale / distance), scale
                self.intensity_factors = factors
        averaged = self.running_distance.update(distance) if distance_mm is None else distance
        if np.isfinite(averaged) and averaged != distance:
            depth, distance = depth * (averaged / distance), averaged
        valid = mask & np.isfinite(depth) & np.isfinite(normals[..., 2])
        depth = np.where(valid, depth, np.nan)
        normals = np.where(valid[..., None], normals, np.nan)
        return HeadMap(normals, depth, albedo, valid, distance, dmr, gradient_volume(normals, valid), done,
                       {"occluded_side_share": occluded, "side_out_of_view_share": side_out_of_view_share(mask)},
                       mask)

    def sheen(self, signal: np.ndarray, saturated: np.ndarray | None, result: HeadMap) -> float:
        """The sheen on the skin over its albedo (core/reconstruction/reflectance.py) on the cycle
        `result` was reconstructed from, seen as `reconstruct` saw it (lens, prefilter, shadows).
        About 5 ms a map, so `process` and the live view look at a map every so often, not at each."""
        return self.redundancy(signal, saturated, result).sheen

    def redundancy(self, signal: np.ndarray, saturated: np.ndarray | None, result: HeadMap) -> RedundancyFit:
        """The sheen and the lights' outputs against the intensities the cycle was solved with
        (core/reconstruction/reflectance.py), as `sheen` sees them."""
        h, s = self.head, self.settings
        signal, saturated, _ = self._as_pinhole(signal, saturated, None)
        solved, solved_saturated = prefiltered(signal, saturated, self._prefilter_px)
        return redundancy_fit(solved, self._rays * result.depth_mm[..., None], result.mask,
                              h.light_positions_mm, self._intensity(), self._axis, self._mu,
                              shadow_threshold(signal, result.mask, s.shadow_fraction), solved_saturated)

    def _as_pinhole(self, signal: np.ndarray, saturated: np.ndarray | None, dark: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """A cycle's signal (float64), saturated flags and dark frame as the pinhole camera would have them."""
        signal = np.ascontiguousarray(signal, dtype=np.float64)
        if saturated is None:
            saturated = np.zeros(signal.shape, dtype=np.bool_)
        if self._lens is not None:
            signal, saturated, dark = self._lens.correct(signal, saturated, dark)
        return signal, saturated, dark

    def _intensity(self) -> np.ndarray:
        """The lights' intensities, times those fitted on a stream's first cycle where asked."""
        return self.head.light_intensity * (self.intensity_factors if self.intensity_factors is not None else 1.0)
