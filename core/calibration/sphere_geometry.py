"""Light calibration from spheres (thesis section 4.3.1, and past it).

Specular sphere: find the sphere and each LED's highlight, reflect the view ray at the
highlight (eq. 4.1) and triangulate each light from all placements at once. Matte sphere:
refine positions and relative intensities photometrically (the shading of a sphere whose
normals are known), which the thesis' homogeneous-light assumption left out.

All positions are in the head's camera frame (OpenCV), millimetres; unit vectors from the
surface towards the light.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix

from core.reconstruction import rays
from core.rig import Head


class CalibrationError(Exception):
    """A calibration input that cannot give a trustworthy answer; the message says which and why."""


def pixel_rays(head: Head, uv: np.ndarray) -> np.ndarray:
    """Rays (N, 3) with z = 1 through pixel positions uv (N, 2), undistorted when the head has distortion."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if np.any(head.dist_coeffs != 0):
        xy = cv2.undistortPoints(uv.reshape(-1, 1, 2), head.camera_matrix, head.dist_coeffs).reshape(-1, 2)
    else:
        xy = np.column_stack([(uv[:, 0] - head.cx) / head.fx, (uv[:, 1] - head.cy) / head.fy])
    return np.column_stack([xy, np.ones(len(xy))])


@dataclass(frozen=True)
class SphereFit:
    centre_mm: np.ndarray  # camera frame
    centre_px: np.ndarray  # (u, v) of the outline's centre
    radius_px: float
    thesis_centre_mm: np.ndarray  # eqs 4.6 and 4.7, for comparison
    outline_rms_px: float
    mask: np.ndarray  # pixels on the sphere, eroded away from the outline
    background_noise: float = 0.0  # rms of the image around the sphere (its units)


# The sphere's shading read between OUTLINE_INSIDE_PX[1] and [0] pixels inside its last edge and carried to
# the edge along a line, on spheres at least OUTLINE_MIN_RADIUS_PX in radius (docs/constants.md)
OUTLINE_INSIDE_PX = (3.0, 1.5)
OUTLINE_MIN_RADIUS_PX = 40.0
OUTLINE_LEVEL_ITERATIONS = 4


def _outline_points(image: np.ndarray, centre: np.ndarray, radius: float, background: float, noise: float,
                    n_angles: int = 360) -> np.ndarray:
    """Sub-pixel outline along radial profiles, where each crosses half the step from the background
    to the sphere's shading at the crossing.

    A sphere darkens towards its limb (the light grazes it there), so its shading is followed up to
    the edge (_shading_at_edge, found again from each new crossing) on spheres large enough in the
    image (OUTLINE_MIN_RADIUS_PX), and read one pixel inside the outermost sample above the background
    on smaller ones. That level, which all spheres took until the thirtieth session, comes from the
    pixels the edge crosses on every profile that runs across the pixel grid: at scale 0.5 the outline
    came out about 0.1 px too wide, the sphere 3-4 mm too near at 2 m, each highlight's normal 0.04 px
    inward, and the LEDs triangulated from them 10-16 mm off along their rays.
    """
    angles = np.linspace(0, 2 * np.pi, n_angles, endpoint=False)
    step = 0.25
    steps = np.arange(radius * 0.5, radius * 1.5, step)
    points = []
    for a in angles:
        xs = centre[0] + steps * np.cos(a)
        ys = centre[1] + steps * np.sin(a)
        profile = ndimage.map_coordinates(image, [ys, xs], order=1, mode="nearest")
        above = profile > background + 6.0 * noise
        if not above.any():
            continue
        if radius < OUTLINE_MIN_RADIUS_PX:
            outer = int(np.flatnonzero(above)[-1])  # the outermost sample clearly on the sphere
            inner = outer - int(round(1.0 / step))  # the full pixel just inside the edge
            s = None if inner < 0 else _half_level_crossing(profile, steps, outer,
                                                            background + 0.5 * (profile[inner] - background))
        elif above[0] and not above.all():
            outer = int(np.argmin(above)) - 1  # the last sample clearly on the sphere before the background
            s = steps[outer] - 0.5
            for _ in range(OUTLINE_LEVEL_ITERATIONS):
                s = _half_level_crossing(profile, steps, outer,
                                         background + 0.5 * (_shading_at_edge(profile, steps, s) - background))
                if s is None:
                    break
        else:
            continue
        if s is not None:
            points.append((centre[0] + s * np.cos(a), centre[1] + s * np.sin(a)))
    return np.array(points)


