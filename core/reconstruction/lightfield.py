"""The near-light field on a coarse grid: camera-rate normal maps with per-pixel light vectors.

The lights seen from the subject change slowly across the image (their directions by a few
degrees over the torso), so the per-pixel model matrix A (rows E_k A_k l_k / r_k^2) and its
pseudo-inverse are computed at grid nodes `step` pixels apart from the current depth map and
interpolated bilinearly per pixel: near-light photometric stereo then costs a 3 x 4 product per
pixel, like the distant-light kind. Pixels where a light is shadowed or saturated are solved
exactly from the three others with the interpolated rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from core.reconstruction.photometric import add_row, solve_symmetric3, store_missing, store_normal
from core.rig import Head


@dataclass(frozen=True)
class LightField:
    step: int
    rows: np.ndarray  # (gy, gx, 4, 3) float32: E_k A_k l_k / r_k^2 at the grid nodes
    pinv: np.ndarray  # (gy, gx, 3, 4) float32: (A^T A)^-1 A^T


def default_step(head: Head, spacing_mm: float = 5.0, distance_mm: float = 2000.0) -> int:
    """Grid step (pixels) that puts nodes about `spacing_mm` apart on a subject at `distance_mm`."""
    return max(1, int(round(spacing_mm * head.fx / distance_mm)))


def light_field(head: Head, depth_mm: np.ndarray, step: int | None = None,
                fallback_depth_mm: float = 2000.0) -> LightField:
    """The field for a depth map (H, W); NaN depth takes the median of the rest (or the fallback)."""
    height, width = head.shape
    step = default_step(head) if step is None else step
    gy = np.arange(0, height + step, step)  # nodes at exact multiples of the step, the last past the edge
    gx = np.arange(0, width + step, step)
    gy, gx = gy[: int(np.ceil((height - 1) / step)) + 2], gx[: int(np.ceil((width - 1) / step)) + 2]
    finite = np.isfinite(depth_mm)
    fill = float(np.median(depth_mm[finite])) if finite.any() else fallback_depth_mm
    z = np.where(finite, depth_mm, fill)[np.ix_(gy.clip(max=height - 1), gx.clip(max=width - 1))]
    u = (gx - head.cx) / head.fx
    v = (gy - head.cy) / head.fy
    points = np.stack(np.broadcast_arrays(u[None, :] * z, v[:, None] * z, z), -1)  # (gy, gx, 3)
    d = head.light_positions_mm[None, None] - points[:, :, None, :]
    r2 = np.sum(d * d, axis=-1)
    l = d / np.sqrt(r2)[..., None]
    gain = head.light_intensity[None, None] / r2
    if head.light_axis is not None and head.light_mu is not None:
        c = np.clip(-np.sum(l * head.light_axis[None, None], axis=-1), 0, None)
        gain = gain * c ** head.light_mu[None, None]
    rows = l * gain[..., None]
    normal_matrix = np.einsum("yxki,yxkj->yxij", rows, rows)
    pinv = np.linalg.inv(normal_matrix) @ np.swapaxes(rows, -1, -2)
    return LightField(step, rows.astype(np.float32), pinv.astype(np.float32))


@njit(inline="always")
def _solve_remaining(lit, i, j, s0, s1, s2, s3, line, ix, tx, min_signal, full_scale, normals, albedo):
    """A pixel where a light is shadowed or saturated: solved from the lights that remain (three or
    more), with the rows interpolated at the pixel; missing otherwise."""
    ux = 1 - tx
    a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    b0 = b1 = b2 = 0.0
    used = 0
    for k in range(4):
        sk = s0 if k == 0 else (s1 if k == 1 else (s2 if k == 2 else s3))
        if sk < min_signal or lit[k, i, j] >= full_scale:
            continue
        r0 = ux * line[ix, 12 + 3 * k] + tx * line[ix + 1, 12 + 3 * k]
        r1 = ux * line[ix, 13 + 3 * k] + tx * line[ix + 1, 13 + 3 * k]
        r2 = ux * line[ix, 14 + 3 * k] + tx * line[ix + 1, 14 + 3 * k]
        a00, a01, a02, a11, a12, a22, b0, b1, b2 = add_row(a00, a01, a02, a11, a12, a22, b0, b1, b2, r0, r1, r2, sk)
        used += 1
    if used < 3:
        store_missing(normals, albedo, i, j)
        return
    m0, m1, m2 = solve_symmetric3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
    store_normal(normals, albedo, i, j, m0, m1, m2)


@njit(parallel=True, fastmath=True, cache=True, nogil=True)
def _normals_from_field(lit, dark, rows, pinv, step, min_signal, full_scale, normals, albedo):
    height, width = dark.shape
    gy, gx = pinv.shape[0], pinv.shape[1]
    inv_step = np.float32(1.0 / step)
    for i in prange(height):
        fy = i * inv_step
        iy = min(int(fy), gy - 2)
        ty = np.float32(fy - iy)
        # This row's grid, interpolated in y once: 12 pseudo-inverse and 12 row entries per node.
        line = np.empty((gx, 24), dtype=np.float32)
        for x in range(gx):
            for c in range(3):
                for k in range(4):
                    line[x, 4 * c + k] = (1 - ty) * pinv[iy, x, c, k] + ty * pinv[iy + 1, x, c, k]
                    line[x, 12 + 3 * k + c] = (1 - ty) * rows[iy, x, k, c] + ty * rows[iy + 1, x, k, c]
        # One grid cell at a time: the pseudo-inverse at the cell's left node (p) and its change
        # per pixel (d), held in scalars (numba keeps them in registers; arrays of 12 were 10 %
        # slower, and finding the cell per pixel 30 %).
        for ix in range(gx - 1):
            j0 = ix * step
            if j0 >= width:
                break
            p00, p01, p02, p03 = line[ix, 0], line[ix, 1], line[ix, 2], line[ix, 3]
            p10, p11, p12, p13 = line[ix, 4], line[ix, 5], line[ix, 6], line[ix, 7]
            p20, p21, p22, p23 = line[ix, 8], line[ix, 9], line[ix, 10], line[ix, 11]
            d00, d01 = (line[ix + 1, 0] - p00) * inv_step, (line[ix + 1, 1] - p01) * inv_step
            d02, d03 = (line[ix + 1, 2] - p02) * inv_step, (line[ix + 1, 3] - p03) * inv_step
            d10, d11 = (line[ix + 1, 4] - p10) * inv_step, (line[ix + 1, 5] - p11) * inv_step
            d12, d13 = (line[ix + 1, 6] - p12) * inv_step, (line[ix + 1, 7] - p13) * inv_step
            d20, d21 = (line[ix + 1, 8] - p20) * inv_step, (line[ix + 1, 9] - p21) * inv_step
            d22, d23 = (line[ix + 1, 10] - p22) * inv_step, (line[ix + 1, 11] - p23) * inv_step
            for j in range(j0, min(j0 + step, width)):
                t = np.float32(j - j0)
                d = np.float32(dark[i, j])
                raw0, raw1, raw2, raw3 = lit[0, i, j], lit[1, i, j], lit[2, i, j], lit[3, i, j]
                s0 = np.float32(raw0) - d
                s1 = np.float32(raw1) - d
                s2 = np.float32(raw2) - d
                s3 = np.float32(raw3) - d
                if (min(min(s0, s1), min(s2, s3)) < min_signal
                        or max(max(raw0, raw1), max(raw2, raw3)) >= full_scale):
                    _solve_remaining(lit, i, j, s0, s1, s2, s3, line, ix, t * inv_step, min_signal, full_scale,
                                     normals, albedo)
                    continue
                # eq. 3.4 with the pixel's own light field: M = pinv(A) I
                m0 = s0 * (p00 + t * d00) + s1 * (p01 + t * d01) + s2 * (p02 + t * d02) + s3 * (p03 + t * d03)
                m1 = s0 * (p10 + t * d10) + s1 * (p11 + t * d11) + s2 * (p12 + t * d12) + s3 * (p13 + t * d13)
                m2 = s0 * (p20 + t * d20) + s1 * (p21 + t * d21) + s2 * (p22 + t * d22) + s3 * (p23 + t * d23)
                store_normal(normals, albedo, i, j, m0, m1, m2)


def normals_from_field(lit: np.ndarray, dark: np.ndarray, field: LightField, min_signal: float, full_scale: float,
                       normals: np.ndarray | None = None, albedo: np.ndarray | None = None,
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Normals (H, W, 3) float32 and albedo from raw lit frames (4, H, W) and the dark frame (H, W)."""
    shape = dark.shape
    if normals is None:
        normals = np.empty(shape + (3,), dtype=np.float32)
    if albedo is None:
        albedo = np.empty(shape, dtype=np.float32)
    _normals_from_field(lit, dark, field.rows, field.pinv, field.step, np.float32(min_signal),
                        np.float32(full_scale), normals, albedo)
    return normals, albedo
