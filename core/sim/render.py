"""The renderer: the image formation model of ARCHITECTURE.md, compiled with numba.

    I_k = rho * E_k * A_k * max(0, n . l_k) / r_k**2 (+ specular) + ambient + noise

Rays are cast through every pixel centre (OpenCV pinhole and, when the head has them, its radial
and tangential distortion, inverted per pixel) and met with the
surface by Newton's method on a height field, warm-started from the previous frame (and, where
it fails on a flank the ray nearly grazes, by marching from the front), or analytically for
spheres. Noise: shot noise (Gaussian with the Poisson variance) and read
noise (after the lens' vignetting), drawn from a counter-based hash of (seed, frame, pixel) so that frames are the same
whatever the number of threads (the normal deviate is the Irwin-Hall sum of four uniforms:
cheap, with tails cut at 3.46 sigma); then full-well saturation and quantisation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numba import njit, prange

from core.rig import Head

_FAST = {"nsz", "arcp", "contract", "afn", "reassoc"}  # no 'nnan': NaN marks "no surface"

# Packed light row: position (3), intensity, axis (3), mu
LIGHT_ROW = 8


@dataclass(frozen=True)
class CameraModel:
    """Sensor radiometry of the simulated camera."""

    full_well_e: float = 18000.0
    read_noise_e: float = 12.0
    white_level: float = 0.6  # fraction of full well: white Lambertian surface facing a light 2000 mm away
    ambient_level: float = 0.04  # fraction of full well added by room light on a white surface
    background_level: float = 0.01  # fraction of full well from the dark background
    reference_distance_mm: float = 2000.0
    noise: bool = True  # False: the exact expected signal, only quantised (for physics tests)

    @property
    def exposure_gain(self) -> float:
        return self.white_level * self.full_well_e * self.reference_distance_mm**2

    def binned(self, factor: float) -> "CameraModel":
        """The sensor read with factor x factor pixels summed (a resampled sensor of the same field
        of view): each output pixel collects factor^2 times the electrons and holds factor^2 full
        wells, with the read noise of factor^2 reads (digital binning); the grey levels stay those
        of one pixel, the noise relative to them falls by `factor`."""
        if factor <= 0:
            raise ValueError(f"binning factor must be positive, got {factor}")
        return replace(self, full_well_e=self.full_well_e * factor**2, read_noise_e=self.read_noise_e * factor)


def camera_rays(head: Head) -> tuple[np.ndarray, np.ndarray]:
    """Each pixel centre's ray (x/z, y/z), each (H, W): the lens' distortion inverted (OpenCV's model)."""
    u, v = head.pixel_rays()
    if np.any(head.dist_coeffs != 0):
        pixels = np.stack(np.meshgrid(np.arange(head.width, dtype=np.float64), np.arange(head.height, dtype=np.float64)),
                          -1).reshape(-1, 1, 2)
        xy = cv2.undistortPoints(pixels, head.camera_matrix, head.dist_coeffs,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12))
        u = np.ascontiguousarray(xy[:, 0, 0].reshape(head.shape))
        v = np.ascontiguousarray(xy[:, 0, 1].reshape(head.shape))
    return u, v


def pack_lights(head: Head) -> np.ndarray:
    rows = np.zeros((4, LIGHT_ROW))
    rows[:, 0:3] = head.light_positions_mm
    rows[:, 3] = head.light_intensity
    if head.light_axis is not None and head.light_mu is not None:
        rows[:, 4:7] = head.light_axis
        rows[:, 7] = head.light_mu
    return rows


@njit(inline="always")
def _splitmix64(z):
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(inline="always")
def _gaussian(key):
    """Unit normal deviate approximated by the sum of four 16-bit uniforms (Irwin-Hall, bounded at 3.46 sigma)."""
    z = _splitmix64(key)
    m = np.uint64(0xFFFF)
    total = (np.float64(z & m) + np.float64((z >> np.uint64(16)) & m) + np.float64((z >> np.uint64(32)) & m)
             + np.float64(z >> np.uint64(48)))
    return (total / 65536.0 - 2.0) * 1.7320508075688772


