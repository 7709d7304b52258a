"""`photopft calibrate lights`: sphere-calibration sessions in, a rig calibration profile out."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.reconstruction.binning import bin_all, bin_mean
from core.calibration.sphere_geometry import (CalibrationError, Highlight, MattePlacement, MatteRefinement, SphereFit,
                                             closest_points, detect_highlight, detect_sphere, pixel_rays,
                                             refine_on_matte, triangulate)
from core.reconstruction.photometric import complete_cycles
from core.calibration.rig_profile import HeadCalibration, RigCalibration
from core.rig import Head
from core.io.session import SessionFile, now_iso

DEFAULT_MAX_RESIDUAL_MM = 25.0
DEFAULT_PRIOR_SIGMA_MM = 15.0
CAPTURE_SECONDS = 1.0  # how long each placement is recorded: 22 light cycles at 110 frames/s
# The matte fit binned to at most this many bins a placement, every pixel's light kept (docs/constants.md)
MATTE_BINS_PER_PLACEMENT = 16000
# LEDs whose fitted falloff is below this are point sources to within 1 % over +-15 degrees
# (cos(15 deg)^0.25 = 0.991): the isotropic model, with fewer unknowns, places them better
ISOTROPIC_MU = 0.25
# A glossy sphere's diffuse shading is read away from its highlights: beyond this many of the
# highlight's own widths (Gaussian sigma) its lobe is below 1e-8 of its peak.
HIGHLIGHT_CLEARANCE_WIDTHS = 6.0
# ... and only where it stands this many times above a pixel's noise (a mirror ball has no shading).
DIFFUSE_MIN_SNR = 3.0
# The shading is taken only while leaving out one placement moves the lights by at most this many times the
# triangulation's standard error: else the LEDs' output changed between captures (docs/constants.md)
MAX_SHADING_LEAVE_ONE_OUT = 8.0
LEDS_THAT_CHANGED = "as when the LEDs' output changes between captures"
LEDS_THAT_CHANGE_ADVICE = ("Where the LEDs' output changed between captures: switch them on some minutes before "
                           "calibrating and capture one place after the other without pausing")
# A glossy sphere's shading is taken only where each light stays within this many of the triangulation's
# standard errors of where its highlights put it (docs/constants.md)
MAX_SHADING_FROM_HIGHLIGHTS = 3.0


@dataclass
class PlacementImages:
    """The mean lit-minus-dark image of each light over one still placement."""

    index: int
    signal: np.ndarray  # (4, H, W)
    saturated: np.ndarray  # (4, H, W) bool: full scale in any frame of the placement
    time_s: float = 0.0  # the placement's cycles' mid-time from the recording's first frame


def placement_images(session: SessionFile, head_name: str) -> list[PlacementImages]:
    """Average every complete light cycle inside each placement (between 'placement' events)."""
    starts = sorted(t for t, label in session.events() if label == "placement")
    if not starts:
        raise CalibrationError(f"{session.path}: no 'placement' events")
    timestamps = session.timestamp_ns(head_name)
    windows = complete_cycles(session.light_index(head_name), session.frame_id(head_name), session.rig.cycle_length)
    frames = session.frames(head_name)
    head = session.rig.heads[head_name]
    bounds = list(starts) + [np.iinfo(np.int64).max]
    out = []
    for k in range(len(starts)):
        inside = [w for w in windows if timestamps[min(w.lit + (w.dark,))] >= bounds[k]
                  and timestamps[w.newest] < bounds[k + 1]]
        # non-overlapping cycles only: each frame counted once
        chosen, last = [], -1
        for w in inside:
            if min(w.lit + (w.dark,)) > last:
                chosen.append(w)
                last = w.newest
        if not chosen:
            raise CalibrationError(f"{session.path}: placement {k + 1} holds no complete light cycle")
        total = np.zeros((4, head.height, head.width))
        saturated = np.zeros((4, head.height, head.width), dtype=bool)
        for w in chosen:
            dark = frames[w.dark].astype(np.float64)
            for light in range(4):
                frame = frames[w.lit[light]]
                saturated[light] |= frame >= head.max_value
                total[light] += frame.astype(np.float64) - dark
        mid_ns = np.mean([timestamps[w.newest] for w in chosen]) - timestamps[0]
        out.append(PlacementImages(k, total / len(chosen), saturated, float(mid_ns) / 1e9))
    return out


@dataclass
class PlacementResult:
    index: int
    sphere: SphereFit
    highlights: dict[int, Highlight] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    image: np.ndarray | None = None  # the four lights' signals summed: what the sphere was found in
    diffuse: MattePlacement | None = None  # the sphere's shading away from its highlights, if it has any


def specular_placements(session: SessionFile, head_name: str, radius_mm: float,
                        shading: bool = False) -> list[PlacementResult]:
    """The sphere and each light's highlight in every placement of a specular-sphere session; with
    `shading`, also its diffuse shading away from the highlights (PlacementResult.diffuse)."""
    head = session.rig.heads[head_name]
    results = []
    for placement in placement_images(session, head_name):
        image = placement.signal.sum(0)
        sphere = detect_sphere(image, head, radius_mm)
        result = PlacementResult(placement.index, sphere, image=image)
        for light in range(4):
            try:
                result.highlights[light] = detect_highlight(placement.signal[light], sphere, head, radius_mm,
                                                            placement.saturated[light])
            except CalibrationError as exc:
                result.problems.append(f"placement {placement.index + 1}, light {light}: {exc}")
        if shading:
            result.diffuse = _diffuse_shading(head, placement, result, radius_mm, str(session.path))
        results.append(result)
    return results


def _diffuse_shading(head: Head, placement: PlacementImages, result: PlacementResult,
                     radius_mm: float, recording: str = "") -> MattePlacement | None:
    """A glossy sphere's diffuse shading as a matte sphere's (dichromatic reflection: a diffuse body
    under a specular surface), with each highlight's neighbourhood and every clipped pixel left out;
    None where a highlight is missing or the shading does not stand out of the noise."""
    if len(result.highlights) < 4:
        return None
    rows, cols = np.indices(placement.signal.shape[1:])
    mask = result.sphere.mask & ~placement.saturated.any(axis=0)
    for highlight in result.highlights.values():
        clearance = max(2.0, HIGHLIGHT_CLEARANCE_WIDTHS * highlight.width_px)
        mask &= (cols - highlight.uv[0]) ** 2 + (rows - highlight.uv[1]) ** 2 > clearance**2
    if mask.sum() < 100:
        return None
    shading = placement.signal / head.relative_illumination()[None] if head.vignetting else placement.signal
    if np.min(np.median(shading[:, mask], axis=1)) < DIFFUSE_MIN_SNR * result.sphere.background_noise:
        return None
    rays, signal = binned_sphere(head, shading, mask, matte_binning(int(mask.sum())))
    return MattePlacement(rays, signal, result.sphere.centre_mm, radius_mm, placement.time_s, recording)


def matte_binning(sphere_pixels: int, max_bins: int = MATTE_BINS_PER_PLACEMENT) -> int:
    """The smallest whole factor whose factor x factor bins cut a sphere of this many pixels into at
    most max_bins."""
    return max(1, int(np.ceil(np.sqrt(sphere_pixels / max_bins))))


def binned_sphere(head: Head, signal: np.ndarray, mask: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """(unit rays (N, 3), signal (4, N)) of the factor x factor bins wholly on the sphere: each bin's
    mean signal, and the mean of its pixels' unit rays (the shading is smooth over a bin, so the
    model at the mean ray is the mean of the model to second order in the bin's size)."""
    rows, cols = np.nonzero(bin_all(mask, factor))
    offsets = np.arange(factor)
    shape = (len(rows), factor, factor)  # bin, row in the bin, column in the bin
    u = np.broadcast_to(cols[:, None, None] * factor + offsets[None, None, :], shape)
    v = np.broadcast_to(rows[:, None, None] * factor + offsets[None, :, None], shape)
    rays = pixel_rays(head, np.column_stack([u.ravel(), v.ravel()]))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays = rays.reshape(len(rows), factor * factor, 3).mean(axis=1)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return rays, bin_mean(signal, factor)[:, rows, cols]


