"""Real normals with real depth, in the folder layout of ../shared/data/diligent-integration (the
DiLiGenT objects as published with bilateral normal integration): normal_map.png, mask.png, K.txt,
depth_gt.npz. Read for testing and benchmarking normal integration on data this project did not
make; never shipped with the application."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class RealSurface:
    normals: np.ndarray  # (h, w, 3) unit normals in the OpenCV camera frame, towards the camera
    mask: np.ndarray  # (h, w) bool, the object's pixels
    camera_matrix: np.ndarray  # 3 x 3 (fx, fy, cx, cy in pixels)
    depth_mm: np.ndarray  # (h, w) the true depth

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        k = self.camera_matrix
        return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])


def load_real_surface(folder: str | Path) -> RealSurface:
    """One object's folder. The normal map's PNG is 16-bit despite the data's README (the scale is
    taken from its type); its channels (B, G, R as OpenCV reads them) are the camera's -z, -y, +x:
    checked against the depth's own normals (tests/core/test_integrate.py)."""
    import cv2  # here: OpenCV takes a while to import, and only benches and tests read DiLiGenT

    folder = Path(folder)
    missing = [n for n in ("normal_map.png", "mask.png", "K.txt", "depth_gt.npz") if not (folder / n).is_file()]
    if missing:
        raise FileNotFoundError(f"{folder}: not a folder of real normals and depth (missing {', '.join(missing)})")
    raw = cv2.imread(str(folder / "normal_map.png"), cv2.IMREAD_UNCHANGED)
    scaled = raw.astype(float) / np.iinfo(raw.dtype).max * 2 - 1
    normals = np.stack([scaled[..., 2], -scaled[..., 1], -scaled[..., 0]], -1)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    mask = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_GRAYSCALE) > 127
    depth = np.load(folder / "depth_gt.npz")["depth_gt"].astype(float)
    return RealSurface(normals, mask, np.loadtxt(folder / "K.txt"), depth)


def mean_abs_depth_error_mm(depth_mm: np.ndarray, truth_mm: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(mean absolute error after removing the mean offset, over the mask's pixels given a depth;
    the fraction of the mask's pixels given one). The offset is the one unknown of integration."""
    given = mask & np.isfinite(depth_mm)
    err = depth_mm[given] - truth_mm[given]
    return float(np.mean(np.abs(err - err.mean()))), float(given.sum() / mask.sum())
