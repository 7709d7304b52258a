"""Subject distance from diffused maxima regions (thesis section 4.3.2).

Pseudo normals (distant-light photometric stereo with the pseudo light vectors) show, for
each light, a region where the surface faces that light: |N . L_i| >= 0.9 (eq. 4.13). The ray
from the lens through the region's centre and the line from the light back along its pseudo
light vector meet (nearly) at the surface; the closest points of the two (eqs 4.2-4.4) give
a depth, and the distance is the mean over the lights.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from core.lights import closest_points

DMR_THRESHOLD = 0.9


@dataclass(frozen=True)
class DmrEstimate:
    distance_mm: float  # mean depth over the lights that gave one
    depths_mm: np.ndarray  # (4,) NaN where a light had no region
    centres_px: np.ndarray  # (4, 2) (u, v) of each region's centre
    points_mm: np.ndarray  # (4, 3) the triangulated surface points


def diffused_maxima_regions(pseudo_normals: np.ndarray, mask: np.ndarray, pseudo_light_vectors: np.ndarray,
                            threshold: float = DMR_THRESHOLD) -> list[np.ndarray | None]:
    """The largest connected region of |N . L_i| >= threshold inside the mask, for each light (eq. 4.13)."""
    regions = []
    for light in pseudo_light_vectors:
        dot = np.abs(np.nan_to_num(pseudo_normals @ light))
        labels, n = ndimage.label(mask & (dot >= threshold))
        if n == 0:
            regions.append(None)
            continue
        sizes = np.bincount(labels.ravel())[1:]
        regions.append(labels == 1 + int(np.argmax(sizes)))
    return regions


def dmr_distance(pseudo_normals: np.ndarray, mask: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                 light_positions_mm: np.ndarray, pseudo_light_vectors: np.ndarray,
                 threshold: float = DMR_THRESHOLD) -> DmrEstimate:
    depths = np.full(4, np.nan)
    centres = np.full((4, 2), np.nan)
    points = np.full((4, 3), np.nan)
    for k, region in enumerate(diffused_maxima_regions(pseudo_normals, mask, pseudo_light_vectors, threshold)):
        if region is None or region.sum() < 4:
            continue
        rows, cols = np.nonzero(region)
        u, v = cols.mean(), rows.mean()
        ray = np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
        point, _ = closest_points(np.zeros(3), ray / np.linalg.norm(ray), light_positions_mm[k],
                                  -pseudo_light_vectors[k])
        centres[k] = (u, v)
        points[k] = point
        depths[k] = point[2]
    finite = np.isfinite(depths)
    distance = float(np.mean(depths[finite])) if finite.any() else float("nan")
    return DmrEstimate(distance, depths, centres, points)