def _shading_at_edge(profile: np.ndarray, steps: np.ndarray, edge: float) -> float:
    """The sphere's shading at its edge (`edge`, along the profile), from a line through the samples
    OUTLINE_INSIDE_PX inside it."""
    d = edge - steps
    inside = (d >= OUTLINE_INSIDE_PX[1]) & (d <= OUTLINE_INSIDE_PX[0])
    if inside.sum() < 4:
        return float(profile[np.argmin(np.abs(d - OUTLINE_INSIDE_PX[1]))])
    design = np.column_stack([np.ones(int(inside.sum())), d[inside]])
    (a, _), *_ = np.linalg.lstsq(design, profile[inside], rcond=None)
    return float(a)


def _half_level_crossing(profile: np.ndarray, steps: np.ndarray, outer: int, level: float) -> float | None:
    """Where a profile falls through `level` about its sample `outer` (linear between samples), or None."""
    k = outer
    while k + 1 < len(profile) and profile[k + 1] >= level:
        k += 1
    while k > 0 and profile[k] < level:
        k -= 1
    if k + 1 >= len(profile) or profile[k] == profile[k + 1]:
        return None
    return float(steps[k] + (profile[k] - level) / (profile[k] - profile[k + 1]) * (steps[1] - steps[0]))


def detect_sphere(image: np.ndarray, head: Head, radius_mm: float) -> SphereFit:
    """The sphere in an image (lit minus dark, all lights): centre in mm, outline in pixels.

    The outline is found to sub-pixel precision and fitted with the exact projection of a
    sphere of known radius (a cone of rays tangent to it), not a circle: off the axis a sphere
    projects to an ellipse. Eqs 4.7 and 4.6 (the thesis' on-axis estimate) start the fit.
    """
    image = np.asarray(image, dtype=np.float64)
    smooth = ndimage.gaussian_filter(image, 1.0)
    background = float(np.median(smooth))
    threshold = background + 0.5 * (np.percentile(smooth, 99.5) - background)
    labels, n = ndimage.label(smooth > threshold)
    if n == 0:
        raise CalibrationError("no sphere found: nothing stands out of the background")
    sizes = ndimage.sum(np.ones_like(smooth), labels, range(1, n + 1))
    blob = labels == (1 + int(np.argmax(sizes)))
    if blob.sum() < 50:
        raise CalibrationError(f"no sphere found: the brightest region has only {int(blob.sum())} pixels")
    filled = ndimage.binary_fill_holes(blob)
    rows, cols = np.nonzero(filled)
    rough_centre = np.array([cols.mean(), rows.mean()])
    rough_radius = float(np.sqrt(filled.sum() / np.pi))
    if (rows.min() <= 1 or cols.min() <= 1 or rows.max() >= image.shape[0] - 2
            or cols.max() >= image.shape[1] - 2):
        raise CalibrationError("the sphere touches the edge of the image: place it fully in view")
    outside = ~ndimage.binary_dilation(filled, iterations=max(3, int(rough_radius / 3)))
    background = float(np.median(image[outside]))
    noise = float(1.4826 * np.median(np.abs(image[outside] - background)))
    if np.median(image[filled]) - background < 10.0 * max(noise, 1e-6):
        raise CalibrationError("no sphere found: nothing stands out of the background")
    edge_points = _outline_points(image, rough_centre, rough_radius, background, max(noise, 1e-6))
    if len(edge_points) < 30:
        raise CalibrationError("the sphere's outline could not be traced (too little contrast)")
    # Thesis eq. 4.7 (distance from the pixel radius) and 4.6 (centre from the pixel position).
    pixel_radius = float(np.mean(np.linalg.norm(edge_points - edge_points.mean(0), axis=1)))
    z_thesis = head.focal_length_mm * radius_mm / (head.pixel_size_mm * pixel_radius)
    ray0 = pixel_rays(head, edge_points.mean(0)[None])[0]
    thesis_centre = ray0 * z_thesis

    rays = pixel_rays(head, edge_points)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)

    def cone(c: np.ndarray) -> np.ndarray:
        distance = np.linalg.norm(c)
        # angle between each outline ray and the centre direction minus the tangent angle
        return np.arccos(np.clip(rays @ (c / distance), -1, 1)) - np.arcsin(min(radius_mm / distance, 1.0))

    fit = least_squares(cone, thesis_centre, loss="soft_l1", f_scale=1e-3)
    centre = fit.x
    residual_px = np.sqrt(np.mean(fit.fun**2)) * head.fx
    centre_px = np.array([head.fx * centre[0] / centre[2] + head.cx, head.fy * centre[1] / centre[2] + head.cy])
    mask = ndimage.binary_erosion(filled, iterations=2)
    return SphereFit(centre, centre_px, pixel_radius, thesis_centre, float(residual_px), mask, noise)