@njit(inline="always", fastmath=_FAST)
def _radiance(px, py, pz, nx, ny, nz, albedo, light, spec, shin):
    """Irradiance-weighted reflectance of one light at one point, before the exposure gain."""
    dx = light[0] - px
    dy = light[1] - py
    dz = light[2] - pz
    r2 = dx * dx + dy * dy + dz * dz
    r = np.sqrt(r2)
    lx = dx / r
    ly = dy / r
    lz = dz / r
    cos_theta = nx * lx + ny * ly + nz * lz
    if cos_theta <= 0.0 or light[3] <= 0.0:
        return 0.0
    aniso = 1.0
    if light[7] > 0.0:
        c = -(lx * light[4] + ly * light[5] + lz * light[6])
        aniso = c ** light[7] if c > 0.0 else 0.0
    value = albedo * cos_theta
    if spec > 0.0:
        pn = np.sqrt(px * px + py * py + pz * pz)
        hx = lx - px / pn
        hy = ly - py / pn
        hz = lz - pz / pn
        hn = np.sqrt(hx * hx + hy * hy + hz * hz)
        ndoth = (nx * hx + ny * hy + nz * hz) / hn
        if ndoth > 0.0:
            value += spec * ndoth**shin
    return light[3] * aniso * value / r2


@njit(inline="always")
def _digitise(signal_e, read_e, dn_per_e, max_dn, key):
    e = signal_e
    if read_e >= 0.0:
        e += np.sqrt(signal_e + read_e * read_e) * _gaussian(key)
    dn = np.floor(e * dn_per_e + 0.5)
    if dn < 0.0:
        return 0.0
    if dn > max_dn:
        return max_dn
    return dn


# The trunk's sideways stretch, one row per grid row (HeightFieldScene.stretch_table): the stretch e
# of the side x > 0 and of the side x < 0, the trunk's half width, and the row derivatives (per mm) of
# e and of e * half width on each side. An empty table: no stretch.
ST_E_POS, ST_E_NEG, ST_HALF_WIDTH, ST_DE_POS, ST_DE_NEG, ST_DEW_POS, ST_DEW_NEG = range(7)
STRETCH_COLUMNS = 7


@njit(inline="always", fastmath=_FAST)
def _unstretched(stretch, gy0, inv_step, xb, yb):
    """The body point the stretch x -> x (1 + e) (within the trunk's half width; beyond it, the arms
    moved out with the side, unstretched) brought to xb, and dx/dX, dx/dy there."""
    if stretch.shape[0] == 0:
        return xb, 1.0, 0.0
    row = int(np.floor((yb - gy0) * inv_step + 0.5))
    if row < 0 or row >= stretch.shape[0]:
        return xb, 1.0, 0.0
    half_width = stretch[row, ST_HALF_WIDTH]
    if xb >= 0.0:
        e, de, dew, sign = stretch[row, ST_E_POS], stretch[row, ST_DE_POS], stretch[row, ST_DEW_POS], 1.0
    else:
        e, de, dew, sign = stretch[row, ST_E_NEG], stretch[row, ST_DE_NEG], stretch[row, ST_DEW_NEG], -1.0
    if abs(xb) <= half_width * (1.0 + e):
        x = xb / (1.0 + e)
        return x, 1.0 / (1.0 + e), -x * de / (1.0 + e)
    return xb - sign * e * half_width, 1.0, -sign * dew


