"""Normals to metric depth.

Perspective integration works on log-depth: for a pixel (u, v) with ray (x, y, 1),
x = (u - cx) / fx, y = (v - cy) / fy, and a normal n, the point Z (x, y, 1) lies on the surface
when d(log Z)/du = -n_x / (fx n.(x, y, 1)) and d(log Z)/dv = -n_y / (fy n.(x, y, 1)). Integrating
those gradients (a Poisson problem, as the thesis did orthographically) gives the shape up to a
scale, which the subject distance fixes (exp of the log-depth times the anchor).

Two solvers: `integrate_dct`, a Poisson solve on the whole rectangle with the gradients
zeroed off the mask (Neumann boundary, the fastest), and `integrate_masked`, least squares over
the mask's own pixel edges (no pull at the mask edge), solved by conjugate gradients with the
DCT solve as preconditioner in a few times the DCT's time. The DCT path flattens a surface
whose outline is not level (a torso's silhouette is deeper at the shoulders than at the flanks):
5-9 % of a simulated torso's relief, and as much of its breathing.

The masked path is robust to depth discontinuities inside the mask (a chin over the neck, an
arm against the trunk, a fold at the waist seen along grazing rays): across one, the normals on
both sides say nothing of the jump, and plain least squares spreads it over the whole surface
(on the DiLiGenT bear, real normals, the head came out lifted off its body). After the first
solve, ROBUST_ITERATIONS reweighted solves give each pixel edge the Cauchy weight
1 / (1 + (r / s)^2) of its residual r, s = ROBUST_SCALE times the median |r|: the few edges that
no surface can satisfy stop pulling. Measured (docs/reconstruction.md): the bear's mean absolute
depth error 0.483 mm -> 0.058 mm; on a simulated torso's full inspiration, the volume integrated
from true normals -1.6 % -> -0.7 % of the true depth maps'.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
import numba
from numba import njit, prange
from scipy.fft import dctn, idctn, next_fast_len

_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}  # no 'nnan': NaN marks pixels off the subject
# A normal this far from the viewing ray is not integrated: the gradient grows as 1 / cos and the
# silhouette's outermost pixels (partly background) would throw the surface around them
MAX_VIEW_ANGLE_DEG = 85.0
MIN_VIEW_COSINE = float(np.cos(np.radians(MAX_VIEW_ANGLE_DEG)))
# scipy's threaded transforms cost more than they save below about a million pixels (a 500 x 350 box:
# 2.0 ms a Poisson solve on one thread, 4.1 ms on two; docs/benchmarks.md, "Process")
THREADED_DCT_MIN_PIXELS = 1_000_000
# Reweighted solves after the first, and the Cauchy scale in median absolute edge residuals
# (module doc): more iterations or another scale from 5 to 20 changed the bear's error by < 0.01 mm.
ROBUST_ITERATIONS = 3
ROBUST_SCALE = 5.0
# The relative residual of the solves before the last reweighting: they only set the weights
# (the bear: 0.058 mm error at 1e-4, 0.059 at 3e-4, 0.077 at 1e-3; 125, 85, 68 ms)
WEIGHTS_TOLERANCE = 3e-4


def log_depth_gradients(normals: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                        ) -> tuple[np.ndarray, np.ndarray]:
    """d(log Z)/du and d(log Z)/dv per pixel (columns, rows) from unit normals (H, W, 3); NaN where
    the normal is more than MAX_VIEW_ANGLE_DEG from the viewing ray."""
    normals = np.ascontiguousarray(normals, dtype=np.float64)
    gu, gv = np.empty(normals.shape[:2]), np.empty(normals.shape[:2])
    _log_depth_gradients(normals, np.isfinite(normals[..., 2]), float(fx), float(fy), float(cx), float(cy),
                         MIN_VIEW_COSINE, gu, gv)
    return gu, gv


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _divergence(gu, gv, out):
    """Divergence of the (NaN as zero) gradient field with the DCT-II Neumann boundary handling."""
    height, width = gu.shape
    for i in prange(height):
        for j in range(width):
            total = 0.0
            if j + 1 < width:
                a, b = gu[i, j], gu[i, j + 1]
                total += 0.5 * ((a if a == a else 0.0) + (b if b == b else 0.0))
            if j > 0:
                a, b = gu[i, j - 1], gu[i, j]
                total -= 0.5 * ((a if a == a else 0.0) + (b if b == b else 0.0))
            if i + 1 < height:
                a, b = gv[i, j], gv[i + 1, j]
                total += 0.5 * ((a if a == a else 0.0) + (b if b == b else 0.0))
            if i > 0:
                a, b = gv[i - 1, j], gv[i, j]
                total -= 0.5 * ((a if a == a else 0.0) + (b if b == b else 0.0))
            out[i, j] = -total


@lru_cache(maxsize=8)
def _dct_eigenvalues(height: int, width: int) -> np.ndarray:
    wu = 2 * np.cos(np.pi * np.arange(width) / width) - 2
    wv = 2 * np.cos(np.pi * np.arange(height) / height) - 2
    denominator = (wv[:, None] + wu[None, :]).astype(np.float32)
    denominator[0, 0] = 1.0
    return -1.0 / denominator


def integrate_dct(gu: np.ndarray, gv: np.ndarray, workers: int | None = None) -> np.ndarray:
    """Least-squares surface from its gradients on the whole rectangle (DCT Poisson, Neumann boundary).

    gu, gv: derivatives along columns and rows (per pixel); NaN counts as zero. The result has
    zero mean. Single precision: the live view's fast path.
    """
    height, width = gu.shape
    div = np.empty((height, width), dtype=np.float32)
    _divergence(np.asarray(gu, dtype=np.float32), np.asarray(gv, dtype=np.float32), div)
    return _dct_poisson(div, workers)


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _log_depth_gradients(normals, mask, fx, fy, cx, cy, min_cosine, gu, gv):
    """d(log Z)/du and d(log Z)/dv (see the module doc), NaN off the mask, single precision."""
    height, width = mask.shape
    for i in prange(height):
        y = (i - cy) / fy
        for j in range(width):
            n0, n1, n2 = normals[i, j, 0], normals[i, j, 1], normals[i, j, 2]
            x = (j - cx) / fx
            den = n0 * x + n1 * y + n2
            if mask[i, j] and abs(den) >= min_cosine * np.sqrt(x * x + y * y + 1.0):
                gu[i, j] = -n0 / (fx * den)
                gv[i, j] = -n1 / (fy * den)
            else:
                gu[i, j] = np.nan
                gv[i, j] = np.nan


def log_depth_dct(normals: np.ndarray, mask: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                  workers: int | None = None) -> np.ndarray:
    """Log-depth (zero mean, NaN off the mask) from normals in one pass: the live view's fast path."""
    height, width = mask.shape
    gu = np.empty((height, width), dtype=np.float32)
    gv = np.empty((height, width), dtype=np.float32)
    _log_depth_gradients(normals, mask & np.isfinite(normals[..., 2]), fx, fy, cx, cy, MIN_VIEW_COSINE, gu, gv)
    div = np.empty((height, width), dtype=np.float32)
    _divergence(gu, gv, div)
    return np.where(mask, _dct_poisson(div, workers), np.nan)


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _edge_divergence(du, dv, wu, wv, mask, out):
    """A^T W d of the weighted least squares z[next] - z[this] = d over the pixel edges (du[i, j]:
    from (i, j) to (i, j + 1), dv[i, j]: to (i + 1, j); weight 0 where there is no equation);
    zero off the mask."""
    height, width = mask.shape
    for i in prange(height):
        for j in range(width):
            total = 0.0
            if mask[i, j]:
                total -= wu[i, j] * du[i, j] + wv[i, j] * dv[i, j]
                if j > 0:
                    total += wu[i, j - 1] * du[i, j - 1]
                if i > 0:
                    total += wv[i - 1, j] * dv[i - 1, j]
            out[i, j] = total


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _trapezoid_edges(gu, gv, mask, du, dv, wu, wv):
    """Each pixel edge inside the mask: the mean of its two pixels' gradients, weight 1; elsewhere
    difference and weight 0."""
    height, width = mask.shape
    for i in prange(height):
        for j in range(width):
            du[i, j] = dv[i, j] = wu[i, j] = wv[i, j] = 0.0
            if mask[i, j]:
                if j + 1 < width and mask[i, j + 1]:
                    du[i, j] = 0.5 * (gu[i, j] + gu[i, j + 1])
                    wu[i, j] = 1.0
                if i + 1 < height and mask[i + 1, j]:
                    dv[i, j] = 0.5 * (gv[i, j] + gv[i + 1, j])
                    wv[i, j] = 1.0


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _cauchy_weights(z, du, dv, wu, wv, scale):
    """Reweights the edges that have an equation (weight > 0) by 1 / (1 + (residual / scale)^2)."""
    height, width = z.shape
    for i in prange(height):
        for j in range(width):
            if wu[i, j] > 0.0:
                r = (z[i, j + 1] - z[i, j] - du[i, j]) / scale
                wu[i, j] = 1.0 / (1.0 + r * r)
            if wv[i, j] > 0.0:
                r = (z[i + 1, j] - z[i, j] - dv[i, j]) / scale
                wv[i, j] = 1.0 / (1.0 + r * r)