def _matte_placements(session: SessionFile, head_name: str, radius_mm: float) -> list[MattePlacement]:
    """Each placement's matte sphere as detected: the rays and signals of its pixels, binned so that
    every pixel's light counts and the fit's size stays bounded at any resolution, and its centre."""
    head = session.rig.heads[head_name]
    # the shading as the light left the sphere: the lens' relative illumination divided out
    illumination = head.relative_illumination()[None] if head.vignetting else None
    out = []
    for placement in placement_images(session, head_name):
        sphere = detect_sphere(placement.signal.sum(0), head, radius_mm)
        shading = placement.signal / illumination if illumination is not None else placement.signal
        rays, signal = binned_sphere(head, shading, sphere.mask, matte_binning(int(sphere.mask.sum())))
        out.append(MattePlacement(rays, signal, sphere.centre_mm, radius_mm, placement.time_s, str(session.path)))
    return out


@dataclass
class HeadReport:
    head: str
    placements: int
    thesis_pair_error_mm: np.ndarray  # eq. 4.5 with the first two placements, per light
    triangulated_mm: np.ndarray
    refined_on: str  # what refined the triangulated lights ('' when nothing did)
    problems: list[str]
    # where the lights stay triangulated, what gave their axes and falloff all the same ('' when nothing did)
    pattern_on: str = ""