@dataclass(frozen=True)
class Highlight:
    uv: np.ndarray  # sub-pixel position
    peak: float
    point_mm: np.ndarray  # on the sphere (eq. 4.12: P = C + R n)
    normal: np.ndarray  # sphere normal at the highlight (towards the camera side)
    light_vector: np.ndarray  # unit, from the highlight towards the light (eq. 4.1)
    width_px: float = 1.0  # the peak's Gaussian sigma, the wider of its two axes


def detect_highlight(signal: np.ndarray, sphere: SphereFit, head: Head, radius_mm: float,
                     saturated: np.ndarray | None = None) -> Highlight:
    """The highlight of one LED on a specular sphere, to sub-pixel precision.

    The peak's position is refined by a Gaussian fit of the 3 x 3 neighbourhood (a parabola
    through the log-intensities along each axis) after removing the diffuse level around it.
    `saturated` marks pixels whose raw frame reached full scale: a clipped peak has no centre.
    """
    on_sphere = ndimage.binary_erosion(sphere.mask, iterations=1)
    if not on_sphere.any():
        raise CalibrationError("the sphere is too small in the image to find highlights")
    values = np.where(on_sphere, signal, -np.inf)
    row, col = np.unravel_index(int(np.argmax(values)), values.shape)
    peak = float(signal[row, col])
    if saturated is not None and saturated[max(row - 1, 0):row + 2, max(col - 1, 0):col + 2].any():
        raise CalibrationError(f"highlight clipped at pixel ({col}, {row}): the frame reached full scale; "
                               "lower the exposure or the LED current")
    diffuse = float(np.median(signal[on_sphere]))
    if peak - diffuse < 8 * max(1.0, float(np.std(signal[on_sphere & (signal < np.percentile(signal[on_sphere], 90))]))):
        raise CalibrationError("no highlight stands out of the sphere: is the sphere specular and the LED on?")
    if not (1 <= row < signal.shape[0] - 1 and 1 <= col < signal.shape[1] - 1):
        raise CalibrationError("the highlight sits on the edge of the image")
    window = np.clip(signal[row - 1:row + 2, col - 1:col + 2] - diffuse, 1e-3, None)
    log = np.log(window)
    du = 0.5 * (log[1, 0] - log[1, 2]) / (log[1, 0] - 2 * log[1, 1] + log[1, 2])
    dv = 0.5 * (log[0, 1] - log[2, 1]) / (log[0, 1] - 2 * log[1, 1] + log[2, 1])
    uv = np.array([col + np.clip(du, -0.5, 0.5), row + np.clip(dv, -0.5, 0.5)])
    # a Gaussian's log is a parabola whose second difference is -1 / sigma^2
    curvature = max(log[1, 0] - 2 * log[1, 1] + log[1, 2], log[0, 1] - 2 * log[1, 1] + log[2, 1])
    width = float(np.sqrt(-1.0 / curvature)) if curvature < 0 else float(max(signal.shape))
    ray = pixel_rays(head, uv[None])[0]
    ray /= np.linalg.norm(ray)
    c = sphere.centre_mm
    b = ray @ c
    disc = b * b - (c @ c - radius_mm**2)
    t = b - np.sqrt(max(disc, 0.0))
    point = ray * t
    normal = (point - c) / radius_mm
    view = -ray  # from the surface towards the camera
    light = 2 * (normal @ view) * normal - view  # eq. 4.1 in the camera frame
    return Highlight(uv, peak, point, normal, light / np.linalg.norm(light), width)