def _median_abs_residual(z: np.ndarray, du: np.ndarray, dv: np.ndarray, used_u: np.ndarray,
                         used_v: np.ndarray) -> float:
    ru = (z[:, 1:] - z[:, :-1] - du[:, :-1])[used_u[:, :-1]]
    rv = (z[1:] - z[:-1] - dv[:-1])[used_v[:-1]]
    return float(np.median(np.abs(np.concatenate([ru, rv])))) if ru.size + rv.size else 0.0


@njit(fastmath=_FAST, cache=True, nogil=True, inline="always")
def _laplacian_at(z, wu, wv, i, j):
    """(A^T W A z) at a pixel: its differences from its neighbours, each times its edge's weight
    (wu[i, j]: the edge to (i, j + 1), wv[i, j]: to (i + 1, j); 0 where there is no equation)."""
    height, width = wu.shape
    centre = z[i, j]
    total = 0.0
    if j + 1 < width:
        total += wu[i, j] * (centre - z[i, j + 1])
    if j > 0:
        total += wu[i, j - 1] * (centre - z[i, j - 1])
    if i + 1 < height:
        total += wv[i, j] * (centre - z[i + 1, j])
    if i > 0:
        total += wv[i - 1, j] * (centre - z[i - 1, j])
    return total


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _masked_laplacian(z, wu, wv, mask, out):
    """A^T W A z on the mask, zero off it."""
    height, width = mask.shape
    for i in prange(height):
        for j in range(width):
            out[i, j] = _laplacian_at(z, wu, wv, i, j) if mask[i, j] else 0.0


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _masked_dot(a, b, mask):
    height, width = mask.shape
    rows = np.zeros(height)
    for i in prange(height):
        row = 0.0
        for j in range(width):
            if mask[i, j]:
                row += a[i, j] * b[i, j]
        rows[i] = row
    return rows.sum()


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _cg_direction(direction, product, preconditioned, mask, wu, wv, beta):
    """The new search direction d = M r + beta d and its image A d = A M r + beta A d, in place on
    the mask (zero off it); returns d . A d."""
    height, width = mask.shape
    rows = np.zeros(height)
    for i in prange(height):
        row = 0.0
        for j in range(width):
            if mask[i, j]:
                d = preconditioned[i, j] + beta * direction[i, j]
                a_d = _laplacian_at(preconditioned, wu, wv, i, j) + beta * product[i, j]
                direction[i, j] = d
                product[i, j] = a_d
                row += d * a_d
            else:
                direction[i, j] = 0.0
                product[i, j] = 0.0
        rows[i] = row
    return rows.sum()


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _cg_step(z, residual, direction, product, mask, step):
    """z += step d; r -= step A d (in place); returns r . r over the mask."""
    height, width = mask.shape
    rows = np.zeros(height)
    for i in prange(height):
        row = 0.0
        for j in range(width):
            if mask[i, j]:
                z[i, j] += step * direction[i, j]
                r = residual[i, j] - step * product[i, j]
                residual[i, j] = r
                row += r * r
        rows[i] = row
    return rows.sum()


