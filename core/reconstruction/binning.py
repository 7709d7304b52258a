"""Pixel binning: a head's frames averaged over factor x factor blocks, and the head whose
intrinsics describe the binned image.

The stream of maps behind the volume curve is reconstructed at about WORKING_WIDTH_PX wide, in the
live view and in `photopft process` alike (what the operator sees is what the report says): a
volume curve needs no more (`photopft bench volume` measures the volume at 350 x 256), the metric
volume's slope then does not depend on the camera's resolution, and a full-resolution map costs
about 1.7 s of CPU on the project's 2-core machine against about 0.1 s binned 4 x 4. Maps asked for
by frame (`process --maps-at`, the report's height maps) keep every pixel.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numba import njit, prange

from core.rig import Head

WORKING_WIDTH_PX = 350


def working_binning(head: Head, target_width_px: int = WORKING_WIDTH_PX) -> int:
    """The whole factor that brings the head's width nearest to the target without going under
    half of it; 1 for a head already that narrow."""
    return max(1, int(np.floor(head.width / target_width_px + 0.5)))


def binned_head(head: Head, factor: int) -> Head:
    """The head seen through factor x factor bins: focal lengths and pixels scaled, the principal
    point moved to the binned pixel grid (binned pixel j covers pixels factor*j .. factor*j +
    factor - 1, its centre at factor*j + (factor - 1)/2), the right and bottom remainders dropped.
    Lights, distortion (in normalised coordinates) and bit depth (bins are averages) unchanged."""
    if factor < 1:
        raise ValueError(f"binning factor must be a positive whole number, got {factor}")
    if factor == 1:
        return head
    offset = (factor - 1) / 2.0
    return replace(head, width=head.width // factor, height=head.height // factor, fx=head.fx / factor,
                   fy=head.fy / factor, cx=(head.cx - offset) / factor, cy=(head.cy - offset) / factor,
                   pixel_size_mm=head.pixel_size_mm * factor)


def _blocks(array: np.ndarray, factor: int) -> np.ndarray:
    """The last two axes cut into factor x factor blocks (..., h, factor, w, factor), remainders dropped."""
    h, w = array.shape[-2] // factor, array.shape[-1] // factor
    return array[..., :h * factor, :w * factor].reshape(*array.shape[:-2], h, factor, w, factor)


@njit(cache=True, parallel=True, nogil=True)
def _frame_bins(image: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, max) over factor x factor blocks of one frame, in one pass: numpy's reduction over
    a reshaped frame took 8 ms a full-resolution frame, a third of the live engine's time."""
    h, w = image.shape[0] // factor, image.shape[1] // factor
    mean = np.empty((h, w))
    top = np.empty((h, w), dtype=image.dtype)
    scale = 1.0 / (factor * factor)
    for i in prange(h):
        for j in range(w):
            total = 0.0
            peak = image[i * factor, j * factor]
            for a in range(i * factor, i * factor + factor):
                for b in range(j * factor, j * factor + factor):
                    value = image[a, b]
                    total += value
                    if value > peak:
                        peak = value
            mean[i, j] = total * scale
            top[i, j] = peak
    return mean, top


def frame_bins(frame: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean (float64), max) of a 2-D frame over factor x factor blocks, remainders dropped."""
    frame = np.ascontiguousarray(frame)
    if factor == 1:
        return frame.astype(np.float64), frame
    return _frame_bins(frame, factor)


def frame_mean(frame: np.ndarray, factor: int) -> float:
    """The mean of a 2-D frame over the part that bins into factor x factor blocks: the mean of
    bin_mean(frame, factor), without binning it."""
    frame = np.asarray(frame)
    h, w = frame.shape[-2] // factor * factor, frame.shape[-1] // factor * factor
    if frame.ndim == 2 and frame.dtype.kind in "ui" and h * w:
        return _integer_mean(frame, h, w)
    return float(frame[..., :h, :w].mean(dtype=np.float64))


@njit(cache=True, nogil=True)
def _integer_mean(frame: np.ndarray, h: int, w: int) -> float:
    total = 0
    for i in range(h):
        for j in range(w):
            total += frame[i, j]
    return total / (h * w)


def bin_mean(image: np.ndarray, factor: int) -> np.ndarray:
    """The mean over factor x factor blocks of the last two axes (float64), remainders dropped."""
    image = np.asarray(image)
    if factor == 1:
        return image.astype(np.float64)
    if image.ndim == 2 and image.dtype.kind in "ui":
        return frame_bins(image, factor)[0]
    return _blocks(image, factor).mean(axis=(-3, -1), dtype=np.float64)


def bin_all(flags: np.ndarray, factor: int) -> np.ndarray:
    """True where every pixel of a factor x factor block is (a bin wholly inside a region)."""
    return ~bin_any(~np.asarray(flags, dtype=bool), factor)


def bin_any(flags: np.ndarray, factor: int) -> np.ndarray:
    """True where any pixel of a factor x factor block is (a saturated pixel spoils its bin)."""
    flags = np.asarray(flags, dtype=bool)
    if factor == 1:
        return flags
    return _blocks(flags, factor).any(axis=(-3, -1))
