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
from numba import njit, prange
from scipy import ndimage
from scipy.optimize import minimize, minimize_scalar

from core.reconstruction.binning import bin_all, bin_mean
from core.reconstruction.photometric import add_row, solve_symmetric3
from core.reconstruction.rays import ParallelRays, closest_points

DMR_THRESHOLD = 0.9
MIN_FIT_PIXELS = 100  # the photometric distance is not fitted on fewer pixels
INTENSITY_TOLERANCE = 0.05  # how far the joint fit may move a light's relative intensity (log scale)


@dataclass(frozen=True)
class DmrEstimate:
    distance_mm: float  # mean depth over the lights that gave one
    depths_mm: np.ndarray  # (4,) NaN where a light had no region
    centres_px: np.ndarray  # (4, 2) (u, v) of each region's centre
    points_mm: np.ndarray  # (4, 3) the triangulated surface points

    @classmethod
    def none(cls) -> DmrEstimate:
        """No region for any light (no subject)."""
        return cls(float("nan"), np.full(4, np.nan), np.full((4, 2), np.nan), np.full((4, 3), np.nan))


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
        try:
            point, _ = closest_points(np.zeros(3), ray / np.linalg.norm(ray), light_positions_mm[k],
                                      -pseudo_light_vectors[k])
        except ParallelRays:  # a region seen along its light's own axis places nothing
            continue
        centres[k] = (u, v)
        points[k] = point
        depths[k] = point[2]
    finite = np.isfinite(depths)
    distance = float(np.mean(depths[finite])) if finite.any() else float("nan")
    return DmrEstimate(distance, depths, centres, points)


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def _chi_square(signal, weight, points, scale, light_positions, light_intensity, light_axis, light_mu):
    n = signal.shape[1]
    partial = np.zeros(n)
    for p in prange(n):
        rows = np.empty((4, 3))  # stays on the stack: numba removes small fixed allocations
        b = np.empty(4)
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        c0 = c1 = c2 = 0.0
        for k in range(4):
            dx = light_positions[k, 0] - points[p, 0] * scale
            dy = light_positions[k, 1] - points[p, 1] * scale
            dz = light_positions[k, 2] - points[p, 2] * scale
            r2 = dx * dx + dy * dy + dz * dz
            f = light_intensity[k] * weight[k, p] / (r2 * np.sqrt(r2))
            if light_mu[k] > 0.0:
                c = -(dx * light_axis[k, 0] + dy * light_axis[k, 1] + dz * light_axis[k, 2]) / np.sqrt(r2)
                f *= c ** light_mu[k] if c > 0.0 else 0.0
            x, y, z = dx * f, dy * f, dz * f
            rows[k, 0] = x
            rows[k, 1] = y
            rows[k, 2] = z
            b[k] = signal[k, p] * weight[k, p]
            a00, a01, a02, a11, a12, a22, c0, c1, c2 = add_row(a00, a01, a02, a11, a12, a22, c0, c1, c2, x, y, z, b[k])
        m0, m1, m2 = solve_symmetric3(a00, a01, a02, a11, a12, a22, c0, c1, c2)
        total = 0.0
        for k in range(4):
            r = b[k] - (rows[k, 0] * m0 + rows[k, 1] * m1 + rows[k, 2] * m2)
            total += r * r
        partial[p] = total
    return partial.sum()


