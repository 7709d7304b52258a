"""`photopft bench lights`: the light calibration of rigs as built, against their truth.

Each rig is drawn as the population bench draws them (benchmarks/population.py: LEDs 0-15 mm off
the drawing, and the clinic world's cos^mu falloff with tilted axes, intensity spread, drift,
mains flicker, lens distortion and vignetting). Its sphere captures are simulated as the calibration
wizard records them (each place its own recording, the LEDs drifting from one to the next) and
calibrated as a user would (core/calibration/light_sessions.py): from the specular sphere alone, and
from the specular and the matte sphere. The truth is read only to
compare (issue 27: every LED within 5 mm from specular sessions alone, better with matte ones).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from app.args import positive
from benchmarks.common import publish
from benchmarks.population import (CAPTURE_INTERVAL_S, LEDS_ON_BEFORE_S, SPHERE_PLACES, VirtualSubject,
                                       draw_subjects, light_errors, lights_truth, sphere_sessions)


WITHIN_MM = 5.0


def run_rig(subject: VirtualSubject, scale: float, folder: str) -> dict:
    """One rig: its LEDs' offsets as built and the errors of both calibrations (or why they failed)."""
    from core.calibration.light_sessions import calibrate_lights
    from core.rig import thesis_rig

    started = time.perf_counter()
    captures = sphere_sessions(subject, scale, Path(folder))
    specular, matte = captures["specular-sphere"], captures["matte-sphere"]
    truth = lights_truth(specular[0])
    drawn = thesis_rig(scale)
    out: dict = {"index": subject.index, "seed": subject.seed,
                 "built_offset_mm": {h: np.linalg.norm(truth[h]["light_positions_mm"]
                                                       - drawn.heads[h].light_positions_mm, axis=1).tolist()
                                     for h in truth}}
    for label, paths in (("specular", specular), ("specular+matte", specular + matte)):
        try:
            calibration, reports = calibrate_lights(paths)
            out[label] = light_errors(calibration, truth)
            out[f"{label} refined on"] = {r.head: r.refined_on or "the highlights alone"
                                          + (f" (axes and falloff: {r.pattern_on})" if r.pattern_on else "")
                                          for r in reports}
        except Exception as exc:  # reported as the wizard would show it
            out[label] = {"failed": str(exc)}
    for path in specular + matte:
        path.unlink(missing_ok=True)
    out["seconds"] = time.perf_counter() - started
    return out


def _values(errors: dict, key: str) -> list[float]:
    """One calibration's errors of a kind (light_errors' keys) over its heads."""
    return [v for head in errors.values() for v in head.get(key, [])]


def _worst(errors: dict, key: str) -> float:
    values = _values(errors, key)
    return max(values) if values else float("nan")


def _all(rows: list[dict], label: str) -> np.ndarray:
    return np.array([v for r in rows if "failed" not in r[label] for v in _values(r[label], "position_mm")])


def lights_table(rows: list[dict], scale: float, seed: int, elapsed: float, workers: int) -> str:
    from core.rig import thesis_head
    from core.sim.simulate import WORLDS

    head = thesis_head(scale=scale)
    world = ", ".join(f"{k} {v:g}" for k, v in WORLDS["clinic"].items()
                      if k.startswith(("led_", "ambient", "lens", "vignetting")) and k != "led_offset_mm")
    lines = [f"{len(rows)} rigs (seed {seed}), two heads of {head.width} x {head.height} pixels; LEDs 0-15 mm off "
             f"the drawing and the clinic's {world}; each rig's specular and matte sphere captured as the wizard "
             f"records them ({SPHERE_PLACES} places of each, one recording each, {CAPTURE_INTERVAL_S:g} s apart, the "
             f"LEDs on {LEDS_ON_BEFORE_S / 60:g} min before), calibrated from the specular captures alone and from "
             "both. Position error: "
             "the distance from each calibrated LED to the LED as built.", "",
             "| rig | LEDs off the drawing (mm, worst) | specular: worst / median (mm) | specular + matte: worst / "
             "median (mm) | axis (deg, worst) | falloff mu (worst error) | placed along the rays by (specular; with "
             "matte) |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = []
        for label in ("specular", "specular+matte"):
            errors = r[label]
            if "failed" in errors:
                cells.append(f"failed: {errors['failed']}")
                continue
            position = _values(errors, "position_mm")
            cells.append(f"{max(position):.1f} / {np.median(position):.1f}")
        matte = r["specular+matte"]
        axis = _worst(matte, "axis_deg") if "failed" not in matte else float("nan")
        mu = _worst(matte, "mu") if "failed" not in matte else float("nan")
        built = max(v for h in r["built_offset_mm"].values() for v in h)
        placed = "; ".join(", ".join(sorted(set(r.get(f"{label} refined on", {}).values()))) or "failed"
                           for label in ("specular", "specular+matte"))
        lines.append(f"| {r['index']} | {built:.1f} | {cells[0]} | {cells[1]} | {axis:.1f} | {mu:.2f} | {placed} |")
    lines.append("")
    for label in ("specular", "specular+matte"):
        errors = _all(rows, label)
        within = int(np.sum(errors <= WITHIN_MM))
        lines.append(f"- {label}: {within} of {len(errors)} LEDs within {WITHIN_MM:g} mm; median "
                     f"{np.median(errors) if len(errors) else float('nan'):.1f} mm, worst "
                     f"{errors.max() if len(errors) else float('nan'):.1f} mm.")
    lines += ["", f"Run time {elapsed:.0f} s with {workers} rig(s) at once on {os.cpu_count()} cores."]
    return "\n".join(lines)


def run_lights_bench(rigs: int, scale: float, seed: int, workers: int) -> tuple[str, list[dict]]:
    started = time.perf_counter()
    population = draw_subjects(rigs, seed, [])
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [(s, scale, tmp) for s in population]
        if workers > 1:
            with get_context("spawn").Pool(workers) as pool:
                rows = pool.starmap(run_rig, jobs)
        else:
            rows = [run_rig(*job) for job in jobs]
    return lights_table(rows, scale, seed, time.perf_counter() - started, workers), rows


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench lights`: its arguments and what it runs."""
    li = what.add_parser("lights", help="light calibration from simulated sphere sessions of rigs as built, against "
                                        "their truth")
    li.add_argument("--rigs", type=int, default=6)
    li.add_argument("--scale", type=positive, default=0.5)
    li.add_argument("--seed", type=int, default=1)
    li.add_argument("--workers", type=int, default=None, help="rigs at once (default: one per core)")
    li.add_argument("--no-write", action="store_true", help="print only")

    def run_lights(args: argparse.Namespace) -> int:
        if args.rigs < 1:
            from app.errors import UserError

            raise UserError("--rigs must be 1 or more")
        workers = max(1, min(args.rigs, args.workers or os.cpu_count() or 1))
        text, _ = run_lights_bench(args.rigs, args.scale, args.seed, workers)
        return publish(args, f"lights-{args.scale:g}", f"Light calibration (`photopft bench lights --rigs {args.rigs} "
                                                        f"--scale {args.scale:g} --seed {args.seed}`)", text)

    li.set_defaults(run=run_lights)
