"""Breathing of a mesh body (core/sim/makehuman.py): two displacement modes of its vertices, and the
volume the closed mesh gains with them, flanks included.

The rib cage moves in pump-handle motion (forward and a little up, most at the sternum, the spine
still) and bucket-handle motion (its sides out), the abdomen forward (its front half) and a little
sideways (Konno and Mead 1967; De Troyer and Boriek 2011). Each mode's strength is a smooth profile
along the trunk, between levels taken as shares of the trunk's length (the trunk's bones' vertices,
crotch to neck), and it fades with the vertex's skinning weight to the trunk (arms, neck and legs
stay). The sideways share of the rib cage, the rib cage's share of the volume in quiet breathing,
slow VC and forced blows, and the abdomen's lag are the body's (MeshBody).

The truth is exact: the mesh's volume is a cubic polynomial of the two amplitudes (each triangle's
signed volume is trilinear in its vertices), fitted once; the amplitudes at each instant are those
whose exact volume is the subject's lung volume change, split between the compartments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

from core.sim.makehuman import MeshBody, MeshData, closed_volume_mm3, triangles

MODES = ("rib_cage", "abdomen")
# Mode strength along the trunk: (share of the trunk's length from the crotch, strength). The costal
# margin lies near 0.52, the xiphoid 0.63, the nipples 0.76, the navel 0.38, the waistband 0.25.
RIB_CAGE_PROFILE = ((0.46, 0.0), (0.53, 0.6), (0.63, 1.0), (0.74, 0.75), (0.86, 0.2), (0.92, 0.0))
ABDOMEN_PROFILE = ((0.18, 0.0), (0.28, 0.7), (0.38, 1.0), (0.50, 0.6), (0.60, 0.0))
XIPHOID_SHARE = 0.63  # of the trunk's length: where the cameras' axes meet the body
PUMP_LIFT = 0.3  # the sternum rises this much per mm it moves forward
ABDOMEN_SIDEWAYS = 0.2  # the abdomen's sides move out this much per mm its front moves forward
SLICE_MM = 10.0
_MONOMIALS = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3))


def _profile(share: np.ndarray, knots) -> np.ndarray:
    xs, ys = zip(*knots)
    inside = (share > xs[0]) & (share < xs[-1])
    out = np.zeros_like(share)
    out[inside] = np.clip(PchipInterpolator(xs, ys)(share[inside]), 0.0, None)
    return out


@dataclass(frozen=True)
class TrunkFrame:
    """The trunk's levels and, per height, its front, back and half width (mesh mm)."""

    crotch_y: float
    top_y: float
    slice_y: np.ndarray
    front_z: np.ndarray
    back_z: np.ndarray
    half_width: np.ndarray

    def share(self, y: np.ndarray) -> np.ndarray:
        return (y - self.crotch_y) / (self.top_y - self.crotch_y)

    @property
    def xiphoid_y(self) -> float:
        return self.crotch_y + XIPHOID_SHARE * (self.top_y - self.crotch_y)

    def at(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.interp(y, self.slice_y, self.front_z), np.interp(y, self.slice_y, self.back_z),
                np.interp(y, self.slice_y, self.half_width))


def trunk_weight_mask(data: MeshData) -> np.ndarray:
    """How much each vertex belongs to the trunk (0-1): its trunk bones' weight less its arms'."""
    return np.clip(data.trunk_weight, 0.0, 1.0) * np.clip(1.0 - 2.0 * data.arm_weight, 0.0, 1.0)


def trunk_frame(verts: np.ndarray, data: MeshData) -> TrunkFrame:
    trunk = (data.trunk_weight > 0.5) & (data.arm_weight < 0.1)
    y, z, x = verts[trunk, 1], verts[trunk, 2], np.abs(verts[trunk, 0])
    crotch, top = float(y.min()), float(y.max())
    edges = np.arange(crotch, top + SLICE_MM, SLICE_MM)
    which = np.clip(np.digitize(y, edges) - 1, 0, len(edges) - 2)
    centres, fronts, backs, halves = [], [], [], []
    for k in range(len(edges) - 1):
        sel = which == k
        if sel.sum() < 4:
            continue
        centres.append(0.5 * (edges[k] + edges[k + 1]))
        fronts.append(z[sel].max())
        backs.append(z[sel].min())
        halves.append(x[sel].max())
    return TrunkFrame(crotch, top, np.array(centres), np.array(fronts), np.array(backs), np.array(halves))


def breathing_modes(verts: np.ndarray, data: MeshData, body: MeshBody) -> np.ndarray:
    """(2, V, 3): each mode's vertex displacement (mm) at unit amplitude (1 mm forward where it is strongest)."""
    frame = trunk_frame(verts, data)
    y = verts[:, 1]
    front, back, half = frame.at(y)
    depth = np.maximum(front - back, 1.0)
    towards_front = np.clip((verts[:, 2] - back) / depth, 0.0, 1.0)
    across = np.clip(verts[:, 0] / np.maximum(half, 1.0), -1.0, 1.0)
    weight = trunk_weight_mask(data)
    share = frame.share(y)
    rib = _profile(share, RIB_CAGE_PROFILE) * weight
    abd = _profile(share, ABDOMEN_PROFILE) * weight
    modes = np.zeros((2,) + verts.shape)
    modes[0, :, 2] = rib * towards_front
    modes[0, :, 1] = PUMP_LIFT * rib * towards_front
    modes[0, :, 0] = body.bucket_share * rib * across
    front_half = np.clip(2.0 * towards_front - 1.0, 0.0, 1.0)
    modes[1, :, 2] = abd * front_half
    modes[1, :, 0] = ABDOMEN_SIDEWAYS * abd * across * np.sqrt(front_half)
    return modes