class PhotometricDistance:
    """The distance at which the near-light model explains all four lights best, for one cycle.

    Beyond the thesis: the diffused maxima regions tell where the surface faces a light, which on a
    curved subject is biased by its shape; the photometric residual of the near-light model at
    every pixel is not. Pixels are chosen and weighted once per cycle, on smoothed images:
    choosing on the noisy values would keep pixels whose noise happens to be positive, and wrong
    weights pull the minimum. The noise of lit minus dark is the shot noise of both frames plus
    their read noise.
    """

    def __init__(self, signal: np.ndarray, mask: np.ndarray, light_positions_mm: np.ndarray,
                 light_intensity: np.ndarray, dark: np.ndarray | None = None, max_pixels: int = 250000,
                 dn_per_electron: float = 4095.0 / 18000.0, read_noise_dn: float = 2.7, binning: int = 1,
                 light_axis: np.ndarray | None = None, light_mu: np.ndarray | None = None) -> None:
        # binning: the fit on factor x factor bins (each bin's mean signal at its mean point), so
        # that every pixel's light counts within max_pixels on a wide head. The noise model below,
        # applied to a bin's mean, overstates its variance by factor^2 in every bin alike, which
        # leaves the minimum where it is.
        self.binning = binning
        self._binned_rays: tuple[np.ndarray, np.ndarray] | None = None  # (rays given, their bins)
        if binning > 1:
            signal, mask = bin_mean(signal, binning), bin_all(mask, binning)
            dark = bin_mean(dark, binning) if dark is not None else None
        inner = ndimage.binary_erosion(mask, iterations=3)
        smooth = np.stack([ndimage.gaussian_filter(channel, 2.0) for channel in signal])
        weakest = np.min(smooth, axis=0)
        lit = weakest > 0.1 * np.percentile(weakest[inner], 95) if inner.any() else inner
        rows, cols = np.nonzero(inner & lit)
        step = max(1, len(rows) // max_pixels)
        self.rows, self.cols = rows[::step], cols[::step]
        dark_level = ndimage.gaussian_filter(dark, 2.0)[self.rows, self.cols] if dark is not None else 0.0
        variance = (dn_per_electron * (np.maximum(smooth[:, self.rows, self.cols], 0.0) + 2.0 * dark_level)
                    + 2.0 * read_noise_dn**2)
        self.weight = np.ascontiguousarray(1.0 / np.sqrt(variance))
        self.signal = np.ascontiguousarray(signal[:, self.rows, self.cols], np.float64)
        self.lights = np.ascontiguousarray(light_positions_mm, np.float64)
        self.intensity = np.ascontiguousarray(light_intensity, np.float64)
        self.axis = np.ascontiguousarray(np.tile([0.0, 0.0, 1.0], (4, 1)) if light_axis is None else light_axis,
                                         np.float64)
        self.mu = np.ascontiguousarray(np.zeros(4) if light_mu is None else light_mu, np.float64)

    def _problem(self, rays: np.ndarray, relative_depth: np.ndarray):
        """(points at unit scale, signal, weight) of the chosen pixels where the depth is known; None
        when fewer than MIN_FIT_PIXELS. rays (H, W, 3) and relative_depth (H, W) at the head's full size."""
        if self.binning > 1:
            if self._binned_rays is None or self._binned_rays[0] is not rays:
                # a bin's mean ray is exactly the ray through its centre (rays are linear in u, v)
                self._binned_rays = (rays, np.moveaxis(bin_mean(np.moveaxis(rays, -1, 0), self.binning), 0, -1))
            rays = self._binned_rays[1]
            relative_depth = bin_mean(relative_depth, self.binning)  # NaN where any pixel has no depth
        relative = relative_depth[self.rows, self.cols]
        keep = np.isfinite(relative)
        if keep.sum() < MIN_FIT_PIXELS:
            return None
        return (np.ascontiguousarray(rays[self.rows[keep], self.cols[keep]] * relative[keep, None]),
                np.ascontiguousarray(self.signal[:, keep]), np.ascontiguousarray(self.weight[:, keep]))

    def scale(self, rays: np.ndarray, relative_depth: np.ndarray, scale_range: tuple[float, float],
              grid_points: int = 9) -> float:
        """The scale s of `relative_depth` (depth = s * relative) within scale_range; NaN when too few pixels."""
        problem = self._problem(rays, relative_depth)
        if problem is None:
            return float("nan")
        base, signal, weight = problem

        def cost(scale: float) -> float:
            return _chi_square(signal, weight, base, scale, self.lights, self.intensity, self.axis, self.mu)

        lo, hi = scale_range
        grid = np.linspace(lo, hi, grid_points)
        values = [cost(g) for g in grid]
        k = int(np.argmin(values))
        bracket = (grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)])
        return float(minimize_scalar(cost, bounds=bracket, method="bounded", options={"xatol": 0.05}).x)

    def scale_and_intensity(self, rays: np.ndarray, relative_depth: np.ndarray, scale_mm: float,
                            tolerance: float = INTENSITY_TOLERANCE) -> tuple[float, np.ndarray]:
        """The scale and the lights' relative intensities fitted together, from `scale_mm`: the
        factors (4,) that multiply the intensities given (the first light's is 1, the others within
        +-tolerance). NaN and ones when too few pixels.

        Why: at 2 m the four lights are nearly equally far from every point, so the inverse-square
        falloff tells the distance through small differences between the lights, and an intensity
        off by 0.1 % moves the distance by about 10 mm (simulated torso, 2200 mm). With the
        intensities free, the distance comes from how the lights' directions and falloff change
        across the subject, which no intensity error can imitate."""
        problem = self._problem(rays, relative_depth)
        if problem is None or not np.isfinite(scale_mm):
            return float("nan"), np.ones(4)
        base, signal, weight = problem

        def factors(x: np.ndarray) -> np.ndarray:
            return np.exp(np.clip(np.r_[0.0, x[1:]], -tolerance, tolerance))

        def cost(x: np.ndarray) -> float:
            return _chi_square(signal, weight, base, x[0], self.lights, self.intensity * factors(x), self.axis,
                               self.mu)

        fit = minimize(cost, np.r_[scale_mm, 0.0, 0.0, 0.0], method="Nelder-Mead",
                       options={"xatol": 0.05, "fatol": 1e-6, "maxiter": 1500})
        return float(fit.x[0]), factors(fit.x)