def _dct_poisson(image: np.ndarray, workers: int | None) -> np.ndarray:
    """The rectangle's Neumann Poisson solve of a right-hand side (the DCT path), single precision.
    workers None: one thread below THREADED_DCT_MIN_PIXELS, else as many as the numba kernels of
    this thread use (numba.set_num_threads is per thread), so a thread given one core keeps to it."""
    if workers is None:
        workers = numba.get_num_threads() if image.size >= THREADED_DCT_MIN_PIXELS else 1
    transformed = dctn(image.astype(np.float32, copy=False), type=2, norm="ortho", workers=workers)
    transformed *= _dct_eigenvalues(*image.shape)
    transformed[0, 0] = 0.0
    return idctn(transformed, type=2, norm="ortho", workers=workers)


def _fast_box(mask: np.ndarray) -> tuple[slice, slice]:
    """The mask's bounding box, grown to sizes the DCT transforms fast (small prime factors)."""
    box = []
    for axis in (1, 0):
        used = np.nonzero(mask.any(axis=axis))[0]
        size = min(next_fast_len(int(used[-1] - used[0] + 1), real=True), mask.shape[1 - axis])
        start = min(int(used[0]), mask.shape[1 - axis] - size)
        box.append(slice(start, start + size))
    return box[0], box[1]