def calibrate_head(head: Head, specular: list[tuple[SessionFile, float]], matte: list[tuple[SessionFile, float]],
                   prior_sigma_mm: float = DEFAULT_PRIOR_SIGMA_MM,
                   max_residual_mm: float = DEFAULT_MAX_RESIDUAL_MM) -> tuple[HeadCalibration, HeadReport]:
    results: list[PlacementResult] = []
    for session, radius in specular:  # the glossy sphere's shading is wanted where no matte sphere is given
        results += specular_placements(session, head.name, radius, shading=not matte)
    problems = [p for r in results for p in r.problems]
    if not results:
        raise CalibrationError(f"head {head.name}: no specular-sphere placements to triangulate the lights from")
    # Pseudo light vectors: the placement nearest the centre of the view (thesis step 1.7).
    centre = np.array([head.cx, head.cy])
    central = min(results, key=lambda r: np.linalg.norm(r.sphere.centre_px - centre))
    if len(central.highlights) < 4:
        raise CalibrationError(f"head {head.name}: the central placement lacks highlights: " + "; ".join(problems))
    pseudo = np.array([central.highlights[k].light_vector for k in range(4)])

    positions = np.zeros((4, 3))
    sigma = np.zeros((4, 3))
    residual = np.zeros(4)
    pair_error = np.full(4, np.nan)
    for light in range(4):
        seen = [r.highlights[light] for r in results if light in r.highlights]
        if len(seen) < 2:
            raise CalibrationError(f"head {head.name}, light {light}: highlights in {len(seen)} placement(s), "
                                   "two or more are needed; " + "; ".join(problems))
        _, pair_error[light] = closest_points(seen[0].point_mm, seen[0].light_vector, seen[1].point_mm,
                                              seen[1].light_vector)
        fit = triangulate(np.array([h.point_mm for h in seen]), np.array([h.light_vector for h in seen]),
                          prior_mm=head.light_positions_mm[light], prior_sigma_mm=prior_sigma_mm)
        positions[light], sigma[light], residual[light] = fit.position_mm, fit.sigma_mm, fit.residual_mm
        if fit.residual_mm > max_residual_mm:
            raise CalibrationError(f"head {head.name}, light {light}: the highlight rays miss each other by "
                                   f"{fit.residual_mm:.1f} mm rms (threshold {max_residual_mm:g} mm): "
                                   "was the sphere moved during a placement, or is the radius wrong?")
    triangulated = positions.copy()
    intensity = np.ones(4)
    extra: dict[str, object] = {"width": int(head.width), "height": int(head.height),
                                "triangulated_positions_mm": np.round(triangulated, 4).tolist(),
                                "thesis_pair_error_mm": np.round(pair_error, 4).tolist()}
    refined_on = pattern_on = ""
    axis = mu = None
    shaded = [r.diffuse for r in results if r.diffuse is not None]
    shading = None
    if matte:
        placements = [p for session, radius in matte for p in _matte_placements(session, head.name, radius)]
        shading, refined_on, pattern_on = _shading(triangulated, sigma, placements, "the matte sphere",
                                                   "the matte sphere's shading", problems)
    elif len(shaded) >= 3:
        shading, refined_on, pattern_on = _shading(triangulated, sigma, shaded, "the specular sphere's diffuse shading",
                                                   "the specular sphere's diffuse shading", problems,
                                                   held_to_highlights=True)
    else:
        problems.append("the specular sphere shows no diffuse shading to refine on (a mirror finish, or too dark): "
                        "the lights are triangulated only (in the clinic world within 1-5 mm with the sphere 60 px "
                        "or more in radius, 2-12 mm below 40 px; docs/reconstruction.md, Light calibration); a matte "
                        "sphere session places them better")
    if shading is not None:
        positions, intensity = shading.positions_mm, shading.intensity
        axis, mu = shading.axis, shading.mu
        extra["refined_on"] = refined_on or "the highlights alone"
        if pattern_on:
            extra["axes_and_falloff_from"] = f"{pattern_on}, each placement's output fitted on its own"
        extra["shading_fit_rms"] = np.round(shading.rms, 6).tolist()
        extra["shading_distance_factors"] = np.round(shading.distance_factors, 6).tolist()
        if shading.leave_one_out_mm is not None:
            extra["shading_leave_one_out_mm"] = np.round(shading.leave_one_out_mm, 2).tolist()
        if shading.drift_per_min is not None:  # each recording of three or more placements, each LED
            extra["shading_drift_per_min"] = np.round(shading.drift_per_min, 5).tolist()
    calibration = HeadCalibration(positions, intensity, sigma, residual, pseudo, extra, axis, mu)
    report = HeadReport(head.name, len(results), pair_error, triangulated, refined_on, problems, pattern_on)
    return calibration, report