def _surface_at_point(fields, amps, gx0, gy0, inv_step, xb, yb, stretch):
    """Height, gradient (x, y) and albedo of the breathing surface at body point (xb, yb), bilinear
    on the grid, the trunk stretched sideways by `stretch`; the height is NaN off the object."""
    xb, dx_dX, dx_dy = _unstretched(stretch, gy0, inv_step, xb, yb)
    fx = (xb - gx0) * inv_step
    fy = (yb - gy0) * inv_step
    jj = int(np.floor(fx))
    ii = int(np.floor(fy))
    if jj < 0 or ii < 0 or jj >= fields.shape[1] - 1 or ii >= fields.shape[0] - 1:
        return np.nan, 0.0, 0.0, 0.0
    tx = fx - jj
    ty = fy - ii
    w00 = (1 - tx) * (1 - ty)
    w01 = tx * (1 - ty)
    w10 = (1 - tx) * ty
    w11 = tx * ty
    hh = w00 * fields[ii, jj, 0] + w01 * fields[ii, jj + 1, 0] + w10 * fields[ii + 1, jj, 0] + w11 * fields[ii + 1, jj + 1, 0]
    if not np.isfinite(hh):
        return np.nan, 0.0, 0.0, 0.0
    gx = w00 * fields[ii, jj, 1] + w01 * fields[ii, jj + 1, 1] + w10 * fields[ii + 1, jj, 1] + w11 * fields[ii + 1, jj + 1, 1]
    gy = w00 * fields[ii, jj, 2] + w01 * fields[ii, jj + 1, 2] + w10 * fields[ii + 1, jj, 2] + w11 * fields[ii + 1, jj + 1, 2]
    alb = w00 * fields[ii, jj, 3] + w01 * fields[ii, jj + 1, 3] + w10 * fields[ii + 1, jj, 3] + w11 * fields[ii + 1, jj + 1, 3]
    for c in range(amps.shape[0]):
        a = amps[c]
        if a != 0.0:
            k = 4 + 3 * c
            hh += a * (w00 * fields[ii, jj, k] + w01 * fields[ii, jj + 1, k]
                       + w10 * fields[ii + 1, jj, k] + w11 * fields[ii + 1, jj + 1, k])
            gx += a * (w00 * fields[ii, jj, k + 1] + w01 * fields[ii, jj + 1, k + 1]
                       + w10 * fields[ii + 1, jj, k + 1] + w11 * fields[ii + 1, jj + 1, k + 1])
            gy += a * (w00 * fields[ii, jj, k + 2] + w01 * fields[ii, jj + 1, k + 2]
                       + w10 * fields[ii + 1, jj, k + 2] + w11 * fields[ii + 1, jj + 1, k + 2])
    return hh, gx * dx_dX, gy + gx * dx_dy, alb


# The Newton step, every pixel of every frame, takes the surface inlined (numba's IR inlining: with every
# helper called instead, the render took 40 % longer); the march and the second look after it, a few pixels
# at a silhouette, take it called. With the digitisation inlined once a pixel, not twice, that cut
# render_height_field's first compilation from 21 s to 10 s and _first_hit's from 2.8 to 1.5 s (2026-12-02,
# an idle machine; render_height_field had the surface inlined three times, _first_hit four)
_surface_at = njit(inline="always", fastmath=_FAST)(_surface_at_point)
_surface_at_called = njit(fastmath=_FAST, cache=True)(_surface_at_point)


@njit(parallel=True, fastmath=_FAST, nogil=True, cache=True)
def breathing_surface(fields, amps):
    """The height field at one instant: its rest height, gradient and albedo plus each breathing
    mode's height and gradient times its amplitude, on the grid (H, W, 4). Interpolating this once a
    frame is what _surface_at does per ray with all the modes, since both are linear. Summed in
    float64, kept in the stored fields' float32 (to 2e-5 mm at 300 mm): render_height_field and
    _first_hit then take one type of field whether the modes are summed here or per ray, and compile
    once, not twice (the live view's first start: 17 s a signature for render_height_field)."""
    rows, cols = fields.shape[0], fields.shape[1]
    out = np.empty((rows, cols, 4), dtype=fields.dtype)
    for i in prange(rows):
        for j in range(cols):
            hh = fields[i, j, 0]
            gx = fields[i, j, 1]
            gy = fields[i, j, 2]
            for c in range(amps.shape[0]):
                a = amps[c]
                if a == 0.0:
                    continue
                k = 4 + 3 * c
                hh += a * fields[i, j, k]
                gx += a * fields[i, j, k + 1]
                gy += a * fields[i, j, k + 2]
            out[i, j, 0] = hh
            out[i, j, 1] = gx
            out[i, j, 2] = gy
            out[i, j, 3] = fields[i, j, 3]
    return out


