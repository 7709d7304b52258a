"""Command-line verbs of the reconstruction: `calibrate lights` and `process`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from app.cli import UserError


def _frame_list(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame indices, got {text!r}") from exc


def add_calibrate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("calibrate", help="calibrate the rig (lights from sphere sessions)",
                       description="Fit calibration profiles from calibration sessions.")
    what = p.add_subparsers(dest="what", metavar="WHAT")
    lights = what.add_parser("lights", help="light positions and intensities from sphere-calibration sessions",
                             description="Triangulate each LED from a specular sphere's highlights at two or more "
                                         "places (and refine positions and intensities on a matte sphere, when "
                                         "given); write the rig calibration profile.")
    lights.add_argument("sessions", nargs="+", type=Path, help="sphere-calibration session files (specular, matte)")
    lights.add_argument("-o", "--output", type=Path, required=True, help="rig calibration profile to write (.json)")
    lights.add_argument("--prior-sigma-mm", type=float, default=15.0,
                        help="tolerance of the drawn LED positions, used as a prior (default 15)")
    lights.add_argument("--max-residual-mm", type=float, default=25.0,
                        help="reject a light whose highlight rays miss each other by more (rms, default 25)")
    lights.set_defaults(run=run_calibrate_lights)
    p.set_defaults(run=lambda args: p.print_help() or 2)


def run_calibrate_lights(args: argparse.Namespace) -> int:
    from core.light_calibration import calibrate_lights
    from core.lights import CalibrationError

    try:
        calibration, reports = calibrate_lights(args.sessions, args.prior_sigma_mm, args.max_residual_mm)
    except CalibrationError as exc:
        raise UserError(str(exc)) from exc
    calibration.save(args.output)
    for report in reports:
        cal = calibration.heads[report.head]
        print(f"{report.head}: {report.placements} placements, "
              f"{'refined on the matte sphere' if report.refined else 'specular triangulation only'}")
        for k in range(4):
            x, y, z = cal.light_positions_mm[k]
            sx, sy, sz = cal.light_position_sigma_mm[k]
            print(f"  light {k}: ({x:8.1f}, {y:8.1f}, {z:7.1f}) mm  +-({sx:.1f}, {sy:.1f}, {sz:.1f})  "
                  f"ray residual {cal.residual_mm[k]:.2f} mm  thesis E {report.thesis_pair_error_mm[k]:.2f} mm  "
                  f"intensity {cal.light_intensity[k]:.3f}")
        for problem in report.problems:
            print(f"  note: {problem}")
    print(f"wrote {args.output}")
    return 0


def add_process(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("process", help="reconstruct a session into a results file",
                       description="Near-light photometric stereo over every light cycle of a session: normals, "
                                   "metric depth, subject distance and gradient volume per head.")
    p.add_argument("session", type=Path)
    p.add_argument("-o", "--output", type=Path, required=True, help="results file to write (.h5)")
    p.add_argument("--rig", type=Path, help="rig calibration profile (default: the session's /rig)")
    p.add_argument("--maps-at", type=_frame_list, default=[], help="frame indices whose full maps to save")
    p.add_argument("--method", choices=("near", "distant"), default="near",
                   help="near: per-pixel light vectors (default); distant: traditional photometric stereo")
    p.add_argument("--integrator", choices=("dct", "masked"), default="dct",
                   help="dct: fast; masked: accurate least squares on the subject only")
    p.add_argument("--every", type=int, default=1, help="reconstruct every n-th cycle window (default 1: all)")
    p.add_argument("--heads", choices=("front", "back", "both"), default="both")
    p.add_argument("--no-motion-compensation", action="store_true",
                   help="use each light's frame as captured (the thesis' static assumption)")
    p.add_argument("--no-tracking", action="store_true",
                   help="search the subject distance afresh in every cycle (slower)")
    p.set_defaults(run=run_process)


def run_process(args: argparse.Namespace) -> int:
    from core.pipeline import ReconstructionSettings
    from core.process import process_session
    from core.profile import ProfileError, load_profile

    calibration = None
    if args.rig is not None:
        try:
            calibration = load_profile(args.rig)
        except ProfileError as exc:
            raise UserError(str(exc)) from exc
    show = sys.stderr.isatty()

    def progress(fraction: float) -> None:
        if show:
            print(f"\rprocessing {args.session.name}: {100 * fraction:5.1f} %", end="", file=sys.stderr, flush=True)

    heads = None if args.heads == "both" else [args.heads]
    try:
        settings = ReconstructionSettings(method=args.method, integrator=args.integrator, track=not args.no_tracking)
        summary = process_session(args.session, args.output, calibration=calibration, maps_at=args.maps_at,
                                  settings=settings, heads=heads, every=args.every,
                                  motion_compensation=not args.no_motion_compensation, progress=progress)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    if show:
        print(file=sys.stderr)
    for name, n in summary.maps.items():
        print(f"{name}: {n} maps, mean subject distance {summary.mean_distance_mm[name]:.1f} mm")
    print(f"wrote {summary.path} in {summary.elapsed_s:.1f} s")
    return 0
