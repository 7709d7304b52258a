"""Normal integration: analytic surfaces integrate back to themselves; real data (DiLiGenT bear)."""

from __future__ import annotations

import numpy as np
import pytest

from core.io.diligent import load_real_surface, mean_abs_depth_error_mm
from core.reconstruction.integrate import depth_from_normals, integrate_dct, integrate_masked, log_depth_gradients


def _normals_of(depth, fx, fy, cx, cy):
    """Unit normals (towards the camera) of a depth map, from the 3D points' tangents."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    points = np.stack([(u - cx) / fx * depth, (v - cy) / fy * depth, depth], -1)
    n = np.cross(np.gradient(points, axis=1), np.gradient(points, axis=0))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.where(n[..., 2:3] > 0, -n, n)


def test_gradients_of_an_analytic_surface_integrate_back():
    h, w = 120, 160
    y, x = np.mgrid[0:h, 0:w].astype(float)
    z = 3.0 * np.sin(x / 17.0) + 2.0 * np.cos(y / 11.0) + 0.01 * (x - 80) ** 2 / 10
    gu = 3.0 / 17.0 * np.cos(x / 17.0) + 0.002 * (x - 80)
    gv = -2.0 / 11.0 * np.sin(y / 11.0)
    mask = (x - 80) ** 2 / 70**2 + (y - 60) ** 2 / 50**2 < 1
    for solver in (lambda: integrate_masked(gu, gv, mask), lambda: integrate_dct(gu, gv)):
        got = solver()
        err = (got - z)[mask]
        assert np.abs(err - err.mean()).max() < 0.05


def _direct_least_squares(gu, gv, mask):
    """The masked least-squares surface by a sparse direct solve: one equation per pixel edge inside
    the mask, z[next] - z[this] = mean of the two pixels' gradients."""
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    index = -np.ones(mask.shape, dtype=np.int64)
    index[mask] = np.arange(int(mask.sum()))
    to, fro, rhs = [], [], []
    for g, both, ahead, behind in (
            (gu, mask[:, :-1] & mask[:, 1:], np.s_[:, 1:], np.s_[:, :-1]),
            (gv, mask[:-1, :] & mask[1:, :], np.s_[1:, :], np.s_[:-1, :])):
        to.append(index[ahead][both])
        fro.append(index[behind][both])
        rhs.append(((g[ahead] + g[behind]) / 2)[both])
    to, fro, rhs = np.concatenate(to), np.concatenate(fro), np.concatenate(rhs)
    k = np.arange(len(rhs))
    a_matrix = sparse.csr_matrix((np.r_[np.ones(len(k)), -np.ones(len(k))], (np.r_[k, k], np.r_[to, fro])),
                                 shape=(len(k), int(mask.sum())))
    z = spsolve((a_matrix.T @ a_matrix + 1e-9 * sparse.identity(int(mask.sum()))).tocsc(), a_matrix.T @ rhs)
    out = np.full(mask.shape, np.nan)
    out[mask] = z - z.mean()
    return out


def test_the_masked_solver_is_the_least_squares_surface_of_noisy_gradients():
    rng = np.random.default_rng(3)
    h, w = 90, 130
    y, x = np.mgrid[0:h, 0:w].astype(float)
    mask = ((x - 60) ** 2 / 55**2 + (y - 45) ** 2 / 40**2 < 1) & ~((x - 70) ** 2 + (y - 40) ** 2 < 64)
    gu = 0.02 * (x - 60) + rng.normal(0, 0.05, (h, w))
    gv = np.sin(x / 9.0) + rng.normal(0, 0.05, (h, w))  # not integrable: no surface has these gradients
    got = integrate_masked(gu, gv, mask, tolerance=1e-8, robust_iterations=0)
    expected = _direct_least_squares(gu, gv, mask)
    assert np.isnan(got[~mask]).all()
    assert np.ptp(expected[mask]) > 10
    assert np.abs(got[mask] - expected[mask]).max() < 1e-4


def test_a_depth_step_inside_the_mask_stays_where_it_is():
    """A surface that winds up 20 units around a point inside the mask, with its step on the
    shortest cut from there to the mask's edge (a chin over a neck, a fold that ends). The
    gradients are the surface's own on both sides of the cut and say nothing of the step. Plain
    least squares smears it over the whole surface; the robust solve keeps the surface true away
    from the cut's end. (Where the step runs is for the normals to show: on a longer cut than the
    shortest, no integrator can tell.)"""
    h, w = 90, 120
    y, x = np.mgrid[0:h, 0:w].astype(float)
    x0, y0 = 25.0, 44.5
    r2 = (x - x0) ** 2 + (y - y0) ** 2
    mask = ((x - 60) ** 2 / 55**2 + (y - 45) ** 2 / 42**2 < 1) & (r2 > 9)
    turns = 20.0 / (2 * np.pi)
    z = 0.01 * (x - 60) ** 2 + 0.3 * y + turns * np.arctan2(y - y0, x - x0)  # the step along x < x0
    gu = 0.02 * (x - 60) - turns * (y - y0) / r2
    gv = 0.3 + turns * (x - x0) / r2
    far = mask & (r2 > 10**2) & (np.abs(y - y0) > 3)

    def mean_error(got):
        err = (got - z)[far]
        return float(np.abs(err - np.median(err)).mean())

    plain = mean_error(integrate_masked(gu, gv, mask, tolerance=1e-8, robust_iterations=0))
    robust = mean_error(integrate_masked(gu, gv, mask, tolerance=1e-8))
    assert plain > 1.0
    assert robust < 0.1