def _shading(triangulated_mm: np.ndarray, sigma_mm: np.ndarray, placements: list[MattePlacement], source: str,
             what: str, problems: list[str], held_to_highlights: bool = False) -> tuple[MatteRefinement, str, str]:
    """(the shading's fit, what placed the lights, what gave their axes and falloff where the highlights
    placed them): the positions the shading gives where it holds them still (and, held_to_highlights,
    within the highlights' standard errors), else held where the highlights put them."""
    fit = steady_shading(_refine(triangulated_mm, placements), sigma_mm, what, problems)
    if fit is None or (held_to_highlights and strays_from_highlights(fit, triangulated_mm, sigma_mm, problems)):
        return _refine(triangulated_mm, placements, held=True), "", source
    return fit, source, ""


def _refine(triangulated_mm: np.ndarray, placements: list[MattePlacement],
            held: bool = False) -> MatteRefinement:
    """The lights refined on a sphere's shading: anisotropic LEDs, or point sources where every
    fitted falloff is that of one; with how far each moves as each placement is left out.

    held: their positions held where the highlights put them and each placement's output per light
    fitted on its own, which leaves the axes, falloff and intensities to measure where the LEDs' output
    changed between placements (each light's falloff across every sphere; on the clinic world's 2 % of
    drift, captures 15 s apart, axes within 0.7 deg and exponents within 0.09 where the full fit was
    1.8-26 deg and 0.2-1.8 off; docs/reconstruction.md)."""
    options = {"gains_per_placement": True} if held else {"leave_one_out": True}
    fit = refine_on_matte(placements, triangulated_mm, anisotropic=True, **options)
    if np.all(fit.mu < ISOTROPIC_MU):
        fit = refine_on_matte(placements, triangulated_mm, anisotropic=False, **options)
    return fit


