"""A mesh body between the two heads (core/sim/makehuman.py), breathing (core/sim/mesh_breathing.py)
and swaying, rendered by ray-casting (core/sim/mesh_render.py); its truth the closed mesh's volume.

World frame = the front camera's (x right, y down, z along the axis). The body faces the front
camera: a mesh point (x, y, z) (y up, z forward) is at (x, -(y - y_x), z_f - z) + (0, 0, distance),
with y_x the xiphoid's level and z_f the trunk's front there, so the cameras' axes meet the body at
the xiphoid; the sway shifts it rigidly.
"""

from __future__ import annotations

import numpy as np

from core.rig import Head
from core.sim.breathing import RATE_HZ, Waveform
from core.sim.makehuman import MeshBody, MeshData, triangles
from core.sim.mesh_breathing import (MODES, VolumePolynomial, amplitudes_for, at_rest, breathing_modes,
                                     chest_share_curve, trunk_frame)
from core.sim.mesh_render import distortion_margin_px, face_normals, rasterise, shade
from core.sim.render import pack_lights
from core.sim.scene import Digitiser, RenderedMaps, Scene, _empty_maps, _Optics


class MeshScene(Scene):
    def __init__(self, body: MeshBody, data: MeshData, waveform: Waveform, distance_mm: float,
                 distance_back_mm: float, sway=None, albedo: float = 0.45, specular: float = 0.0,
                 shininess: float = 20.0) -> None:
        verts = body.vertices_mm(data)
        self.body = body
        self.tris = np.ascontiguousarray(triangles(data.quads))
        self.modes = breathing_modes(verts, data, body)
        self.polynomial = VolumePolynomial.fit(verts, self.tris, self.modes)
        frame = trunk_frame(verts, data)
        xiphoid = frame.xiphoid_y
        front, back, _ = frame.at(np.array(xiphoid))
        self.rest_world = np.column_stack([verts[:, 0], -(verts[:, 1] - xiphoid), float(front) - verts[:, 2]])
        self.rest_world[:, 2] += distance_mm
        self.world_modes = self.modes * np.array([1.0, -1.0, -1.0])
        self.baseline_mm = float(distance_mm + (front - back) + distance_back_mm)
        self.albedo, self.specular, self.shininess = albedo, specular, shininess
        self._sway = sway
        self.events = list(waveform.events)
        self.kind = "simulation"
        t = np.arange(len(waveform.volume_l)) / RATE_HZ
        lung = waveform.volume_l - waveform.volume_l[0]
        share = chest_share_curve(t, at_rest(t, lung, self.events), body.chest_share)
        lagged = np.interp(np.clip(t - body.abdomen_lag_s, 0.0, None), t, lung)
        rib_l, abdomen_l = share * lung, (1.0 - share) * lagged
        self._t = t
        self._amplitudes = amplitudes_for(self.polynomial, rib_l * 1e6, abdomen_l * 1e6)
        self._compartments_l = np.column_stack([rib_l, abdomen_l])
        self._volume_l = self.polynomial(self._amplitudes[:, 0], self._amplitudes[:, 1]) * 1e-6
        self._flow_lps = np.gradient(self._volume_l) * RATE_HZ
        self._optics = _Optics()
        self._margins: dict[str, float] = {}
        self._normals = np.empty((len(self.tris), 3))
        self.root_attrs = {"simulated_scene": "torso", "simulated_body": body.name, "compartments": ",".join(MODES)}

    def sway_mm(self, t_s: np.ndarray) -> np.ndarray:
        return super().sway_mm(t_s) if self._sway is None else self._sway(np.asarray(t_s, dtype=float))

    def amplitudes(self, t_s: float) -> np.ndarray:
        return np.array([np.interp(t_s, self._t, self._amplitudes[:, k]) for k in range(2)])

    def world_vertices(self, t_s: float) -> np.ndarray:
        a = self.amplitudes(t_s)
        return self.rest_world + a[0] * self.world_modes[0] + a[1] * self.world_modes[1] + self.sway_mm(np.array(t_s))

    def render(self, head: Head, t_s: float, light: int, key: np.uint64, digitiser: Digitiser,
               want_maps: bool = False) -> tuple[np.ndarray, RenderedMaps | None]:
        world = self.world_vertices(t_s)
        if head.name == "front":
            camera = world
        else:  # the back camera looks back along the axis from the baseline
            camera = np.column_stack([-world[:, 0], world[:, 1], self.baseline_mm - world[:, 2]])
        camera = np.ascontiguousarray(camera)
        face_normals(camera, self.tris, self._normals)
        u, v, vignette = self._optics.of(head)
        margin = self._margin(head, u, v)
        depth = np.empty(head.shape)
        tri_id = np.empty(head.shape, np.int64)
        bary = np.empty(head.shape + (2,))
        rasterise(camera, self.tris, u, v, head.fx, head.fy, head.cx, head.cy, margin, depth, tri_id, bary)
        out = np.empty(head.shape, dtype=head.frame_dtype)
        depth_out, normal_out = _empty_maps(head, want_maps)
        shade(out, depth, tri_id, bary, self.tris, self._normals, u, v, vignette, self.albedo, self.specular,
              self.shininess, pack_lights(head)[max(light, 0)], light >= 0, *digitiser.args(), key, want_maps,
              depth_out, normal_out, True)
        return out, (RenderedMaps(depth_out, normal_out) if want_maps else None)

    def _margin(self, head: Head, u: np.ndarray, v: np.ndarray) -> float:
        if head.name not in self._margins:
            self._margins[head.name] = distortion_margin_px(u, v, head.fx, head.fy, head.cx, head.cy)
        return self._margins[head.name]

    def truth_volume_l(self, t_s: np.ndarray) -> np.ndarray:
        """The closed mesh's volume since t = 0 (L), flanks and all."""
        return np.interp(np.asarray(t_s, dtype=float), self._t, self._volume_l)

    def truth_flow_lps(self, t_s: np.ndarray) -> np.ndarray:
        return np.interp(np.asarray(t_s, dtype=float), self._t, self._flow_lps)

    def compartment_volumes_l(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        return np.stack([np.interp(t, self._t, self._compartments_l[:, k]) for k in range(2)], -1)
