"""`photopft bench accuracy`: normals, distance and height against the truth (thesis Table 4.3)."""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from app.args import WORLD_NAMES, finite, positive
from benchmarks.common import world_words, write_section


SHAPES = ("sphere", "torso", "vase", "relief")

DISTANCES = (1800, 1900, 2000, 2100, 2200)


@dataclass


class Row:
    shape: str
    distance_mm: float
    method: str
    angular_deg: float
    distance_error_mm: float
    height_error_mm: float
    tracked_distance_error_mm: float = float("nan")  # ours, after TRACKED_CYCLES cycles of a stream
    distance_sd_mm: float = float("nan")  # ours, the standard deviation of one cycle's distance over the stream

TRACKED_CYCLES = 10


def _cycles(session, head_name: str):
    """Every complete light cycle of a head, in order: (newest frame, signal, saturated, dark), as
    `photopft process` makes them (without its motion compensation: the subjects stand still)."""
    from core.reconstruction.photometric import complete_cycles
    from core.pipeline.head_maps import cycle_signal

    frames, ids, stamps = session.frames(head_name), session.frame_id(head_name), session.timestamp_ns(head_name)
    max_value = session.rig.heads[head_name].max_value
    for window in complete_cycles(session.light_index(head_name), ids,
                                  session.rig.cycle_length)[::session.rig.cycle_length]:
        yield (window.newest, *cycle_signal(frames, window, None, max_value, {}, ids, stamps))