def closest_points(p1: np.ndarray, l1: np.ndarray, p2: np.ndarray, l2: np.ndarray) -> tuple[np.ndarray, float]:
    """Where two highlight rays pass closest (core/reconstruction/rays.py): parallel rays are a placement to change."""
    try:
        return rays.closest_points(p1, l1, p2, l2)
    except rays.ParallelRays:
        raise CalibrationError("two highlight rays are parallel: move the sphere further between placements") from None


@dataclass(frozen=True)
class Triangulation:
    position_mm: np.ndarray
    sigma_mm: np.ndarray
    residual_mm: float  # rms distance of the rays from the position
    ray_distances_mm: np.ndarray


def triangulate(points: np.ndarray, directions: np.ndarray, prior_mm: np.ndarray | None = None,
                prior_sigma_mm: float = 15.0, ray_sigma_mm: float | None = None) -> Triangulation:
    """The point nearest to all rays in least squares, optionally pulled towards a drawn position.

    Each ray contributes (I - d d^T)(X - p) = 0. With a prior the drawing counts as one more
    observation with its tolerance; the ray noise is taken from the rays' own scatter.
    """
    points = np.asarray(points, float)
    directions = np.asarray(directions, float)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    projectors = np.eye(3)[None] - directions[:, :, None] * directions[:, None, :]
    a = projectors.sum(0)
    b = np.einsum("nij,nj->i", projectors, points)
    free = np.linalg.lstsq(a, b, rcond=None)[0]

    def distances(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.einsum("nij,nj->ni", projectors, x - points), axis=1)

    n = len(points)
    sigma_ray = ray_sigma_mm
    if sigma_ray is None:
        sigma_ray = float(np.sqrt(np.sum(distances(free) ** 2) / max(1, 2 * n - 3))) if n > 2 else 2.0
        sigma_ray = max(sigma_ray, 0.5)
    weight_a = a / sigma_ray**2
    weight_b = b / sigma_ray**2
    if prior_mm is not None:
        weight_a = weight_a + np.eye(3) / prior_sigma_mm**2
        weight_b = weight_b + np.asarray(prior_mm, float) / prior_sigma_mm**2
    position = np.linalg.solve(weight_a, weight_b)
    covariance = np.linalg.inv(weight_a)
    d = distances(position)
    return Triangulation(position, np.sqrt(np.diag(covariance)), float(np.sqrt(np.mean(d**2))), d)


@dataclass
class MattePlacement:
    """A matte sphere as detected in one placement: its pixels' unit rays and each light's signal."""

    rays: np.ndarray  # (N, 3) unit
    signal: np.ndarray  # (4, N) lit minus dark
    centre_mm: np.ndarray  # (3,) from the outline
    radius_mm: float
    # when the placement was held (its cycles' mid-time, s, on its recording's clock) and which
    # recording: an LED's intensity drifts as it warms, and within one recording that is fitted
    time_s: float = 0.0
    recording: str = ""


@dataclass(frozen=True)
class MatteRefinement:
    positions_mm: np.ndarray  # (4, 3)
    intensity: np.ndarray  # (4,) relative, mean 1
    distance_factors: np.ndarray  # per placement: the fitted centre over the outline's (along its ray)
    rms: np.ndarray  # (4,) relative rms residual per light
    axis: np.ndarray | None = None  # (4, 3) unit vectors each LED points along (anisotropic model)
    mu: np.ndarray | None = None  # (4,) exponent of each LED's cos^mu falloff about its axis
    # (recordings of three or more placements, 4): each LED's intensity change per minute within one
    drift_per_min: np.ndarray | None = None
    # (4,) with leave_one_out: how far each light moves (jackknife standard error, mm) as each placement
    # is left out of the fit in turn (on the fit's sample of the bins)
    leave_one_out_mm: np.ndarray | None = None


