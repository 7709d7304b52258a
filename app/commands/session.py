"""The verbs on session files: `simulate`, `info`, `validate`, `recover`."""

from __future__ import annotations

import argparse
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.args import WORLD_NAMES, _positive, finite, positive
from app.errors import UserError
from core.io.outputs import check_output
from core.io.session import SessionFile, validate_session

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)

BLOW_KINDS = ("good", "slow-start", "early-stop", "cough", "weak")


def _float_list(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame indices, got {text!r}") from exc


def _blows(text: str):
    from core.sim.breathing import ForcedBlow

    table = {"good": ForcedBlow(), "slow-start": ForcedBlow(rise_time_s=0.4), "early-stop": ForcedBlow(stop_after_s=1.2),
             "cough": ForcedBlow(cough_at_s=0.45), "weak": ForcedBlow(effort=0.7)}
    names = [x.strip() for x in text.split(",") if x.strip()]
    unknown = [n for n in names if n not in table]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown blow {unknown[0]!r}: use {', '.join(BLOW_KINDS)}")
    return [table[n] for n in names]




def add_simulate(sub: argparse._SubParsersAction) -> None:
    from core.sim.breathing import PROTOCOLS
    from core.sim.simulate import SCENES

    p = sub.add_parser("simulate", help="simulate a session on the simulated rig",
                       description="Render a session of the simulated rig into a session file (with /truth).")
    p.add_argument("-o", "--output", type=Path, help="session file to write (.h5); required unless --list-bodies")
    p.add_argument("--scene", choices=SCENES, default="torso", help="what stands between the heads (default torso)")
    p.add_argument("--protocol", choices=PROTOCOLS, default="full",
                   help="torso manoeuvres: tidal, vc (slow vital capacity), forced, full (all three), short, "
                        "clinical (quiet breathing and a slow VC through the flow sensor, mouthpiece-off, then "
                        "tidal, slow VC and forced blows without it), static")
    p.add_argument("--seconds", type=_positive(float), help="length (default: the protocol's own length)")
    p.add_argument("--scale", type=_positive(float), default=0.25, help="sensor resolution scale, 1.0 = 1400 x 1024")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--heads", choices=("front", "both"), default="both", help="front-only or both heads")
    p.add_argument("--distance-mm", type=_positive(float), default=2000.0,
                   help="front camera to the subject's surface on the optical axis")
    p.add_argument("--distance-back-mm", type=_positive(float), default=2000.0)
    p.add_argument("--sway-mm", type=finite, default=None,
                   help="peak postural sway along the optical axis (torso default 50; other scenes 0)")
    p.add_argument("--lateral-sway-mm", type=finite, default=15.0)
    s = p.add_argument_group("subject")
    s.add_argument("--body", help="the trunk: 'random' (drawn with --seed), a preset (photopft simulate --list-bodies), "
                   "a body .toml file, or 'mesh:N': the test population's human body mesh N (MakeHuman, read from "
                   "../shared/data/makehuman, ray-cast); its sex, age, height and weight replace those below "
                   "(default: our own torso)")
    s.add_argument("--list-bodies", action="store_true", help="list the body presets and exit")
    s.add_argument("--subject-id", default="SIM-0001")
    s.add_argument("--sex", choices=("male", "female"), default="male")
    s.add_argument("--age", type=positive, default=30.0, help="years")
    s.add_argument("--height", type=positive, default=175.0, help="cm")
    s.add_argument("--weight", type=positive, default=75.0, help="kg")
    s.add_argument("--fvc", type=_positive(float), help="L (default: predicted)")
    s.add_argument("--fev1", type=_positive(float), help="L (default: predicted)")
    s.add_argument("--pef", type=_positive(float), help="L/s (default: predicted)")
    s.add_argument("--tidal-volume", type=_positive(float), help="L (default 7 mL/kg)")
    s.add_argument("--rate", type=_positive(float), default=14.0, help="breaths per minute")
    s.add_argument("--chest-share", type=finite, default=0.62, help="share of each breath in the chest (0-1)")
    s.add_argument("--blow-waveform", type=Path, metavar="FILE.wf",
                   help="the forced blows follow this standard volume-time waveform (ATS-24, ISO 26782 .wf), "
                        "scaled to the subject's FVC")
    s.add_argument("--irregular", action="store_true",
                   help="tidal breathing with an irregular rate (15 %% spread) and a sigh every dozen breaths")
    s.add_argument("--blows", type=_blows, help=f"forced blows, comma-separated: {', '.join(BLOW_KINDS)}")
    c = p.add_argument_group("camera and lights")
    c.add_argument("--bits", type=int, choices=(8, 10, 12, 16), default=12)
    c.add_argument("--fps", type=_positive(float), default=110.0)
    c.add_argument("--world", choices=WORLD_NAMES, default="ideal",
                   help="realism: ideal (today's rig as drawn) or clinic (LEDs as built with cos^mu falloff, tilt and "
                        "drift, mains flicker, oily skin, lens distortion and vignetting, steps, lost frames); "
                        "clinic-polarised: the clinic behind crossed polarisers on the LEDs and lenses; "
                        "clinic-widening: that, with a --body's trunk widening as it breathes; "
                        "an option below given explicitly wins over the world's value")
    c.add_argument("--skin-type", type=int, choices=range(1, 7), metavar="1-6",
                   help="Fitzpatrick skin type of a --body's bare skin (default: albedo 0.45)")
    c.add_argument("--clothing", choices=("tshirt", "skin"), default="tshirt")
    c.add_argument("--specular", type=finite, help="specular weight of the torso's surface (default 0)")
    c.add_argument("--led-offset-mm", type=finite, help="as built: LEDs this far from the drawing (default 0)")
    c.add_argument("--led-intensity-spread", type=finite,
                   help="as built: relative intensities 1 +- this (default 0)")
    c.add_argument("--led-mu", type=finite, help="LED anisotropy exponent (default 0: isotropic)")
    c.add_argument("--drop-rate", type=finite, help="fraction of frames lost, gaps in frame_id (default 0)")
    c.add_argument("--no-flow", action="store_true", help="no flow sensor recording")
    c.add_argument("--created", type=_iso_time, help="the session's recording time, ISO 8601 with a time zone "
                                                     "(default now), for a simulated patient history")
    c.add_argument("--truth-maps-at", type=_float_list, help="frame indices of the true maps (default: five)")
    k = p.add_argument_group("sphere calibration scenes")
    k.add_argument("--placements", type=int, default=7, help="sphere placements (>= 2)")
    k.add_argument("--sphere-radius-mm", type=_positive(float), default=75.0)
    p.add_argument("--force", action="store_true",
                   help="replace an existing file that is not a session (a recorded session is never replaced)")
    p.set_defaults(run=run_simulate)


# the options a --world also sets: given explicitly, they win over the world's value
WORLD_OPTIONS = ("specular", "led_offset_mm", "led_intensity_spread", "led_mu", "drop_rate")


def _iso_time(text: str) -> str:
    from datetime import datetime

    try:
        moment = datetime.fromisoformat(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected an ISO 8601 time such as 2026-11-26T09:00:00+00:00, got "
                                         f"{text!r}") from exc
    if moment.tzinfo is None:
        raise argparse.ArgumentTypeError(f"{text!r} has no time zone (add +00:00 or Z)")
    return moment.isoformat(timespec="seconds")


def run_simulate(args: argparse.Namespace) -> int:
    from core.sim.breathing import Subject, Sway
    from core.sim.flowsensor import FlowSensorModel
    from core.sim.bodies import PRESETS, body_named
    from core.sim.simulate import SimConfig, in_world, simulate

    if args.list_bodies:
        for name, b in PRESETS.items():
            print(f"{name:18s} {b.sex:6s} {b.age_years:4.0f} y {b.height_cm:5.1f} cm {b.weight_kg:5.1f} kg "
                  f"BMI {b.bmi:4.1f}  arms {b.arms}")
        return 0
    if args.output is None:
        raise UserError("simulate needs -o/--output FILE.h5")
    if args.placements < 2:
        raise UserError("--placements must be 2 or more")
    given = {k: getattr(args, k) for k in WORLD_OPTIONS if getattr(args, k) is not None}
    if not 0.0 <= given.get("drop_rate", 0.0) < 0.5:
        raise UserError(f"--drop-rate must be in [0, 0.5), got {args.drop_rate}")
    try:
        subject = Subject(id=args.subject_id, sex=args.sex, age_years=args.age, height_cm=args.height,
                          weight_kg=args.weight, fvc_l=args.fvc, fev1_l=args.fev1, pef_lps=args.pef,
                          tidal_volume_l=args.tidal_volume, respiratory_rate_bpm=args.rate,
                          chest_share=args.chest_share, rate_variability=0.15 if args.irregular else 0.06,
                          sigh_every=12 if args.irregular else 0)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    blows = args.blows
    if args.blow_waveform is not None:
        from core.sim.breathing import ForcedBlow, standard_curve
        from core.analysis.spirometry import read_waveform

        try:
            standard = read_waveform(args.blow_waveform)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
        curve = standard_curve(standard.volume_l, standard.rate_hz)
        blows = [ForcedBlow(effort=e, standard=curve) for e in ((1.0, 0.97, 1.02) if blows is None else
                                                                 [b.effort for b in blows])]
    try:
        body = body_named(args.body, args.seed) if args.body else None
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    sway_default = 50.0 if args.scene == "torso" else 0.0
    axial = sway_default if args.sway_mm is None else args.sway_mm
    lateral = args.lateral_sway_mm if (args.scene == "torso" or args.sway_mm) else 0.0
    sway = Sway(axial, lateral, 3.0 if axial or lateral else 0.0, seed=args.seed)
    config = SimConfig(
        scene=args.scene, body=body, protocol=args.protocol, seconds=args.seconds, scale=args.scale, seed=args.seed,
        heads=("front",) if args.heads == "front" else ("front", "back"), distance_mm=args.distance_mm,
        distance_back_mm=args.distance_back_mm, sway=sway, subject=subject, blows=blows, bit_depth=args.bits,
        frame_rate_hz=args.fps, clothing=args.clothing,
        flow_sensor=None if args.no_flow else FlowSensorModel(),
        truth_maps_at=args.truth_maps_at, sphere_radius_mm=args.sphere_radius_mm, placements=args.placements,
        skin_type=args.skin_type, created=args.created)
    config = replace(in_world(config, args.world), **given)
    from app.progress import Progress

    check_output(args.output, force=args.force)
    try:
        with Progress(f"simulating {args.output.name}") as progress:
            summary = simulate(args.output, config, progress)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    frames = ", ".join(f"{h} {n}" for h, n in summary.frames.items())
    print(f"wrote {summary.path}: {summary.duration_s:.1f} s, frames {frames}, "
          f"flow samples {summary.flow_samples}, simulated in {summary.elapsed_s:.1f} s")
    lo, hi = summary.truth_volume_range_l
    if hi - lo > 0:
        print(f"true volume change {lo:+.3f} to {hi:+.3f} L")
    return 0


def add_info(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="summarise a session file", description="A human summary of a session file.")
    p.add_argument("session", type=Path)
    p.add_argument("--json", action="store_true", help="the summary as JSON, for scripts")
    p.set_defaults(run=run_info)


def session_summary(path: Path) -> dict:
    """What `info` says about a session, as plain data (`info --json` prints it)."""
    with SessionFile(path) as s:
        out: dict = {"path": str(path), "kind": s.kind, "created": s.created, "software": s.software,
                     "rig": {"name": s.rig.name, "frame_rate_hz": float(s.rig.frame_rate_hz),
                             "sequence": [int(k) for k in s.rig.sequence]}, "heads": {}}
        for name in s.heads:
            head = s.rig.heads[name]
            n = s.n_frames(name)
            ts = s.timestamp_ns(name)
            out["heads"][name] = {
                "width_px": int(head.width), "height_px": int(head.height), "bit_depth": int(head.bit_depth),
                "fx_px": float(head.fx), "frames": int(n), "lost_frames": int(s.lost_frames(name)),
                "duration_s": float((ts[-1] - ts[0]) / 1e9 + 1 / s.rig.frame_rate_hz) if n else 0.0,
                "lights_calibrated": head.calibrated or None}
        flow = s.flow
        out["flow_sensor"] = None if flow is None else {
            "sensor": flow.sensor, "samples": int(flow.n_samples), "sample_rate_hz": float(flow.sample_rate_hz),
            "adc_bits": int(flow.adc_bits), "gain_lps": flow.gain_lps, "offset_lps": flow.offset_lps,
            "conditions": flow.conditions}
        sub = s.subject
        out["subject"] = None if sub is None else {"id": sub.id, "sex": sub.sex, "age_years": float(sub.age_years),
                                                   "height_cm": float(sub.height_cm),
                                                   "weight_kg": float(sub.weight_kg)}
        if s.kind == "sphere-calibration":
            out["sphere"] = {"radius_mm": float(s.attrs["sphere_radius_mm"]), "finish": str(s.attrs["sphere_finish"])}
        start = min((s.timestamp_ns(h)[0] for h in s.heads if s.n_frames(h)), default=0)
        out["events"] = [{"time_s": float((t - start) / 1e9), "label": label} for t, label in s.events()]
        out["truth"] = None
        if s.has_truth:
            truth = s.truth()
            volume = np.asarray(truth["volume_l"])
            out["truth"] = {"volume_min_l": float(volume.min()), "volume_max_l": float(volume.max()),
                            "map_frames": {h: np.asarray(truth[h]["map_frame_index"]).tolist() for h in s.heads
                                           if h in truth}}
    return out


def describe_session(path: Path) -> str:
    info = session_summary(path)
    rig = info["rig"]
    lines = [f"{path}: {info['kind']} session, created {info['created']} by {info['software']}",
             f"rig {rig['name']!r}: {rig['frame_rate_hz']:.1f} frames/s, cycle {rig['sequence']}"]
    for name, h in info["heads"].items():
        lines.append(f"  {name}: {h['width_px']} x {h['height_px']} px, {h['bit_depth']}-bit, f {h['fx_px']:.1f} px, "
                     f"{h['frames']} frames over {h['duration_s']:.2f} s, {h['lost_frames']} lost, lights calibrated "
                     f"{h['lights_calibrated'] or 'never'}")
    flow = info["flow_sensor"]
    if flow is None:
        lines.append("flow sensor: none")
    else:
        calibration = (f"flow = {flow['gain_lps']:g} * adc {flow['offset_lps']:+g} L/s" if flow["gain_lps"] is not None
                       else "uncalibrated")
        lines.append(f"flow sensor: {flow['sensor']}, {flow['samples']} samples at {flow['sample_rate_hz']:g} Hz, "
                     f"{flow['adc_bits']}-bit, {calibration}, {flow['conditions']}")
    if (sub := info["subject"]) is not None:
        lines.append(f"subject {sub['id']}: {sub['sex']}, {sub['age_years']:g} years, {sub['height_cm']:g} cm, "
                     f"{sub['weight_kg']:g} kg")
    if "sphere" in info:
        lines.append(f"sphere: radius {info['sphere']['radius_mm']:g} mm, {info['sphere']['finish']}")
    lines.append("events: " + (", ".join(f"{e['label']} at {e['time_s']:.2f} s" for e in info["events"]) or "none"))
    if (truth := info["truth"]) is not None:
        lines.append(f"truth: volume {truth['volume_min_l']:+.3f} to {truth['volume_max_l']:+.3f} L; maps at "
                     + "; ".join(f"{h} {frames}" for h, frames in truth["map_frames"].items()))
    return "\n".join(lines)


def run_info(args: argparse.Namespace) -> int:
    if args.json:
        print(json.dumps(session_summary(args.session), indent=2, ensure_ascii=False))
    else:
        print(describe_session(args.session))
    return 0


def add_validate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help="check a session file against the format spec",
                       description="Exit 0 if the file follows the session format, 1 with the problems listed.")
    p.add_argument("session", type=Path)
    p.set_defaults(run=run_validate)


