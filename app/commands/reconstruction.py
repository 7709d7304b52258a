"""Command-line verbs of the reconstruction: `calibrate lights` and `process`."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from app.args import add_force, positive
from app.errors import UserError

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def _frame_list(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame indices, got {text!r}") from exc


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected a number of pixels, got {text!r}") from exc
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"expected 0 or more pixels, got {text!r}")
    return value


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
    lights.add_argument("--prior-sigma-mm", type=positive, default=15.0,
                        help="tolerance of the drawn LED positions, used as a prior (default 15)")
    lights.add_argument("--max-residual-mm", type=positive, default=25.0,
                        help="reject a light whose highlight rays miss each other by more (rms, default 25)")
    add_force(lights)
    lights.set_defaults(run=run_calibrate_lights)
    flow = what.add_parser("flow", help="the flow sensor's gain and offset from steady flows (thesis eq. 5.4)",
                           description="Fit flow (L/s) = C1 * adc + C0 to steady flows read off a reference "
                                       "flowmeter: a CSV with columns reference_lps, adc_mean, or a flow-calibration "
                                       "session whose events are labelled flow=<L/s> (each lasting to the next event).")
    flow.add_argument("source", type=Path, help="pairs.csv or a flow-calibration session (.h5)")
    flow.add_argument("-o", "--output", type=Path, required=True, help="flow calibration profile (.json)")
    add_force(flow)
    flow.set_defaults(run=run_calibrate_flow)
    volume = what.add_parser("volume", help="the thesis' volume regression from training sessions (eqs 5.1-5.3)",
                             description="Fit phi = (X^T X)^-1 X^T pv, X = [gradient volume, valid pixels, distance], "
                                         "pv the flow-sensor volume, from results files of processed sessions.")
    volume.add_argument("results", nargs="+", type=Path, help="results files (their sessions need a flow sensor)")
    volume.add_argument("-o", "--output", type=Path, required=True, help="volume calibration profile (.json)")
    add_force(volume)
    volume.set_defaults(run=run_calibrate_volume)
    p.set_defaults(run=lambda args: p.print_help() or 2)


def _calibration_audit():
    """The records database that logs the calibration; refused before any work for a user who may
    not calibrate (roles enforced)."""
    from app.calibration_store import calibration_audit
    from app.records import RecordsError

    try:
        return calibration_audit()
    except RecordsError as exc:
        raise UserError(str(exc)) from exc


def _logged(audit, kind: str, saved: Path) -> None:
    from app.calibration_store import log_calibration

    if audit is not None:
        with audit:
            log_calibration(audit, kind, saved)


def run_calibrate_lights(args: argparse.Namespace) -> int:
    from core.calibration.light_sessions import advice, calibrate_lights
    from core.calibration.sphere_geometry import CalibrationError
    from core.io.outputs import check_output

    check_output(args.output, args.sessions, force=args.force)
    audit = _calibration_audit()
    try:
        calibration, reports = calibrate_lights(args.sessions, args.prior_sigma_mm, args.max_residual_mm)
    except CalibrationError as exc:
        raise UserError(str(exc)) from exc
    calibration.save(args.output)
    _logged(audit, "lights", args.output)
    for report in reports:
        cal = calibration.heads[report.head]
        how = f"refined on {report.refined_on}" if report.refined_on else "specular triangulation only"
        if report.pattern_on:
            how += f", axes and falloff from {report.pattern_on} (each placement's output on its own)"
        print(f"{report.head}: {report.placements} placements, {how}")
        for k in range(4):
            x, y, z = cal.light_positions_mm[k]
            sx, sy, sz = cal.light_position_sigma_mm[k]
            print(f"  light {k}: ({x:8.1f}, {y:8.1f}, {z:7.1f}) mm  +-({sx:.1f}, {sy:.1f}, {sz:.1f})  "
                  f"ray residual {cal.residual_mm[k]:.2f} mm  thesis E {report.thesis_pair_error_mm[k]:.2f} mm  "
                  f"intensity {cal.light_intensity[k]:.3f}"
                  + (f"  falloff cos^{cal.light_mu[k]:.2f}, axis tilted "
                     f"{np.degrees(np.arccos(cal.light_axis[k, 2])):.1f} deg" if cal.light_mu is not None else ""))
        for drift in cal.extra.get("shading_drift_per_min", []):
            print("  the LEDs' output drifted by " + ", ".join(f"{100 * d:+.2f}" for d in drift)
                  + " % a minute over a recording (fitted with the shading)")
        for problem in report.problems:
            print(f"  note: {problem}")
    for line in advice(reports):
        print(line)
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
    p.add_argument("--integrator", choices=("dct", "masked"), default="masked",
                   help="masked: least squares on the subject only (default); dct: faster, flattens the relief "
                        "and the breathing by 5-9 %%")
    p.add_argument("--every", type=int, default=None,
                   help="slide the cycle window by N frames (default: a cycle's length, each light cycle once; "
                        "1: a map at every frame)")
    p.add_argument("--heads", choices=("front", "back", "both"), default="both")
    p.add_argument("--full-resolution", action="store_true",
                   help="reconstruct the stream from every pixel (default: binned to about 350 px wide, as the "
                        "live view does; --maps-at maps keep every pixel either way)")
    p.add_argument("--workers", type=int, default=None,
                   help="processes reconstructing at once, one head each (default: one per core for a "
                        "session long enough to repay starting them)")
    p.add_argument("--no-motion-compensation", action="store_true",
                   help="use each light's frame as captured (the thesis' static assumption)")
    p.add_argument("--volume-calibration", type=Path,
                   help="a volume calibration profile (photopft calibrate volume): write /volume from the thesis' "
                        "regression")
    p.add_argument("--no-tracking", action="store_true",
                   help="search the subject distance afresh in every cycle (slower)")
    p.add_argument("--distance-from", choices=("heads", "photometric"), default="heads",
                   help="the subject distance: from the two heads' trunk widths and baseline (default; a session "
                        "of one head: photometric) or each head's photometric fit")
    p.add_argument("--prefilter-px", type=_non_negative, default=None, metavar="SIGMA",
                   help="Gaussian sigma in pixels on the images before the normals are solved (default: 0.56 "
                        "for a head 1400 px wide, none up to about 1000 px; 0: none)")
    add_force(p)
    p.set_defaults(run=run_process)


def run_process(args: argparse.Namespace) -> int:
    from core.reconstruction.pipeline import ReconstructionSettings
    from core.pipeline.process import process_session
    from core.io.outputs import check_output
    from core.calibration.rig_profile import ProfileError, load_profile

    check_output(args.output, [p for p in (args.session, args.rig, args.volume_calibration) if p is not None],
                 force=args.force)
    volume_calibration = None
    if args.volume_calibration is not None:
        from core.calibration.spirometer import CalibrationProfileError, VolumeCalibration
        from core.calibration.spirometer import load_profile as load_calibration

        try:
            volume_calibration = load_calibration(args.volume_calibration)
        except CalibrationProfileError as exc:
            raise UserError(str(exc)) from exc
        if not isinstance(volume_calibration, VolumeCalibration):
            raise UserError(f"{args.volume_calibration} is a flow calibration, not a volume calibration")
    calibration = None
    if args.rig is not None:
        try:
            calibration = load_profile(args.rig)
        except ProfileError as exc:
            raise UserError(str(exc)) from exc
    from app.progress import Progress

    heads = None if args.heads == "both" else [args.heads]
    try:
        settings = ReconstructionSettings(method=args.method, integrator=args.integrator, track=not args.no_tracking,
                                          prefilter_px=args.prefilter_px)
        with Progress(f"processing {args.session.name}") as progress:
            summary = process_session(args.session, args.output, calibration=calibration, maps_at=args.maps_at,
                                      settings=settings, heads=heads, every=args.every,
                                      motion_compensation=not args.no_motion_compensation,
                                      volume_calibration=volume_calibration, progress=progress,
                                      workers=args.workers, distance_from=args.distance_from,
                                      binning=1 if args.full_resolution else None)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    for name, n in summary.maps.items():
        offset = summary.photometric_offset_mm.get(name)
        if summary.distance_refused:
            print(f"{name}: {n} maps")
            continue
        sheen = summary.sheen.get(name, float("nan"))
        print(f"{name}: {n} maps, mean subject distance {summary.mean_distance_mm[name]:.1f} mm"
              + (f" (the two heads' geometry; the photometric fit {offset:+.0f} mm from it)" if offset is not None else "")
              + (f", sheen {sheen:.3f} of the albedo" if np.isfinite(sheen) else ""))
    if summary.distance_refused:
        print(f"no subject distance: {summary.distance_refused}")
    if summary.optical_refused:
        print(f"no optical volume: {summary.optical_refused}")
    print(f"wrote {summary.path} in {summary.elapsed_s:.1f} s")
    return 0


def is_hdf5(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError as exc:
        raise UserError(f"cannot read {path}: {exc}") from exc


def steady_flows(source: Path) -> tuple[list[float], list[float]]:
    """(mean ADC, reference flow) pairs from a CSV or from a flow-calibration session's events."""
    import csv

    import numpy as np

    if source.suffix.lower() == ".csv":
        try:
            with open(source, newline="", encoding="utf-8") as fh:
                rows = list(csv.DictReader(fh))
        except UnicodeDecodeError as exc:
            raise UserError(f"{source} is not a text CSV file ({exc.reason} at byte {exc.start})") from exc
        try:
            means, flows = [float(r["adc_mean"]) for r in rows], [float(r["reference_lps"]) for r in rows]
        except (KeyError, ValueError, TypeError) as exc:
            raise UserError(f"{source}: needs numeric columns reference_lps and adc_mean ({exc})") from exc
        bad = [k + 2 for k, pair in enumerate(zip(means, flows)) if not np.all(np.isfinite(pair))]
        if bad:
            raise UserError(f"{source}: line {bad[0]} holds a value that is not a finite number")
        return means, flows
    if not is_hdf5(source):
        raise UserError(f"{source} is neither a CSV file (.csv) nor a flow-calibration session (HDF5)")
    from core.io.session import SessionFile

    with SessionFile(source) as s:
        adc, stamps = s.flow_samples()
        events = s.events()
    marks = [(t, label) for t, label in events if label.startswith("flow=")]
    if len(marks) < 3:
        raise UserError(f"{source}: needs three or more events labelled flow=<L/s>, found {len(marks)}")
    means, flows = [], []
    for k, (t, label) in enumerate(marks):
        end = marks[k + 1][0] if k + 1 < len(marks) else stamps[-1] + 1
        inside = (stamps >= t) & (stamps < end)
        settled = np.nonzero(inside)[0][int(0.2 * inside.sum()):]  # skip the first fifth: the flow settling
        if len(settled) < 10:
            raise UserError(f"{source}: the step {label} holds too few samples")
        try:
            flows.append(float(label.split("=", 1)[1]))
        except ValueError as exc:
            raise UserError(f"{source}: event {label!r} is not flow=<number>") from exc
        means.append(float(np.mean(adc[settled])))
    return means, flows


