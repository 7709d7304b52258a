"""Normals to metric depth.

Perspective integration works on log-depth: for a pixel (u, v) with ray (x, y, 1),
x = (u - cx) / fx, y = (v - cy) / fy, and a normal n, the point Z (x, y, 1) lies on the surface
when d(log Z)/du = -n_x / (fx n.(x, y, 1)) and d(log Z)/dv = -n_y / (fy n.(x, y, 1)). Integrating
those gradients (a Poisson problem, as the thesis did orthographically) gives the shape up to a
scale, which the subject distance fixes (exp of the log-depth times the anchor).

Two solvers: `integrate_dct`, a Poisson solve on the whole rectangle with the gradients
zeroed off the mask (Neumann boundary, fast, for the live view), and `integrate_masked`,
least squares over the mask's own pixel edges (accurate, no artefacts at the mask edge).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numba import njit, prange
from scipy import sparse
from scipy.fft import dctn, idctn
from scipy.sparse.linalg import spsolve

_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}  # no 'nnan': NaN marks pixels off the subject


def log_depth_gradients(normals: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                        ) -> tuple[np.ndarray, np.ndarray]:
    """d(log Z)/du and d(log Z)/dv per pixel (columns, rows) from unit normals (H, W, 3)."""
    height, width = normals.shape[:2]
    x = ((np.arange(width) - cx) / fx)[None, :]
    y = ((np.arange(height) - cy) / fy)[:, None]
    denominator = normals[..., 0] * x + normals[..., 1] * y + normals[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        return -normals[..., 0] / (fx * denominator), -normals[..., 1] / (fy * denominator)


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


def integrate_dct(gu: np.ndarray, gv: np.ndarray, workers: int = -1) -> np.ndarray:
    """Least-squares surface from its gradients on the whole rectangle (DCT Poisson, Neumann boundary).

    gu, gv: derivatives along columns and rows (per pixel); NaN counts as zero. The result has
    zero mean. Single precision: the live view's fast path.
    """
    height, width = gu.shape
    div = np.empty((height, width), dtype=np.float32)
    _divergence(np.asarray(gu, dtype=np.float32), np.asarray(gv, dtype=np.float32), div)
    transformed = dctn(div, type=2, norm="ortho", workers=workers)
    transformed *= _dct_eigenvalues(height, width)
    transformed[0, 0] = 0.0
    return idctn(transformed, type=2, norm="ortho", workers=workers)


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def _log_depth_gradients(normals, mask, fx, fy, cx, cy, gu, gv):
    """d(log Z)/du and d(log Z)/dv (see the module doc), NaN off the mask, single precision."""
    height, width = mask.shape
    for i in prange(height):
        y = (i - cy) / fy
        for j in range(width):
            n0, n1, n2 = normals[i, j, 0], normals[i, j, 1], normals[i, j, 2]
            den = n0 * (j - cx) / fx + n1 * y + n2
            if mask[i, j] and den != 0.0:
                gu[i, j] = -n0 / (fx * den)
                gv[i, j] = -n1 / (fy * den)
            else:
                gu[i, j] = np.nan
                gv[i, j] = np.nan


def log_depth_dct(normals: np.ndarray, mask: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                  workers: int = -1) -> np.ndarray:
    """Log-depth (zero mean, NaN off the mask) from normals in one pass: the live view's fast path."""
    height, width = mask.shape
    gu = np.empty((height, width), dtype=np.float32)
    gv = np.empty((height, width), dtype=np.float32)
    _log_depth_gradients(normals, mask & np.isfinite(normals[..., 2]), fx, fy, cx, cy, gu, gv)
    div = np.empty((height, width), dtype=np.float32)
    _divergence(gu, gv, div)
    transformed = dctn(div, type=2, norm="ortho", workers=workers)
    transformed *= _dct_eigenvalues(height, width)
    transformed[0, 0] = 0.0
    out = idctn(transformed, type=2, norm="ortho", workers=workers)
    return np.where(mask, out, np.nan)


def _edge_system(mask: np.ndarray, gu: np.ndarray, gv: np.ndarray):
    index = -np.ones(mask.shape, dtype=np.int64)
    index[mask] = np.arange(int(mask.sum()))
    rows, cols, vals, rhs = [], [], [], []
    n_eq = 0
    for axis, g in ((1, gu), (0, gv)):
        a = mask[:, :-1] & mask[:, 1:] if axis == 1 else mask[:-1, :] & mask[1:, :]
        if axis == 1:
            i0, i1 = index[:, :-1][a], index[:, 1:][a]
            target = ((g[:, :-1] + g[:, 1:]) / 2)[a]
        else:
            i0, i1 = index[:-1, :][a], index[1:, :][a]
            target = ((g[:-1, :] + g[1:, :]) / 2)[a]
        k = np.arange(n_eq, n_eq + len(i0))
        rows += [k, k]
        cols += [i1, i0]
        vals += [np.ones(len(k)), -np.ones(len(k))]
        rhs.append(target)
        n_eq += len(k)
    a_matrix = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                 shape=(n_eq, int(mask.sum())))
    return a_matrix, np.concatenate(rhs), index


def integrate_masked(gu: np.ndarray, gv: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Least-squares surface over the mask's own edges; NaN off the mask; zero mean per connected piece.

    Each pixel edge inside the mask gives one equation z[next] - z[this] = mean of their gradients.
    """
    mask = mask & np.isfinite(gu) & np.isfinite(gv)
    out = np.full(mask.shape, np.nan)
    if mask.sum() < 2:
        return out
    a_matrix, rhs, _ = _edge_system(mask, gu, gv)
    normal = (a_matrix.T @ a_matrix).tocsr()
    # Fix the null space (one constant per connected piece) with a tiny pull towards zero.
    normal = normal + sparse.identity(normal.shape[0], format="csr") * 1e-9
    z = spsolve(normal.tocsc(), a_matrix.T @ rhs)
    out[mask] = z - z.mean()
    return out


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