def run_validate(args: argparse.Namespace) -> int:
    from core.io.session import session_plausibility

    problems = validate_session(args.session)
    if problems:
        print(f"{args.session}: {len(problems)} problem(s)")
        for problem in problems:
            print(f"  - {problem}")
        return 1
    implausible = session_plausibility(args.session)
    if implausible:
        print(f"{args.session}: follows the session format, but {len(implausible)} signal(s) no instrument "
              "gives; the values they touch are refused:")
        for problem in implausible:
            print(f"  - {problem}")
        return 1
    print(f"{args.session}: valid photopft session (format version 1)")
    return 0


def add_recover(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("recover", help="recover a recording that was cut off (crash, power loss)",
                       description="Copy what every dataset of a cut-off recording reached into a consistent "
                                   "session file under the same name; the original is kept as NAME.crashed.h5 "
                                   "(NAME.crashed-2.h5 and on when that exists). A complete session is refused.")
    p.add_argument("session", type=Path)
    p.set_defaults(run=run_recover)


def run_recover(args: argparse.Namespace) -> int:
    from core.io.recovery import recover_session

    recovery = recover_session(args.session)
    print(f"recovered {args.session}: " + ", ".join(f"{k} {v}" for k, v in recovery.kept.items())
          + f"; the original is kept as {recovery.original}")
    for note in recovery.notes:
        print(f"  note: {note}")
    problems = validate_session(args.session)
    for problem in problems:
        print(f"  still wrong: {problem}")
    return 1 if problems else 0