def sphere_surface(rays: np.ndarray, centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each ray first meets the sphere, and the normal there (rays that miss: the closest point)."""
    b = rays @ centre
    disc = np.clip(b * b - (centre @ centre - radius**2), 0.0, None)
    points = rays * (b - np.sqrt(disc))[:, None]
    normals = points - centre
    return points, normals / np.linalg.norm(normals, axis=1, keepdims=True)


# The anisotropic model's LED axes: within this of the optical axis (tangent of the tilt), and
# exponents within these bounds (an isotropic point source is 0, a Lambertian emitter 1).
MAX_AXIS_TILT = np.tan(np.radians(30.0))
MU_BOUNDS = (0.0, 8.0)
COARSE_BINS_PER_PLACEMENT = 400
# An LED's intensity drifts as it warms (2 % over minutes in the clinic world): within a recording of
# at least this many placements each LED's intensity is fitted as a line in time, which the placements'
# spread in time and space tells from the inverse square of their distances (docs/reconstruction.md)
MIN_PLACEMENTS_FOR_DRIFT = 3
# Each leave-one-out refit starts from the whole fit's solution and stops after this many evaluations
LEAVE_ONE_OUT_MAX_NFEV = 12


def _placement_major(misfit: np.ndarray, sizes: list[int]) -> np.ndarray:
    """(4, all pixels) residuals in the order placement, light, pixel."""
    blocks = np.split(misfit, np.cumsum(sizes)[:-1], axis=1)
    return np.concatenate([b.ravel() for b in blocks])


def _drift_groups(placements: list["MattePlacement"]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each placement's drift group (its recording, where that holds MIN_PLACEMENTS_FOR_DRIFT or
    more placements; -1 elsewhere), its time from the group's mean over the group's span (so the
    fitted drift is the change over the recording), and each group's span in minutes."""
    recordings = [p.recording for p in placements]
    kept = sorted({r for r in recordings if recordings.count(r) >= MIN_PLACEMENTS_FOR_DRIFT})
    group = np.array([kept.index(r) if r in kept else -1 for r in recordings], dtype=int)
    times = np.array([p.time_s for p in placements], dtype=float)
    share = np.zeros(len(placements))
    spans = np.zeros(len(kept))
    for g in range(len(kept)):
        inside = group == g
        spans[g] = max(float(np.ptp(times[inside])), 1e-3) / 60.0
        share[inside] = (times[inside] - times[inside].mean()) / (60.0 * spans[g])
    return group, share, spans


def _sparsity(sizes: list[int], anisotropic: bool, drift_group: np.ndarray | None = None):
    """Which parameters move which residuals: a light's own (position, intensity, axis, falloff)
    only its pixels, a placement's distance only that placement's, a recording's drift of a light
    only that light's pixels in its placements. Finite differences then perturb the four lights
    (and all placements) at once."""
    n_placements = len(sizes)
    n_base = 16 + n_placements
    n_shape = n_base + (12 if anisotropic else 0)
    groups = 0 if drift_group is None else int(drift_group.max(initial=-1)) + 1
    out = lil_matrix((4 * sum(sizes), n_shape + 4 * groups), dtype=np.int8)
    row = 0
    for p, size in enumerate(sizes):
        for k in range(4):
            rows = slice(row, row + size)
            own = list(range(3 * k, 3 * k + 3)) + [12 + k, 16 + p]
            if anisotropic:
                own += [n_base + 2 * k, n_base + 2 * k + 1, n_base + 8 + k]
            if groups and drift_group[p] >= 0:
                own.append(n_shape + 4 * int(drift_group[p]) + k)
            for c in own:
                out[rows, c] = 1
            row += size
    return out


def _jackknife_mm(left_out_mm: np.ndarray) -> np.ndarray:
    """(4,) each light's jackknife standard error (mm) from its positions (n, 4, 3) fitted with each of
    the n placements left out in turn."""
    n = len(left_out_mm)
    variance = (n - 1) / n * np.sum((left_out_mm - left_out_mm.mean(axis=0)) ** 2, axis=0)
    return np.sqrt(np.sum(variance, axis=1))


def refine_on_matte(placements: list[MattePlacement], initial_mm: np.ndarray,
                    anisotropic: bool = True, leave_one_out: bool = False,
                    gains_per_placement: bool = False) -> MatteRefinement:
    """Positions, relative intensities and (anisotropic) each LED's axis and falloff exponent from
    a matte sphere's shading, with each placement's distance along its ray fitted too.

    Model: signal_k = s_k * cos(a_k, X - P_k)^mu_k * max(0, n . (P_k - X)) / |P_k - X|^3 (Lambertian,
    inverse square, an LED's radiant intensity falling off as cos^mu of the angle from its own axis
    a_k; the thesis' point source is mu = 0), X and n where the pixel's ray meets the sphere (known
    radius) at its centre c * f, f fitted per placement. Within a recording of MIN_PLACEMENTS_FOR_DRIFT
    or more placements s_k is s_k (1 + d_k t), t the placement's time from the recording's mean over its
    span, d_k fitted (MatteRefinement.drift_per_min: d_k over the span in minutes). The outline alone leaves the sphere's
    distance off by a fraction of a pixel of its radius (a few mm at 2 m, docs/reconstruction.md),
    and the lights would absorb that error; the shading inside the outline tells the distance too,
    through how fast the normal turns from pixel to pixel. Every pixel (or bin of pixels) facing
    the camera counts; those near the limb, where the outline's error matters most, are left out
    (normal within 70 degrees of the view). An isotropic model fitted to LEDs that are not moves
    them hundreds of millimetres to mimic their falloff: the falloff belongs in the model.

    leave_one_out: each light's jackknife standard error too (MatteRefinement.leave_one_out_mm), the fit
    repeated with each placement left out in turn on the first stage's sample of bins, from the solution.
    gains_per_placement: the positions held at initial_mm and s_k free in every placement (the first's
    the reference), which leaves each light's axis and falloff to the shading across each sphere: what
    an output that changed from one placement to the next, unknown, still lets the fit measure.
    """
    rays, signal, centres, radii = [], [], [], []
    for placement in placements:
        _, normals = sphere_surface(placement.rays, placement.centre_mm, placement.radius_mm)
        facing = np.nonzero(-np.sum(normals * placement.rays, axis=1) > np.cos(np.radians(70.0)))[0]
        rays.append(placement.rays[facing])
        signal.append(placement.signal[:, facing])
        centres.append(placement.centre_mm)
        radii.append(placement.radius_mm)
    n_placements = len(rays)
    sizes = [len(r) for r in rays]
    typical = float(np.median(np.concatenate([s[s > 0] for s in signal]))) if signal else 1.0

    def shading(positions: np.ndarray, factors: np.ndarray, axes: np.ndarray, mus: np.ndarray,
                every: int = 1) -> list[np.ndarray]:
        out = []
        for r, c, radius, f in zip(rays, centres, radii, factors):
            points, normals = sphere_surface(r[::every], c * f, radius)
            d = positions[:, None, :] - points[None]  # (4, N, 3)
            distance = np.linalg.norm(d, axis=2)
            value = np.clip(np.sum(normals[None] * d, axis=2), 0.0, None) / distance**3
            if anisotropic:
                cosine = np.clip(-np.sum(d * axes[:, None, :], axis=2) / distance, 1e-6, None)
                value = value * cosine ** mus[:, None]
            out.append(value)
        return out

    initial = np.asarray(initial_mm, float)
    nominal_axes = np.tile([0.0, 0.0, 1.0], (4, 1))
    model0 = shading(initial, np.ones(n_placements), nominal_axes, np.zeros(4))
    scale0 = np.array([sum(m[k] @ s[k] for m, s in zip(model0, signal)) / sum(m[k] @ m[k] for m in model0)
                       for k in range(4)])
    n_base = 16 + n_placements
    n_shape = n_base + (12 if anisotropic else 0)
    if gains_per_placement:  # every placement but the first its own gain per light (its "drift" at t = 1)
        drift_group, share = np.arange(-1, n_placements - 1), np.ones(n_placements)
        spans_min = np.ones(n_placements - 1)
    else:
        drift_group, share, spans_min = _drift_groups(placements)
    n_groups = len(spans_min)

    def unpack(x: np.ndarray):
        positions, scales, factors = x[:12].reshape(4, 3), scale0 * x[12:16], x[16:n_base]
        drift = x[n_shape:].reshape(n_groups, 4)
        if not anisotropic:
            return positions, scales, factors, nominal_axes, np.zeros(4), drift
        axes = np.column_stack([x[n_base:n_base + 8].reshape(4, 2), np.ones(4)])
        axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
        return positions, scales, factors, axes, x[n_base + 8:n_shape], drift

    def misfit(x: np.ndarray, every: int = 1, left_out: int = -1) -> np.ndarray:
        """(4, all pixels, or every so many) model minus signal, relative to the typical signal; a
        placement left out has no pixels."""
        positions, scales, factors, axes, mus, drift = unpack(x)
        model = shading(positions, factors, axes, mus, every)
        gains = [scales * (1.0 + drift[g] * t) if g >= 0 else scales for g, t in zip(drift_group, share)]
        return np.concatenate([(gain[:, None] * m - s[:, ::every])[:, :0 if p == left_out else None]
                               for p, (gain, m, s) in enumerate(zip(gains, model, signal))], axis=1) / typical

    def solve(x_start: np.ndarray, stride: int, left_out: int = -1) -> np.ndarray:
        """The parameters fitted from x_start (those not free held as they are)."""
        sampled = [0 if p == left_out else len(range(0, n, stride)) for p, n in enumerate(sizes)]

        def residuals(free_x: np.ndarray) -> np.ndarray:
            x = x_start.copy()
            x[free] = free_x
            return _placement_major(misfit(x, stride, left_out), sampled)

        sparsity = _sparsity(sampled, anisotropic, drift_group).tocsc()[:, np.nonzero(free)[0]]
        fit = least_squares(residuals, x_start[free], x_scale=x_scale[free], bounds=(lower[free], upper[free]),
                            jac_sparsity=sparsity, tr_solver="lsmr", ftol=1e-6,
                            max_nfev=LEAVE_ONE_OUT_MAX_NFEV if left_out >= 0 else None)
        x = x_start.copy()
        x[free] = fit.x
        return x

    x0 = np.r_[initial.ravel(), np.ones(4), np.ones(n_placements)]
    x_scale = np.r_[np.full(12, 10.0), np.full(4, 0.01), np.full(n_placements, 0.001)]
    lower, upper = np.full(n_base, -np.inf), np.full(n_base, np.inf)
    if anisotropic:
        x0 = np.r_[x0, np.zeros(8), np.ones(4)]
        x_scale = np.r_[x_scale, np.full(8, 0.02), np.full(4, 0.3)]
        lower = np.r_[lower, np.full(8, -MAX_AXIS_TILT), np.full(4, MU_BOUNDS[0])]
        upper = np.r_[upper, np.full(8, MAX_AXIS_TILT), np.full(4, MU_BOUNDS[1])]
    x0, x_scale = np.r_[x0, np.zeros(4 * n_groups)], np.r_[x_scale, np.full(4 * n_groups, 0.002)]
    lower, upper = np.r_[lower, np.full(4 * n_groups, -np.inf)], np.r_[upper, np.full(4 * n_groups, np.inf)]
    # first on a sample of the bins (where most of the iterations are spent), then on all of them; to a
    # relative change of the misfit of 1e-6 (at 1e-8 the drifts' weak direction took 81 steps for 8, the
    # lights moving by under 0.1 mm)
    free = np.ones(len(x0), dtype=bool)
    free[:12] = not gains_per_placement  # the positions held where they start
    every = max(1, int(np.ceil(max(sizes) / COARSE_BINS_PER_PLACEMENT)))
    stages = [every, 1] if every > 1 else [1]
    for stride in stages:
        x0 = solve(x0, stride)
    positions, scales, factors, axes, mus, drift = unpack(x0)
    rms = np.sqrt(np.mean(misfit(x0) ** 2, axis=1))
    drift_per_min = drift / spans_min[:, None] if n_groups and not gains_per_placement else None
    if gains_per_placement:  # each light's intensity: its mean over the placements
        scales = scales * (1.0 + np.sum(drift, axis=0) / n_placements)
    spread = None
    if leave_one_out and n_placements > 2:
        left = np.array([unpack(solve(x0, stages[0], p))[0] for p in range(n_placements)])
        spread = _jackknife_mm(left)
    if not anisotropic:
        return MatteRefinement(positions, scales / scales.mean(), factors, rms, drift_per_min=drift_per_min,
                               leave_one_out_mm=spread)
    return MatteRefinement(positions, scales / scales.mean(), factors, rms, axes, mus, drift_per_min, spread)
