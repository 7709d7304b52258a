"""A light Gaussian prefilter of a cycle's images before the normals are solved, for heads whose
pixels are small enough that the camera noise, not the surface, sets the angular error.

At 1400 x 1024 a pixel sees about 0.45 mm of a subject at 2 m and collects a quarter of the
photons of a 700 x 512 pixel; photometric stereo turns the shot noise straight into normal
noise (the same solver handed the true surface and lights reaches 2.4 deg on a torso at 2.2 m,
docs/reconstruction.md). A torso has no detail at half a millimetre, so averaging neighbouring
pixels as 2 x 2 bins would, while keeping every pixel's place, costs nothing a breathing volume
needs. The filter is linear, so filtering the lit-minus-dark images equals filtering each frame
as it arrives.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

# Heads up to 1.5 times this wide are left as they are; wider ones are filtered to the noise of a
# head this wide (the project's half-resolution head, where the targets are met unfiltered).
PREFILTER_REFERENCE_WIDTH_PX = 700


def prefilter_sigma_px(width_px: int, reference_width_px: int = PREFILTER_REFERENCE_WIDTH_PX) -> float:
    """The Gaussian's sigma in pixels that leaves white noise with the variance of k x k bins,
    k = width / reference (a Gaussian of sigma s divides the variance by about 4 pi s^2), or 0 when
    k is under 1.5 (the head is already about the reference's size)."""
    k = width_px / reference_width_px
    return 0.0 if k < 1.5 else float(k / (2.0 * np.sqrt(np.pi)))


def noise_binning(width_px: int, reference_width_px: int = PREFILTER_REFERENCE_WIDTH_PX) -> int:
    """The whole bin size of the same rule: 1 up to 1.5 times the reference's width, 2 at 1400."""
    k = width_px / reference_width_px
    return 1 if k < 1.5 else int(round(k))


def _kernel_size(sigma_px: float) -> int:
    """The Gaussian's kernel: 2.5 sigma each side, rounded, at least one pixel (3 x 3 at 0.56 px,
    whose weight beyond is 0.2 %)."""
    return 2 * max(1, int(round(2.5 * sigma_px))) + 1


def prefilter_frame(frame: np.ndarray, sigma_px: float, out: np.ndarray | None = None) -> np.ndarray:
    """One image filtered with a Gaussian of sigma_px, reflected at the border (a camera frame as it
    arrives: filtering each frame once equals filtering lit minus dark). Integer frames come out
    float32: OpenCV filters those about three times faster than 16-bit ones, and rounding back
    would add noise."""
    if not np.issubdtype(frame.dtype, np.floating):
        frame = frame.astype(np.float32)
    size = _kernel_size(sigma_px)
    return cv2.GaussianBlur(frame, (size, size), sigma_px, dst=out, borderType=cv2.BORDER_REFLECT)


def prefiltered(signal: np.ndarray, saturated: np.ndarray, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(signal, saturated) of a cycle (4, H, W) filtered with a Gaussian of sigma_px, and a
    saturated pixel's flag spread over every pixel its value reaches; unchanged when sigma_px is 0."""
    if sigma_px <= 0:
        return signal, saturated
    filtered = np.stack([prefilter_frame(np.ascontiguousarray(channel, dtype=np.float64), sigma_px)
                         for channel in signal])
    if saturated.any():
        size = _kernel_size(sigma_px)
        saturated = ndimage.binary_dilation(saturated, structure=np.ones((1, size, size), dtype=bool))
    return filtered, saturated
