"""Scenes: objects placed between the two heads, their motion, and what is true about them.

World frame = the front camera's frame. The back camera looks back along the axis from
`baseline_mm`: a world point (x, y, z) is (-x, y, baseline - z) in the back camera's frame.
A height-field object has its mid-plane at world z = z_mid; its front surface is
z = z_mid - h_front(x, y) and its back surface z = z_mid + h_back(x, y), both shifted rigidly
by the sway.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np

from core.rig import Head
from core.sim.render import (STRETCH_COLUMNS, CameraModel, breathing_surface, camera_rays, pack_lights,
                             render_height_field, render_spheres)
from core.sim.surfaces import F_H, HeightField, Sphere, mode_volumes_mm3, stretched_volume_mm3

HEAD_KEYS = {"front": 0, "back": 1}


@dataclass
class Digitiser:
    """Electron to DN conversion of one head."""

    camera: CameraModel
    bit_depth: int
    ambient_scale: float = 1.0  # the room light's level at this frame against its mean (mains flicker)

    @property
    def max_dn(self) -> float:
        return float((1 << self.bit_depth) - 1)

    @property
    def dn_per_e(self) -> float:
        return self.max_dn / self.camera.full_well_e

    def args(self) -> tuple:
        c = self.camera
        return (c.exposure_gain, c.ambient_level * c.full_well_e * self.ambient_scale, c.background_level * c.full_well_e,
                c.read_noise_e if c.noise else -1.0, self.dn_per_e, self.max_dn)


def noise_key(seed: int, head: str, frame_index: int, n_pixels: int) -> np.uint64:
    return np.uint64(((seed * 1_000_003 + HEAD_KEYS[head]) * (1 << 40) + frame_index * n_pixels) % (1 << 64))


class _Optics:
    """Each head's pixel rays and relative illumination, computed once."""

    def __init__(self) -> None:
        self._cache: dict[tuple, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def of(self, head: Head) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = (head.name, head.shape, head.fx, head.fy, head.cx, head.cy, tuple(head.dist_coeffs), head.vignetting)
        if key not in self._cache:
            self._cache[key] = (*camera_rays(head), np.ascontiguousarray(head.relative_illumination()))
        return self._cache[key]


@dataclass
class RenderedMaps:
    depth_mm: np.ndarray
    normals: np.ndarray


class Scene:
    """Base: a scene renders frames of a head at a time, and knows its truth."""

    kind = "simulation"
    events: list[tuple[float, str]]
    root_attrs: dict[str, object]

    def render(self, head: Head, t_s: float, light: int, key: np.uint64, digitiser: Digitiser,
               want_maps: bool = False) -> tuple[np.ndarray, RenderedMaps | None]:
        raise NotImplementedError

    def truth_volume_l(self, t_s: np.ndarray) -> np.ndarray:
        return np.zeros_like(np.asarray(t_s, dtype=float))

    def truth_flow_lps(self, t_s: np.ndarray) -> np.ndarray:
        return np.zeros_like(np.asarray(t_s, dtype=float))

    def sway_mm(self, t_s: np.ndarray) -> np.ndarray:
        return np.zeros(np.shape(t_s) + (3,))


def _empty_maps(head: Head, want: bool) -> tuple[np.ndarray, np.ndarray]:
    shape = head.shape if want else (1, 1)
    return np.empty(shape, np.float64), np.empty(shape + (3,), np.float64)


# Summing the breathing modes on the body's grid once a frame (breathing_surface) pays where the grid
# has fewer than this many cells per ray of the image; with more, each ray sums them where it looks.
# Measured on our torso (517 000 cells at 1 mm), 2 s of tidal breathing, on the grid against per ray:
# scale 0.05 (145 cells a ray) 1.58 s against 0.73 s, scale 0.1 (36) 1.74 against 0.91, scale 0.25 (5.8)
# 2.21 against 2.16; at scale 0.5 (1.4) the grid took 15.0 ms a frame against 21.1.
GRID_CELLS_PER_RAY = 6.0


def stretch_table(surface: HeightField, amplitudes: np.ndarray) -> np.ndarray:
    """The renderer's table of the trunk's sideways stretch at these amplitudes (core/sim/render.py,
    ST_*): one row per grid row; empty where the surface has no stretch."""
    if surface.stretch_modes is None:
        return np.zeros((0, STRETCH_COLUMNS))
    e = np.einsum("m,mrs->rs", np.asarray(amplitudes, dtype=float), surface.stretch_modes)
    half_width = surface.trunk_half_width_mm
    step = surface.grid.step
    de = np.gradient(e, step, axis=0)
    dew = np.gradient(e * half_width[:, None], step, axis=0)
    return np.ascontiguousarray(np.column_stack([e[:, 0], e[:, 1], half_width, de[:, 0], de[:, 1],
                                                 dew[:, 0], dew[:, 1]]))


class HeightFieldScene(Scene):
    """A height-field object (torso, board, vase, relief) with optional breathing and sway."""

    def __init__(self, surfaces: dict[str, HeightField], z_mid_mm: float, baseline_mm: float,
                 mode_amplitudes: Callable[[float], np.ndarray] | None = None,
                 sway: Callable[[np.ndarray], np.ndarray] | None = None,
                 compartment_volumes_l: Callable[[np.ndarray], np.ndarray] | None = None,
                 flow_lps: Callable[[np.ndarray], np.ndarray] | None = None,
                 events: list[tuple[float, str]] | None = None, kind: str = "simulation") -> None:
        self.surfaces = surfaces
        self.z_mid_mm = z_mid_mm
        self.baseline_mm = baseline_mm
        self._amps = mode_amplitudes
        self._sway = sway
        self._compartments = compartment_volumes_l
        self._flow = flow_lps
        self.events = events or []
        self.kind = kind
        self.root_attrs = {}
        self._z_state: dict[str, np.ndarray] = {}
        self._optics = _Optics()

    def sway_mm(self, t_s: np.ndarray) -> np.ndarray:
        if self._sway is None:
            return super().sway_mm(t_s)
        return self._sway(np.asarray(t_s, dtype=float))

    def amplitudes(self, t_s: float) -> np.ndarray:
        n = next(iter(self.surfaces.values())).n_modes
        return self._amps(t_s) if self._amps is not None and n else np.zeros(n)

    def render(self, head: Head, t_s: float, light: int, key: np.uint64, digitiser: Digitiser,
               want_maps: bool = False) -> tuple[np.ndarray, RenderedMaps | None]:
        surface = self.surfaces[head.name]
        if head.name not in self._z_state:
            self._z_state[head.name] = np.full(head.shape, np.nan)
        u, v, vignette = self._optics.of(head)
        sx, sy, sz = self.sway_mm(np.array(t_s))
        if head.name == "front":
            sign_x, z0 = 1.0, self.z_mid_mm + sz
        else:
            sign_x, z0 = -1.0, self.baseline_mm - self.z_mid_mm - sz
        out = np.empty(head.shape, dtype=head.frame_dtype)
        depth, normals = _empty_maps(head, want_maps)
        lights = pack_lights(head)
        g = surface.grid
        amps = self.amplitudes(t_s).astype(np.float64)
        # the modes summed once a frame on the grid, not per ray and Newton step: the same surface,
        # cheaper where the grid has fewer than GRID_CELLS_PER_RAY cells a ray (docs/simulator.md)
        cells = surface.fields.shape[0] * surface.fields.shape[1]
        on_grid = np.any(amps) and head.width * head.height * GRID_CELLS_PER_RAY >= cells
        fields = breathing_surface(surface.fields, amps) if on_grid else surface.fields
        render_height_field(out, self._z_state[head.name], u, v, vignette, fields, g.x0, g.y0, g.step,
                            np.zeros(0) if on_grid else amps, sign_x, sx, sy, z0, surface.front_mm(amps),
                            surface.specular, surface.shininess, lights[max(light, 0)], light >= 0,
                            *digitiser.args(), key,
                            want_maps, depth, normals, stretch_table(surface, amps))
        return out, (RenderedMaps(depth, normals) if want_maps else None)

    def volume_mm3(self, amplitudes: np.ndarray) -> float:
        """The volume between front and back surfaces at these mode amplitudes less at rest (mm^3):
        each mode's quadrature and the sideways stretch's exact widening (stretched_volume_mm3)."""
        amplitudes = np.asarray(amplitudes, dtype=float)
        return float(amplitudes @ self._mode_volumes_mm3 + sum(stretched_volume_mm3(s, amplitudes)
                                                              for s in self.surfaces.values()))

    @cached_property
    def _mode_volumes_mm3(self) -> np.ndarray:
        """Each mode's volume at unit amplitude, both heads (a grid quadrature: once, not per sample)."""
        return sum(mode_volumes_mm3(s) for s in self.surfaces.values())

    def truth_volume_l(self, t_s: np.ndarray) -> np.ndarray:
        """Volume swept between front and back surfaces since t = 0 (L)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        if self._amps is None:
            return np.zeros_like(t)
        base = self.volume_mm3(self._amps(0.0))
        return np.array([self.volume_mm3(self._amps(ti)) - base for ti in t]) * 1e-6

    def truth_flow_lps(self, t_s: np.ndarray) -> np.ndarray:
        return self._flow(np.asarray(t_s, dtype=float)) if self._flow is not None else super().truth_flow_lps(t_s)

    def compartment_volumes_l(self, t_s: np.ndarray) -> np.ndarray | None:
        return self._compartments(np.asarray(t_s, dtype=float)) if self._compartments is not None else None

    def on_axis_height_mm(self, head: str) -> float:
        s = self.surfaces[head]
        j = int(round(-s.grid.x0 / s.grid.step))
        i = int(round(-s.grid.y0 / s.grid.step))
        return float(s.fields[i, j, F_H])


@dataclass
class SpherePlacement:
    start_s: float
    centre_mm: np.ndarray  # world frame


@dataclass
class SphereScene(Scene):
    """A sphere, still during each placement, seen by every head (calibration sessions)."""

    radius_mm: float
    placements: list[SpherePlacement]
    baseline_mm: float
    albedo: float = 0.8
    specular: float = 0.0
    shininess: float = 1.0
    kind: str = "simulation"
    supersample: int = 3
    events: list[tuple[float, str]] = field(default_factory=list)
    root_attrs: dict[str, object] = field(default_factory=dict)
    _optics: "_Optics" = field(default_factory=lambda: _Optics(), repr=False)

    def __post_init__(self) -> None:
        if not self.events:
            self.events = [(p.start_s, "placement") for p in self.placements]

    def centre_in(self, head: str, t_s: float) -> np.ndarray:
        current = [p for p in self.placements if p.start_s <= t_s + 1e-9] or self.placements[:1]
        c = np.asarray(current[-1].centre_mm, dtype=float)
        return c if head == "front" else np.array([-c[0], c[1], self.baseline_mm - c[2]])

    def spheres_in(self, head: str, t_s: float) -> list[Sphere]:
        return [Sphere(self.centre_in(head, t_s), self.radius_mm, self.albedo, self.specular, self.shininess)]

    def render(self, head: Head, t_s: float, light: int, key: np.uint64, digitiser: Digitiser,
               want_maps: bool = False) -> tuple[np.ndarray, RenderedMaps | None]:
        rows = np.array([s.as_row() for s in self.spheres_in(head.name, t_s)])
        u, v, vignette = self._optics.of(head)
        out = np.empty(head.shape, dtype=head.frame_dtype)
        depth, normals = _empty_maps(head, want_maps)
        lights = pack_lights(head)
        render_spheres(out, u, v, vignette, 1.0 / head.fx, rows, lights[max(light, 0)], light >= 0, *digitiser.args(), key,
                       self.supersample, want_maps, depth, normals)
        return out, (RenderedMaps(depth, normals) if want_maps else None)
