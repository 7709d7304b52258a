"""A sheen on the skin, measured from the four lights' one redundant value per pixel.

Four lights and three unknowns (the albedo times the normal, eq. 3.4) leave one value per pixel
that the Lambertian model fixes. With b_k each light's signal over its irradiance at the pixel
(I_k r_k^2 / (E_k A_k), the rows near_light_normals solves) and w the unit vector orthogonal to
the pixel's four light directions (w . L = 0), Lambertian skin gives w . b = 0 up to noise.

- A sheen adds spec (n . h_k)^e to each b_k (Blinn-Phong, h_k the half vector between light k
  and the camera); its projection on w is not zero wherever the normal leans off the lights'
  axes, a saddle over the trunk.
- A light brighter or dimmer than the calibration says (its drift, a calibration's intensity)
  adds delta_k b_k, whose projection is sum_k delta_k w_k (n . l_k): three more columns, since the
  four sum to zero.

Fitted together over the trunk's frontal pixels, what is left to the lobe measures the sheen's
weight relative to the albedo (spec / rho), the quantity that bends the normals
(docs/history/reconstruction-log.md, "Glossy skin"; docs/history/volume-log.md, "A sheen, measured"). It is spec / rho
itself only where the skin's lobe has SHEEN_EXPONENT and the normals are unbent; the skin's exponent
is not known, so the estimate was measured against sheens rendered with exponents 5-60 (same section).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# the Blinn-Phong exponent of the lobe fitted, broader than the simulator's skin (30): skin rendered with
# 5, 10, 30 and 60 all read far above matte (docs/history/volume-log.md, "A sheen, measured")
SHEEN_EXPONENT = 10.0
# the pixels a map's estimate takes: a regular subsample of those lit by all four lights (the fit has 4 unknowns)
SHEEN_PIXELS = 4000
# frontal: the normal within this of the view ray (the lobe is negligible beyond; the rim is noisy)
FRONTAL_DEG = 45.0


def null_vectors(directions: np.ndarray) -> np.ndarray:
    """(n, 4) unit vectors w with w . directions[i] = 0, from (n, 4, 3) light directions: the signed
    3 x 3 minors (the cofactors of a 4 x 4 matrix whose last column would be free)."""
    minors = []
    for k in range(4):
        rows = [r for r in range(4) if r != k]
        minors.append((-1) ** k * np.linalg.det(directions[:, rows, :]))
    w = np.stack(minors, axis=1)
    return w / np.linalg.norm(w, axis=1, keepdims=True)


@dataclass(frozen=True)
class RedundancyFit:
    """What the four lights' redundant value says of one cycle."""
    sheen: float  # the sheen's weight over the albedo (spec / rho)
    light_gain: np.ndarray  # (4,) each light's output over the one its intensity says, the last light's taken as 1

    @classmethod
    def none(cls) -> "RedundancyFit":
        return cls(float("nan"), np.full(4, np.nan))


def sheen_relative_to_albedo(signal: np.ndarray, points_mm: np.ndarray, pixels: np.ndarray,
                             light_positions_mm: np.ndarray, light_intensity: np.ndarray,
                             light_axis: np.ndarray, light_mu: np.ndarray, min_signal: float,
                             saturated: np.ndarray | None = None) -> float:
    """The sheen's weight over the albedo (spec / rho) on one cycle (redundancy_fit)."""
    return redundancy_fit(signal, points_mm, pixels, light_positions_mm, light_intensity, light_axis, light_mu,
                          min_signal, saturated).sheen


def redundancy_fit(signal: np.ndarray, points_mm: np.ndarray, pixels: np.ndarray,
                   light_positions_mm: np.ndarray, light_intensity: np.ndarray,
                   light_axis: np.ndarray, light_mu: np.ndarray, min_signal: float,
                   saturated: np.ndarray | None = None) -> RedundancyFit:
    """The sheen's weight over the albedo (spec / rho) and the lights' outputs against their
    intensities (1 + delta_k; the four's common factor is the albedo's, so the last light is the
    reference) on one cycle: signal (4, H, W) lit minus dark, points_mm (H, W, 3) the map's surface
    in the head's frame, pixels (H, W) the map's valid ones. NaN where fewer than 50 frontal pixels
    have all four lights."""
    use = pixels & np.isfinite(points_mm[..., 2]) & (signal >= min_signal).all(axis=0)
    if saturated is not None:
        use &= ~saturated.any(axis=0)
    index = np.flatnonzero(use)
    if len(index) > SHEEN_PIXELS:
        index = index[np.linspace(0, len(index) - 1, SHEEN_PIXELS).astype(np.int64)]
    p = points_mm.reshape(-1, 3)[index]
    values = signal.reshape(4, -1)[:, index].T  # (n, 4)
    towards = np.asarray(light_positions_mm, float)[None] - p[:, None, :]
    r2 = np.sum(towards ** 2, axis=-1)
    l = towards / np.sqrt(r2)[..., None]  # (n, 4, 3)
    irradiance = np.asarray(light_intensity, float)[None] / r2
    mu = np.asarray(light_mu, float)
    if np.any(mu > 0):
        cos_axis = -np.einsum("nki,ki->nk", l, np.asarray(light_axis, float))
        irradiance = irradiance * np.where(mu > 0, np.clip(cos_axis, 0.0, None) ** mu, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        b = values / irradiance
    g = np.linalg.solve(np.einsum("nki,nkj->nij", l, l), np.einsum("nki,nk->ni", l, b)[..., None])[..., 0]
    albedo = np.linalg.norm(g, axis=1)
    normal = g / albedo[:, None]
    view = -p / np.linalg.norm(p, axis=1, keepdims=True)
    frontal = np.einsum("ni,ni->n", normal, view) > np.cos(np.radians(FRONTAL_DEG))
    keep = frontal & np.isfinite(b).all(axis=1) & (albedo > 0)
    if keep.sum() < 50:
        return RedundancyFit.none()
    l, b, albedo, normal, view = l[keep], b[keep], albedo[keep], normal[keep], view[keep]
    w = null_vectors(l)
    half = l + view[:, None, :]
    half /= np.linalg.norm(half, axis=-1, keepdims=True)
    lobe = np.clip(np.einsum("nki,ni->nk", half, normal), 0.0, None) ** SHEEN_EXPONENT
    # w . b / rho = sum_k delta_k w_k (n . l_k) + (spec / rho) w . lobe
    lambertian = w * np.einsum("nki,ni->nk", l, normal)
    design = np.column_stack([lambertian[:, :3], np.einsum("nk,nk->n", w, lobe)])
    target = np.einsum("nk,nk->n", w, b) / albedo
    coefficients, *_ = np.linalg.lstsq(design, target, rcond=None)
    return RedundancyFit(float(coefficients[-1]), np.r_[1.0 + coefficients[:3], 1.0])
