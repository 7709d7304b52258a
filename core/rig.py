"""The rig: camera heads (pinhole intrinsics, lights) and the capture cycle.

Every position is in the head's camera frame (OpenCV convention: x right, y down,
z along the optical axis into the scene), in millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

DEFAULT_SEQUENCE = (0, 1, 2, 3, -1)
DARK = -1


@dataclass(frozen=True)
class Head:
    """One camera head: a mono camera and its four LEDs."""

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    pixel_size_mm: float
    bit_depth: int
    light_positions_mm: np.ndarray  # (4, 3)
    light_intensity: np.ndarray = field(default_factory=lambda: np.ones(4))
    light_axis: np.ndarray | None = None  # (4, 3) unit vectors, None = isotropic
    light_mu: np.ndarray | None = None  # (4,) anisotropy exponents
    dist_coeffs: np.ndarray = field(default_factory=lambda: np.zeros(5))
    # the lens' relative illumination: 1 - vignetting * (r / r_corner)^2, r from the principal point
    # (measured with the lens, as its distortion is; 0: none)
    vignetting: float = 0.0
    calibrated: str = ""

    def __post_init__(self) -> None:
        positions = np.asarray(self.light_positions_mm, dtype=float)
        if positions.shape != (4, 3):
            raise ValueError(f"head {self.name!r}: light_positions_mm must be 4 x 3, got {positions.shape}")
        object.__setattr__(self, "light_positions_mm", positions)
        object.__setattr__(self, "light_intensity", np.asarray(self.light_intensity, dtype=float).reshape(4))
        object.__setattr__(self, "dist_coeffs", np.asarray(self.dist_coeffs, dtype=float).reshape(5))
        if self.light_axis is not None:
            axis = np.asarray(self.light_axis, dtype=float).reshape(4, 3)
            object.__setattr__(self, "light_axis", axis / np.linalg.norm(axis, axis=1, keepdims=True))
        if self.light_mu is not None:
            object.__setattr__(self, "light_mu", np.asarray(self.light_mu, dtype=float).reshape(4))
        if not (np.isfinite(self.vignetting) and 0.0 <= self.vignetting < 0.9):
            raise ValueError(f"head {self.name!r}: vignetting must be in [0, 0.9), got {self.vignetting}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"head {self.name!r}: sensor size must be positive, got {self.width} x {self.height}")
        if self.bit_depth not in (8, 10, 12, 16):
            raise ValueError(f"head {self.name!r}: bit_depth must be 8, 10, 12 or 16, got {self.bit_depth}")

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def frame_dtype(self) -> np.dtype:
        return np.dtype(np.uint8) if self.bit_depth <= 8 else np.dtype(np.uint16)

    @property
    def max_value(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def focal_length_mm(self) -> float:
        return self.fx * self.pixel_size_mm

    @property
    def camera_matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Normalised image coordinates (x/z, y/z) of every pixel centre, each (H, W)."""
        u = (np.arange(self.width) - self.cx) / self.fx
        v = (np.arange(self.height) - self.cy) / self.fy
        return np.broadcast_to(u[None, :], self.shape).copy(), np.broadcast_to(v[:, None], self.shape).copy()

    def relative_illumination(self) -> np.ndarray:
        """(H, W) the share of the light the lens brings to each pixel, against the principal point's."""
        yy, xx = np.mgrid[0:self.height, 0:self.width]
        r2 = ((xx - self.cx) ** 2 + (yy - self.cy) ** 2) / (self.cx**2 + self.cy**2)
        return 1.0 - self.vignetting * r2

    def with_lights(self, light_positions_mm: np.ndarray, light_intensity: np.ndarray | None = None) -> "Head":
        intensity = self.light_intensity if light_intensity is None else light_intensity
        return replace(self, light_positions_mm=np.asarray(light_positions_mm, float), light_intensity=intensity)