# The march that backs up Newton's method: the surface comes towards a ray at most 1 + slope * ray slope
# mm per mm of depth (grid slopes are cut at 80 degrees, build_height_field; rays stay within 15
# degrees of the axis), so steps of a third of the gap to the surface cannot pass through it; then
# 1 mm steps near it, and bisection to 1 mm / 2**14.
_MARCH_STEP_MM = 1.0
_MARCH_GAP_FRACTION = 1.0 / 3.0
_BISECTIONS = 14


@njit(fastmath=_FAST, nogil=True, cache=True)
def _first_hit(fields, amps, gx0, gy0, inv_step, uj, vi, sign_x, sx, sy, z0, z_front, stretch):
    """The nearest meeting of the ray with the surface, marched from depth z_front (in front of the
    whole surface) and bisected: (hit, depth). Newton's method fails on a flank the ray nearly
    grazes; the silhouette is where the ray is tangent to the surface, not where Newton's method,
    started from the mid-plane, stops converging."""
    za = z_front
    hh, gx, gy, alb = _surface_at_called(fields, amps, gx0, gy0, inv_step, sign_x * za * uj - sx, za * vi - sy, stretch)
    if not np.isfinite(hh) or za - z0 + hh >= 0.0:
        return False, za
    gap = z0 - hh - za
    while True:
        zb = za + max(_MARCH_STEP_MM, _MARCH_GAP_FRACTION * gap)
        hh, gx, gy, alb = _surface_at_called(fields, amps, gx0, gy0, inv_step, sign_x * zb * uj - sx, zb * vi - sy, stretch)
        if not np.isfinite(hh):
            return False, zb
        if zb - z0 + hh >= 0.0:
            break
        za = zb
        gap = z0 - hh - za
    for _ in range(_BISECTIONS):
        zm = 0.5 * (za + zb)
        hh, gx, gy, alb = _surface_at_called(fields, amps, gx0, gy0, inv_step, sign_x * zm * uj - sx, zm * vi - sy, stretch)
        if not np.isfinite(hh):
            return False, zm
        if zm - z0 + hh >= 0.0:
            zb = zm
        else:
            za = zm
    return True, zb


@njit(parallel=True, fastmath=_FAST, nogil=True, cache=True)
def render_height_field(out, z_state, ray_u, ray_v, vignette, fields, gx0, gy0, step, amps, sign_x, sx, sy, z0, front_mm,
                        spec, shin, light, lit, gain, ambient_e, background_e, read_e, dn_per_e, max_dn,
                        key0, want_maps, depth_out, normal_out, stretch):
    """Render one frame of a height field `Z = z0 - h(sign_x * X - sx, Y - sy)`; returns nothing.

    front_mm: no point of the surface stands out of the mid-plane by more. z_state holds each
    pixel's depth from the previous call (NaN: none) and is updated. stretch: the trunk's sideways
    stretch (ST_* rows, HeightFieldScene's stretch_table; empty: none).
    """
    height, width = out.shape
    inv_step = 1.0 / step
    for i in prange(height):
        for j in range(width):
            uj = ray_u[i, j]
            vi = ray_v[i, j]
            zc = z_state[i, j]
            if not np.isfinite(zc):
                zc = z0
            hit = False
            for _ in range(16):
                hh, gx, gy, alb = _surface_at(fields, amps, gx0, gy0, inv_step, sign_x * zc * uj - sx, zc * vi - sy,
                                              stretch)
                if not np.isfinite(hh):
                    break
                g = zc - z0 + hh
                dg = 1.0 + gx * sign_x * uj + gy * vi
                if dg < 0.05:
                    break
                dz = g / dg
                zc -= dz
                if abs(dz) < 1e-4:
                    hit = True
                    break
            if not hit:
                hit, zc = _first_hit(fields, amps, gx0, gy0, inv_step, uj, vi, sign_x, sx, sy, z0, z0 - front_mm,
                                     stretch)
                if hit:
                    hh, gx, gy, alb = _surface_at_called(fields, amps, gx0, gy0, inv_step, sign_x * zc * uj - sx,
                                                  zc * vi - sy, stretch)
            key = key0 + np.uint64(i * width + j)
            if hit:
                z_state[i, j] = zc
                nxx = -sign_x * gx
                nyy = -gy
                norm = np.sqrt(nxx * nxx + nyy * nyy + 1.0)
                nxx /= norm
                nyy /= norm
                nzz = -1.0 / norm
                px = zc * uj
                py = zc * vi
                signal = ambient_e * alb
                if lit:
                    signal += gain * _radiance(px, py, zc, nxx, nyy, nzz, alb, light, spec, shin)
                signal_e = signal * vignette[i, j]
                if want_maps:
                    depth_out[i, j] = zc
                    normal_out[i, j, 0] = nxx
                    normal_out[i, j, 1] = nyy
                    normal_out[i, j, 2] = nzz
            else:
                z_state[i, j] = np.nan
                signal_e = background_e * vignette[i, j]
                if want_maps:
                    depth_out[i, j] = np.nan
                    normal_out[i, j, 0] = np.nan
                    normal_out[i, j, 1] = np.nan
                    normal_out[i, j, 2] = np.nan
            out[i, j] = _digitise(signal_e, read_e, dn_per_e, max_dn, key)  # once: one inlined copy


