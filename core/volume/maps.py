"""Volumes from height maps: the thesis' gradient volume, and the building blocks of the metric volume.

Metric volume of one head: each map is compared with a reference map of the same head in the
body's own frame (BodySilhouette: resampled through the scale and shift that carry the
reference's trunk silhouette onto the map's, sub-pixel), both referred to the level their
trunk would have at its sides (RimModel), so a rigid shift of the whole torso (sway, along the axis
or sideways) is not breathing; every pixel's displacement is weighted by its footprint
(Z / fx)(Z / fy). The level comes from a model: breathing moves the trunk along the axis in
proportion to the lateral distance from its side (the ribs hinge there) and stretches it sideways
(the ribs widen), fitted to the band of pixels inside the silhouette and extrapolated to the side,
which lies a few mm beyond the silhouette on a rounded trunk (rim_side_mm). Sides that move along
the axis are taken for sway, and the strip beyond the outermost pixels, which neither head sees,
is not counted. Each map's own level is the live view's; `process` fits the level over the whole
session from the sums each map keeps of its band (core/volume/metric.py, session_shifts).

The result scales with the depth map's absolute scale times the relief above the rim (about
10 L per head for an adult), so every map's scale is set afterwards from a distance that
breathing does not move (core/volume/metric.py). With both heads it comes from the trunk's widths:
both see the same sides, so their widths in pixels stand in the inverse ratio of the distances,
D_f / D_b = W_b / W_f, and D_f + D_b is the baseline between the heads.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange
from scipy import ndimage

from core.rig import Head

# The silhouette's outermost pixels, dim and noisy, left out of the rim fits (docs/constants.md)
RIM_SKIP_PX = 2
RIM_SKIP_MM = 14.0
# The rim's band inside the silhouette: wider steadies it against sway (docs/benchmarks.md, constants).
RIM_BAND_MM = 70.0


def torso_rows(mask: np.ndarray, min_width_fraction: float = 0.6) -> np.ndarray:
    """Rows of the trunk: as wide as 60 % of the widest row or more (the neck and head are narrower)."""
    widths = mask.sum(axis=1)
    return np.nonzero(widths >= min_width_fraction * widths.max())[0] if widths.max() > 0 else np.zeros(0, int)


def _silhouette_centre_px(mask: np.ndarray) -> tuple[float, float]:
    rows = torso_rows(mask)
    if len(rows) == 0:
        return float("nan"), float("nan")
    centres = [0.5 * (cols[0] + cols[-1]) for cols in (np.nonzero(mask[r])[0] for r in rows)]
    return float(np.mean(centres)), 0.5 * float(rows[0] + rows[-1])


@dataclass(frozen=True)
class BodyFrame:
    """The similarity that carries a reference map's pixels (u, v) onto another map's:
    u' = cx + (u - cx) scale + shift_u_px, likewise v about cy; scale is the other map's image size
    over the reference's (image size goes as 1 / distance)."""

    scale: float
    shift_u_px: float
    shift_v_px: float

    def resampled(self, depth_mm: np.ndarray, valid: np.ndarray, shape: tuple[int, int], head: Head) -> np.ndarray:
        """The other map's depth on the reference's pixels; NaN where it shows no valid pixel."""
        out = np.full(shape, np.nan)
        if all(np.isfinite([self.scale, self.shift_u_px, self.shift_v_px])):
            _resample_bilinear(np.ascontiguousarray(depth_mm, dtype=np.float64), np.ascontiguousarray(valid),
                               float(head.cx), float(head.cy), float(self.scale), float(self.shift_u_px),
                               float(self.shift_v_px), out)
        return out


@njit(cache=True, nogil=True, inline="always")
def _bracket(position, size):
    """(lower index, upper index, fraction towards the upper) of a position along an axis of `size`
    samples; lower index -1 when the position lies off the axis."""
    if position < 0.0 or position > size - 1:
        return -1, -1, 0.0
    lower = min(int(position), size - 1)
    return lower, min(lower + 1, size - 1), position - lower


@njit(cache=True, parallel=True, nogil=True)
def _resample_bilinear(depth, valid, cx, cy, scale, shift_u, shift_v, out):
    """BodyFrame.resampled's kernel: each of out's pixels (u, v) takes the depth at (cx + (u - cx)
    scale + shift_u, likewise v) bilinearly from the valid pixels around it, where they carry more
    than 0.99 of its weight (so a pixel on the silhouette's edge or off the image stays NaN)."""
    height, width = depth.shape
    for i in prange(out.shape[0]):
        i0, i1, fy = _bracket(cy + (i - cy) * scale + shift_v, height)
        if i0 < 0:
            continue
        for j in range(out.shape[1]):
            j0, j1, fx = _bracket(cx + (j - cx) * scale + shift_u, width)
            if j0 < 0:
                continue
            total = 0.0
            weight = 0.0
            for a, wa in ((i0, 1.0 - fy), (i1, fy)):
                for b, wb in ((j0, 1.0 - fx), (j1, fx)):
                    w = wa * wb
                    if w > 0.0 and valid[a, b]:
                        total += w * depth[a, b]
                        weight += w
            if weight > 0.99:
                out[i, j] = total / weight


# Body-frame fit (BodySilhouette.frame): the silhouettes are compared blurred by FRAME_BLUR_PX (a
# smooth function of the shift, so the fit is sub-pixel), and pixels of the reference's outline band
# that differ by more than FRAME_OUTLIER are parts that came or went (an arm), not the body's shift.
FRAME_BLUR_PX = 1.0
FRAME_OUTLIER = 0.5
# Rows trimmed from each end of the reference's trunk rows for the width ratio, so that every one
# of them stays on the trunk under +-3 % of scale (+-60 mm at 2000 mm) and a few pixels of shift.
FRAME_TRIM_ROWS = 8
MIN_TRUNK_ROWS = 4  # fewer trunk rows than this: the map shows no trunk


SCALE_REFINEMENTS = 3  # BodySilhouette.frame's rounds of scale (rows' widths) and shift (outline)