@dataclass(frozen=True)
class Rig:
    """The capture rig: one or two heads sharing one light cycle and frame rate."""

    name: str
    heads: dict[str, Head]
    frame_rate_hz: float = 110.0
    sequence: tuple[int, ...] = DEFAULT_SEQUENCE
    baseline_mm: float | None = None  # front to back camera centre along the shared axis, when known
    mains_hz: float = 50.0  # the room's mains supply: its lamps flicker at twice this (core/reconstruction/ambient.py)

    def __post_init__(self) -> None:
        if "front" not in self.heads:
            raise ValueError("a rig needs a 'front' head")
        unknown = set(self.heads) - {"front", "back"}
        if unknown:
            raise ValueError(f"unknown head names {sorted(unknown)}: heads are 'front' and 'back'")
        lights = sorted(i for i in self.sequence if i != DARK)
        if lights != [0, 1, 2, 3] or self.sequence.count(DARK) < 1:
            raise ValueError(f"sequence {self.sequence} must hold lights 0-3 once each and at least one dark slot")

    @property
    def cycle_length(self) -> int:
        return len(self.sequence)

    @property
    def frame_period_ns(self) -> float:
        return 1e9 / self.frame_rate_hz


MIN_LIGHT_SEPARATION_MM = 10.0  # a head's LEDs sit hundreds of mm apart and from the lens; closer is a wrong file


def light_position_problems(positions_mm: np.ndarray) -> list[str]:
    """What makes four light positions impossible: non-finite, at the camera's centre, or two at one place
    (photometric stereo then has no light direction to solve with, and the distance fit reads 0)."""
    p = np.asarray(positions_mm, dtype=float)
    if p.shape != (4, 3):
        return [f"must be 4 x 3, found {p.shape}"]
    if not np.all(np.isfinite(p)):
        return ["holds non-finite values"]
    problems = [f"light {k} is {np.linalg.norm(p[k]):.1f} mm from the camera's centre"
                for k in range(4) if np.linalg.norm(p[k]) < MIN_LIGHT_SEPARATION_MM]
    problems += [f"lights {i} and {j} are {np.linalg.norm(p[i] - p[j]):.1f} mm apart"
                 for i in range(4) for j in range(i + 1, 4) if np.linalg.norm(p[i] - p[j]) < MIN_LIGHT_SEPARATION_MM]
    return problems


def lens_square_lights(half_side_mm: float = 500.0) -> np.ndarray:
    """Four LEDs at the corners of a square around the lens, in the lens plane (z = 0)."""
    s = half_side_mm
    return np.array([[-s, -s, 0.0], [s, -s, 0.0], [s, s, 0.0], [-s, s, 0.0]])


def thesis_head(
    name: str = "front",
    scale: float = 1.0,
    width: int = 1400,
    height: int = 1024,
    pixel_size_um: float = 7.4,
    focal_length_mm: float = 25.0,
    bit_depth: int = 12,
    light_half_side_mm: float = 500.0,
) -> Head:
    """A head like the thesis rig: Genie HM1400 (1400 x 1024, 7.4 um), 25 mm lens, LEDs at +-500 mm.

    `scale` resamples the sensor (0.25 gives 350 x 256 with 29.6 um pixels): same field of view.
    """
    if not 0.01 <= scale <= 1.0:
        raise ValueError(f"scale must be in (0.01, 1], got {scale}")
    w = max(8, int(round(width * scale)))
    h = max(8, int(round(height * scale)))
    pixel_mm = pixel_size_um * 1e-3 * width / w
    f_px = focal_length_mm / pixel_mm
    return Head(
        name=name,
        width=w,
        height=h,
        fx=f_px,
        fy=f_px,
        cx=(w - 1) / 2.0,
        cy=(h - 1) / 2.0,
        pixel_size_mm=pixel_mm,
        bit_depth=bit_depth,
        light_positions_mm=lens_square_lights(light_half_side_mm),
    )


def thesis_rig(scale: float = 1.0, heads: tuple[str, ...] = ("front", "back"), bit_depth: int = 12,
               frame_rate_hz: float = 110.0) -> Rig:
    """The default simulated rig: two thesis heads facing each other across the subject."""
    return Rig(
        name="simulated",
        heads={h: thesis_head(h, scale=scale, bit_depth=bit_depth) for h in heads},
        frame_rate_hz=frame_rate_hz,
    )
