"""The lens between the scene and the sensor, undone: its relative illumination divided out and
its distortion removed, so that the reconstruction sees the pinhole camera it assumes.

Both are properties of a lens measured once, as a camera calibration does (OpenCV's distortion
model from a checkerboard, the relative illumination from a flat field); /rig carries them
(`dist_coeffs`, `vignetting`).
"""

from __future__ import annotations

import cv2
import numpy as np

from core.rig import Head


def needs_correction(head: Head) -> bool:
    return bool(np.any(head.dist_coeffs != 0) or head.vignetting)


class LensCorrection:
    """Brings one head's cycles to its pinhole camera (the same camera matrix, no distortion,
    even illumination)."""

    def __init__(self, head: Head) -> None:
        self._gain = (1.0 / head.relative_illumination()) if head.vignetting else None
        self._maps = None
        if np.any(head.dist_coeffs != 0):
            self._maps = cv2.initUndistortRectifyMap(head.camera_matrix, head.dist_coeffs, None, head.camera_matrix,
                                                     (head.width, head.height), cv2.CV_32FC1)

    def _remap(self, image: np.ndarray, interpolation: int) -> np.ndarray:
        return cv2.remap(image, self._maps[0], self._maps[1], interpolation, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)

    def correct(self, signal: np.ndarray, saturated: np.ndarray, dark: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """signal (4, H, W), saturated (4, H, W) bool, dark (H, W) as the pinhole camera would have them."""
        if self._gain is not None:
            signal = signal * self._gain[None]
        if self._maps is None:
            return signal, saturated, dark
        signal = np.stack([self._remap(np.ascontiguousarray(s, dtype=np.float32), cv2.INTER_LINEAR) for s in signal])
        saturated = np.stack([self._remap(s.astype(np.uint8), cv2.INTER_NEAREST) > 0 for s in saturated])
        if dark is not None:
            dark = self._remap(np.ascontiguousarray(dark, dtype=np.float32), cv2.INTER_LINEAR).astype(np.float64)
        return signal.astype(np.float64), saturated, dark