class BodySilhouette:
    """A reference map's trunk silhouette, to find the body frame of other maps against it.

    The frame used to come from whole-pixel features: the middle of the first and last trunk rows
    (the first flips between two rows on the rounded shoulders, the last is the image's edge) and
    the trunk's mean width over its rows (a shoulder row entering the set moves it by 0.3-0.4 px).
    Each step shifted the resampled map and the volume by about 0.1 L for a few maps (docs/volume.md).
    Here both are sub-pixel and follow the body continuously:
    - scale: the ratio of the trunk's widths between its sides (side_columns) on the same body rows,
      the reference's trunk rows less FRAME_TRIM_ROWS at each end, each carried into the other map
      (widths interpolated between its rows);
    - shift: the two silhouettes, blurred, brought onto each other over the band about the
      reference's outline by least squares (Lucas-Kanade, Gauss-Newton), with the scale held; the
      image's edge is no part of the outline.
    Under sway the trunk is nearly rigid, but not flat: its outline lies at different depths (the
    shoulders' top on the front of the trunk, the sides farther), so a 3 mm vertical sway shifts the
    outline by fy 3 / Z with Z between those depths; the fit finds that one shift of the whole.
    """

    def __init__(self, valid: np.ndarray, widths_px: np.ndarray, head: Head,
                 silhouette: np.ndarray | None = None) -> None:
        """valid: the reference map's valid pixels; widths_px: its row_widths_px."""
        self.head = head
        rows = torso_rows(valid)
        if len(rows) > 2 * FRAME_TRIM_ROWS + MIN_SIDE_ROWS:
            rows = rows[FRAME_TRIM_ROWS:-FRAME_TRIM_ROWS]
        self._rows = rows.astype(float)
        self._widths = widths_px[rows]
        self._centre = _silhouette_centre_px(valid)
        blurred = _blurred(valid)
        band = (blurred > 0.01) & (blurred < 0.99)
        self._band = np.nonzero(band)[::-1]
        self._band_values = blurred[band]

    def frame(self, valid: np.ndarray, widths_px: np.ndarray, scale: float, refine_scale: bool = True) -> BodyFrame:
        """The body frame of a map (its valid pixels and row_widths_px) against the reference, from a
        first guess of its scale (e.g. the ratio of trunk_width_px), refined on the trunk's widths
        unless `refine_scale` is False (the scale held)."""
        (u, v), (u_ref, v_ref) = _silhouette_centre_px(valid), self._centre
        cx, cy = self.head.cx, self.head.cy
        frame = BodyFrame(scale, u - cx - (u_ref - cx) * scale, v - cy - (v_ref - cy) * scale)
        if not all(np.isfinite([scale, u, u_ref])):
            return frame
        blurred = _blurred(valid)
        gradient = np.gradient(blurred)
        frame = self._shifted(frame, blurred, gradient, iterations=3)
        if not refine_scale:
            return frame
        for _ in range(SCALE_REFINEMENTS):  # a first guess far off carries the widths from the wrong rows
            ratio = self.width_ratio(widths_px, frame)
            if not np.isfinite(ratio):
                break
            frame = self._shifted(BodyFrame(ratio, frame.shift_u_px, frame.shift_v_px), blurred, gradient, iterations=2)
        return frame

    def width_ratio(self, widths_px: np.ndarray, frame: BodyFrame) -> float:
        """The other map's trunk widths on the reference's rows, carried through the frame, over the
        reference's: the median of the rows' ratios (NaN with fewer than MIN_SIDE_ROWS rows in both).
        An arm that joins the trunk's silhouette on some rows widens those rows by a quarter, and
        their sum with them (a population subject's trunk read 141 px against 133 in a quarter of
        its maps, docs/volume.md); the median leaves such rows out, in either map."""
        rows = self.head.cy + (self._rows - self.head.cy) * frame.scale + frame.shift_v_px
        if len(rows) == 0 or len(widths_px) < 2:
            return float("nan")
        below = np.clip(np.floor(rows).astype(int), 0, len(widths_px) - 2)
        after = rows - below
        carried = (1.0 - after) * widths_px[below] + after * widths_px[below + 1]
        carried[(after < 0) | (after > 1)] = np.nan  # rows outside the image
        both = np.isfinite(carried) & np.isfinite(self._widths)
        if both.sum() < MIN_SIDE_ROWS:
            return float("nan")
        return float(np.median(carried[both] / self._widths[both]))

    def _shifted(self, frame: BodyFrame, blurred: np.ndarray, gradient: list[np.ndarray], iterations: int) -> BodyFrame:
        """The shift that brings the other map's blurred silhouette onto the reference's, scale held
        (Lucas-Kanade on the reference's outline band, Gauss-Newton)."""
        u, v = self._band
        if len(u) < 3:
            return frame
        cx, cy = self.head.cx, self.head.cy
        du, dv, s = frame.shift_u_px, frame.shift_v_px, frame.scale
        gradient_v, gradient_u = gradient
        for _ in range(iterations):
            at = [cy + (v - cy) * s + dv, cx + (u - cx) * s + du]  # the band on the other map's pixels
            residual = ndimage.map_coordinates(blurred, at, order=1, mode="nearest") - self._band_values
            jacobian = np.stack([ndimage.map_coordinates(g, at, order=1, mode="nearest")
                                 for g in (gradient_u, gradient_v)], axis=1)
            near = np.abs(residual) < FRAME_OUTLIER
            if near.sum() < 3:
                return frame
            step = np.linalg.lstsq(jacobian[near], -residual[near], rcond=None)[0]
            du, dv = du + step[0], dv + step[1]
        return BodyFrame(s, float(du), float(dv))


def _blurred(mask: np.ndarray) -> np.ndarray:
    """The silhouette blurred by FRAME_BLUR_PX; the image's edge is no part of it (the mask is
    extended past it)."""
    return ndimage.gaussian_filter(mask.astype(float), FRAME_BLUR_PX, mode="nearest")


def body_aligned_displacement(depth_a: np.ndarray, mask_a: np.ndarray, depth_b: np.ndarray, mask_b: np.ndarray,
                              head: Head) -> np.ndarray:
    """How far each point of the trunk moved towards the camera from map b to map a, on map b's
    pixels, with the subject's sway between the maps removed.

    A body that sways farther from the camera looks smaller, and sideways it shifts in the image:
    differencing two maps pixel by pixel would see a sloped surface slide past the pixel and call
    it breathing. Map a is resampled through the body frame (BodySilhouette: scale about the
    principal point and shift) that carries b's trunk silhouette onto a's, and both are referred to
    the level of their trunk's sides (RimModel), as the metric volume does (DisplacementTracker).
    """
    valid_a, valid_b = mask_a & np.isfinite(depth_a), mask_b & np.isfinite(depth_b)
    out = np.full(depth_b.shape, np.nan)
    if len(torso_rows(valid_b)) < MIN_TRUNK_ROWS:
        return out
    widths_a, widths_b = row_widths_px(depth_a, valid_a, head), row_widths_px(depth_b, valid_b, head)
    image_size = trunk_width_px(depth_a, valid_a, head, widths_a) / trunk_width_px(depth_b, valid_b, head, widths_b)
    frame = BodySilhouette(valid_b, widths_b, head).frame(valid_a, widths_a, image_size)
    z_a = frame.resampled(depth_a, valid_a, mask_b.shape, head)
    inside = valid_b & np.isfinite(z_a)
    rim = rim_model(depth_b, valid_b, head, rim_band_px(depth_b, valid_b, head), rim_skip_px(depth_b, valid_b, head))
    out[inside] = (depth_b - rim.level(depth_b, inside))[inside] - (z_a - rim.level(z_a, inside))[inside]
    return out


