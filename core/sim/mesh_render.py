"""A second renderer: a triangle mesh ray-cast through every pixel, with the image formation of
core/sim/render.py (the same LEDs, skin reflectance, sensor noise and digitisation).

Each frame, every triangle facing the camera is met by the rays of the pixels its projection may
cover (Moller-Trumbore; the nearest hit wins), then each pixel is shaded with its triangle's own
normal: the surface the pixel's depth lies on. Normals interpolated from the vertices' (Phong) are
smooth, but disagree with the flat triangles' depth by millimetres near the silhouette, where
breathing slides the contour across them: integrated, they kept -0.19 to 0.24 of a mesh body's
breath where its depth kept 0.37-0.64 (`bench visible`, docs/simulator.md). The height-field
renderer knows nothing of this one: a body rendered here has flanks, arms and a neck as a mesh has them.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from core.sim.render import _FAST, _digitise, _radiance


@njit(cache=True, nogil=True)
def vertex_normals(verts, quads, out):
    """Area-weighted vertex normals of a quad mesh (each quad's diagonals' cross product), unit length."""
    out[:] = 0.0
    for f in range(quads.shape[0]):
        a, b, c, d = quads[f, 0], quads[f, 1], quads[f, 2], quads[f, 3]
        p0 = verts[c] - verts[a]
        p1 = verts[d] - verts[b]
        nx = p0[1] * p1[2] - p0[2] * p1[1]
        ny = p0[2] * p1[0] - p0[0] * p1[2]
        nz = p0[0] * p1[1] - p0[1] * p1[0]
        for v in (a, b, c, d):
            out[v, 0] += nx
            out[v, 1] += ny
            out[v, 2] += nz
    for v in range(out.shape[0]):
        n = np.sqrt(out[v, 0] ** 2 + out[v, 1] ** 2 + out[v, 2] ** 2)
        if n > 0.0:
            out[v] /= n


@njit(cache=True, nogil=True)
def face_normals(verts, tris, out):
    """Each triangle's unit normal by its winding (outward on the closed mesh)."""
    for t in range(tris.shape[0]):
        a, b, c = verts[tris[t, 0]], verts[tris[t, 1]], verts[tris[t, 2]]
        e1x, e1y, e1z = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        e2x, e2y, e2z = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        n = np.sqrt(nx * nx + ny * ny + nz * nz)
        if n > 0.0:
            nx, ny, nz = nx / n, ny / n, nz / n
        out[t, 0], out[t, 1], out[t, 2] = nx, ny, nz


@njit(cache=True, nogil=True, fastmath=_FAST)
def rasterise(verts, tris, ray_u, ray_v, fx, fy, cx, cy, margin, depth, tri_id, bary):
    """Nearest hit of each pixel's ray (u, v, 1) among the triangles (camera frame, mm): its depth,
    triangle (-1: none) and barycentric coordinates. `margin`: pixels the lens' distortion moves a
    point from its pinhole projection, at most."""
    height, width = depth.shape
    depth[:] = np.inf
    tri_id[:] = -1
    for t in range(tris.shape[0]):
        a = verts[tris[t, 0]]
        b = verts[tris[t, 1]]
        c = verts[tris[t, 2]]
        if a[2] <= 1.0 or b[2] <= 1.0 or c[2] <= 1.0:
            continue
        e1x, e1y, e1z = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        e2x, e2y, e2z = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        nx = e1y * e2z - e1z * e2y
        ny = e1z * e2x - e1x * e2z
        nz = e1x * e2y - e1y * e2x
        if nx * a[0] + ny * a[1] + nz * a[2] >= 0.0:  # faces away from the camera
            continue
        ja = fx * a[0] / a[2] + cx
        jb = fx * b[0] / b[2] + cx
        jc = fx * c[0] / c[2] + cx
        ia = fy * a[1] / a[2] + cy
        ib = fy * b[1] / b[2] + cy
        ic = fy * c[1] / c[2] + cy
        j0 = max(int(np.floor(min(ja, jb, jc) - margin)), 0)
        j1 = min(int(np.ceil(max(ja, jb, jc) + margin)), width - 1)
        i0 = max(int(np.floor(min(ia, ib, ic) - margin)), 0)
        i1 = min(int(np.ceil(max(ia, ib, ic) + margin)), height - 1)
        for i in range(i0, i1 + 1):
            for j in range(j0, j1 + 1):
                dx, dy = ray_u[i, j], ray_v[i, j]
                px = dy * e2z - e2y
                py = e2x - dx * e2z
                pz = dx * e2y - dy * e2x
                det = e1x * px + e1y * py + e1z * pz
                if abs(det) < 1e-12:
                    continue
                inv = 1.0 / det
                sx, sy, sz = -a[0], -a[1], -a[2]
                uu = (sx * px + sy * py + sz * pz) * inv
                if uu < 0.0 or uu > 1.0:
                    continue
                qx = sy * e1z - sz * e1y
                qy = sz * e1x - sx * e1z
                qz = sx * e1y - sy * e1x
                vv = (dx * qx + dy * qy + qz) * inv
                if vv < 0.0 or uu + vv > 1.0:
                    continue
                z = (e2x * qx + e2y * qy + e2z * qz) * inv
                if 0.0 < z < depth[i, j]:
                    depth[i, j] = z
                    tri_id[i, j] = t
                    bary[i, j, 0] = uu
                    bary[i, j, 1] = vv


