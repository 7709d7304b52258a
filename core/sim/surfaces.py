"""Simulated surfaces: height fields sampled on a fine body grid, and analytic spheres.

A height field describes one side of an object as seen by one head: `h(x, y)` is how far
the surface stands out of the object's mid-plane towards that head (mm), over body
coordinates x (to the right of the front image), y (down). Breathing is a sum of
displacement modes, `h + sum_c a_c(t) m_c`, each mode a field on the same grid, so the
volume swept by the surfaces is exact to the grid's quadrature (see `mode_volumes_mm3`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

# Field layout of HeightField.fields[..., k]: height and its gradient, albedo, then per mode (m, m_x, m_y).
F_H, F_HX, F_HY, F_ALBEDO, F_MODES = 0, 1, 2, 3, 4


@dataclass(frozen=True)
class BodyGrid:
    """A regular grid over body coordinates (mm): x = x0 + j * step, y = y0 + i * step."""

    x0: float
    y0: float
    step: float
    nx: int
    ny: int

    @classmethod
    def covering(cls, half_width_mm: float, y_min_mm: float, y_max_mm: float, step_mm: float) -> "BodyGrid":
        nx = int(np.ceil(2 * half_width_mm / step_mm)) + 1
        ny = int(np.ceil((y_max_mm - y_min_mm) / step_mm)) + 1
        return cls(-half_width_mm, y_min_mm, step_mm, nx, ny)

    def coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        x = self.x0 + self.step * np.arange(self.nx)
        y = self.y0 + self.step * np.arange(self.ny)
        return np.meshgrid(x, y)

    @property
    def cell_area_mm2(self) -> float:
        return self.step * self.step


@dataclass(frozen=True)
class HeightField:
    """One side of an object for one head, ready for the renderer."""

    grid: BodyGrid
    fields: np.ndarray  # float32 (ny, nx, 4 + 3 * n_modes); height NaN off the object
    mode_names: tuple[str, ...] = ()
    specular: float = 0.0  # Blinn-Phong weight relative to a white Lambertian surface
    shininess: float = 1.0
    # what each mode sweeps on the object itself, where the rendered modes are hidden in places
    # (arms in front of the trunk's sides); None: the rendered modes' own quadrature
    swept_mode_volumes_mm3: tuple[float, ...] | None = None
    # A trunk whose sides move out as it breathes (None: its modes move it along the axis only). The
    # stretch x -> x (1 + e) of each grid row's two sides (x > 0, x < 0) per unit amplitude of each
    # mode (n_modes, ny, 2), within the trunk's half width on each row (ny,); and for the truth, the
    # area of this head's half of the trunk's section on each row side at rest (ny, 2; mm^2) and
    # each mode's at unit amplitude (n_modes, ny, 2). Both heads hold the same stretch.
    stretch_modes: np.ndarray | None = field(default=None, compare=False)
    trunk_half_width_mm: np.ndarray | None = field(default=None, compare=False)
    section_area_mm2: np.ndarray | None = field(default=None, compare=False)
    mode_section_area_mm2: np.ndarray | None = field(default=None, compare=False)

    @property
    def n_modes(self) -> int:
        return len(self.mode_names)

    @property
    def height_mm(self) -> np.ndarray:
        return self.fields[..., F_H]

    def mode(self, k: int) -> np.ndarray:
        return self.fields[..., F_MODES + 3 * k]

    @cached_property
    def _peaks_mm(self) -> tuple[float, np.ndarray]:
        return (float(np.nanmax(self.height_mm)),
                np.array([float(np.max(np.abs(self.mode(k)))) for k in range(self.n_modes)]))

    def front_mm(self, amplitudes: np.ndarray) -> float:
        """How far the surface can stand out of the mid-plane with these mode amplitudes (mm), at most."""
        height, modes = self._peaks_mm
        return height + float(np.abs(amplitudes) @ modes) + 1.0


def build_height_field(grid: BodyGrid, height_mm: np.ndarray, albedo: np.ndarray,
                       modes: dict[str, np.ndarray] | None = None, *, max_slope_deg: float = 80.0,
                       specular: float = 0.0, shininess: float = 1.0) -> HeightField:
    """Pack height, albedo and modes into renderer fields; gradients by central differences.

    Cells steeper than `max_slope_deg` are cut off the object (NaN): grazing surfaces that no
    photometric method can see are also where the grid's derivatives stop being accurate.
    """
    modes = modes or {}
    fields = np.empty((grid.ny, grid.nx, F_MODES + 3 * len(modes)), dtype=np.float32)
    hy, hx = np.gradient(height_mm, grid.step)
    steep = np.hypot(hx, hy) > np.tan(np.radians(max_slope_deg))
    height = np.where(steep | ~np.isfinite(hx) | ~np.isfinite(hy), np.nan, height_mm)
    fields[..., F_H] = height
    fields[..., F_HX] = np.nan_to_num(hx)
    fields[..., F_HY] = np.nan_to_num(hy)
    fields[..., F_ALBEDO] = albedo
    for k, m in enumerate(modes.values()):
        m = np.where(np.isfinite(height_mm), m, 0.0)
        my, mx = np.gradient(m, grid.step)
        fields[..., F_MODES + 3 * k] = m
        fields[..., F_MODES + 3 * k + 1] = mx
        fields[..., F_MODES + 3 * k + 2] = my
    return HeightField(grid, fields, tuple(modes), specular, shininess)


def mode_volumes_mm3(surface: HeightField) -> np.ndarray:
    """Volume (mm^3) swept by each mode at unit amplitude: the grid quadrature of the rendered
    surface, or of the object's own where something hides part of it."""
    if surface.swept_mode_volumes_mm3 is not None:
        return np.array(surface.swept_mode_volumes_mm3, dtype=float)
    return np.array([float(np.sum(surface.mode(k), dtype=np.float64)) * surface.grid.cell_area_mm2
                     for k in range(surface.n_modes)])


@dataclass(frozen=True)
class Sphere:
    """A sphere in a head's camera frame."""

    centre_mm: np.ndarray
    radius_mm: float
    albedo: float = 0.8
    specular: float = 0.0
    shininess: float = 1.0

    def as_row(self) -> np.ndarray:
        return np.array([*np.asarray(self.centre_mm, float), self.radius_mm, self.albedo, self.specular,
                         self.shininess])


def stretched_volume_mm3(surface: HeightField, amplitudes: np.ndarray, modes_too: bool = True) -> float:
    """What the trunk's sideways stretch adds to this head's half of the trunk at these amplitudes
    (mm^3): each row side's section area (its rest area and, with `modes_too`, the modes') times its
    stretch e, since x -> x (1 + e) widens every area by the factor 1 + e. 0 for a surface without a
    stretch."""
    if surface.stretch_modes is None:
        return 0.0
    amplitudes = np.asarray(amplitudes, dtype=float)
    e = np.einsum("m,mrs->rs", amplitudes, surface.stretch_modes)
    area = surface.section_area_mm2
    if modes_too:
        area = area + np.einsum("m,mrs->rs", amplitudes, surface.mode_section_area_mm2)
    return float(np.sum(e * area, dtype=np.float64)) * surface.grid.step