@njit(inline="always", fastmath=_FAST)
def _sphere_hit(du, dv, spheres):
    """Nearest sphere hit along the ray (du, dv, 1): (index, t) or (-1, inf)."""
    best = -1
    best_t = np.inf
    dd = du * du + dv * dv + 1.0
    for s in range(spheres.shape[0]):
        cx = spheres[s, 0]
        cy = spheres[s, 1]
        cz = spheres[s, 2]
        r = spheres[s, 3]
        dc = du * cx + dv * cy + cz
        disc = dc * dc - dd * (cx * cx + cy * cy + cz * cz - r * r)
        if disc >= 0.0:
            t = (dc - np.sqrt(disc)) / dd
            if 0.0 < t < best_t:
                best = s
                best_t = t
    return best, best_t


@njit(parallel=True, fastmath=_FAST, nogil=True, cache=True)
def render_spheres(out, ray_u, ray_v, vignette, du_sub, spheres, light, lit, gain, ambient_e, background_e, read_e, dn_per_e,
                   max_dn, key0, supersample, want_maps, depth_out, normal_out):
    """Render spheres (rows: centre xyz, radius, albedo, specular, shininess, -) with pixel-area sampling."""
    height, width = out.shape
    ss = supersample
    for i in prange(height):
        for j in range(width):
            signal = 0.0
            for si in range(ss):
                for sj in range(ss):
                    du = ray_u[i, j] + du_sub * ((sj + 0.5) / ss - 0.5)
                    dv = ray_v[i, j] + du_sub * ((si + 0.5) / ss - 0.5)
                    s, t = _sphere_hit(du, dv, spheres)
                    if s < 0:
                        signal += background_e
                        continue
                    px = t * du
                    py = t * dv
                    pz = t
                    r = spheres[s, 3]
                    nxx = (px - spheres[s, 0]) / r
                    nyy = (py - spheres[s, 1]) / r
                    nzz = (pz - spheres[s, 2]) / r
                    alb = spheres[s, 4]
                    signal += ambient_e * alb
                    if lit:
                        signal += gain * _radiance(px, py, pz, nxx, nyy, nzz, alb, light, spheres[s, 5],
                                                   spheres[s, 6])
            signal *= vignette[i, j] / (ss * ss)
            out[i, j] = _digitise(signal, read_e, dn_per_e, max_dn, key0 + np.uint64(i * width + j))
            if want_maps:
                s, t = _sphere_hit(ray_u[i, j], ray_v[i, j], spheres)
                if s < 0:
                    depth_out[i, j] = np.nan
                    for c in range(3):
                        normal_out[i, j, c] = np.nan
                else:
                    depth_out[i, j] = t
                    r = spheres[s, 3]
                    normal_out[i, j, 0] = (t * ray_u[i, j] - spheres[s, 0]) / r
                    normal_out[i, j, 1] = (t * ray_v[i, j] - spheres[s, 1]) / r
                    normal_out[i, j, 2] = (t - spheres[s, 2]) / r
