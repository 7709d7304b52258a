"""Whether the two heads' height maps agree on where the trunk's sides lie, along its height.

The heads face each other on one axis. The trunk's occluding contour (its side, where the surface
turns parallel to the axis) is about the same curve in both views, so at every height its depth
from the front head and from the back head add up to the baseline. The maps' scale is set from the
two heads' widths (core/pipeline/distance_pass.py, geometric_distances), which fixes that sum on
average; what is left is its change along the height. Maps bent by normals the light model does not
explain (a sheen on the skin: docs/history/reconstruction-log.md, "Glossy skin") tilt the sum by tens of mm per
100 mm of height, and their volume is not the breathing's (docs/history/volume-log.md, "Skin the light model
does not describe, and bent maps").
"""

from __future__ import annotations

import numpy as np

from core.rig import Head
from core.volume.maps import contour_rows_mm

# How far the two heads' side contours may part (mm per mm of height) before the maps are bent (docs/constants.md)
MAX_SIDES_TILT = 0.25
SIDES_GRID_MM = 10.0
MIN_SIDES_SPAN_MM = 150.0  # the heights both heads' sides must share for a tilt: half a child's trunk


def side_profile_mm(depth_mm: np.ndarray, valid: np.ndarray, silhouette: np.ndarray, head: Head,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(height, depth) in mm of the trunk's sides along its height: each trunk row whose both sides
    give a contour (core/volume/maps.py, contour_rows_mm), at their mean depth, its height
    (v - cy) Z / fy in the head's camera frame (y down)."""
    rows, sides = contour_rows_mm(depth_mm, valid, silhouette, head)
    both = np.isfinite(sides).all(axis=1)
    depth = sides[both].mean(axis=1)
    return (rows[both] - head.cy) * depth / head.fy, depth


def sides_tilt(front: tuple[np.ndarray, np.ndarray], back: tuple[np.ndarray, np.ndarray]) -> float:
    """The slope (mm per mm of height) of the front and back side depths' sum over the heights both
    profiles (side_profile_mm) cover; NaN where they share less than MIN_SIDES_SPAN_MM."""
    (h_front, z_front), (h_back, z_back) = front, back
    if len(h_front) < 2 or len(h_back) < 2:
        return float("nan")
    low, high = max(h_front.min(), h_back.min()), min(h_front.max(), h_back.max())
    if high - low < MIN_SIDES_SPAN_MM:
        return float("nan")
    grid = np.arange(low, high, SIDES_GRID_MM)
    order_front, order_back = np.argsort(h_front), np.argsort(h_back)
    total = (np.interp(grid, h_front[order_front], z_front[order_front])
             + np.interp(grid, h_back[order_back], z_back[order_back]))
    return float(np.polyfit(grid, total, 1)[0])


def paired_tilts(front: tuple[np.ndarray, list], back: tuple[np.ndarray, list]) -> np.ndarray:
    """sides_tilt of each front profile with the back profile nearest it in time; front and back are
    (timestamp_ns, profiles)."""
    (t_front, p_front), (t_back, p_back) = front, back
    if not len(t_front) or not len(t_back):
        return np.zeros(0)
    t_back = np.asarray(t_back, dtype=float)
    nearest = [int(np.argmin(np.abs(t_back - float(t)))) for t in t_front]
    return np.array([sides_tilt(p, p_back[j]) for p, j in zip(p_front, nearest)])
