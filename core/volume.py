"""Volumes from height maps: the thesis' gradient volume, and the building blocks of the metric volume.

Metric volume of one head: each map is compared with a reference map of the same head in the
body's own frame (resampled so the trunk silhouettes coincide), both referred to the depth of
their own silhouette (the rim, where the ribs hinge), so a rigid shift of the whole torso (sway,
along the axis or sideways) is not breathing; every pixel's displacement is weighted by its
footprint (Z / fx)(Z / fy). What moves the rim itself is not seen: lateral expansion of the ribs
widens the silhouette, and a rim that moves along the axis is taken for sway.

The result scales with the depth map's absolute scale times the relief above the rim (about
10 L per head for an adult), so every map's scale is set afterwards from a distance that
breathing does not move (core/metric_volume.py). With both heads it comes from the silhouettes:
both see the same lateral edges, so their widths in pixels stand in the inverse ratio of the
distances, D_f / D_b = W_b / W_f, and D_f + D_b is the baseline between the heads.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from core.rig import Head

# The silhouette's outermost pixels left out of the rim's line (rim_depths). On a simulated subject
# at 2000 mm with sway, with the subject mask grown to the silhouette: r against the true volume
# 0.9952 with them, 0.9971 without (slope 0.866 both); docs/volume.md.
RIM_SKIP_PX = 2


def torso_rows(mask: np.ndarray, min_width_fraction: float = 0.6) -> np.ndarray:
    """Rows of the trunk: as wide as 60 % of the widest row or more (the neck and head are narrower)."""
    widths = mask.sum(axis=1)
    return np.nonzero(widths >= min_width_fraction * widths.max())[0] if widths.max() > 0 else np.zeros(0, int)


def side_depth_mm(depth_mm: np.ndarray, mask: np.ndarray, edge_px: int = 2) -> float:
    """Median depth of the trunk's lateral silhouette edges (the sides, which breathing barely moves)."""
    valid = mask & np.isfinite(depth_mm)
    z = []
    for r in torso_rows(valid):
        cols = np.nonzero(valid[r])[0]
        z.append(depth_mm[r, cols[:edge_px]])
        z.append(depth_mm[r, cols[-edge_px:]])
    return float(np.median(np.concatenate(z))) if z else float("nan")


def _silhouette_centre_px(mask: np.ndarray) -> tuple[float, float]:
    rows = torso_rows(mask)
    if len(rows) == 0:
        return float("nan"), float("nan")
    centres = [0.5 * (cols[0] + cols[-1]) for cols in (np.nonzero(mask[r])[0] for r in rows)]
    return float(np.mean(centres)), 0.5 * float(rows[0] + rows[-1])


def _aligned_depth(depth_a: np.ndarray, mask_a: np.ndarray, mask_b: np.ndarray, head: Head,
                   ratio: float) -> np.ndarray:
    """Map a resampled onto map b's pixels through the similarity (scale `ratio`, a's image size over
    b's, about the principal point, and shift) that carries b's trunk silhouette onto a's."""
    (ua, va), (ub, vb) = _silhouette_centre_px(mask_a), _silhouette_centre_px(mask_b)
    if not all(np.isfinite([ratio, ua, ub])):
        return np.full(mask_b.shape, np.nan)
    v, u = np.mgrid[0:mask_b.shape[0], 0:mask_b.shape[1]].astype(float)
    u_a = head.cx + (u - head.cx) * ratio + (ua - head.cx - (ub - head.cx) * ratio)
    v_a = head.cy + (v - head.cy) * ratio + (va - head.cy - (vb - head.cy) * ratio)
    valid = mask_a & np.isfinite(depth_a)
    z = ndimage.map_coordinates(np.where(valid, depth_a, 0.0), [v_a, u_a], order=1, cval=0.0)
    weight = ndimage.map_coordinates(valid.astype(float), [v_a, u_a], order=1, cval=0.0)
    return np.where(weight > 0.99, z / np.maximum(weight, 1e-9), np.nan)


def body_aligned_displacement(depth_a: np.ndarray, mask_a: np.ndarray, depth_b: np.ndarray, mask_b: np.ndarray,
                              head: Head) -> np.ndarray:
    """How far each point of the trunk moved towards the camera from map b to map a, on map b's
    pixels, with the subject's sway between the maps removed.

    A body that sways farther from the camera looks smaller, and sideways it shifts in the image:
    differencing two maps pixel by pixel would see a sloped surface slide past the pixel and call
    it breathing. Map a is resampled through the similarity (scale about the principal point and
    shift) that carries b's trunk silhouette onto a's, and brought to b's distance by the depth of
    the sides (side_depth_mm).
    """
    side_a, side_b = side_depth_mm(depth_a, mask_a), side_depth_mm(depth_b, mask_b)
    z_a = _aligned_depth(depth_a, mask_a, mask_b, head, side_b / side_a)  # image size goes as 1 / distance
    out = np.full(depth_b.shape, np.nan)
    inside = mask_b & np.isfinite(depth_b) & np.isfinite(z_a)
    out[inside] = depth_b[inside] - (z_a[inside] + side_b - side_a)
    return out


