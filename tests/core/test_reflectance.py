"""The sheen estimate (core/reconstruction/reflectance.py) on a surface whose shading is written in
closed form: the thesis rig's four LEDs on an ellipsoidal trunk 2000 mm away, Lambertian with and
without a Blinn-Phong lobe, with one LED brighter than its calibration says."""

from __future__ import annotations

import numpy as np

from core.reconstruction.reflectance import null_vectors, sheen_relative_to_albedo
from core.rig import thesis_rig


def _trunk(head, distance_mm: float = 2000.0):
    """Points (H, W, 3) and normals of an ellipsoid cap (semi-axes 170 x 300 mm across, 120 mm deep)
    seen by `head`, and the mask of the pixels on it."""
    u = (np.arange(head.width) - head.cx) / head.fx
    v = (np.arange(head.height) - head.cy) / head.fy
    x_mm, y_mm = np.meshgrid(u * distance_mm, v * distance_mm)  # near enough for a test surface
    a, b, c = 170.0, 300.0, 120.0
    inside = (x_mm / a) ** 2 + (y_mm / b) ** 2 < 0.9
    bulge = c * np.sqrt(np.clip(1 - (x_mm / a) ** 2 - (y_mm / b) ** 2, 0.0, None))
    z = distance_mm - bulge
    points = np.stack([x_mm, y_mm, z], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        normal = np.stack([x_mm / a ** 2, y_mm / b ** 2, -bulge / c ** 2], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return points, normal, inside


def _signal(head, points, normal, albedo: float, sheen: float, gains=(1.0, 1.0, 1.0, 1.0), exponent: float = 30.0):
    """Each light's signal: E_k / r^2 (albedo n.l + sheen (n.h)^exponent), times a gain the calibration
    does not know."""
    out = []
    view = -points / np.linalg.norm(points, axis=-1, keepdims=True)
    for k, position in enumerate(head.light_positions_mm):
        towards = position - points
        r2 = np.sum(towards ** 2, axis=-1)
        light = towards / np.sqrt(r2)[..., None]
        half = light + view
        half /= np.linalg.norm(half, axis=-1, keepdims=True)
        shading = albedo * np.clip(np.sum(normal * light, axis=-1), 0.0, None)
        lobe = sheen * np.clip(np.sum(normal * half, axis=-1), 0.0, None) ** exponent
        out.append(gains[k] * head.light_intensity[k] / r2 * (shading + lobe))
    return np.nan_to_num(np.stack(out))


def _estimate(head, signal, points, mask) -> float:
    return sheen_relative_to_albedo(signal, points, mask, head.light_positions_mm, head.light_intensity,
                                    np.zeros((4, 3)), np.zeros(4), 0.0)


def test_null_vectors_are_orthogonal_to_the_four_light_directions():
    directions = np.random.default_rng(0).normal(size=(50, 4, 3))
    w = null_vectors(directions)
    assert np.allclose(np.einsum("nk,nki->ni", w, directions), 0.0, atol=1e-12)
    assert np.allclose(np.linalg.norm(w, axis=1), 1.0)


def test_matte_skin_reads_no_sheen_even_with_a_light_brighter_than_calibrated():
    head = thesis_rig(0.25).heads["front"]
    points, normal, mask = _trunk(head)
    matte = _estimate(head, _signal(head, points, normal, 0.45, 0.0), points, mask)
    drifted = _estimate(head, _signal(head, points, normal, 0.45, 0.0, gains=(1.03, 1.0, 0.98, 1.0)), points, mask)
    assert abs(matte) < 1e-6 and abs(drifted) < 1e-3, (matte, drifted)


def test_a_sheen_reads_in_proportion_to_itself_over_the_albedo():
    """A sheen of 0.02 and 0.05 of white over skin of albedo 0.45, and 0.05 over dark skin (0.1): the
    estimate grows with the sheen over the albedo and passes MAX_SHEEN for each (it is fitted with a
    broader lobe than the skin's, and with normals the sheen has bent, so it is not spec / rho itself)."""
    from core.pipeline.quality import MAX_SHEEN

    head = thesis_rig(0.25).heads["front"]
    points, normal, mask = _trunk(head)
    estimates = [_estimate(head, _signal(head, points, normal, albedo, sheen), points, mask)
                 for albedo, sheen in ((0.45, 0.02), (0.45, 0.05), (0.1, 0.05))]
    assert MAX_SHEEN < estimates[0] < estimates[1] < estimates[2], estimates
    drifted = _estimate(head, _signal(head, points, normal, 0.45, 0.02, gains=(1.03, 1.0, 0.98, 1.0)), points, mask)
    assert abs(drifted - estimates[0]) < 0.2 * estimates[0], (drifted, estimates[0])


def test_too_few_frontal_pixels_give_no_estimate():
    head = thesis_rig(0.25).heads["front"]
    points, normal, mask = _trunk(head)
    few = np.zeros_like(mask)
    few[np.nonzero(mask)[0][:20], np.nonzero(mask)[1][:20]] = True
    assert np.isnan(_estimate(head, _signal(head, points, normal, 0.45, 0.05), points, few))


def test_the_redundancy_reads_each_light_s_output_against_its_calibration():
    """Lights 1-3 % brighter or dimmer than calibrated: each read as its output over the last light's (the
    four's common factor is the albedo's), on matte skin within 0.06 %; on glossy skin (a lobe of exponent 30
    where the fit's is 10) within 0.6 %, and within 0.2 % read again with the first reading's outputs."""
    from core.reconstruction.reflectance import redundancy_fit

    head = thesis_rig(0.25).heads["front"]
    points, normal, mask = _trunk(head)
    gains = np.array([1.02, 0.99, 1.03, 1.01])
    for sheen, first, second in ((0.0, 0.0006, 0.0001), (0.05, 0.006, 0.002)):
        signal = _signal(head, points, normal, 0.6, sheen, gains)
        fit = redundancy_fit(signal, points, mask, head.light_positions_mm, head.light_intensity, np.zeros((4, 3)),
                             np.zeros(4), 0.0)
        np.testing.assert_allclose(fit.light_gain, gains / gains[3], atol=first)
        again = redundancy_fit(signal, points, mask, head.light_positions_mm, head.light_intensity * fit.light_gain,
                               np.zeros((4, 3)), np.zeros(4), 0.0)
        np.testing.assert_allclose(fit.light_gain * again.light_gain, gains / gains[3], atol=second)