def steady_shading(fit: MatteRefinement, sigma_mm: np.ndarray, what: str,
                   problems: list[str]) -> MatteRefinement | None:
    """The shading's fit, or None (with the reason among the problems) where leaving out one placement
    moves a light by more than MAX_SHADING_LEAVE_ONE_OUT times its triangulation's standard error
    (sigma_mm, (4, 3)): the LEDs' output changed between placements."""
    if fit.leave_one_out_mm is None:  # two placements or fewer: nothing to leave out
        return fit
    ratio = fit.leave_one_out_mm / np.maximum(np.linalg.norm(sigma_mm, axis=1), 1e-6)
    k = int(np.argmax(ratio))
    if ratio[k] <= MAX_SHADING_LEAVE_ONE_OUT:
        return fit
    problems.append(f"{what} does not hold light {k} still: leaving out one placement moves it by "
                    f"{fit.leave_one_out_mm[k]:.1f} mm (jackknife), {ratio[k]:.0f} times the highlights' own "
                    f"{np.linalg.norm(sigma_mm[k]):.1f} mm, {LEDS_THAT_CHANGED}; the lights are where the highlights "
                    "put them")
    return None


def advice(reports: list["HeadReport"]) -> list[str]:
    """What the engineer can do about the heads' problems, each piece of advice once for all heads."""
    changed = any(LEDS_THAT_CHANGED in p for r in reports for p in r.problems)
    return [LEDS_THAT_CHANGE_ADVICE] if changed else []


def strays_from_highlights(fit: MatteRefinement, triangulated_mm: np.ndarray, sigma_mm: np.ndarray,
                           problems: list[str]) -> bool:
    """Whether a light of the glossy sphere's shading lies more than MAX_SHADING_FROM_HIGHLIGHTS standard
    errors (sigma_mm, (4, 3), per axis, in quadrature) from its triangulation (the reason among the
    problems)."""
    moved = np.sqrt(np.sum(np.square((fit.positions_mm - triangulated_mm) / np.maximum(sigma_mm, 1e-6)), axis=1))
    k = int(np.argmax(moved))
    if moved[k] <= MAX_SHADING_FROM_HIGHLIGHTS:
        return False
    shift_mm = np.linalg.norm(fit.positions_mm[k] - triangulated_mm[k])
    problems.append(f"the specular sphere's diffuse shading moves light {k} {shift_mm:.1f} mm from where its "
                    f"highlights put it, {moved[k]:.1f} of their standard errors (at most "
                    f"{MAX_SHADING_FROM_HIGHLIGHTS:g}): the lights are where the highlights put them (a matte "
                    "sphere session places them more surely)")
    return True


def calibrate_lights(paths: list[str | os.PathLike], prior_sigma_mm: float = DEFAULT_PRIOR_SIGMA_MM,
                     max_residual_mm: float = DEFAULT_MAX_RESIDUAL_MM) -> tuple[RigCalibration, list[HeadReport]]:
    """Calibrate every head from specular-sphere sessions (and matte ones, when given)."""
    specular: list[tuple[SessionFile, float]] = []
    matte: list[tuple[SessionFile, float]] = []
    opened = []
    try:
        for path in paths:
            session = SessionFile(path)
            opened.append(session)
            if session.kind != "sphere-calibration":
                raise CalibrationError(f"{path} is a {session.kind} session, not a sphere-calibration session")
            radius = float(session.attrs["sphere_radius_mm"])
            finish = str(session.attrs["sphere_finish"])
            (specular if finish == "specular" else matte).append((session, radius))
        if not specular:
            raise CalibrationError("no specular-sphere session among the inputs: the highlights give the lights")
        rig = specular[0][0].rig
        for session, _ in specular + matte:
            for name, head in session.rig.heads.items():
                ref = rig.heads.get(name)
                if ref is None or (ref.width, ref.height) != (head.width, head.height):
                    raise CalibrationError(f"{session.path}: head {name} does not match the first session's rig")
        heads, reports = {}, []
        for name, head in rig.heads.items():
            heads[name], report = calibrate_head(head, specular, matte, prior_sigma_mm, max_residual_mm)
            reports.append(report)
        calibration = RigCalibration(now_iso(), [Path(p).name for p in paths], heads,
                                     {"prior_sigma_mm": prior_sigma_mm, "max_residual_mm": max_residual_mm})
        return calibration, reports
    finally:
        for session in opened:
            session.close()