@njit(parallel=True, cache=True, nogil=True, fastmath=_FAST)
def shade(out, depth, tri_id, bary, tris, normals, ray_u, ray_v, vignette, albedo, spec, shin, light, lit,
          gain, ambient_e, background_e, read_e, dn_per_e, max_dn, key0, want_maps, depth_out, normal_out,
          per_face=False):
    """Each pixel's grey level: the hit point's radiance under `light` (when `lit`) and the room's,
    or the background; noise and digitisation as core/sim/render.py. `normals`: the triangles' own
    (per_face, face_normals) or the vertices', interpolated (vertex_normals)."""
    height, width = out.shape
    for i in prange(height):
        for j in range(width):
            t = tri_id[i, j]
            key = key0 + np.uint64(i * width + j)
            if t >= 0:
                if per_face:
                    nx, ny, nz = normals[t, 0], normals[t, 1], normals[t, 2]
                else:
                    w1 = bary[i, j, 0]
                    w2 = bary[i, j, 1]
                    w0 = 1.0 - w1 - w2
                    n0, n1, n2 = normals[tris[t, 0]], normals[tris[t, 1]], normals[tris[t, 2]]
                    nx = w0 * n0[0] + w1 * n1[0] + w2 * n2[0]
                    ny = w0 * n0[1] + w1 * n1[1] + w2 * n2[1]
                    nz = w0 * n0[2] + w1 * n1[2] + w2 * n2[2]
                    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
                    nx /= norm
                    ny /= norm
                    nz /= norm
                z = depth[i, j]
                px = z * ray_u[i, j]
                py = z * ray_v[i, j]
                signal = ambient_e * albedo
                if lit:
                    signal += gain * _radiance(px, py, z, nx, ny, nz, albedo, light, spec, shin)
                signal_e = signal * vignette[i, j]
                if want_maps:
                    depth_out[i, j] = z
                    normal_out[i, j, 0] = nx
                    normal_out[i, j, 1] = ny
                    normal_out[i, j, 2] = nz
            else:
                signal_e = background_e * vignette[i, j]
                if want_maps:
                    depth_out[i, j] = np.nan
                    normal_out[i, j, 0] = np.nan
                    normal_out[i, j, 1] = np.nan
                    normal_out[i, j, 2] = np.nan
            out[i, j] = _digitise(signal_e, read_e, dn_per_e, max_dn, key)


def distortion_margin_px(ray_u: np.ndarray, ray_v: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> float:
    """How far (px) a pixel's ray lands from the pixel under the pinhole model, at most, plus one."""
    rows, cols = np.indices(ray_u.shape)
    off = np.maximum(np.abs(fx * ray_u + cx - cols), np.abs(fy * ray_v + cy - rows))
    return float(off.max()) + 1.0