def integrate_masked(gu: np.ndarray, gv: np.ndarray, mask: np.ndarray, tolerance: float = 1e-4,
                     max_iterations: int = 200, workers: int | None = None,
                     robust_iterations: int = ROBUST_ITERATIONS, start: np.ndarray | None = None) -> np.ndarray:
    """Least-squares surface over the mask's own pixel edges; NaN off the mask; zero mean over it.

    Each pixel edge inside the mask gives one equation z[next] - z[this] = mean of their gradients;
    no equation crosses the mask's edge, so the surface is not pulled towards the background as
    the DCT path's is (which flattens a torso's relief by 5-9 %, docs/reconstruction.md). The
    normal equations are solved by conjugate gradients preconditioned with the DCT Poisson solve
    of the mask's bounding box, started from the DCT surface; on a torso 5-10 iterations bring
    the residual to `tolerance` times the right-hand side. Then `robust_iterations` reweighted
    solves, each started from the last (module doc: depth discontinuities); 0 gives the plain
    least-squares surface.

    `start`, a log-depth near the answer (a cycle's previous iteration, the stream's previous
    cycle), replaces the DCT surface where it is finite: the same solution, in fewer iterations,
    and none at all when it already solves these gradients.
    """
    full_mask = mask & np.isfinite(gu) & np.isfinite(gv)
    out = np.full(full_mask.shape, np.nan)
    if full_mask.sum() < 2:
        return out
    box = _fast_box(full_mask)
    mask = np.ascontiguousarray(full_mask[box])
    gu = np.ascontiguousarray(np.where(mask, gu[box], 0.0))
    gv = np.ascontiguousarray(np.where(mask, gv[box], 0.0))
    du, dv, wu, wv = (np.empty(mask.shape) for _ in range(4))
    _trapezoid_edges(gu, gv, mask, du, dv, wu, wv)
    used_u, used_v = wu > 0, wv > 0
    z = _starting_surface(gu, gv, mask, None if start is None else start[box], workers)
    for robust in range(robust_iterations + 1):
        if robust:
            scale = ROBUST_SCALE * _median_abs_residual(z, du, dv, used_u, used_v)
            if not scale > 0:
                break
            _cauchy_weights(z, du, dv, wu, wv, scale)
        last = robust == robust_iterations
        # a solve that only sets the next weights need not be exact
        _conjugate_gradients(z, du, dv, wu, wv, mask, tolerance if last else max(tolerance, WEIGHTS_TOLERANCE),
                             max_iterations, workers)
    out[box] = np.where(mask, z - z[mask].mean(), np.nan)
    return out


def _starting_surface(gu: np.ndarray, gv: np.ndarray, mask: np.ndarray, start: np.ndarray | None,
                      workers: int) -> np.ndarray:
    """The first guess on the mask (zero off it): `start` where it is finite, the DCT surface
    elsewhere, lifted to meet `start` on average."""
    known = mask if start is None else mask & np.isfinite(start)
    if start is not None and known.all(where=mask):
        return np.where(mask, start, 0.0)
    z = integrate_dct(gu, gv, workers).astype(np.float64)
    if start is not None and known.any():
        z = np.where(known, start, z + np.mean(start[known] - z[known]))
    return np.where(mask, z, 0.0)


def _conjugate_gradients(z: np.ndarray, du: np.ndarray, dv: np.ndarray, wu: np.ndarray, wv: np.ndarray,
                         mask: np.ndarray, tolerance: float, max_iterations: int, workers: int) -> None:
    """Solves A^T W A z = A^T W d on the mask in place, from z, preconditioned with the DCT solve."""
    rhs = np.empty(mask.shape)
    _edge_divergence(du, dv, wu, wv, mask, rhs)
    rhs_norm = np.sqrt(_masked_dot(rhs, rhs, mask))
    residual = np.empty(mask.shape)
    _masked_laplacian(z, wu, wv, mask, residual)
    residual = np.where(mask, rhs - residual, 0.0)
    residual_norm = np.sqrt(_masked_dot(residual, residual, mask))
    direction, product = np.zeros(mask.shape), np.zeros(mask.shape)
    rho = 1.0
    for _ in range(max_iterations):
        if rhs_norm == 0.0 or residual_norm <= tolerance * rhs_norm:
            break
        preconditioned = _dct_poisson(residual, workers)
        rho, previous = _masked_dot(residual, preconditioned, mask), rho
        if rho <= 0.0:
            break
        curvature = _cg_direction(direction, product, preconditioned, mask, wu, wv, rho / previous)
        residual_norm = np.sqrt(_cg_step(z, residual, direction, product, mask, rho / curvature))


def depth_from_normals(normals: np.ndarray, mask: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                       anchor_depth_mm: float, method: str = "masked") -> np.ndarray:
    """Metric depth (mm) from normals: perspective log-depth integration, scaled so that the
    median depth over the mask is `anchor_depth_mm` (the estimated subject distance)."""
    gu, gv = log_depth_gradients(normals, fx, fy, cx, cy)
    mask = mask & np.isfinite(gu) & np.isfinite(gv)
    if method == "masked":
        log_depth = integrate_masked(gu, gv, mask)
    elif method == "dct":
        log_depth = np.where(mask, integrate_dct(np.where(mask, gu, 0.0), np.where(mask, gv, 0.0)), np.nan)
    else:
        raise ValueError(f"unknown integration method {method!r}: masked or dct")
    relative = np.exp(log_depth - np.nanmedian(log_depth))
    return anchor_depth_mm * relative