def run_calibrate_flow(args: argparse.Namespace) -> int:
    from core.calibration.spirometer import CalibrationProfileError, fit_flow, save_profile
    from core.io.outputs import check_output
    from core.io.session import now_iso

    check_output(args.output, [args.source], force=args.force)
    audit = _calibration_audit()
    means, flows = steady_flows(args.source)
    try:
        profile = fit_flow(means, flows, created=now_iso(), sources=[args.source.name])
    except CalibrationProfileError as exc:
        raise UserError(f"{args.source}: {exc}") from exc
    save_profile(profile, args.output)
    _logged(audit, "flow sensor", args.output)
    print(f"flow (L/s) = {profile.gain_lps:.6g} * adc {profile.offset_lps:+.6g}; R^2 {profile.r_squared:.5f}; "
          f"{profile.points} steady flows from {profile.range_lps[0]:g} to {profile.range_lps[1]:g} L/s; "
          f"largest residual {max(abs(r) for r in profile.residuals_lps):.4f} L/s")
    print(f"wrote {args.output}")
    return 0


def regression_samples(results_path: Path):
    """Features [gradient volume, valid pixels, distance] and flow-sensor volume at the map times."""
    import h5py
    import numpy as np

    from core.analysis.session_analysis import analyse_session

    from core.calibration.spirometer import regression_features
    from core.io.results import ResultsFile, session_of_results
    from core.io.results import check_results, is_results_file

    if not is_hdf5(results_path) or not is_results_file(results_path):
        raise UserError(f"{results_path} is not a results file of `photopft process`: process the session first")
    check_results(results_path)
    with ResultsFile(results_path) as r:
        heads = r.heads
        session = session_of_results(results_path)
        if not r.has_series(heads[0], "valid_pixels"):
            raise UserError(f"{results_path} predates the pixel counts: process the session again")
        t, features = regression_features(r.series, heads)
    report = analyse_session(session)
    if report.flow_volume is None:
        raise UserError(f"{session} has no flow sensor recording to train the volume regression on")
    with h5py.File(session, "r") as s:
        start = int(min(s[f"heads/{h}/timestamp_ns"][0] for h in heads))
    flow_t, flow_v = report.flow_volume
    pv = np.interp((t - start) / 1e9, flow_t, flow_v)
    return features, pv, session.name


def run_calibrate_volume(args: argparse.Namespace) -> int:
    import numpy as np

    from core.calibration.spirometer import CalibrationProfileError, fit_volume, save_profile
    from core.io.outputs import check_output
    from core.io.session import now_iso

    check_output(args.output, args.results, force=args.force)
    audit = _calibration_audit()
    features, volumes, names = [], [], []
    for path in args.results:
        x, pv, name = regression_samples(path)
        features.append(x)
        volumes.append(pv)
        names.append(name)
    try:
        profile = fit_volume(np.vstack(features), np.concatenate(volumes), created=now_iso(), sessions=names)
    except CalibrationProfileError as exc:
        raise UserError(f"{args.source}: {exc}") from exc
    save_profile(profile, args.output)
    _logged(audit, "volume", args.output)
    print(f"phi = {np.array2string(profile.phi, precision=6)}; r = {profile.correlation:.4f}, "
          f"R^2 = {profile.r_squared:.4f} over {profile.samples} samples from {len(names)} session(s)")
    print(f"wrote {args.output}")
    return 0
