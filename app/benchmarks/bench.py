"""`photopft bench`: accuracy and speed figures, printed and written to docs/benchmarks.md."""

from __future__ import annotations

import argparse
import itertools
import os
import re
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from app.args import WORLD_NAMES, finite, positive

# The benches write their tables into the repository's docs/benchmarks.md: only from a source
# checkout (an installed or bundled application has no docs/ to write to, and reads nothing there)
_CHECKOUT = Path(__file__).resolve().parents[2]
DOCS = _CHECKOUT / "docs" / "benchmarks.md"


def in_checkout() -> bool:
    return (_CHECKOUT / "pyproject.toml").is_file() and DOCS.parent.is_dir()
SHAPES = ("sphere", "torso", "vase", "relief")
DISTANCES = (1800, 1900, 2000, 2100, 2200)
# The project's reference data, beside the checkout (never shipped with the application).
# ../shared beside the checkout, or where PHOTOPFT_SHARED says (as the tests read it)
# bench population --subset: a fixed subset of either population, quick enough to rerun between full runs
SUBSET_SUBJECTS = 8
SUBSET_SCALE = 0.25
SHARED = Path(os.environ.get("PHOTOPFT_SHARED", Path(__file__).resolve().parents[3] / "shared"))
DILIGENT_BEAR = SHARED / "data" / "diligent-integration" / "bear"


def write_section(name: str, text: str, path: Path = DOCS) -> None:
    """Replace (or add) the section between <!-- name --> markers in docs/benchmarks.md."""
    begin, end = f"<!-- {name} begin -->", f"<!-- {name} end -->"
    block = f"{begin}\n{text.rstrip()}\n{end}"
    current = path.read_text() if path.exists() else "# Benchmarks\n\nFigures measured by `photopft bench`.\n"
    if begin in current:
        current = re.sub(re.escape(begin) + ".*?" + re.escape(end), lambda _: block, current, flags=re.S)
    else:
        current = current.rstrip() + "\n\n" + block + "\n"
    path.write_text(current)


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
    from core.pipeline.process import cycle_signal

    frames, ids, stamps = session.frames(head_name), session.frame_id(head_name), session.timestamp_ns(head_name)
    max_value = session.rig.heads[head_name].max_value
    for window in complete_cycles(session.light_index(head_name), ids,
                                  session.rig.cycle_length)[::session.rig.cycle_length]:
        yield (window.newest, *cycle_signal(frames, window, None, max_value, {}, ids, stamps))