def trunk_regions(mask: np.ndarray, head_name: str) -> dict[str, np.ndarray]:
    """The trunk's quadrants on a map's pixels: the upper and lower half of the trunk rows (chest and
    abdomen), split at the silhouette's mean column (the midline). The front head sees the
    patient's left on the image's right, the back head on the image's left. Empty if the map
    shows no trunk."""
    rows = torso_rows(mask)
    if len(rows) < MIN_TRUNK_ROWS:
        return {}
    mid_row = int(rows[len(rows) // 2])
    mid_col = int(np.round(np.nonzero(mask[rows])[1].mean()))
    image_right, image_left = ("left", "right") if head_name == "front" else ("right", "left")
    upper = np.zeros(mask.shape, bool)
    upper[rows[0]:mid_row] = True
    lower = np.zeros(mask.shape, bool)
    lower[mid_row:rows[-1] + 1] = True
    left_columns = np.zeros(mask.shape, bool)
    left_columns[:, :mid_col] = True
    return {f"upper {image_left}": mask & upper & left_columns, f"upper {image_right}": mask & upper & ~left_columns,
            f"lower {image_left}": mask & lower & left_columns, f"lower {image_right}": mask & lower & ~left_columns}


REGIONS = ("upper left", "upper right", "lower left", "lower right")
# The share of the reference trunk mask's rows, from the top, whose displacement DisplacementSums.neck_mm
# gives: the neck (from the back also the back of the head; 28-48 px wide where the chest is 100-120 at
# scale 0.25) on both simulated populations
NECK_ROWS = 0.1
MIN_NECK_PIXELS = 5


@dataclass(frozen=True)
class DisplacementSums:
    """One map against the reference map of its head, in footprint-weighted sums (mm^3) over the
    pixels both show, per region ("all" is every such pixel, the neck and shoulders included):
    reference = sum fp (Z_ref - level_ref), current = sum fp (z - level) with z the current map
    resampled into the reference's body frame and level each map's RimModel.level.
    Kept apart so the two maps' scales can be set afterwards (metric_head_volume_l)."""

    side_mm: float  # depth of the trunk's sides (RimModel.side_depth_mm, followed by rim_depths), at the map's own scale
    width_px: float
    reference: dict[str, float]
    current: dict[str, float]
    # for a level fitted over the session (core/volume/metric.py, session_shifts): each part's footprint
    # (mm^2) and sum of fp (z - Z_ref) (mm^3) over the pixels both show, the two maps' levels
    # (reference's, this map's) and the band's RimModel.edge_statistics of z - Z_ref
    areas: dict[str, float] = field(default_factory=dict)
    displaced: dict[str, float] = field(default_factory=dict)
    levels_mm: tuple[float, float] = (float("nan"), float("nan"))
    band: np.ndarray | None = None
    # the trunk's widths over the reference's on the same body rows (BodySilhouette.width_ratio; 1 on
    # the reference): what the width follows where an arm joins the trunk on some rows
    width_ratio: float = float("nan")
    # the body's shift in the image plane since the reference (mm across, mm down; the body frame's
    # shift at the map's distance): what core/volume/steps.py finds steps in
    body_shift_mm: tuple[float, float] = (float("nan"), float("nan"))
    # the median of z - Z_ref over the reference trunk's top NECK_ROWS rows (the neck), at the map's own
    # scale (NaN: too few pixels); neck_referred_volume_l reads the plain displacement referred to it
    neck_mm: float = float("nan")


def _row_edges(mask: np.ndarray, width: int):
    """(row, columns from the silhouette inwards) of both sides of every trunk row, `width` long
    or as long as half the row."""
    for r in torso_rows(mask):
        cols = np.nonzero(mask[r])[0]
        n = min(width, len(cols) // 2)
        yield r, cols[:n]
        yield r, cols[::-1][:n]


def rim_depths(depth_a: np.ndarray, depth_b: np.ndarray, mask: np.ndarray, band_px: int,
               skip_px: int = RIM_SKIP_PX) -> tuple[float, float]:
    """Depths of two aligned maps at the trunk's silhouette (the rim), extrapolated from the band of
    `band_px` pixels inside it on both sides of every trunk row, after the outermost `skip_px`: a
    straight line through each map's mean depth at skip_px, skip_px + 1, ... pixels from the edge,
    taken half a pixel outside.

    A straight line, because breathing moves the trunk less the nearer a point is to its sides (the
    ribs hinge there), about in proportion to the distance from the rim: the band's own movement
    would otherwise be taken for sway and lost from the volume. The outermost pixels are dim (lit
    at grazing angles) and noisy; they place the rim but do not enter the line. The fit is linear in
    the depths, so the rim of a difference is the difference of the rims."""
    width = skip_px + band_px
    sums_a, sums_b, counts = np.zeros(width), np.zeros(width), np.zeros(width)
    _edge_sums(np.ascontiguousarray(depth_a, dtype=np.float64), np.ascontiguousarray(depth_b, dtype=np.float64),
               np.ascontiguousarray(mask), torso_rows(mask), sums_a, sums_b, counts)
    used = counts > 0
    used[:skip_px] = False
    if used.sum() < 2:
        return float("nan"), float("nan")
    j = np.arange(width)[used]
    at_rim = [np.polyval(np.polyfit(j, sums[used] / counts[used], 1), -0.5) for sums in (sums_a, sums_b)]
    return float(at_rim[0]), float(at_rim[1])


@njit(cache=True, nogil=True)
def _edge_sums(depth_a, depth_b, mask, rows, sums_a, sums_b, counts):
    """rim_depths' sums over _row_edges: the k-th pixel from each side of every trunk row, for k up to
    len(sums_a) or half the row's pixels, added to sums_a[k], sums_b[k] and counted."""
    width = len(sums_a)
    for r in rows:
        n = 0
        for j in range(mask.shape[1]):
            if mask[r, j]:
                n += 1
        reach = min(width, n // 2)
        for direction in (1, -1):
            k = 0
            j = 0 if direction == 1 else mask.shape[1] - 1
            while k < reach:
                if mask[r, j]:
                    sums_a[k] += depth_a[r, j]
                    sums_b[k] += depth_b[r, j]
                    counts[k] += 1.0
                    k += 1
                j += direction


# Outermost pixels of each trunk row whose depth profile places the body's side (rim_side_mm), the
# farthest the side may lie beyond the outermost pixel, and the least tilt from the viewing ray, at
# the outermost pair, of an edge that is an occluding contour.
SIDE_FIT_PX = 6
SIDE_MAX_GAP_PX = 4
# Trunk rows that must give both sides for the trunk's width to come from them (trunk_width_px)
MIN_SIDE_ROWS = 10
CONTOUR_MIN_VIEW_ANGLE_DEG = 60.0


def rim_side_mm(lateral_mm: np.ndarray, depth_mm: np.ndarray, ray_slope: np.ndarray) -> tuple[float, float]:
    """How far beyond the outermost pixel of one row the body's side lies, and how much deeper (mm):
    where the surface, which the camera sees up to where its ray grazes it, turns parallel to the
    axis. A circle through
    the outermost SIDE_FIT_PX pixels (least squares in the row's plane), its outermost point, when
    it lies deeper than the edge and within SIDE_MAX_GAP_PX pixels of it. Half a pixel (where the
    silhouette lies on average) where the edge is no occluding contour (the surface there is tilted
    less than CONTOUR_MIN_VIEW_ANGLE_DEG from facing the ray) or the circle does not qualify, at the
    outermost pixel's depth. lateral_mm, depth_mm, ray_slope: from the silhouette inwards, lateral
    outwards."""
    gap, deeper = rim_sides_mm(*(np.asarray(a, dtype=float)[None, :] for a in (lateral_mm, depth_mm, ray_slope)))
    return float(gap[0]), float(deeper[0])


def rim_sides_mm(lateral_mm: np.ndarray, depth_mm: np.ndarray, ray_slope: np.ndarray,
                 ) -> tuple[np.ndarray, np.ndarray]:
    """rim_side_mm of many edges at once: (E, n) arrays, NaN-padded past each edge's length."""
    n_px = np.sum(np.isfinite(lateral_mm) & np.isfinite(depth_mm), axis=1)
    if lateral_mm.shape[1] < 2:
        return np.zeros(len(lateral_mm)), np.zeros(len(lateral_mm))
    step = lateral_mm[:, 0] - lateral_mm[:, 1]
    tangent_x, tangent_z = step, depth_mm[:, 0] - depth_mm[:, 1]
    ray_x = ray_slope[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_view = np.abs(tangent_x - tangent_z * ray_x) / (np.hypot(tangent_x, tangent_z) * np.hypot(ray_x, 1.0))
        contour = np.degrees(np.arccos(np.clip(cos_view, 0.0, 1.0))) >= CONTOUR_MIN_VIEW_ANGLE_DEG
    fit = contour & (n_px >= SIDE_FIT_PX) & (step > 0)
    gap, deeper = np.where(step > 0, 0.5 * step, 0.0), np.zeros(len(step))
    if fit.any() and lateral_mm.shape[1] >= SIDE_FIT_PX:
        x = lateral_mm[fit, :SIDE_FIT_PX] - lateral_mm[fit, :1]
        z = depth_mm[fit, :SIDE_FIT_PX] - depth_mm[fit, :1]
        # x^2 + z^2 + a x + b z + c = 0: centre (-a/2, -b/2); least squares by the normal equations
        design = np.stack([x, z, np.ones_like(x)], axis=-1)
        normal = np.einsum("eki,ekj->eij", design, design)
        rhs = np.einsum("eki,ek->ei", design, -(x * x + z * z))
        solvable = np.abs(np.linalg.det(normal)) > 1e-12 * np.einsum("eii->e", normal) ** 3
        a, b, c = np.full((3, len(x)), np.nan)
        if solvable.any():
            a[solvable], b[solvable], c[solvable] = np.linalg.solve(normal[solvable], rhs[solvable][..., None])[..., 0].T
        radius_sq = (a * a + b * b) / 4.0 - c
        with np.errstate(invalid="ignore"):
            g, d = -a / 2.0 + np.sqrt(radius_sq), -b / 2.0
            ok = (radius_sq > 0) & (d > 0) & (g > 0) & (g < SIDE_MAX_GAP_PX * step[fit])
        gap[np.flatnonzero(fit)[ok]] = g[ok]
        deeper[np.flatnonzero(fit)[ok]] = d[ok]
    return gap, deeper


def side_columns(depth_mm: np.ndarray, valid: np.ndarray, head: Head, rows: np.ndarray) -> np.ndarray:
    """(len(rows), 2): the columns (sub-pixel) where the trunk's left and right sides lie on each of
    `rows` (rim_sides_mm: beyond the silhouette, where the surface turns parallel to the axis); NaN
    on a row with fewer than 2 SIDE_FIT_PX pixels."""
    rows = np.asarray(rows, dtype=int)
    on_rows = valid[rows]
    count = np.cumsum(on_rows, axis=1)
    total = count[:, -1:]
    # the k-th valid pixel from each end of every row: from the silhouette inwards
    left = np.stack([np.argmax(on_rows & (count == k + 1), axis=1) for k in range(SIDE_FIT_PX)], axis=1)
    right = np.stack([np.argmax(on_rows & (count == total - k), axis=1) for k in range(SIDE_FIT_PX)], axis=1)
    edge = np.stack([left, right], axis=1)  # (rows, 2, SIDE_FIT_PX)
    depth = depth_mm[rows[:, None, None], edge]
    slope = np.array([-1.0, 1.0])[None, :, None] * (edge - head.cx) / head.fx
    lateral = slope * depth
    too_narrow = total[:, 0] < 2 * SIDE_FIT_PX
    for a in (depth, lateral, slope):
        a[too_narrow] = np.nan
    gap, deeper = rim_sides_mm(lateral.reshape(-1, SIDE_FIT_PX), depth.reshape(-1, SIDE_FIT_PX),
                               slope.reshape(-1, SIDE_FIT_PX))
    side_lateral = lateral[..., 0] + gap.reshape(-1, 2)
    side_depth = depth[..., 0] + deeper.reshape(-1, 2)
    return head.cx + np.array([-1.0, 1.0]) * head.fx * side_lateral / side_depth


@dataclass(frozen=True)
class RimModel:
    """The band of pixels inside the trunk's silhouette on a reference map, with the two ways
    breathing moves it, each seen along the ray (a flank near grazing stretches a displacement
    along the axis by 1 / (1 - slope * ray slope)):
    - forward: along the axis, in proportion to (half width)^2 - x^2 across the row, zero at both
      sides (the ribs hinge there);
    - sideways: the rib cage widening, a stretch x -> x (1 + e) about the row's middle, which moves
      the band's depth by -e x dz/dx (steepest on the flank, where the forward motion is least).
    Each edge (one side of one trunk row) has its own amount of each."""

    rows: np.ndarray  # (E,) row of each edge (two per trunk row)
    cols: np.ndarray  # (E, W) columns from the silhouette inwards, -1 where the row is too short
    regressor: np.ndarray  # (E, W) the hinge model's displacement profile over the stretch (mm); 0 unused
    lateral: np.ndarray  # (E, W) the sideways stretch's displacement profile (mm per unit stretch)
    side_depth_mm: float = float("nan")  # median depth of the sides on the reference map
    sideways: bool = False  # whether the band tells the stretch from a shift (sideways_told_apart)

    def level(self, depth_mm: np.ndarray, valid: np.ndarray) -> float:
        """The depth the trunk would have at its side if it only breathed as modelled: the intercept,
        common to all edges, of depth against the two profiles with amounts per edge (least squares:
        each edge's depths and ones projected off its own profiles). Linear in the depths, so the
        level of a difference is the difference of the levels."""
        cols = np.maximum(self.cols, 0)
        y = depth_mm[self.rows[:, None], cols]
        w = (self.cols >= 0) & (self.regressor > 0) & valid[self.rows[:, None], cols] & np.isfinite(y)
        profiles = [self.regressor, self.lateral] if self.sideways else [self.regressor]
        numerator, denominator = _intercept_sums(np.where(w, y, 0.0), w, profiles)
        return numerator / denominator if denominator > 0 else float("nan")

    def edge_statistics(self, displacement_mm: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """(edges, len(EDGE_STATISTICS)): per edge, the sums over its band pixels in `valid` that a least-
        squares fit of the displacement on the two profiles needs (core/volume/metric.py, session_shifts)."""
        cols = np.maximum(self.cols, 0)
        y = displacement_mm[self.rows[:, None], cols]
        w = (self.cols >= 0) & (self.regressor > 0) & valid[self.rows[:, None], cols] & np.isfinite(y)
        y, h, lat = (np.where(w, a, 0.0) for a in (y, self.regressor, self.lateral))
        return np.stack([w.sum(axis=1), y.sum(axis=1), h.sum(axis=1), lat.sum(axis=1), (y * h).sum(axis=1),
                         (y * lat).sum(axis=1), (h * h).sum(axis=1), (h * lat).sum(axis=1), (lat * lat).sum(axis=1)],
                        axis=1).astype(float)


# RimModel.edge_statistics' columns: pixels, sum y, sum h, sum l, sum yh, sum yl, sum hh, sum hl, sum ll
# (y the displacement, h and l the hinge's and the stretch's profiles)
EDGE_STATISTICS = ("n", "y", "h", "l", "yh", "yl", "hh", "hl", "ll")


# The sideways stretch enters the rim's level where, on the median edge, it and the hinge leave this
# share of a shift's information (on the simulated bodies 0.05-0.08; a parabolic dome 0).
SIDEWAYS_MIN_SHARE = 0.01


def sideways_told_apart(hinge: np.ndarray, sideways: np.ndarray, used: np.ndarray) -> bool:
    """Whether a band tells the sideways stretch from a shift of the whole: on the median edge the
    hinge and the stretch leave at least SIDEWAYS_MIN_SHARE of what the hinge alone leaves of a
    shift. Where the profile across the row is a parabola (no steep flank) the three are one and the
    same, and the stretch is left out."""
    ones = used.astype(float)
    both, alone = (np.clip(_projections(ones, used, profiles)[1], 0.0, None)
                   for profiles in ([hinge, sideways], [hinge]))
    usable = (alone > 0) & (used.sum(axis=1) > 3)
    return bool(usable.any() and np.median(both[usable] / alone[usable]) >= SIDEWAYS_MIN_SHARE)


def _projections(y: np.ndarray, w: np.ndarray, profiles: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per edge, the sum of y and the count of pixels, less their parts along the edge's profiles
    (least squares on the pixels w): what is left of y and of a constant once each edge's own
    amounts are fitted."""
    design = np.stack([np.where(w, p, 0.0) for p in profiles], axis=-1)
    ones = w.astype(float)
    gram = np.linalg.pinv(np.einsum("ewi,ewj->eij", design, design))
    on_ones, on_y = np.einsum("ewi,ew->ei", design, ones), np.einsum("ewi,ew->ei", design, y)
    left_y = y.sum(axis=1) - np.einsum("ei,eij,ej->e", on_ones, gram, on_y)
    left_ones = ones.sum(axis=1) - np.einsum("ei,eij,ej->e", on_ones, gram, on_ones)
    return left_y, left_ones


def _intercept_sums(y: np.ndarray, w: np.ndarray, profiles: list[np.ndarray]) -> tuple[float, float]:
    """The common intercept's least-squares sums over the edges with more pixels than profiles + 1."""
    keep = w.sum(axis=1) > len(profiles) + 1
    left_y, left_ones = _projections(y[keep], w[keep], [p[keep] for p in profiles])
    return float(np.sum(left_y)), float(np.sum(left_ones))


def rim_model(depth_mm: np.ndarray, mask: np.ndarray, head: Head, band_px: int,
              skip_px: int = RIM_SKIP_PX) -> RimModel:
    """The RimModel of a reference map: band_px pixels after the outermost skip_px of both sides of
    every trunk row; the side of each side of the trunk at the median of its rows' rim_side_mm."""
    width = skip_px + band_px
    edges = list(_row_edges(mask, width))
    if not edges:
        return RimModel(np.zeros(0, int), np.zeros((0, width), int), np.zeros((0, width)), np.zeros((0, width)))
    rows = np.array([r for r, _ in edges])
    cols = np.full((len(edges), width), -1)
    for e, (_, c) in enumerate(edges):
        cols[e, :len(c)] = c
    used = cols >= 0
    safe = np.maximum(cols, 0)
    z = np.where(used, depth_mm[rows[:, None], safe], np.nan)
    u = (safe - head.cx) / head.fx
    outward = np.sign(u[:, :1] * z[:, :1] - u[:, -1:] * z[:, -1:])
    outward[outward == 0] = 1.0
    lateral = outward * u * z
    ray_slope = outward * u
    gaps, deeper = rim_sides_mm(lateral, z, ray_slope)
    side = np.zeros(len(edges))
    for parity in (0, 1):  # the image's left and right sides of the trunk
        on_side = np.arange(len(edges)) % 2 == parity
        side[on_side] = lateral[on_side, 0] + np.median(gaps[on_side])
    slope = np.full(z.shape, np.nan)
    for e in range(len(edges)):
        ok = np.flatnonzero(used[e] & np.isfinite(z[e]))
        if len(ok) >= 2:
            slope[e, ok] = np.gradient(z[e, ok], lateral[e, ok])
    stretch = np.clip(1.0 - slope * ray_slope, 0.2, None)
    from_side = side[:, None] - lateral
    half_width = np.repeat(0.5 * (side[0::2] + side[1::2]), 2)[:, None]  # edges come in pairs, row by row
    hinge = from_side * (1.0 - from_side / (2.0 * half_width))  # in proportion to half_width^2 - x^2 across the row
    regressor = np.where(used & np.isfinite(stretch), hinge / stretch, 0.0)
    regressor[:, :skip_px] = 0.0
    regressor = np.clip(regressor, 0.0, None)
    # the stretch's displacement: (distance from the row's middle) * dz/dx, seen along the ray
    sideways = np.where(used & np.isfinite(stretch) & np.isfinite(slope),
                        (half_width - from_side) * slope / stretch, 0.0)
    return RimModel(rows, cols, regressor, sideways, float(np.nanmedian(z[:, 0] + deeper)),
                    sideways_told_apart(regressor, sideways, used & (regressor > 0) & np.isfinite(z)))


# The contour model is fitted to the pixels with a depth within CONTOUR_FIT_MM (across, at the
# map's depth) of the outermost one, which may lie up to CONTOUR_MAX_GAP_MM inside the silhouette's
# edge (the band of grazing light without normals: about two pixels at 210 px wide, 2.3 m).
CONTOUR_FIT_MM = 25.0
CONTOUR_MAX_GAP_MM = 18.0


def contour_depth_mm(depth_mm: np.ndarray, valid: np.ndarray, silhouette: np.ndarray, head: Head) -> float:
    """The depth of the trunk's occluding contour, the median over its rows' both sides.

    Near an occluding contour a smooth surface's depth goes as the square root of the image
    distance from it: Z = Z_c - a sqrt(d) + b d, d = |u - u_c|, u_c the silhouette's edge (half a
    pixel outside its outermost pixel), b the next term of the curvature. The maps lack the
    silhouette's outermost pixels (the far lights graze the surface there and no normal is solved),
    which hold tens of mm of depth: extrapolating the rim's
    band to the side put the maps 22-37 mm too far on a population subject; the contour model
    within 10 mm (docs/reconstruction.md). NaN where fewer than MIN_SIDE_ROWS row sides give one."""
    _, sides = contour_rows_mm(depth_mm, valid, silhouette, head)
    found = sides[np.isfinite(sides)]
    return float(np.median(found)) if len(found) >= MIN_SIDE_ROWS else float("nan")


def contour_rows_mm(depth_mm: np.ndarray, valid: np.ndarray, silhouette: np.ndarray, head: Head,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(trunk rows, (rows, 2) depth of the occluding contour at each row's left and right side):
    contour_depth_mm's model on each row side; NaN where a side gives none."""
    rows = torso_rows(valid)
    sides = np.full((len(rows), 2), np.nan)
    pixel_mm = float(np.nanmedian(depth_mm[valid])) / head.fx if valid.any() else float("nan")
    if not np.isfinite(pixel_mm):
        return rows, sides
    fit_px = max(4, int(round(CONTOUR_FIT_MM / pixel_mm)))
    gap_px = max(2.0, CONTOUR_MAX_GAP_MM / pixel_mm)
    for k, row in enumerate(rows):
        run = np.flatnonzero(silhouette[row])
        cols = np.flatnonzero(valid[row] & np.isfinite(depth_mm[row]))
        if len(run) == 0 or len(cols) < 3 * fit_px:
            continue
        for side, (edge, inner) in enumerate(((run[0] - 0.5, cols[:fit_px]), (run[-1] + 0.5, cols[::-1][:fit_px]))):
            if abs(inner[0] - edge) > gap_px:
                continue
            away = np.abs(inner - edge)
            design = np.column_stack([np.ones(len(away)), -np.sqrt(away), away])
            (z_contour, a, _), *_ = np.linalg.lstsq(design, depth_mm[row, inner], rcond=None)
            if a > 0:  # the surface recedes towards its contour
                sides[k, side] = z_contour
    return rows, sides


def row_widths_px(depth_mm: np.ndarray, valid: np.ndarray, head: Head) -> np.ndarray:
    """The distance between the trunk's sides (side_columns) on every row of a map; NaN where a row
    does not give both."""
    return np.diff(side_columns(depth_mm, valid, head, np.arange(valid.shape[0])), axis=1)[:, 0]


def rim_band_px(depth_mm: np.ndarray, valid: np.ndarray, head: Head, rim_band_mm: float = RIM_BAND_MM) -> int:
    """The rim's band (rim_model, rim_depths) in pixels on a map: rim_band_mm at its median depth."""
    return max(4, int(round(rim_band_mm * head.fx / np.median(depth_mm[valid]))))


def rim_skip_px(depth_mm: np.ndarray, valid: np.ndarray, head: Head) -> int:
    """The silhouette's outermost pixels the rim's fits leave out on a map: RIM_SKIP_MM at its median
    depth, RIM_SKIP_PX at least."""
    return max(RIM_SKIP_PX, int(round(RIM_SKIP_MM * head.fx / np.median(depth_mm[valid]))))


def trunk_width_px(depth_mm: np.ndarray, valid: np.ndarray, head: Head, widths_px: np.ndarray | None = None) -> float:
    """The trunk's width in the image: the mean distance between its sides (side_columns) over its
    rows; the silhouette's mean width where fewer than MIN_SIDE_ROWS rows give both sides.
    widths_px: the map's row_widths_px, if already known.

    It gives the first guess of the image scale between maps (the sway along the axis;
    BodySilhouette refines it on the same body rows), and over the map's width_ratio the reference's
    width that the two heads' distances start from (core/volume/metric.py, HeadDisplacements.width_px).
    The silhouette's width did that before, but breathing moves it: the steeper a flank gets, the
    more of its outermost pixels turn past the integrator's grazing limit. On a simulated 30 s slow
    VC the silhouette narrowed by 0.06 px (of 206) per litre, and resampling the maps by that lost
    3 % of the volume (docs/volume.md)."""
    rows = torso_rows(valid)
    if len(rows) == 0:
        return float("nan")
    if widths_px is None:
        widths = np.diff(side_columns(depth_mm, valid, head, rows), axis=1)[:, 0]
    else:
        widths = widths_px[rows]
    if np.isfinite(widths).sum() < MIN_SIDE_ROWS:
        return float(np.mean(valid[rows].sum(axis=1)))
    return float(np.nanmean(widths))


# A map's image scale held at the median of the last maps' when it jumps further (docs/constants.md)
SCALE_JUMP = 0.03
SCALE_WINDOW_MAPS = 9


class DisplacementTracker:
    """A head's metric volume, map by map: the first map with a trunk becomes the reference."""

    def __init__(self, head: Head, rim_band_mm: float = RIM_BAND_MM) -> None:
        self.head = head
        self.rim_band_mm = rim_band_mm
        self._band_px = 0
        self._skip_px = RIM_SKIP_PX
        self._reference: tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]] | None = None
        self._rim: RimModel | None = None
        self._scales: deque[float] = deque(maxlen=SCALE_WINDOW_MAPS)  # the scales the last maps measured

    def _gated(self, frame: BodyFrame, valid: np.ndarray, row_widths: np.ndarray, width: float,
               ) -> tuple[BodyFrame, float]:
        """The frame, and the width, with an image scale that jumps by more than SCALE_JUMP from the
        median of the last SCALE_WINDOW_MAPS maps' (this one's included) replaced by that median: a
        jump over fewer than half of them is held back; one that lasts moves the median, and is taken."""
        self._scales.append(frame.scale)
        median = float(np.median(self._scales))
        if abs(frame.scale / median - 1.0) <= SCALE_JUMP:
            return frame, width
        held = self._silhouette.frame(valid, row_widths, median, refine_scale=False)
        return held, self._reference_width * median

    def add(self, depth_mm: np.ndarray, mask: np.ndarray, silhouette: np.ndarray | None = None,
            distance_mm: float | None = None, row_widths: np.ndarray | None = None) -> DisplacementSums:
        """silhouette: the trunk's mask with the pixels that have no depth (HeadMap.silhouette); with
        it the reference's sides are placed at its occluding contour (contour_depth_mm).
        distance_mm: the subject's distance when known from elsewhere (the two heads' geometry); the
        body frame's scale is then the reference's distance over it, not the ratio of the trunk's
        widths, which breathing moves on bodies whose flanks move (docs/volume.md).
        row_widths: the map's row_widths_px, if the caller already measured them."""
        known = distance_mm is not None and bool(np.isfinite(distance_mm)) and distance_mm > 0
        valid = mask & np.isfinite(depth_mm)
        if row_widths is None:
            row_widths = row_widths_px(depth_mm, valid, self.head)
        width = trunk_width_px(depth_mm, valid, self.head, row_widths)
        if self._reference is None:
            regions = trunk_regions(valid, self.head.name)
            if not regions:
                return DisplacementSums(float("nan"), width, {}, {})
            footprint = (depth_mm / self.head.fx) * (depth_mm / self.head.fy)
            self._reference = (np.where(valid, depth_mm, np.nan), valid, footprint, regions)
            self._reference_width = width
            self._reference_distance = float(distance_mm) if known else float("nan")
            self._reference_depth_mm = float(np.median(depth_mm[valid]))
            self._silhouette = BodySilhouette(valid, row_widths, self.head, silhouette)
            self._band_px = rim_band_px(depth_mm, valid, self.head, self.rim_band_mm)
            self._skip_px = rim_skip_px(depth_mm, valid, self.head)
            self._rim = rim_model(depth_mm, valid, self.head, self._band_px, self._skip_px)
            rim_of_reference, _ = rim_depths(depth_mm, depth_mm, valid, self._band_px, self._skip_px)
            # the trunk widths place the sides (its occluding contour), which lie deeper than its rim
            contour = contour_depth_mm(depth_mm, valid, silhouette, self.head) if silhouette is not None else float("nan")
            side = contour if np.isfinite(contour) else self._rim.side_depth_mm
            self._side_per_rim = side / rim_of_reference
            self._neck = neck_pixels(valid)
        ref_depth, ref_mask, footprint, regions = self._reference
        if known and np.isfinite(self._reference_distance):
            frame = self._silhouette.frame(valid, row_widths, self._reference_distance / distance_mm,
                                           refine_scale=False)
        else:
            frame, width = self._gated(self._silhouette.frame(valid, row_widths, width / self._reference_width),
                                       valid, row_widths, width)
        width_ratio = self._silhouette.width_ratio(row_widths, frame)
        at_mm = float(distance_mm) if known else self._reference_depth_mm / frame.scale
        body_shift_mm = (frame.shift_u_px * at_mm / self.head.fx, frame.shift_v_px * at_mm / self.head.fy)
        z = frame.resampled(depth_mm, valid, ref_mask.shape, self.head)
        both = ref_mask & np.isfinite(z)
        _, rim = rim_depths(ref_depth, z, both, self._band_px, self._skip_px)
        level_ref, level = self._rim.level(ref_depth, both), self._rim.level(z, both)
        reference = np.where(both, footprint * (ref_depth - level_ref), 0.0)
        current = np.where(both, footprint * (z - level), 0.0)
        parts = dict(regions, all=ref_mask)
        area = np.where(both, footprint, 0.0)
        displaced = np.where(both, footprint * (z - ref_depth), 0.0)
        neck = self._neck & both
        neck_mm = float(np.median((z - ref_depth)[neck])) if neck.sum() >= MIN_NECK_PIXELS else float("nan")
        sums = DisplacementSums(rim * self._side_per_rim, width, {k: float(reference[m].sum()) for k, m in parts.items()},
                                {k: float(current[m].sum()) for k, m in parts.items()},
                                {k: float(area[m].sum()) for k, m in parts.items()},
                                {k: float(displaced[m].sum()) for k, m in parts.items()},
                                (level_ref, level), self._rim.edge_statistics(z - ref_depth, both), width_ratio,
                                body_shift_mm, neck_mm)
        return sums


def neck_pixels(valid: np.ndarray, share: float = NECK_ROWS) -> np.ndarray:
    """The trunk mask's pixels on its top `share` of rows (two at least): the neck."""
    rows = np.nonzero(valid.any(axis=1))[0]
    top = np.zeros_like(valid)
    if len(rows):
        top[rows[0]:rows[min(len(rows) - 1, max(2, int(round(share * len(rows)))) - 1)] + 1] = True
    return valid & top


def head_volume_l(reference, current, k_reference, k):
    """Volume (L) from DisplacementSums (mm^3) with the reference map scaled by k_reference and the
    current one by k: V = k0^2 (k0 C - k S) (the footprint goes as the reference's scale squared,
    depths as each map's own)."""
    return k_reference ** 2 * (k_reference * np.asarray(reference) - np.asarray(k) * np.asarray(current)) * 1e-6


def plain_volume_l(displaced_mm3):
    """Volume (L) a head saw the trunk gain since its reference map along its rays, with no level:
    -sum fp (z - Z_ref) (DisplacementSums.displaced)."""
    return -1e-6 * np.asarray(displaced_mm3)


def neck_referred_volume_l(displaced_mm3, areas_mm2, neck_mm):
    """The plain volume (plain_volume_l) less the neck's displacement over the same footprint
    (DisplacementSums.neck_mm): a shift of the whole map cancels; NaN where the map showed no neck."""
    return -1e-6 * (np.asarray(displaced_mm3) - np.asarray(neck_mm) * np.asarray(areas_mm2))


def metric_head_volume_l(reference: np.ndarray, current: np.ndarray, side_mm: np.ndarray,
                         side_target_mm: np.ndarray) -> np.ndarray:
    """Volume (L) a head saw the trunk gain since its reference map, from the DisplacementSums
    series, with each map scaled so that its rim lies at side_target_mm (the reference map is the
    first): k = target / side."""
    k = np.asarray(side_target_mm) / np.asarray(side_mm)
    k0 = k[np.flatnonzero(np.isfinite(k))[0]] if np.isfinite(k).any() else np.nan
    return head_volume_l(reference, current, k0, k)


def maps_within(seconds: np.ndarray, window_s: float) -> int:
    """How many maps of a series (times in s, nearly even) a running median over window_s takes: an odd
    number, 3 at least."""
    step = float(np.median(np.diff(seconds)))
    return max(3, int(round(window_s / step)) | 1) if step > 0 else 3


def smooth_in_time(t_s: np.ndarray, values: np.ndarray, sigma_s: float, apart_s: float | None = None) -> np.ndarray:
    """Gaussian smoothing of a series in time (sigma in s); NaNs bridged by interpolation. On (nearly)
    even steps a Gaussian filter over the samples; on a series that holds a stretch of samples much
    closer together than the rest (maps at every frame beside maps at every light cycle: uneven_steps)
    each sample the value at it of the line fitted, with Gaussian weights in time, to the samples within
    4 sigma of it: on even steps the same as the Gaussian's mean, and where the samples crowd on one
    side it is not pulled to their side. apart_s: a gap between samples longer than this divides the
    series into pieces smoothed each on its own (maps left out for a step: the body is elsewhere after it)."""
    t, x = np.asarray(t_s, float), np.asarray(values, float)
    if apart_s is not None and len(t) > 1:
        cuts = np.flatnonzero(np.diff(t) > apart_s) + 1
        if len(cuts):
            return np.concatenate([smooth_in_time(tp, xp, sigma_s)
                                   for tp, xp in zip(np.split(t, cuts), np.split(x, cuts))])
    good = np.isfinite(x)
    if good.sum() < 2:
        return x.copy()
    x = np.interp(t, t[good], x[good])
    step = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    if step <= 0:
        return x
    if uneven_steps(t):
        return _weighted_in_time(t, x, sigma_s)
    return ndimage.gaussian_filter1d(x, sigma_s / step, mode="nearest")


def uneven_steps(t_s: np.ndarray) -> bool:
    """Whether a series' time steps (increasing times) are not nearly even: some step under half the
    median step, or more than a tenth of them over twice it."""
    steps = np.diff(np.asarray(t_s, float))
    if len(steps) < 2:
        return False
    median = float(np.median(steps))
    return bool(steps.min() < 0.5 * median or np.mean(steps > 2.0 * median) > 0.1)


def _weighted_in_time(t: np.ndarray, x: np.ndarray, sigma_s: float) -> np.ndarray:
    """Each sample the value at it of the line fitted with Gaussian weights (sigma_s) to the samples within
    4 sigma_s of it (t increasing; local-linear regression)."""
    n = len(t)
    reach = 4.0 * sigma_s
    index = np.arange(n)
    before = int((index - np.searchsorted(t, t - reach, "left")).max())
    after = int((np.searchsorted(t, t + reach, "right") - 1 - index).max())
    s0, s1, s2, x0, x1 = (np.zeros(n) for _ in range(5))
    for offset in range(-before, after + 1):
        j = index + offset
        inside = (j >= 0) & (j < n)
        j = np.clip(j, 0, n - 1)
        d = (t[j] - t) / sigma_s
        w = np.where(inside & (np.abs(d) <= 4.0), np.exp(-0.5 * d ** 2), 0.0)
        s0 += w
        s1 += w * d
        s2 += w * d * d
        x0 += w * x[j]
        x1 += w * d * x[j]
    determinant = s0 * s2 - s1 * s1
    with np.errstate(invalid="ignore", divide="ignore"):
        line = (s2 * x0 - s1 * x1) / determinant
    return np.where(determinant > 1e-9 * s0 * s0, line, x0 / s0)


def two_head_distances(width_front_px: np.ndarray, width_back_px: np.ndarray, baseline_mm: float,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Depths of the trunk's sides from front and back, from the two heads' trunk widths
    (trunk_width_px) and the baseline."""
    ratio = np.asarray(width_front_px) / np.asarray(width_back_px)
    front = baseline_mm / (1.0 + ratio)
    return front, baseline_mm - front


def normalised_gradient_volume(values: np.ndarray) -> np.ndarray:
    """Thesis eq. 3.27: (V - mean V) / max |V - mean V|."""
    centred = values - np.nanmean(values)
    return centred / np.nanmax(np.abs(centred))


def gradient_volume_correlations(series: dict[str, tuple[np.ndarray, np.ndarray]], t_reference: np.ndarray,
                                 reference: np.ndarray) -> dict[str, float]:
    """r of each head's normalised gradient volume (eq. 3.27) and of their sum ("combined") against a
    reference volume curve, on the first head's time stamps. series: head -> (timestamps, gradient volume)."""
    t = next(iter(series.values()))[0]
    reference_at = np.interp(t, t_reference, reference)
    normalised = {h: normalised_gradient_volume(np.interp(t, ts, gv)) for h, (ts, gv) in series.items()}
    out = {h: float(np.corrcoef(v, reference_at)[0, 1]) for h, v in normalised.items()}
    out["combined"] = float(np.corrcoef(sum(normalised.values()), reference_at)[0, 1])
    return out
