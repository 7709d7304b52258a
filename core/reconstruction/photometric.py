"""Photometric stereo: cycle assembly, ambient subtraction and the per-pixel solve.

Normals are in the head's camera frame (OpenCV) and point towards the camera (n_z < 0);
light vectors point from the surface towards each light.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from core.rig import DARK

_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}  # no 'nnan': NaN marks "no point here"


@dataclass(frozen=True)
class CycleWindow:
    """The frames of one complete light cycle: positions in the head's arrays."""

    newest: int  # position of the newest frame (the map's frame index)
    lit: tuple[int, int, int, int]  # position of the frame lit by light 0, 1, 2, 3
    dark: int


def complete_cycles(light_index: np.ndarray, frame_id: np.ndarray, cycle_length: int) -> list[CycleWindow]:
    """Every window of `cycle_length` consecutive frame ids that holds each light once and a dark frame.

    The window slides one frame at a time (the thesis' circular shift), so there is a map at
    nearly every frame; windows that span a lost frame are skipped, never shifted.
    """
    ids = np.asarray(frame_id, dtype=np.int64)
    lights = np.asarray(light_index)
    windows = []
    for end in range(cycle_length - 1, len(ids)):
        start = end - cycle_length + 1
        if ids[end] - ids[start] != cycle_length - 1:
            continue
        window = lights[start:end + 1]
        lit = [-1] * 4
        dark = -1
        for offset, light in enumerate(window):
            if light == DARK:
                dark = start + offset
            elif 0 <= light < 4:
                lit[light] = start + offset
        if dark >= 0 and min(lit) >= 0:
            windows.append(CycleWindow(end, tuple(lit), dark))
    return windows


def windows_apart(windows: list[CycleWindow], frame_id: np.ndarray, every_frames: int) -> list[CycleWindow]:
    """Of complete_cycles' windows, one each `every_frames` frame ids, by the frames' ids and not
    their positions: where the camera dropped frames, the cycles around the gap are all kept."""
    ids = np.asarray(frame_id, dtype=np.int64)
    chosen, last = [], None
    for window in windows:
        newest = int(ids[window.newest])
        if last is None or newest - last >= every_frames:
            chosen.append(window)
            last = newest
    return chosen