def trunk_regions(mask: np.ndarray, head_name: str) -> dict[str, np.ndarray]:
    """The trunk's quadrants on a map's pixels: the upper and lower half of the trunk rows (chest and
    abdomen), split at the silhouette's mean column (the midline). The front head sees the
    patient's left on the image's right, the back head on the image's left. Empty if the map
    shows no trunk."""
    rows = torso_rows(mask)
    if len(rows) < 4:
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


@dataclass(frozen=True)
class DisplacementSums:
    """One map against the reference map of its head, in footprint-weighted sums (mm^3) over the
    pixels both show, per region ("all" is every such pixel, the neck and shoulders included):
    reference = sum fp (Z_ref - rim_ref), current = sum fp (z - rim) with z the current map
    resampled into the reference's body frame and rim each map's silhouette depth (rim_depths).
    Kept apart so the two maps' scales can be set afterwards (metric_head_volume_l)."""

    side_mm: float  # depth of the trunk's silhouette (rim_depths), at the map's own scale
    width_px: float
    reference: dict[str, float]
    current: dict[str, float]


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
    for r in torso_rows(mask):
        cols = np.nonzero(mask[r])[0]
        n = min(width, len(cols) // 2)
        for edge in (cols[:n], cols[::-1][:n]):
            sums_a[:n] += depth_a[r, edge]
            sums_b[:n] += depth_b[r, edge]
            counts[:n] += 1
    used = counts > 0
    used[:skip_px] = False
    if used.sum() < 2:
        return float("nan"), float("nan")
    j = np.arange(width)[used]
    at_rim = [np.polyval(np.polyfit(j, sums[used] / counts[used], 1), -0.5) for sums in (sums_a, sums_b)]
    return float(at_rim[0]), float(at_rim[1])


class DisplacementTracker:
    """A head's metric volume, map by map: the first map with a trunk becomes the reference."""

    def __init__(self, head: Head, rim_band_px: int = 12) -> None:
        self.head = head
        self.rim_band_px = rim_band_px
        self._reference: tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]] | None = None

    def add(self, depth_mm: np.ndarray, mask: np.ndarray) -> DisplacementSums:
        valid = mask & np.isfinite(depth_mm)
        rows = torso_rows(valid)
        width = float(np.mean(valid[rows].sum(axis=1))) if len(rows) else float("nan")
        if self._reference is None:
            regions = trunk_regions(valid, self.head.name)
            if not regions:
                return DisplacementSums(float("nan"), width, {}, {})
            footprint = (depth_mm / self.head.fx) * (depth_mm / self.head.fy)
            self._reference = (np.where(valid, depth_mm, np.nan), valid, footprint, regions)
            self._reference_width = width
        ref_depth, ref_mask, footprint, regions = self._reference
        # the silhouette's width gives the image scale more steadily than the photometric distance
        z = _aligned_depth(depth_mm, valid, ref_mask, self.head, width / self._reference_width)
        both = ref_mask & np.isfinite(z)
        rim_ref, rim = rim_depths(ref_depth, z, both, self.rim_band_px)
        reference = np.where(both, footprint * (ref_depth - rim_ref), 0.0)
        current = np.where(both, footprint * (z - rim), 0.0)
        parts = dict(regions, all=ref_mask)
        return DisplacementSums(rim, width, {k: float(reference[m].sum()) for k, m in parts.items()},
                                {k: float(current[m].sum()) for k, m in parts.items()})


def head_volume_l(reference, current, k_reference, k):
    """Volume (L) from DisplacementSums (mm^3) with the reference map scaled by k_reference and the
    current one by k: V = k0^2 (k0 C - k S) (the footprint goes as the reference's scale squared,
    depths as each map's own)."""
    return k_reference ** 2 * (k_reference * np.asarray(reference) - np.asarray(k) * np.asarray(current)) * 1e-6


def metric_head_volume_l(reference: np.ndarray, current: np.ndarray, side_mm: np.ndarray,
                         side_target_mm: np.ndarray) -> np.ndarray:
    """Volume (L) a head saw the trunk gain since its reference map, from the DisplacementSums
    series, with each map scaled so that its rim lies at side_target_mm (the reference map is the
    first): k = target / side."""
    k = np.asarray(side_target_mm) / np.asarray(side_mm)
    k0 = k[np.flatnonzero(np.isfinite(k))[0]] if np.isfinite(k).any() else np.nan
    return head_volume_l(reference, current, k0, k)


def smooth_in_time(t_s: np.ndarray, values: np.ndarray, sigma_s: float) -> np.ndarray:
    """Gaussian smoothing of a series on (nearly) even time steps; NaNs bridged by interpolation."""
    t, x = np.asarray(t_s, float), np.asarray(values, float)
    good = np.isfinite(x)
    if good.sum() < 2:
        return x.copy()
    x = np.interp(t, t[good], x[good])
    step = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    return ndimage.gaussian_filter1d(x, sigma_s / step, mode="nearest") if step > 0 else x


def two_head_distances(width_front_px: np.ndarray, width_back_px: np.ndarray, baseline_mm: float,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Silhouette-plane depths of front and back from the two silhouette widths and the baseline."""
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