def test_the_masked_solver_keeps_a_relief_the_dct_path_flattens():
    """A dome whose rim is not level (a torso's outline is deeper at the shoulders than at the
    flanks): the DCT path's zero gradients outside the mask pull the rim level and flatten the
    dome; the masked solver keeps it."""
    h, w = 100, 140
    y, x = np.mgrid[0:h, 0:w].astype(float)
    r2 = (x - 70) ** 2 / 60**2 + (y - 50) ** 2 / 42**2
    mask = r2 < 1
    z = 30.0 * np.sqrt(np.clip(1 - r2, 0, None)) + 0.2 * (y - 50)
    gv, gu = np.gradient(z)
    inner = mask & (r2 < 0.9)  # np.gradient is one-sided across the edge

    def relief(got):
        return np.polyfit(z[inner], got[inner], 1)[0]

    assert abs(relief(integrate_masked(gu, gv, mask)) - 1) < 0.01
    assert relief(np.where(mask, integrate_dct(np.where(mask, gu, 0), np.where(mask, gv, 0)), np.nan)) < 0.97


def test_perspective_depth_of_a_sphere_is_metric():
    fx = fy = 800.0
    cx, cy = 79.5, 59.5
    h, w = 120, 160
    centre, radius = np.array([20.0, -10.0, 1000.0]), 120.0
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u, float)], -1)
    dc = d @ centre
    disc = dc**2 - np.sum(d * d, -1) * (centre @ centre - radius**2)
    t = (dc - np.sqrt(np.clip(disc, 0, None))) / np.sum(d * d, -1)
    mask = disc > 0.05 * disc.max()
    depth = np.where(mask, t, np.nan)
    normals = (d * t[..., None] - centre) / radius
    got = depth_from_normals(normals, mask, fx, fy, cx, cy, float(np.nanmedian(depth)), "masked")
    assert np.nanmax(np.abs(got - depth)) < 0.5  # mm, on a sphere 1 m away


@pytest.fixture(scope="module")
def bear(shared_data):
    surface = load_real_surface(shared_data / "diligent-integration" / "bear")
    return surface.normals, surface.mask, surface.camera_matrix, surface.depth_mm


def _mean_abs_error(got, truth, mask):
    """At most 0.1 % of the mask's pixels may be left out (normals past MAX_VIEW_ANGLE_DEG at the
    silhouette)."""
    error, given = mean_abs_depth_error_mm(got, truth, mask)
    assert given >= 0.999
    return error


def test_real_normals_integrate_within_a_tenth_of_a_mm(bear):
    normals, mask, k, truth = bear
    got = depth_from_normals(normals, mask, k[0, 0], k[1, 1], k[0, 2], k[1, 2], float(np.median(truth[mask])))
    assert _mean_abs_error(got, truth, mask) <= 0.1  # 0.058 mm; 0.48 mm without the robust reweighting
    fast = depth_from_normals(normals, mask, k[0, 0], k[1, 1], k[0, 2], k[1, 2], float(np.median(truth[mask])),
                              "dct")
    assert _mean_abs_error(fast, truth, mask) <= 3.6  # the plain DCT reference is 3.27 mm


def test_the_normal_convention_matches_the_depth(bear):
    normals, mask, k, truth = bear
    from_depth = _normals_of(truth, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    inner = mask & np.isfinite(from_depth).all(-1)
    angle = np.degrees(np.arccos(np.clip(np.sum(normals * from_depth, -1), -1, 1)))
    assert np.median(angle[inner]) < 2.0
    gu, gv = log_depth_gradients(normals, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    assert np.isfinite(gu[inner]).mean() > 0.999 and np.isfinite(gv[inner]).mean() > 0.999


def test_normals_at_grazing_view_are_not_integrated():
    """A normal nearly perpendicular to its viewing ray (a silhouette pixel that is partly
    background) would give a gradient of any size; it is left out, not integrated."""
    fx = fy = 800.0
    normals = np.tile(np.array([0.0, 0.0, -1.0]), (3, 4, 1))
    tilt = np.radians(88.0)
    normals[1, 1] = [np.sin(tilt), 0.0, -np.cos(tilt)]
    gu, gv = log_depth_gradients(normals, fx, fy, 1.5, 1.0)
    assert np.isnan(gu[1, 1]) and np.isnan(gv[1, 1])
    assert np.isfinite(np.delete(gu.ravel(), 5)).all()