def distant_light_normals(images: np.ndarray, dark: np.ndarray, light_vectors: np.ndarray,
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Woodham's photometric stereo with one light vector per light for every pixel.

    images (4, H, W) lit frames, dark (H, W) the cycle's dark frame (background subtraction),
    light_vectors (4, 3) unit vectors towards the lights. M = (L^T L)^-1 L^T I (eq. 3.4);
    albedo = |M| (3.7); N = M / |M| (3.6). Returns normals (H, W, 3) and albedo (H, W).
    """
    signal = images.astype(np.float64) - dark.astype(np.float64)[None]
    pinv = np.linalg.pinv(np.asarray(light_vectors, dtype=np.float64))  # (3, 4)
    m = np.einsum("ck,khw->hwc", pinv, signal)
    albedo = np.linalg.norm(m, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = m / albedo[..., None]
    normals[albedo <= 0] = np.nan
    return normals, albedo


def gradients_from_normals(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """p = -n_x / n_z, q = -n_y / n_z (eq. 3.5): dZ/dX and dZ/dY of the surface."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return -normals[..., 0] / normals[..., 2], -normals[..., 1] / normals[..., 2]


@njit(inline="always")
def add_row(a00, a01, a02, a11, a12, a22, b0, b1, b2, r0, r1, r2, value):
    """The normal equations (A^T A, A^T b) of a least squares in three unknowns, with one more row
    (r0, r1, r2) whose value is `value` (eq. 3.4 builds them from the lights' rows)."""
    return (a00 + r0 * r0, a01 + r0 * r1, a02 + r0 * r2, a11 + r1 * r1, a12 + r1 * r2, a22 + r2 * r2,
            b0 + r0 * value, b1 + r1 * value, b2 + r2 * value)


@njit(inline="always", fastmath=True)
def solve_symmetric3(a00, a01, a02, a11, a12, a22, b0, b1, b2):
    """x = A^-1 b for a symmetric 3 x 3 A by its adjugate; NaN when A is singular."""
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    det = a00 * c00 + a01 * c01 + a02 * c02
    if abs(det) < 1e-300:
        return np.nan, np.nan, np.nan
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    inv = 1.0 / det
    return ((c00 * b0 + c01 * b1 + c02 * b2) * inv, (c01 * b0 + c11 * b1 + c12 * b2) * inv,
            (c02 * b0 + c12 * b1 + c22 * b2) * inv)


@njit(inline="always")
def store_normal(normals, albedo, i, j, m0, m1, m2):
    """Write albedo |m| and normal m / |m| at pixel (i, j); NaN when m vanishes (eqs 3.6, 3.7)."""
    rho = np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    if rho > 0.0:
        inv = np.reciprocal(rho)  # in rho's own precision (float32 in the camera-rate kernel)
        albedo[i, j] = rho
        normals[i, j, 0] = m0 * inv
        normals[i, j, 1] = m1 * inv
        normals[i, j, 2] = m2 * inv
    else:
        store_missing(normals, albedo, i, j)


@njit(inline="always")
def store_missing(normals, albedo, i, j):
    albedo[i, j] = np.nan
    normals[i, j, 0] = np.nan
    normals[i, j, 1] = np.nan
    normals[i, j, 2] = np.nan


@njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
def near_light_normals(signal, points, light_positions, light_intensity, light_axis, light_mu, saturated,
                       min_signal, normals, albedo, n_lights_used):
    """Per-pixel light vectors from each pixel's 3D point, with inverse-square falloff and LED anisotropy.

    signal (4, H, W) lit minus dark; points (H, W, 3) mm; a light whose signal is below
    `min_signal` (shadow) or whose frame is saturated is left out, so a pixel that one light
    misses is solved from the other three. Writes normals (H, W, 3), albedo (H, W) and the
    number of lights used (H, W); NaN where fewer than three lights remain.
    """
    _, height, width = signal.shape
    for i in prange(height):
        for j in range(width):
            px = points[i, j, 0]
            py = points[i, j, 1]
            pz = points[i, j, 2]
            a00 = a01 = a02 = a11 = a12 = a22 = 0.0
            b0 = b1 = b2 = 0.0
            used = 0
            if np.isfinite(pz):
                for k in range(4):
                    if saturated[k, i, j] or signal[k, i, j] < min_signal:
                        continue
                    dx = light_positions[k, 0] - px
                    dy = light_positions[k, 1] - py
                    dz = light_positions[k, 2] - pz
                    r2 = dx * dx + dy * dy + dz * dz
                    r = np.sqrt(r2)
                    lx = dx / r
                    ly = dy / r
                    lz = dz / r
                    scale = light_intensity[k] / r2
                    if light_mu[k] > 0.0:
                        c = -(lx * light_axis[k, 0] + ly * light_axis[k, 1] + lz * light_axis[k, 2])
                        scale *= c ** light_mu[k] if c > 0.0 else 0.0
                    if scale <= 0.0:
                        continue
                    # I_k / scale = rho * n . l_k: one row of the per-pixel system
                    b = signal[k, i, j] / scale
                    a00, a01, a02, a11, a12, a22, b0, b1, b2 = add_row(a00, a01, a02, a11, a12, a22, b0, b1, b2,
                                                                       lx, ly, lz, b)
                    used += 1
            n_lights_used[i, j] = used
            if used < 3:
                store_missing(normals, albedo, i, j)
                continue
            m0, m1, m2 = solve_symmetric3(a00, a01, a02, a11, a12, a22, b0, b1, b2)
            store_normal(normals, albedo, i, j, m0, m1, m2)
