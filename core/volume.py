"""Volumes from height maps: the thesis' gradient volume and the metric volume in litres.

Metric volume of one head ("cap volume"): the volume between the torso's surface and the plane
through its lateral silhouette edges, each pixel weighted by its footprint (Z / fx)(Z / fy).
The plane moves with the body, so a rigid shift of the whole torso (sway, along the axis or
sideways) leaves the cap volume as it is, while breathing, which lifts the chest and abdomen
off their sides, changes it. The front and back caps add up to the volume change of the trunk
(what moves the sides themselves, lateral expansion of the ribs, is not seen by either head).

The cap volume scales as the cube of the depth map's scale, so its distance must be right from
frame to frame to a millimetre or so (about 30 mL per mm for an adult at 2 m). With both
heads, the distance comes from the silhouettes: both heads see the same lateral edges, so
their widths in pixels stand in the inverse ratio of the distances, D_f / D_b = W_b / W_f, and
D_f + D_b is the baseline between the heads: a triangulation across the subject that lateral
expansion cannot disturb (it widens both silhouettes alike).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from core.rig import Head


@dataclass(frozen=True)
class CapMeasure:
    volume_l: float  # cap volume at the map's own scale
    side_depth_mm: float  # depth of the silhouette plane on the optical axis
    width_px: float  # mean silhouette width over the torso rows
    rows: int


def torso_rows(mask: np.ndarray, min_width_fraction: float = 0.6) -> np.ndarray:
    """Rows of the trunk: as wide as 60 % of the widest row or more (the neck and head are narrower)."""
    widths = mask.sum(axis=1)
    return np.nonzero(widths >= min_width_fraction * widths.max())[0] if widths.max() > 0 else np.zeros(0, int)


def _silhouette_plane(depth_mm: np.ndarray, valid: np.ndarray, rows: np.ndarray,
                      edge_px: int) -> tuple[np.ndarray, list[int]]:
    """Plane z = c0 + c1 u + c2 v through the lateral silhouette edges of the trunk rows, and the
    width of each row."""
    xs, ys, zs, widths = [], [], [], []
    for r in rows:
        cols = np.nonzero(valid[r])[0]
        left, right = cols[0], cols[-1]
        widths.append(right - left + 1)
        for c in np.unique(np.concatenate([cols[:edge_px], cols[-edge_px:]])):
            xs.append(c)
            ys.append(r)
            zs.append(depth_mm[r, c])
    a = np.column_stack([np.ones(len(xs)), xs, ys])
    z = np.asarray(zs)
    coefficients = np.linalg.lstsq(a, z, rcond=None)[0]
    for _ in range(2):  # robust: drop edge points far from the plane (a hand, a fold)
        residual = z - a @ coefficients
        keep = np.abs(residual) < 3.0 * max(1.4826 * np.median(np.abs(residual)), 1.0)
        coefficients = np.linalg.lstsq(a[keep], z[keep], rcond=None)[0]
    return coefficients, widths


def cap_measure(depth_mm: np.ndarray, mask: np.ndarray, head: Head, edge_px: int = 2) -> CapMeasure:
    """Cap volume, silhouette plane and width of one height map."""
    valid = mask & np.isfinite(depth_mm)
    rows = torso_rows(valid)
    if len(rows) < 5:
        return CapMeasure(float("nan"), float("nan"), float("nan"), 0)
    coefficients, widths = _silhouette_plane(depth_mm, valid, rows, edge_px)
    region = np.zeros_like(valid)
    region[rows] = valid[rows]
    r_idx, c_idx = np.nonzero(region)
    plane = coefficients[0] + coefficients[1] * c_idx + coefficients[2] * r_idx
    z_px = depth_mm[r_idx, c_idx]
    footprint = (z_px / head.fx) * (z_px / head.fy)
    volume = float(np.sum((plane - z_px) * footprint)) * 1e-6
    side_depth = float(coefficients[0] + coefficients[1] * head.cx + coefficients[2] * head.cy)
    return CapMeasure(volume, side_depth, float(np.mean(widths)), len(rows))


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
    (ua, va), (ub, vb) = _silhouette_centre_px(mask_a), _silhouette_centre_px(mask_b)
    out = np.full(depth_b.shape, np.nan)
    if not all(np.isfinite([side_a, side_b, ua, ub])):
        return out
    ratio = side_b / side_a  # image size goes as 1 / distance
    v, u = np.mgrid[0:depth_b.shape[0], 0:depth_b.shape[1]].astype(float)
    u_a = head.cx + (u - head.cx) * ratio + (ua - head.cx - (ub - head.cx) * ratio)
    v_a = head.cy + (v - head.cy) * ratio + (va - head.cy - (vb - head.cy) * ratio)
    valid = mask_a & np.isfinite(depth_a)
    z = ndimage.map_coordinates(np.where(valid, depth_a, 0.0), [v_a, u_a], order=1, cval=0.0)
    weight = ndimage.map_coordinates(valid.astype(float), [v_a, u_a], order=1, cval=0.0)
    z_a = np.where(weight > 0.99, z / np.maximum(weight, 1e-9), np.nan) + (side_b - side_a)
    inside = mask_b & np.isfinite(depth_b)
    out[inside] = depth_b[inside] - z_a[inside]
    return out


def two_head_distances(width_front_px: np.ndarray, width_back_px: np.ndarray, baseline_mm: float,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Silhouette-plane depths of front and back from the two silhouette widths and the baseline."""
    ratio = np.asarray(width_front_px) / np.asarray(width_back_px)
    front = baseline_mm / (1.0 + ratio)
    return front, baseline_mm - front


def rescaled_cap(volume_l: np.ndarray, side_depth_mm: np.ndarray, distance_mm: np.ndarray) -> np.ndarray:
    """Cap volume after scaling the map so its silhouette plane lies at `distance_mm` (volume ~ scale^3)."""
    return np.asarray(volume_l) * (np.asarray(distance_mm) / np.asarray(side_depth_mm)) ** 3


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