@dataclass(frozen=True)
class VolumePolynomial:
    """The mesh's volume change (mm^3) as a cubic of the two amplitudes."""

    coefficients: np.ndarray  # along _MONOMIALS

    @classmethod
    def fit(cls, verts: np.ndarray, tris: np.ndarray, modes: np.ndarray, span: float = 40.0) -> "VolumePolynomial":
        rest = closed_volume_mm3(verts, tris)
        grid = np.linspace(-span, span, 5)
        samples = [(a, b) for a in grid for b in grid]
        design = np.array([[a**i * b**j for i, j in _MONOMIALS] for a, b in samples])
        volumes = np.array([closed_volume_mm3(verts + a * modes[0] + b * modes[1], tris) - rest for a, b in samples])
        coefficients, *_ = np.linalg.lstsq(design, volumes, rcond=None)
        coefficients[0] = 0.0
        return cls(coefficients)

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return sum(c * a**i * b**j for c, (i, j) in zip(self.coefficients, _MONOMIALS))

    def gradient(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        da = sum(c * i * a ** max(i - 1, 0) * b**j for c, (i, j) in zip(self.coefficients, _MONOMIALS) if i)
        db = sum(c * j * a**i * b ** max(j - 1, 0) for c, (i, j) in zip(self.coefficients, _MONOMIALS) if j)
        return da, db

    @property
    def linear_mm3(self) -> np.ndarray:
        return np.array([self.coefficients[1], self.coefficients[2]])


def manoeuvre_of(t_s: np.ndarray, events: list[tuple[float, str]]) -> np.ndarray:
    """The manoeuvre under way at each time: 'vc' or 'forced' between its start and its end, else 'tidal'."""
    out = np.full(np.shape(t_s), "tidal", dtype=object)
    starts = [(t, label[: -len("-start")]) for t, label in events if label in ("vc-start", "forced-start")]
    ends = sorted(t for t, label in events if label == "maneuver-end")
    for start, kind in starts:
        end = next((e for e in ends if e > start), np.inf)
        out[(t_s >= start) & (t_s < end)] = kind
    return out


RAMP_S = 1.0  # the rib cage's share changes from one manoeuvre's to the next over this long
REST_SEARCH_S = 3.0  # how far before its start and after its end a manoeuvre's share reaches, to the rest volume


def at_rest(t_s: np.ndarray, lung_l: np.ndarray, events: list[tuple[float, str]]) -> list[tuple[float, str]]:
    """The manoeuvres' starts and ends moved, within REST_SEARCH_S, to where the lung volume is nearest its
    rest (the inspiration before a blow starts there; the recovery after it ends there): a share changed at
    TLC or RV would trade volume between rib cage and abdomen while the lung volume holds (a litre and more
    at a blow's start)."""
    lung = np.abs(np.asarray(lung_l, dtype=float))
    out = []
    for at, label in events:
        if label in ("vc-start", "forced-start"):
            near = (t_s >= at - REST_SEARCH_S) & (t_s <= at)
        elif label == "maneuver-end":
            near = (t_s >= at) & (t_s <= at + REST_SEARCH_S)
        else:
            near = np.zeros(len(t_s), dtype=bool)
        out.append((float(t_s[near][np.argmin(lung[near])]) if near.any() else at, label))
    return out


def chest_share_curve(t_s: np.ndarray, events: list[tuple[float, str]], shares: dict[str, float]) -> np.ndarray:
    """The rib cage's share of the volume at each time: the manoeuvre's, blended over RAMP_S."""
    kinds = manoeuvre_of(t_s, events)
    raw = np.array([shares[k] for k in kinds], dtype=float)
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1.0
    width = max(int(round(RAMP_S / dt)), 1)
    kernel = np.hanning(width + 2)[1:-1]
    padded = np.pad(raw, (width, width), mode="edge")
    return np.convolve(padded, kernel / kernel.sum(), mode="same")[width:-width]


def amplitudes_for(polynomial: VolumePolynomial, rib_mm3: np.ndarray, abdomen_mm3: np.ndarray,
                   iterations: int = 8) -> np.ndarray:
    """(N, 2) amplitudes whose exact volume is rib + abdomen, in the compartments' proportion
    (each compartment's linear volume scaled by one factor, found by Newton's method)."""
    linear = polynomial.linear_mm3
    a, b = rib_mm3 / linear[0], abdomen_mm3 / linear[1]
    target = rib_mm3 + abdomen_mm3
    scale = np.ones_like(target)
    for _ in range(iterations):
        value = polynomial(scale * a, scale * b) - target
        da, db = polynomial.gradient(scale * a, scale * b)
        slope = da * a + db * b
        step = np.divide(value, slope, out=np.zeros_like(value), where=np.abs(slope) > 1e-9)
        scale = scale - step
    return np.stack([scale * a, scale * b], axis=-1)


def body_triangles(data: MeshData) -> np.ndarray:
    return triangles(data.quads)
