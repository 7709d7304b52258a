"""Where two rays pass closest: the thesis' triangulation of a point from two rays (eqs 4.2-4.5), which
the distance from the diffused maxima and the sphere calibration's highlights both use."""

from __future__ import annotations

import numpy as np


class ParallelRays(ValueError):
    """Two rays without one pair of closest points."""


def closest_points(p1: np.ndarray, l1: np.ndarray, p2: np.ndarray, l2: np.ndarray) -> tuple[np.ndarray, float]:
    """Thesis eqs 4.2-4.5: the midpoint of the closest points of two rays, and their distance E."""
    cross = np.cross(l1, l2)
    denominator = cross @ cross
    if denominator < 1e-12:
        raise ParallelRays("the two rays are parallel")
    lp1 = p1 + (np.cross(l2, p1 - p2) @ cross) / denominator * l1  # eq. 4.2 (sign as in the thesis)
    lp2 = p2 + (np.cross(l1, p1 - p2) @ cross) / denominator * l2  # eq. 4.3
    return (lp1 + lp2) / 2, float(np.linalg.norm(lp1 - lp2))  # eqs 4.4, 4.5