def _angular_error(normals: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    dot = np.clip(np.sum(normals[valid] * truth[valid], axis=-1), -1, 1)
    return float(np.degrees(np.mean(np.arccos(dot))))


def _depth_errors(depth: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> tuple[float, float]:
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
                    cycle_errors.append(_depth_errors(streamed.depth_mm, last_depth, on_subject)[0])
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
                offset, height = _depth_errors(result.depth_mm, true_depth, ok)
                ours = name == "ours"
                rows.append(Row(shape, distance, name, _angular_error(result.normals, true_normals, ok),
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
            rows.append(Row(shape, distance, "noise floor", _angular_error(floor, true_normals, ok), floor_errors[0],
                            float("nan"), distance_sd_mm=float(np.std(floor_errors))))
            if sigma_px > 0:
                unfiltered = np.full(true_head.shape + (3,), np.nan)
                near_light_normals(signal, points, true_positions, true_intensity, true_axis, true_mu, saturated,
                                   shadow, unfiltered, albedo, used)
                rows.append(Row(shape, distance, "noise floor, unfiltered",
                                _angular_error(unfiltered, true_normals, ok & np.isfinite(unfiltered[..., 2])),
                                float("nan"), float("nan")))
            both = ok & np.isfinite(calibrated[..., 2])
            lights_effect.append(_angular_error(calibrated, floor, both))

    lines.append(f"## Accuracy (`photopft bench accuracy --scale {scale:g}"
                 + (f" --world {world}`)" if world != "ideal" else "`)"))
    lines.append("")
    lines.append(f"World: {world} ({_world_words(world)}).")
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


def _world_words(world: str) -> str:
    """What a named world of the simulator holds, for a bench's table."""
    from core.sim.simulate import WORLDS, world_words

    settings = WORLDS[world]
    if not settings:
        return "the rig as drawn: isotropic point LEDs, matte surfaces, a pinhole camera"
    return world_words(settings)


def _noises_ml(text: str) -> list[float]:
    """--noise-ml: comma-separated noises of a map, 0 mL or more."""
    from app.errors import UserError

    try:
        noise = [finite(n) for n in text.split(",")]
    except argparse.ArgumentTypeError as exc:
        raise UserError(f"--noise-ml: {exc}") from exc
    if any(n < 0 for n in noise):
        raise UserError(f"--noise-ml takes noises of 0 mL or more, not {text}")
    return noise


def _publish(args: argparse.Namespace, section: str, heading: str, text: str) -> int:
    """Print a bench's table and, unless --no-write, put it in its section of docs/benchmarks.md."""
    print(text)
    if args.no_write:
        return 0
    if not in_checkout():
        print(f"not written: docs/benchmarks.md is written from a source checkout of photopft, and {_CHECKOUT} "
              "is not one", file=sys.stderr)
        return 0
    write_section(section, f"## {heading}\n\n{text}\n")
    return 0


def add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="measure accuracy and speed (writes docs/benchmarks.md)",
                       description="Benchmarks on the simulated rig; each prints its table and writes it to "
                                   "docs/benchmarks.md.")
    what = p.add_subparsers(dest="what", metavar="WHAT")
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
    sp = what.add_parser("speed", help="maps per second at 1400 x 1024 against numpy references")
    sp.add_argument("--no-write", action="store_true", help="print only")
    sp.set_defaults(run=lambda args: print(run_speed(not args.no_write)) or 0)
    ig = what.add_parser("integration", help="normals to depth on real data (DiLiGenT bear): error and time")
    ig.add_argument("--data", type=Path, default=None,
                    help=f"a folder of real normals and depth (default {DILIGENT_BEAR})")
    ig.add_argument("--no-write", action="store_true", help="print only")
    ig.set_defaults(run=lambda args: print(run_integration(args.data or DILIGENT_BEAR, not args.no_write)) or 0)
    mo = what.add_parser("motion", help="maps and the volume during a forced expiration, as captured, "
                                        "extrapolated and interpolated to one instant")
    mo.add_argument("--no-write", action="store_true", help="print only")
    mo.set_defaults(run=lambda args: print(run_motion(not args.no_write)) or 0)
    rec = what.add_parser("record", help="record from two fake GigE cameras and the simulated rig")
    rec.add_argument("--seconds", type=positive, default=60.0)
    rec.add_argument("--rate", type=positive, default=110.0, help="frames/s asked of the fake cameras")
    rec.add_argument("--compression", choices=("none", "blosc-lz4"), default="blosc-lz4",
                     help="the frames' filter, as a rig file's [recording] compression (default blosc-lz4)")
    rec.add_argument("--no-write", action="store_true", help="print only")
    rec.set_defaults(run=lambda args: print(run_record(args.seconds, not args.no_write, args.rate,
                                                       args.compression)) or 0)
    vol = what.add_parser("volume", help="tidal volume, VC, FVC, FEV1 and the optical volume against the truth")
    vol.add_argument("--scale", type=positive, default=0.25)
    vol.add_argument("--seconds", type=positive, default=60.0)
    vol.add_argument("--every", type=int, default=2, help="reconstruct every Nth cycle window (1: at the camera rate)")
    vol.add_argument("--world", choices=WORLD_NAMES, default="ideal",
                   help="realism of the simulated rig")
    vol.add_argument("--no-write", action="store_true", help="print only")

    def run_volume(args: argparse.Namespace) -> int:
        from app.benchmarks.volume import run_volume_bench

        text = run_volume_bench(args.scale, args.seconds, every=args.every, world=args.world)
        section = "volume" if args.world == "ideal" else f"volume-{args.world}"
        return _publish(args, section, f"Volume (`photopft bench volume --scale {args.scale:g} --seconds "
                                       f"{args.seconds:g} --every {args.every}"
                                       + (f" --world {args.world}" if args.world != "ideal" else "") + "`)",
                        f"World: {args.world} ({_world_words(args.world)}).\n\n{text}")

    vol.set_defaults(run=run_volume)
    from core.sim.breathing import PROTOCOLS  # as simulate's parser takes them (app/commands/session.py)

    sc = what.add_parser("scales", help="the metric volume's slope on the truth, one session rendered at several "
                                        "of the camera's scales")
    sc.add_argument("--bodies", default="torso,average-man,random-1004",
                    help="torso (our own) or bodies as simulate --body names them, comma-separated")
    sc.add_argument("--scales", default="0.25,0.5,1")
    sc.add_argument("--protocol", choices=[p for p in PROTOCOLS if p != "static"], default="vc",
                    help="the simulated protocol (simulate --protocol; static holds no breath to compare)")
    sc.add_argument("--seconds", type=positive, default=None, help="the protocol's length (default: its own)")
    sc.add_argument("--seed", type=int, default=1)
    sc.add_argument("--world", choices=WORLD_NAMES, default="ideal", help="realism of the simulated rig")
    sc.add_argument("--no-write", action="store_true", help="print only")

    def run_scales(args: argparse.Namespace) -> int:
        from app.benchmarks.scales import named_body, run_scales_bench
        from app.errors import UserError

        try:  # each name and scale checked before the first body's minutes of rendering
            scales = tuple(positive(s) for s in args.scales.split(","))
            bodies = tuple(args.bodies.split(","))
            for body in bodies:
                if body != "torso":
                    named_body(body, args.seed)
        except (argparse.ArgumentTypeError, ValueError) as exc:
            raise UserError(f"--scales {args.scales} --bodies {args.bodies}: {exc}") from exc
        text = run_scales_bench(bodies, scales, args.protocol, args.seconds, args.seed, args.world)
        section = "scales" if args.world == "ideal" else f"scales-{args.world}"
        command = " ".join(f"--{k} {v}" for k, v in (("bodies", args.bodies), ("scales", args.scales),
                                                     ("protocol", args.protocol), ("seconds", args.seconds),
                                                     ("seed", args.seed), ("world", args.world)) if v is not None)
        return _publish(args, section, f"Scales (`photopft bench scales {command}`)",
                        f"World: {args.world} ({_world_words(args.world)}).\n\n{text}")

    sc.set_defaults(run=run_scales)
    pr = what.add_parser("process", help="the whole `photopft process` at the camera's resolution, against real time")
    pr.add_argument("--seconds", type=positive, default=2.0)
    pr.add_argument("--scale", type=positive, default=1.0)
    pr.add_argument("--workers", default=None, help="worker counts to time, comma-separated (default 1,2,...,cores)")
    pr.add_argument("--no-write", action="store_true", help="print only")

    def run_process(args: argparse.Namespace) -> int:
        from app.benchmarks.process import run_process_bench

        counts = (tuple(int(w) for w in args.workers.split(",")) if args.workers
                  else tuple(range(1, min(os.cpu_count() or 1, 2) + 1)))
        text = run_process_bench(args.seconds, args.scale, counts)
        return _publish(args, "process", f"Process (`photopft bench process --seconds {args.seconds:g}"
                                         f"{'' if args.scale == 1 else f' --scale {args.scale:g}'}`)", text)

    pr.set_defaults(run=run_process)
    po = what.add_parser("population", help="clinical values of simulated subjects in a clinic-like world, "
                                            "against the truth (Bland-Altman)")
    po.add_argument("--subjects", type=int, default=30)
    po.add_argument("--scale", type=positive, default=0.5)
    po.add_argument("--seed", type=int, default=1)
    po.add_argument("--quick", action="store_true", help="two small subjects and 14 s each (what the tests run)")
    po.add_argument("--workers", type=int, default=None, help="subjects at once (default: one per core)")
    po.add_argument("--waveforms", type=Path, default=SHARED / "data" / "spirometry-waveforms",
                    help="the standard test waveforms the blows follow (default ../shared/data/spirometry-waveforms)")
    po.add_argument("--max-sheen", type=finite, default=None,
                    help="skin sheen drawn from 0 to this (default 0.3; 0: matte skin)")
    po.add_argument("--world", choices=tuple(w for w in WORLD_NAMES if w != "ideal"), default="clinic-widening",
                    help="the clinic's rig, or the same behind crossed polarisers on the LEDs and lenses, or that "
                         "with bodies whose trunk widens as they breathe (clinic-widening, the default)")
    po.add_argument("--bodies", choices=("parametric", "mesh"), default="parametric",
                    help="the development population (parametric trunks, the default) or the test population "
                         "(MakeHuman body meshes from ../shared/data/makehuman, ray-cast; no method is tuned on it)")
    po.add_argument("--keep", type=Path, default=None,
                    help="keep each finished subject here and, run again, go on from them (long runs)")
    po.add_argument("--renders", type=Path, default=None, metavar="DIR",
                    help="keep the subjects' rendered sessions here and reuse them while the simulator's code is "
                         "unchanged: a rerun after a change to the reconstruction or the analysis costs "
                         "calibration and processing only")
    po.add_argument("--renders-max-gb", type=positive, default=40.0,
                    help="the renders kept at most (GB); the least recently used are removed first")
    po.add_argument("--subset", action="store_true",
                    help=f"the fixed subset for use between full runs: the population's first {SUBSET_SUBJECTS} "
                         f"subjects at scale {SUBSET_SCALE:g} (overrides --subjects and --scale)")
    po.add_argument("--no-write", action="store_true", help="print only")

    def run_population(args: argparse.Namespace) -> int:
        from app.benchmarks.population import run_population_bench

        if args.subjects < 1:
            from app.errors import UserError

            raise UserError("--subjects must be 1 or more")
        if args.keep is not None and args.keep.exists() and not args.keep.is_dir():
            from app.errors import UserError

            raise UserError(f"{args.keep}: --keep must be a folder (the finished subjects are kept in it), this is a file")
        if args.subset:
            args.subjects, args.scale = SUBSET_SUBJECTS, SUBSET_SCALE
        if args.renders is not None and args.renders.exists() and not args.renders.is_dir():
            from app.errors import UserError

            raise UserError(f"{args.renders}: --renders must be a folder (the rendered sessions are kept in it), "
                            "this is a file")
        subjects = 2 if args.quick else args.subjects
        workers = max(1, min(subjects, args.workers or os.cpu_count() or 1))
        images = None if args.no_write or not in_checkout() else DOCS.parent / "images"
        from app.benchmarks.population import MAX_SHEEN, WORLD, population_section

        sheen = MAX_SHEEN if args.max_sheen is None else args.max_sheen
        from app.benchmarks.renders import RenderCache

        renders = RenderCache(args.renders, args.renders_max_gb * 1e9) if args.renders is not None else None
        text, _ = run_population_bench(subjects, args.scale, args.seed, args.quick, workers, args.waveforms, images,
                                       sheen, args.keep, args.world, args.bodies, renders)
        suffix = ("" if sheen == MAX_SHEEN else f" --max-sheen {sheen:g}") + (
            "" if args.world == WORLD else f" --world {args.world}") + (
            " --bodies mesh" if args.bodies == "mesh" else "")
        section = population_section(args.scale, sheen, args.world, args.bodies)
        return _publish(args, section, f"Population (`photopft bench population --subjects {subjects} --scale "
                                       f"{args.scale:g} --seed {args.seed}{suffix}`)", text)

    po.set_defaults(run=run_population)
    lv = what.add_parser("live", help="the live view's metric volume against the simulated subject's true volume")
    lv.add_argument("--seconds", type=positive, default=60.0)
    lv.add_argument("--scale", type=positive, default=0.25)
    lv.add_argument("--seed", type=int, default=1)
    lv.add_argument("--no-write", action="store_true", help="print only")

    def run_live(args: argparse.Namespace) -> int:
        from app.benchmarks.live import run_live_bench

        text, _ = run_live_bench(args.seconds, args.scale, args.seed)
        return _publish(args, f"live-{args.scale:g}", f"Live volume (`photopft bench live --seconds {args.seconds:g} "
                                                      f"--scale {args.scale:g}`)", text)

    lv.set_defaults(run=run_live)
    li = what.add_parser("lights", help="light calibration from simulated sphere sessions of rigs as built, against "
                                        "their truth")
    li.add_argument("--rigs", type=int, default=6)
    li.add_argument("--scale", type=positive, default=0.5)
    li.add_argument("--seed", type=int, default=1)
    li.add_argument("--workers", type=int, default=None, help="rigs at once (default: one per core)")
    li.add_argument("--no-write", action="store_true", help="print only")

    def run_lights(args: argparse.Namespace) -> int:
        from app.benchmarks.lights import run_lights_bench

        if args.rigs < 1:
            from app.errors import UserError

            raise UserError("--rigs must be 1 or more")
        workers = max(1, min(args.rigs, args.workers or os.cpu_count() or 1))
        text, _ = run_lights_bench(args.rigs, args.scale, args.seed, workers)
        return _publish(args, f"lights-{args.scale:g}", f"Light calibration (`photopft bench lights --rigs {args.rigs} "
                                                        f"--scale {args.scale:g} --seed {args.seed}`)", text)

    li.set_defaults(run=run_lights)
    bl = what.add_parser("blows", help="the standard waveforms read as optical maps with noise: FEV1, FVC, "
                                       "acceptability and PEF, read straight and fitted")
    bl.add_argument("--noise-ml", default="0,5,10,15,20,25,35", help="noise of a map, mL (comma-separated)")
    bl.add_argument("--phases", type=int, default=4, help="phases of the light cycle each waveform is sampled at")
    bl.add_argument("--draws", type=int, default=2, help="noise draws per phase and noise")
    bl.add_argument("--seed", type=int, default=0)
    bl.add_argument("--waveforms", type=Path, default=SHARED / "data" / "spirometry-waveforms",
                    help="the standard test waveforms (default ../shared/data/spirometry-waveforms)")
    bl.add_argument("--every-frame", action="store_true",
                    help="one map a frame (1/110 s), as process makes through the top of each forced blow")
    bl.add_argument("--no-write", action="store_true", help="print only")

    def run_blows(args: argparse.Namespace) -> int:
        from app.benchmarks.blows import run_blows_bench
        from app.errors import UserError

        noise = _noises_ml(args.noise_ml)
        if args.phases < 1 or args.draws < 1:
            raise UserError("--phases and --draws take 1 or more")
        try:
            text = run_blows_bench(args.waveforms, noise, args.phases, args.draws, args.seed, args.every_frame)
        except (FileNotFoundError, ValueError) as exc:
            raise UserError(str(exc)) from exc
        frames = " --every-frame" if args.every_frame else ""
        return _publish(args, "blows-frames" if args.every_frame else "blows",
                        f"Forced expirations read through the maps' noise (`photopft bench blows "
                        f"--noise-ml {args.noise_ml} --phases {args.phases} --draws {args.draws} "
                        f"--seed {args.seed}{frames}`)", text)

    bl.set_defaults(run=run_blows)
    ti = what.add_parser("tidal", help="the population's quiet breathing read as optical maps with noise: TV and RR")
    ti.add_argument("--subjects", type=int, default=30)
    ti.add_argument("--seed", type=int, default=1, help="the population's seed (bench population's)")
    ti.add_argument("--noise-ml", default="0,5,10,15,20,25,35", help="noise of a map, mL (comma-separated)")
    ti.add_argument("--draws", type=int, default=4, help="noise draws per subject and noise")
    ti.add_argument("--no-write", action="store_true", help="print only")

    def run_tidal(args: argparse.Namespace) -> int:
        from app.benchmarks.tidal import run_tidal_bench
        from app.errors import UserError

        noise = _noises_ml(args.noise_ml)
        if args.subjects < 1 or args.draws < 1:
            raise UserError("--subjects and --draws take 1 or more")
        try:
            text = run_tidal_bench(args.subjects, args.seed, noise, args.draws)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
        return _publish(args, "tidal", f"Quiet breathing read through the maps' noise (`photopft bench tidal "
                                       f"--subjects {args.subjects} --seed {args.seed} --noise-ml {args.noise_ml} "
                                       f"--draws {args.draws}`)", text)

    ti.set_defaults(run=run_tidal)
    co = what.add_parser("compression", help="lossless HDF5 filters on the rig's frames: ratio, MB/s, GB a minute")
    co.add_argument("--scale", type=positive, default=1.0)
    co.add_argument("--frames", type=int, default=110)
    co.add_argument("--no-write", action="store_true", help="print only")

    def run_compression(args: argparse.Namespace) -> int:
        from app.benchmarks.compression import run_compression_bench

        text = run_compression_bench(args.scale, max(1, args.frames))
        return _publish(args, "compression", "Compression (`photopft bench compression`"
                        + (f" --scale {args.scale:g}" if args.scale != 1 else "") + ")", text)

    co.set_defaults(run=run_compression)
    gui = what.add_parser("gui", help="the live view: display updates/s, GUI-thread stalls, maps/s, memory")
    gui.add_argument("--scale", type=positive, default=0.5)
    gui.add_argument("--seconds", type=positive, default=20.0)
    gui.add_argument("--no-record", action="store_true", help="live view only (no session file written)")
    gui.add_argument("--warmup", type=positive, default=30.0,
                     help="seconds of live view before the measurement (as while positioning the patient)")
    gui.add_argument("--loop", type=int, default=0, metavar="CYCLES",
                     help="render this many light cycles once and deliver them in a loop (the renderer then does "
                          "not limit the rate; the images repeat)")
    gui.add_argument("--no-write", action="store_true", help="print only")

    def run_gui(args: argparse.Namespace) -> int:
        from app.benchmarks.gui import run_gui_bench

        text = run_gui_bench(args.scale, args.seconds, not args.no_record, args.warmup, args.loop)
        return _publish(args, f"gui-{args.scale:g}-{'live' if args.no_record else 'recording'}"
                              + (f"-loop{args.loop}" if args.loop else ""),
                        f"Live view (`photopft bench gui --scale {args.scale:g} --seconds {args.seconds:g}"
                        f"{' --no-record' if args.no_record else ''}{f' --loop {args.loop}' if args.loop else ''}`)",
                        text)

    gui.set_defaults(run=run_gui)
    p.set_defaults(run=lambda args: p.print_help() or 2)


def _rate(function, repeat: int) -> float:
    function()
    started = time.perf_counter()
    for _ in range(repeat):
        function()
    return repeat / (time.perf_counter() - started)


def numpy_near_normals(signal: np.ndarray, points: np.ndarray, positions: np.ndarray,
                       intensity: np.ndarray) -> np.ndarray:
    """Plain numpy reference: per-pixel light vectors and falloff, a 3 x 3 solve per pixel."""
    d = positions[None, None] - points[:, :, None, :]
    r2 = np.sum(d * d, axis=-1)
    rows = d / (np.sqrt(r2) * r2)[..., None] * intensity[None, None, :, None]
    normal = np.einsum("hwki,hwkj->hwij", rows, rows)
    rhs = np.einsum("hwki,khw->hwi", rows, signal)
    m = np.linalg.solve(normal, rhs[..., None])[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        return m / np.linalg.norm(m, axis=-1, keepdims=True)


def numpy_poisson(gu: np.ndarray, gv: np.ndarray) -> np.ndarray:
    """Plain numpy reference: Poisson solve by FFT of the mirrored gradient field (Frankot-Chellappa)."""
    gu = np.nan_to_num(gu)
    gv = np.nan_to_num(gv)
    h, w = gu.shape
    gu_m = np.block([[gu, -gu[:, ::-1]], [gu[::-1, :], -gu[::-1, ::-1]]])
    gv_m = np.block([[gv, gv[:, ::-1]], [-gv[::-1, :], -gv[::-1, ::-1]]])
    fy = np.fft.fftfreq(2 * h)[:, None] * 2 * np.pi
    fx = np.fft.fftfreq(2 * w)[None, :] * 2 * np.pi
    denominator = fx**2 + fy**2
    denominator[0, 0] = 1.0
    z = (-1j * fx * np.fft.fft2(gu_m) - 1j * fy * np.fft.fft2(gv_m)) / denominator
    z[0, 0] = 0.0
    return np.real(np.fft.ifft2(z))[:h, :w]


def run_speed(write: bool, repeat: int = 20) -> str:
    import cv2
    import numba

    from core.reconstruction.integrate import ROBUST_ITERATIONS, integrate_masked, log_depth_dct, log_depth_gradients
    from core.reconstruction.lightfield import LightField, light_field, normals_from_field
    from core.reconstruction.photometric import distant_light_normals
    from core.reconstruction.pipeline import default_pseudo_light_vectors, subject_mask
    from core.reconstruction.prefilter import prefilter_frame, prefilter_sigma_px
    from core.io.session import SessionFile
    from core.sim.breathing import Sway
    from core.sim.simulate import SimConfig, simulate

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "torso.h5"
        simulate(path, SimConfig(scene="torso", protocol="static", seconds=5 / 110, scale=1.0, heads=("front",),
                                 sway=Sway(0, 0, 0), truth_maps_at=[4]))
        with SessionFile(path) as s:
            head = s.rig.heads["front"]
            frames = s.frames("front")[:5]
            truth_depth = np.asarray(s.truth()["front/depth_mm"][0], dtype=np.float64)
    lit = np.ascontiguousarray(frames[:4])
    dark = np.ascontiguousarray(frames[4])
    signal = lit.astype(np.float64) - dark.astype(np.float64)
    mask = subject_mask(signal, 0.1)
    depth = np.where(mask, np.nan_to_num(truth_depth, nan=2000.0), np.nan)
    pseudo = default_pseudo_light_vectors(head)
    field = light_field(head, depth)
    rows = np.broadcast_to((pseudo * head.light_intensity[:, None] / 2000.0**2)[None, None],
                           field.rows.shape).astype(np.float32)
    distant_field = LightField(field.step, np.ascontiguousarray(rows),
                               np.ascontiguousarray(np.broadcast_to(np.linalg.pinv(rows[0, 0]), field.pinv.shape)))
    full = float(head.max_value)
    normals = np.empty(head.shape + (3,), np.float32)
    albedo = np.empty(head.shape, np.float32)
    min_signal = 0.01 * full
    points = np.ascontiguousarray((np.stack(np.broadcast_arrays(
        ((np.arange(head.width) - head.cx) / head.fx)[None], ((np.arange(head.height) - head.cy) / head.fy)[:, None],
        1.0), -1) * np.nan_to_num(depth, nan=2000.0)[..., None]))
    figures = {
        "distant": _rate(lambda: normals_from_field(lit, dark, distant_field, min_signal, full, normals, albedo),
                         repeat),
        "distant_numpy": _rate(lambda: distant_light_normals(lit, dark, pseudo), 3),
        "near": _rate(lambda: normals_from_field(lit, dark, field, min_signal, full, normals, albedo), repeat),
        "near_numpy": _rate(lambda: numpy_near_normals(signal, points, head.light_positions_mm,
                                                       head.light_intensity), 2),
        "field": _rate(lambda: light_field(head, depth), 5),
    }
    # At 1400 px wide the pipeline solves from prefiltered images (core/reconstruction/prefilter.py): in a stream
    # each frame is filtered once as it arrives, so a map costs one frame's filter more.
    sigma_px = prefilter_sigma_px(head.width)
    filtered_lit = np.stack([prefilter_frame(frame, sigma_px) for frame in lit])
    filtered_dark = prefilter_frame(dark, sigma_px)
    arriving = itertools.count()

    def near_prefiltered() -> None:
        k = next(arriving) % 4
        prefilter_frame(lit[k], sigma_px, out=filtered_lit[k])
        normals_from_field(filtered_lit, filtered_dark, field, min_signal, full, normals, albedo)

    # OpenCV on one thread: its pool's threads, spinning after each call, held up numba's
    # (measured in a stream of frames: 96 maps/s with OpenCV's two threads, 106 with one)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        figures["near_prefiltered"] = _rate(near_prefiltered, repeat)
    finally:
        cv2.setNumThreads(threads)
    near_normals, _ = normals_from_field(lit, dark, field, min_signal, full)
    figures["depth_fast"] = _rate(lambda: log_depth_dct(near_normals, mask, head.fx, head.fy, head.cx, head.cy),
                                  repeat)

    def numpy_depth() -> None:
        g1, g2 = log_depth_gradients(near_normals.astype(np.float64), head.fx, head.fy, head.cx, head.cy)
        numpy_poisson(np.where(mask, g1, 0.0), np.where(mask, g2, 0.0))

    figures["depth_numpy"] = _rate(numpy_depth, 3)
    gradients = log_depth_gradients(near_normals, head.fx, head.fy, head.cx, head.cy)
    figures["depth_masked"] = _rate(lambda: integrate_masked(*gradients, mask, robust_iterations=0), 5)
    figures["depth_robust"] = _rate(lambda: integrate_masked(*gradients, mask), 3)

    lines = ["## Speed (`photopft bench speed`)", "",
             f"One head at {head.width} x {head.height}, a rendered torso cycle, {numba.get_num_threads()} threads, "
             "maps per second (higher is better); each against a plain numpy implementation of the same "
             "computation, timed in the same run.", "",
             "| what | photopft | numpy reference | ratio |", "|---|---|---|---|",
             f"| distant-light normal maps | {figures['distant']:.1f}/s | {figures['distant_numpy']:.1f}/s | "
             f"{figures['distant'] / figures['distant_numpy']:.1f}x |",
             f"| near-light normal maps (light field on a {field.step}-px grid) | {figures['near']:.1f}/s | "
             f"{figures['near_numpy']:.2f}/s (per-pixel solve) | {figures['near'] / figures['near_numpy']:.0f}x |",
             f"| the same from prefiltered frames (Gaussian, sigma {sigma_px:.2f} px; one frame filtered per map) | "
             f"{figures['near_prefiltered']:.1f}/s | | |",
             f"| light field update (when the depth changes) | {figures['field']:.1f}/s | | |",
             f"| depth maps, fast (DCT, log-depth) | {figures['depth_fast']:.1f}/s | {figures['depth_numpy']:.1f}/s "
             f"(FFT Poisson) | {figures['depth_fast'] / figures['depth_numpy']:.1f}x |",
             f"| depth maps, masked least squares (the default; conjugate gradients, DCT-preconditioned) | "
             f"{figures['depth_masked']:.1f}/s | | |",
             f"| the same, robust to depth steps (reweighted {ROBUST_ITERATIONS} times; a cycle's final depth) | "
             f"{figures['depth_robust']:.1f}/s | | |", "",
             "Targets: near-light normal maps >= 110/s per head (the camera rate), depth maps >= 25/s."]
    text = "\n".join(lines)
    if write:
        write_section("speed", text)
    return text


def run_integration(folder: Path, write: bool, repeat: int = 10) -> str:
    """Both integrators of depth_from_normals on real normals with their true depth: the mean
    absolute depth error after the offset, and the median time of `repeat` runs."""
    import numba

    from core.io.diligent import load_real_surface, mean_abs_depth_error_mm
    from core.reconstruction.integrate import ROBUST_ITERATIONS, depth_from_normals

    surface = load_real_surface(folder)
    anchor = float(np.median(surface.depth_mm[surface.mask]))
    rows = []
    for method, label in (("masked", f"accurate: masked least squares, reweighted {ROBUST_ITERATIONS} times "
                                     "(the default)"),
                          ("dct", "fast: DCT Poisson on the whole image, gradients zeroed off the mask "
                                  "(`--integrator dct`)")):
        times = []
        for _ in range(repeat):
            started = time.perf_counter()
            depth = depth_from_normals(surface.normals, surface.mask, *surface.intrinsics, anchor, method)
            times.append(time.perf_counter() - started)
        error, given = mean_abs_depth_error_mm(depth, surface.depth_mm, surface.mask)
        rows.append(f"| {label} | {error:.3f} | {100 * given:.2f} % | {1000 * np.median(times):.0f} ms |")
    h, w = surface.mask.shape
    lines = ["## Integration on real data (`photopft bench integration`)", "",
             f"{folder.name} ({folder.parent.name}): real normals and depth, {w} x {h}, "
             f"{int(surface.mask.sum())} pixels on the object; perspective, metric, anchored at the median true "
             f"depth; error: mean absolute depth error after removing the offset; time: median of {repeat} runs, "
             f"{numba.get_num_threads()} numba threads.", "",
             "| integrator | error (mm) | pixels given a depth | time |", "|---|---|---|---|", *rows, "",
             "Target: the accurate solver at most 1.0 mm. For reference (the data's README): BiNI 0.334 mm in about "
             "1.3 s; a plain orthographic DCT Poisson solve 3.27 mm in about 20 ms."]
    text = "\n".join(lines)
    if write:
        write_section("integration", text)
    return text


MOTION_LABELS = {"none": "as captured", "extrapolated": "extrapolated", "interpolated": "interpolated"}


def run_motion(write: bool, scale: float = 0.25) -> str:
    """Maps during a forced expiration, and the metric volume through it, with each light's frame as
    captured, extrapolated from the cycle before and interpolated towards the cycle after."""
    import h5py

    from core.io.results import optical_volume
    from core.io.session import SessionFile
    from core.reconstruction.pipeline import ReconstructionSettings
    from app.benchmarks.true_lights import with_true_lights
    from core.pipeline.process import MOTION_MODES, process_session
    from core.sim.breathing import Sway
    from core.sim.simulate import SimConfig, simulate

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        session = folder / "forced.h5"
        blow_frame = 692  # the blow starts 6.29 s in: one tidal breath, 1.6 s inhalation, 0.4 s hold
        frames = [blow_frame + k for k in (2, 7, 12, 17, 22, 27, 32, 42, 52, 62)]
        simulate(session, SimConfig(protocol="forced", seconds=8.0, scale=scale, heads=("front",),
                                    sway=Sway(0, 0, 0), truth_maps_at=frames))
        with SessionFile(session) as s:
            calibration = with_true_lights(s)
            truth = s.truth()
            true_normals = truth["front/normals"][:]
            true_depth = truth["front/depth_mm"][:]
        table = {}
        for mode in MOTION_MODES:
            out = folder / f"r-{mode}.h5"
            process_session(session, out, calibration=calibration, maps_at=frames, heads=["front"], every=1000,
                            motion_compensation=mode,
                            settings=ReconstructionSettings(integrator="masked", iterations=3))
            with h5py.File(out) as f:
                normals = f["heads/front/maps/normals"][:]
                depth = f["heads/front/maps/depth_mm"][:]
            angles, heights = [], []
            for k in range(len(frames)):
                ok = np.isfinite(normals[k][..., 2]) & np.isfinite(true_normals[k][..., 2])
                angles.append(_angular_error(normals[k], true_normals[k], ok))
                heights.append(_depth_errors(depth[k], true_depth[k], ok)[1])
            table[mode] = (angles, heights)
        # the volume through the blow: both heads, every light cycle, as `process` makes it
        both = folder / "forced-both.h5"
        simulate(both, SimConfig(protocol="forced", seconds=9.0, scale=scale, sway=Sway(0, 0, 0), truth_maps_at=[],
                                 seed=2))
        with SessionFile(both) as s:
            calibration = with_true_lights(s)
            truth_t, truth_v = s.truth()["timestamp_ns"][:], s.truth()["volume_l"][:]
        volumes = {}
        for mode in MOTION_MODES:
            out = folder / f"v-{mode}.h5"
            process_session(both, out, calibration=calibration, motion_compensation=mode)
            t_ns, volume = optical_volume(out)
            volumes[mode] = _volume_through_blow(t_ns, volume, np.interp(t_ns, truth_t, truth_v))
    lines = ["## Motion within a cycle (`photopft bench motion`)", "",
             f"A forced expiration (PEF 9.6 L/s), front head at {scale:g} x 1400 x 1024, true lights, no sway; maps "
             "during the first 0.6 s of the blow, against the true surface at the map's (newest) frame. "
             "Each light's frame as captured, extrapolated to the newest frame's instant along the same light's "
             "frame one cycle earlier (the live view), or interpolated towards its frame one cycle later "
             "(`process`); the change spatially smoothed, 2 px.", "",
             "| ms after the blow starts | " + " | ".join(f"{(f - blow_frame) / 0.11:.0f}" for f in frames) + " |",
             "|---|" + "---|" * len(frames)]
    for mode, label in MOTION_LABELS.items():
        angles, heights = table[mode]
        lines.append(f"| angular error (deg), {label} | " + " | ".join(f"{a:.2f}" for a in angles) + " |")
        lines.append(f"| height error (mm), {label} | " + " | ".join(f"{h:.2f}" for h in heights) + " |")
    lines += ["", "Mean height error " + ", ".join(f"{np.mean(table[m][1]):.2f} mm {label}"
                                                   for m, label in MOTION_LABELS.items())
              + "; mean angular error " + ", ".join(f"{np.mean(table[m][0]):.2f}" for m in MOTION_LABELS) + " deg.",
              "", "The metric volume through a forced expiration (our torso, both heads, 9 s, seed 2, true lights, "
              "no sway, every light cycle, `process` defaults but the motion), against the true volume at each "
              "map's instant after a straight-line fit (its slope the scale); PEF read straight from the samples "
              "against the truth sampled at the same instants:", "",
              "| frames | slope | residual rms (mL) | largest residual (mL) | PEF (L/s) | truth's PEF at those instants |",
              "|---|---|---|---|---|---|"]
    for mode, label in MOTION_LABELS.items():
        v = volumes[mode]
        lines.append(f"| {label} | {v['slope']:.4f} | {v['rms_ml']:.1f} | {v['largest_ml']:.1f} | {v['pef']:.2f} | "
                     f"{v['true_pef']:.2f} |")
    text = "\n".join(lines)
    if write:
        write_section("motion", text)
    return text


def _volume_through_blow(t_ns: np.ndarray, volume_l: np.ndarray, truth_l: np.ndarray) -> dict[str, float]:
    """A volume curve against the truth at its samples: the slope and residuals of a straight-line fit,
    and the largest fall in L/s between samples (PEF read straight) of each."""
    ok = np.isfinite(volume_l)
    t, v, true = t_ns[ok] / 1e9, volume_l[ok], truth_l[ok]
    design = np.c_[true, np.ones(len(true))]
    coef = np.linalg.lstsq(design, v, rcond=None)[0]
    residual = v - design @ coef
    return {"slope": float(coef[0]), "rms_ml": 1000 * float(residual.std()),
            "largest_ml": 1000 * float(np.abs(residual).max()),
            "pef": float(np.max(-np.diff(v) / np.diff(t))), "true_pef": float(np.max(-np.diff(true) / np.diff(t)))}


def run_record(seconds: float, write: bool, rate_hz: float = 110.0, compression: str = "blosc-lz4") -> str:
    """Two fake GigE cameras at 1400 x 1024 with the flow emulator, then the simulated rig at 700 x 512."""
    import resource
    import shutil
    import subprocess

    from core.rig import Rig, thesis_head
    from core.io.session import SubjectRecord
    from drivers.camera import AravisCamera, CameraSettings, find_aravis_device
    from drivers.flowsensor import FlowSensor, FlowSensorEmulator
    from drivers.light_phase import LightPhase
    from drivers.recorder import Recorder

    def cpu_s() -> float:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    lines = [f"## Recording (`photopft bench record --seconds {seconds:g} --compression {compression}`)", ""]
    fake = shutil.which("arv-fake-gv-camera-0.8")
    rows, sizes = [], []  # sizes: the file's MB per second recorded, as it landed on the disk
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)

        def record_aravis(identifiers: dict[str, str], interfaces: tuple[str, ...]):
            cameras = {}
            for head, identifier in identifiers.items():
                camera = AravisCamera(identifier, buffers=64, interfaces=interfaces, name=head)
                camera.configure(CameraSettings(width=1400, height=1024, pixel_format="Mono8", frame_rate_hz=rate_hz))
                cameras[head] = camera
            heads = {h: thesis_head(h, bit_depth=8) for h in cameras}
            rig = Rig("bench-aravis", heads, frame_rate_hz=rate_hz)
            with FlowSensorEmulator() as emulator:
                flow = FlowSensor(emulator.port)
                recorder = Recorder(folder / "aravis.h5", rig, cameras, LightPhase(rig, first_trigger=0), flow,
                                    (0.0075, -15.36), SubjectRecord("BENCH", "male", 30, 175, 75), queue_items=4000,
                                    compression=compression)
                cpu0 = cpu_s()
                summary = recorder.run(seconds)
                cpu = (cpu_s() - cpu0) / summary.elapsed_s
                flow.close()
            sizes.append(summary.path.stat().st_size / summary.elapsed_s / 1e6)
            summary.path.unlink()  # a minute at 1400 x 1024 is about 19 GB: one recording on the disk at a time
            for camera in cameras.values():
                camera.close()
            return summary, cpu

        # Aravis' in-process Fake interface: each opening of Fake_1 is a camera of its own
        rows.append(("two in-process Aravis Fake cameras, 1400 x 1024 Mono8, flow emulator",
                     *record_aravis({"front": "Fake_1", "back": "Fake_1"}, ("Fake",))))
        if fake is not None:
            subprocess.run(["ip", "addr", "add", "127.0.0.2/8", "dev", "lo"], capture_output=True)
            processes = [subprocess.Popen([fake, "-i", a, "-s", s], stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL)
                         for a, s in (("127.0.0.1", "BENCHF"), ("127.0.0.2", "BENCHB"))]
            try:
                for serial in ("BENCHF", "BENCHB"):
                    for _ in range(50):
                        try:
                            find_aravis_device(serial)
                            break
                        except Exception:
                            time.sleep(0.2)
                rows.append(("two fake GigE cameras (arv-fake-gv-camera on the loopback), 1400 x 1024 Mono8, "
                             "flow emulator", *record_aravis({"front": "BENCHF", "back": "BENCHB"}, ())))
            finally:
                for process in processes:
                    process.kill()
                    process.wait()
        from core.sim.breathing import Sway
        from core.sim.simulate import SimConfig
        from drivers.simulated import SimCamera, SimFlowSensor, SimulatedRigState

        for loop_cycles, name in ((0, "simulated rig, 700 x 512 (binned size for a gigabit link), 12-bit, flow "
                                      "sensor, every frame rendered on the same 2 cores"),
                                  (22, "simulated rig as above, 22 light cycles (1 s) rendered beforehand and "
                                       "delivered in a loop, so the renderer does not limit the rate")):
            state = SimulatedRigState.build(SimConfig(protocol="tidal", seconds=seconds + 5, scale=0.5, sway=Sway()))
            cameras = {h: SimCamera(state, h, loop_cycles=loop_cycles) for h in state.rig.heads}
            for camera in cameras.values():
                camera.start()
            state.start_ns = time.monotonic_ns()  # the clock starts once the loops are rendered
            recorder = Recorder(folder / "sim.h5", state.rig, cameras, LightPhase(state.rig),
                                SimFlowSensor(state), (0.0075, -15.36), SubjectRecord("BENCH", "male", 30, 175, 75),
                                kind="simulation", queue_items=4000, compression=compression)
            cpu0 = cpu_s()
            summary = recorder.run(seconds)
            rows.append((name, summary, (cpu_s() - cpu0) / summary.elapsed_s))
            sizes.append(summary.path.stat().st_size / summary.elapsed_s / 1e6)
            summary.path.unlink()
    lines += [f"Each for {seconds:g} s at {rate_hz:g} frames/s asked, frames written with compression "
              f"{compression}; 2 cores. Written: frame data handed to the file; on disk: the file's size.", "",
              "| source | frames per head (rate) | lost at the cameras | dropped by the software | flow samples (lost) "
              "| queue peak | CPU (cores) | written | on disk |", "|---|---|---|---|---|---|---|---|---|"]
    for (name, s, cpu), disk in zip(rows, sizes):
        per_head = ", ".join(f"{h} {n} ({n / s.elapsed_s:.1f}/s)" for h, n in s.frames.items())
        lost = ", ".join(f"{h} {s.camera_failed[h]} failed, {s.camera_lost[h]} gaps" for h in s.frames)
        lines.append(f"| {name} | {per_head} | {lost} | {s.dropped_by_software} | {s.flow_samples} ({s.flow_lost}) | "
                     f"{100 * s.max_queue_fill:.0f} % | {cpu:.2f} | {s.written_mb / s.elapsed_s:.0f} MB/s | "
                     f"{disk:.0f} MB/s ({disk * 60 / 1000:.1f} GB/min) |")
        for problem in s.problems:
            lines.append(f"| | stopped: {problem} | | | | | | | |")
    if fake is None:
        lines.append("(arv-fake-gv-camera-0.8 not installed: the GigE row is missing)")
    text = "\n".join(lines)
    if write:
        write_section("record" if compression == "none" else f"record-{compression}", text)
    return text