def angular_error(normals: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    dot = np.clip(np.sum(normals[valid] * truth[valid], axis=-1), -1, 1)
    return float(np.degrees(np.mean(np.arccos(dot))))


def depth_errors(depth: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
    difference = depth[valid] - truth[valid]
    offset = float(np.median(depth[valid]) - np.median(truth[valid]))
    return offset, float(np.mean(np.abs(difference - difference.mean())))


def _blank_nan(value: float, spec: str) -> str:
    return format(value, spec) if np.isfinite(value) else ""


def _distance_floor(reconstructor, signal: np.ndarray, dark: np.ndarray, true_depth: np.ndarray,
                    true_lights: tuple[np.ndarray, np.ndarray]) -> float:
    """The distance noise floor of one cycle: the error of the same photometric distance fit
    (the reconstructor's pixels, binning and noise model) handed the true surface and the true
    lights, so that only the camera noise is left."""
    from core.reconstruction.distance import PhotometricDistance
    from core.reconstruction.pipeline import subject_mask

    settings = reconstructor.settings
    mask = subject_mask(signal, settings.mask_fraction, settings.mask_edge_fraction) & np.isfinite(true_depth)
    median = float(np.median(true_depth[mask]))
    fit = PhotometricDistance(signal, mask, true_lights[0], true_lights[1], dark, max_pixels=settings.distance_pixels,
                               binning=reconstructor._distance_binning, light_axis=true_lights[2],
                               light_mu=true_lights[3])
    relative = np.where(mask, true_depth / median, np.nan)
    return fit.scale(reconstructor._rays, relative, (0.97 * median, 1.03 * median), grid_points=7) - median


def _cycle(session, head_name: str):
    """The first complete light cycle of a head: (newest frame, signal, saturated, dark)."""
    return next(_cycles(session, head_name))


def run_accuracy(scale: float, shapes: tuple[str, ...], distances: tuple[int, ...], seed: int,
                 led_offset_mm: float, write: bool, world: str = "ideal") -> str:
    from core.calibration.light_sessions import CAPTURE_SECONDS, calibrate_lights
    from core.reconstruction.photometric import near_light_normals
    from core.reconstruction.pipeline import (HeadReconstructor, ReconstructionSettings, RunningDistance,
                                              shadow_threshold)
    from core.reconstruction.prefilter import prefilter_sigma_px, prefiltered
    from core.rig import thesis_rig
    from core.io.session import SessionFile
    from core.sim.breathing import Sway
    from core.sim.simulate import SimConfig, in_world, simulate

    def config(**settings) -> SimConfig:
        """A scene in the bench's world, its LEDs the bench's distance off the drawing."""
        return replace(in_world(SimConfig(**settings), world), led_offset_mm=led_offset_mm)

    started = time.perf_counter()
    lines: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        common = dict(scale=scale, seed=seed, heads=("front",), led_offset_mm=led_offset_mm,
                      led_intensity_spread=0.05)
        calibration_files = []
        # each placement held as long as a capture records it (the sphere wizard's CAPTURE_SECONDS)
        rig = thesis_rig(scale, heads=("front",))
        hold_cycles = int(round(CAPTURE_SECONDS * rig.frame_rate_hz / rig.cycle_length))
        for scene in ("specular-sphere", "matte-sphere"):
            path = folder / f"{scene}.h5"
            simulate(path, config(scene=scene, placement_cycles=hold_cycles, **common))
            calibration_files.append(path)
        calibration, reports = calibrate_lights(calibration_files)
        with SessionFile(calibration_files[0]) as s:
            true_positions = np.asarray(s.truth()["front/light_positions_mm"])
            true_intensity = np.asarray(s.truth()["front/light_intensity"])
            # the floor's lights as built: with their falloff and axes where the world has them
            true_axis = np.asarray(s.truth()["front/light_axis"]) if "front/light_axis" in s.truth() \
                else np.tile([0.0, 0.0, 1.0], (4, 1))
            true_mu = np.asarray(s.truth()["front/light_mu"]) if "front/light_mu" in s.truth() else np.zeros(4)
            drawn = s.rig.heads["front"].light_positions_mm
        cal = calibration.heads["front"]
        position_error = np.linalg.norm(cal.light_positions_mm - true_positions, axis=1)
        triangulated_error = np.linalg.norm(reports[0].triangulated_mm - true_positions, axis=1)
        drawing_error = np.linalg.norm(drawn - true_positions, axis=1)
        intensity_error = cal.light_intensity - true_intensity / true_intensity.mean()

        rows: list[Row] = []
        lights_effect: list[float] = []
        sigma_px = prefilter_sigma_px(rig.heads["front"].width)
        ours_settings = ReconstructionSettings(method="near", integrator="masked", iterations=3)
        for scene_number, (shape, distance) in enumerate((s, d) for s in shapes for d in distances):
            path = folder / f"{shape}-{distance}.h5"
            last_frame = 5 * TRACKED_CYCLES - 1
            # the same rig and shapes for every scene (seed), the camera noise drawn anew for each:
            # with one draw for all, the one-cycle errors of every scene were one sample, not many
            simulate(path, config(scene=shape, protocol="static", seconds=5 * TRACKED_CYCLES / 110,
                                     distance_mm=float(distance), sway=Sway(0, 0, 0),
                                     truth_maps_at=[4, last_frame], noise_seed=1000 * seed + scene_number,
                                     **common))
            with SessionFile(path) as session:
                frame, signal, saturated, dark = _cycle(session, "front")
                truth = session.truth()
                true_normals = np.asarray(truth["front/normals"][0], dtype=np.float64)
                true_depth = np.asarray(truth["front/depth_mm"][0], dtype=np.float64)
                head = calibration.apply(session.rig).heads["front"]
                true_head = session.rig.heads["front"]
                # ours on a stream of a still subject: every cycle's own distance (its scatter
                # is the camera noise's), and their running average as `photopft process` and the
                # live view keep it (`distance_cycles`), at the last cycle
                stream = HeadReconstructor(head, cal.pseudo_light_vectors, replace(ours_settings, distance_cycles=1))
                last_depth = np.asarray(truth["front/depth_mm"][1], dtype=np.float64)
                true_lights = (true_positions, true_intensity, true_axis, true_mu)
                cycle_errors, floor_errors = [], []
                running = RunningDistance(ours_settings.distance_cycles)
                for newest, cycle_signal, cycle_saturated, cycle_dark in _cycles(session, "front"):
                    streamed = stream.reconstruct(cycle_signal, cycle_saturated, cycle_dark)
                    on_subject = streamed.mask & np.isfinite(last_depth) & np.isfinite(streamed.depth_mm)
                    cycle_errors.append(depth_errors(streamed.depth_mm, last_depth, on_subject)[0])
                    measured = streamed.distance_mm
                    running.update(measured)
                    floor_errors.append(_distance_floor(stream, cycle_signal, cycle_dark, last_depth, true_lights))
                # the depth scales with the distance: the error of the running average's map
                true_median = float(np.median(last_depth[on_subject]))
                tracked_error = (cycle_errors[-1] + true_median) * running.distance_mm / measured - true_median
            true_head = replace(true_head, light_positions_mm=true_positions, light_intensity=true_intensity)
            methods = {
                "traditional": (head, ReconstructionSettings(method="distant", integrator="masked")),
                "thesis": (head, ReconstructionSettings(method="near", distance="dmr", integrator="masked",
                                                        iterations=3)),
                "ours": (head, ours_settings),
            }
            results = {}
            for name, (h, settings) in methods.items():
                reconstructor = HeadReconstructor(h, cal.pseudo_light_vectors, settings)
                results[name] = reconstructor.reconstruct(signal, saturated, dark)
            valid = results["ours"].mask & np.isfinite(true_normals[..., 2])
            for name, result in results.items():
                ok = valid & np.isfinite(result.normals[..., 2]) & np.isfinite(result.depth_mm)
                offset, height = depth_errors(result.depth_mm, true_depth, ok)
                ours = name == "ours"
                rows.append(Row(shape, distance, name, angular_error(result.normals, true_normals, ok),
                                offset, height, tracked_error if ours else float("nan"),
                                float(np.std(cycle_errors)) if ours else float("nan")))
            # The noise floor: the same solver handed the true surface and the true lights.
            shadow = shadow_threshold(signal, valid, ours_settings.shadow_fraction)
            rays = HeadReconstructor(true_head)._rays
            points = np.ascontiguousarray(rays * np.nan_to_num(true_depth, nan=float(distance))[..., None])
            floor = np.full(true_head.shape + (3,), np.nan)
            calibrated = np.full(true_head.shape + (3,), np.nan)
            albedo = np.full(true_head.shape, np.nan)
            used = np.zeros(true_head.shape, dtype=np.int64)
            axis, mu = np.tile([0.0, 0.0, 1.0], (4, 1)), np.zeros(4)
            # the same solver: the images prefiltered as ours has them (core/reconstruction/prefilter.py)
            solved, solved_saturated = prefiltered(signal, saturated, sigma_px)
            near_light_normals(solved, points, true_positions, true_intensity, true_axis, true_mu, solved_saturated,
                               shadow, floor, albedo, used)
            near_light_normals(solved, points, cal.light_positions_mm, cal.light_intensity, axis, mu,
                               solved_saturated, shadow, calibrated, albedo, used)
            ok = valid & np.isfinite(floor[..., 2])
            rows.append(Row(shape, distance, "noise floor", angular_error(floor, true_normals, ok), floor_errors[0],
                            float("nan"), distance_sd_mm=float(np.std(floor_errors))))
            if sigma_px > 0:
                unfiltered = np.full(true_head.shape + (3,), np.nan)
                near_light_normals(signal, points, true_positions, true_intensity, true_axis, true_mu, saturated,
                                   shadow, unfiltered, albedo, used)
                rows.append(Row(shape, distance, "noise floor, unfiltered",
                                angular_error(unfiltered, true_normals, ok & np.isfinite(unfiltered[..., 2])),
                                float("nan"), float("nan")))
            both = ok & np.isfinite(calibrated[..., 2])
            lights_effect.append(angular_error(calibrated, floor, both))

    lines.append(f"## Accuracy (`photopft bench accuracy --scale {scale:g}"
                 + (f" --world {world}`)" if world != "ideal" else "`)"))
    lines.append("")
    lines.append(f"World: {world} ({world_words(world)}).")
    lines.append("")
    lines.append(f"Simulated 12-bit camera (18 000 e- full well, 12 e- read noise, shot noise), {scale:g} x "
                 f"1400 x 1024, front head; every method on the first light cycle, and ours also on a stream of "
                 f"{TRACKED_CYCLES} cycles of the subject standing still: the standard deviation of each cycle's "
                 "own distance (the camera noise's scatter), and the error of the running average "
                 "(`distance_cycles`, as `photopft process` and the live view keep it) at the last cycle. "
                 "The rig as built has every LED "
                 f"{led_offset_mm:g} mm off the drawing and intensities within 5 %; the lights come from a "
                 "simulated calibration (specular sphere at 7 places, then a matte sphere at the same places, "
                 f"each held {hold_cycles} light cycles, the {CAPTURE_SECONDS:g} s a capture records), "
                 f"not from the truth. Rig and shapes from seed {seed}; each scene's camera noise drawn anew "
                 "(`noise_seed`), so the one-cycle errors of different scenes are independent draws.")
    lines.append("")
    lines.append("Light calibration, error against the built rig per LED (mm): "
                 f"drawing {np.round(drawing_error, 1).tolist()}, specular triangulation "
                 f"{np.round(triangulated_error, 1).tolist()}, after the matte refinement "
                 f"{np.round(position_error, 1).tolist()}; intensity error {np.round(intensity_error, 4).tolist()}; "
                 f"normals with the calibrated lights against the true lights (true surface): mean "
                 f"{np.mean(lights_effect):.3f} deg, largest {np.max(lights_effect):.3f} deg.")
    lines.append("")
    lines.append("Methods: *traditional*: distant-light photometric stereo with the pseudo light vectors (thesis "
                 "eq. 3.4-3.7); *thesis*: per-pixel light vectors from the diffused-maxima distance (eq. 4.13); "
                 "*ours*: per-pixel lights with inverse-square falloff and intensities, distance from the "
                 "photometric residual, iterated; *noise floor*: the same solver with the true surface and "
                 "lights" + (f" (all methods see the images prefiltered with a Gaussian of {sigma_px:.2f} px, "
                             "core/reconstruction/prefilter.py; *unfiltered*: the floor without it)" if sigma_px > 0 else "")
                 + "; its distance: the same photometric distance fit (same pixels, noise model) handed the "
                 "true surface and lights, each cycle: the scatter that the camera noise alone leaves in one "
                 "cycle's distance. Distance error: median depth over the subject against the truth. Height error: mean "
                 "absolute depth error after removing the mean offset (masked integrator).")
    lines.append("")
    lines.append("| shape | distance (mm) | method | angular error (deg) | distance error (mm) | height error (mm) "
                 f"| distance sd, one cycle (mm) | distance error, {TRACKED_CYCLES} cycles (mm) |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for r in rows:
        lines.append(f"| {r.shape} | {r.distance_mm:.0f} | {r.method} | {r.angular_deg:.2f} | "
                     f"{_blank_nan(r.distance_error_mm, '+.1f')} | {_blank_nan(r.height_error_mm, '.2f')} | "
                     f"{_blank_nan(r.distance_sd_mm, '.1f')} | {_blank_nan(r.tracked_distance_error_mm, '+.1f')} |")
    lines.append("")
    ours = [r for r in rows if r.method == "ours"]
    floor_rows = [r for r in rows if r.method == "noise floor"]
    floors = {(r.shape, r.distance_mm): r.angular_deg for r in floor_rows}
    above = [r.angular_deg - floors[(r.shape, r.distance_mm)] for r in ours]
    lines.append("Summary (ours): angular error "
                 f"{min(r.angular_deg for r in ours):.2f}-{max(r.angular_deg for r in ours):.2f} deg, "
                 f"{min(above):+.2f} to {max(above):+.2f} deg above the noise floor; distance error "
                 f"{min(r.distance_error_mm for r in ours):+.1f} to {max(r.distance_error_mm for r in ours):+.1f} mm "
                 f"from one cycle (sd {min(r.distance_sd_mm for r in ours):.1f}-{max(r.distance_sd_mm for r in ours):.1f} "
                 "mm from cycle to cycle; the noise floor's sd "
                 f"{min(r.distance_sd_mm for r in floor_rows):.1f}-{max(r.distance_sd_mm for r in floor_rows):.1f} mm), "
                 f"{min(r.tracked_distance_error_mm for r in ours):+.1f} to "
                 f"{max(r.tracked_distance_error_mm for r in ours):+.1f} mm after {TRACKED_CYCLES}; "
                 f"height error {min(r.height_error_mm for r in ours):.2f}-{max(r.height_error_mm for r in ours):.2f} mm.")
    lines.append("Thesis (Table 4.3, Figure 4.5, real and synthetic data): angular error 4.53 deg (sphere), "
                 "2.33-2.36 deg (other shapes), traditional 6.5 deg; height error 6.6-11.8 mm; distance +-20 mm "
                 "over 1800-2200 mm.")
    lines.append(f"Run time {time.perf_counter() - started:.0f} s on this machine.")
    text = "\n".join(lines)
    if write:
        write_section(f"accuracy-{scale:g}" + ("" if world == "ideal" else f"-{world}"), text)
    return text


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench accuracy`: its arguments and what it runs."""
    a = what.add_parser("accuracy", help="normals, distance and height against the truth (thesis Table 4.3)")
    a.add_argument("--scale", type=positive, default=0.5)
    a.add_argument("--shapes", default=",".join(SHAPES))
    a.add_argument("--distances", default=",".join(map(str, DISTANCES)))
    a.add_argument("--seed", type=int, default=3)
    a.add_argument("--led-offset-mm", type=finite, default=12.0)
    a.add_argument("--world", choices=WORLD_NAMES, default="ideal",
                   help="realism of the simulated rig")
    a.add_argument("--no-write", action="store_true", help="print only")

    def run(args: argparse.Namespace) -> int:
        text = run_accuracy(args.scale, tuple(args.shapes.split(",")), tuple(int(d) for d in args.distances.split(",")),
                            args.seed, args.led_offset_mm, not args.no_write, args.world)
        print(text)
        return 0

    a.set_defaults(run=run)
