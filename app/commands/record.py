"""`photopft record` and `photopft devices`: the rig from its configuration."""

from __future__ import annotations

import argparse
import os
import sys
from contextlib import ExitStack
from pathlib import Path

from app.args import positive
from app.errors import UserError
from core.io.session import file_write_failed
from app.progress import Progress

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def add_record(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record a session from a rig (the simulated rig by default)",
                       description="Record both heads and the flow sensor into a session file, with a progress "
                                   "line; capture is never blocked by the writer.")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--rig", type=Path, help="rig configuration (default resources/rigs/simulated.toml)")
    p.add_argument("--seconds", type=positive, default=10.0)
    p.add_argument("--subject", default="ANON-0001", help="pseudonymous subject id")
    p.add_argument("--sex", choices=("male", "female"), default="male")
    p.add_argument("--age", type=positive, default=30.0)
    p.add_argument("--height", type=positive, default=175.0)
    p.add_argument("--weight", type=positive, default=75.0)
    p.set_defaults(run=run_record)
    d = sub.add_parser("devices", help="list cameras and serial ports, check the rig's devices",
                       description="List the GigE Vision cameras and serial ports this machine sees, and check "
                                   "each device the rig configuration names.")
    d.add_argument("--rig", type=Path)
    d.set_defaults(run=run_devices)


def run_record(args: argparse.Namespace) -> int:
    from app.calibration_store import in_force
    from core.calibration.spirometer import CalibrationProfileError
    from core.calibration.rig_profile import ProfileError
    from core.io.session import SubjectRecord
    from drivers.assembly import assemble_rig
    from drivers.camera import CameraError
    from drivers.flowsensor import FlowSensorError
    from drivers.recorder import Recorder
    from drivers.rig import RigConfigError, load_rig_config
    from drivers.sequencer import SequencerError

    from core.io.outputs import check_output

    check_output(args.output, [args.rig] if args.rig else [], replaceable=False)
    try:
        config = load_rig_config(args.rig)
        subject = SubjectRecord(args.subject, args.sex, args.age, args.height, args.weight)
    except (RigConfigError, ValueError) as exc:
        raise UserError(str(exc)) from exc
    with ExitStack() as stack:
        try:
            profiles = in_force(config.name)
            rig = assemble_rig(config, stack, seconds=args.seconds + 5.0, light_profile=profiles.lights,
                               flow_profile=profiles.flow)
        except (CameraError, SequencerError, FlowSensorError, ProfileError, CalibrationProfileError) as exc:
            raise UserError(str(exc)) from exc
        print(f"calibrations in force: lights {rig.lights_from}"
              + (f"; flow sensor {rig.flow_from}" if rig.flow_from else ""), file=sys.stderr)
        bar = stack.enter_context(Progress(f"recording {args.output.name}"))

        def progress(elapsed: float, counts: dict) -> None:
            bar(elapsed / args.seconds, "frames " + ", ".join(f"{h} {n}" for h, n in counts.items()))

        recorder = Recorder(args.output, rig.rig, rig.cameras, rig.lights, rig.flow, rig.flow_calibration, subject,
                            kind="simulation" if config.simulated else "patient", compression=config.compression)
        summary = recorder.run(args.seconds, progress)
    frames = ", ".join(f"{h} {n}" for h, n in summary.frames.items())
    camera = ", ".join(f"{h} {summary.camera_failed[h]} failed / {summary.camera_lost[h]} lost"
                       for h in summary.frames)
    print(f"wrote {summary.path}: {summary.elapsed_s:.1f} s, frames {frames} ({camera} at the cameras), "
          f"{summary.flow_samples} flow samples ({summary.flow_lost} lost), dropped by the software "
          f"{summary.dropped_by_software}, queue at most {100 * summary.max_queue_fill:.0f} % full, "
          f"{summary.written_mb / summary.elapsed_s:.1f} MB/s written")
    for notice in summary.notices:
        print(f"note: {notice}", file=sys.stderr)
    for problem in summary.problems:
        print(f"stopped: {problem}", file=sys.stderr)
    if file_write_failed():
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(1)  # HDF5 crashes tearing down a file it could not close; what is on disk is kept
    return 1 if summary.problems else 0


def run_devices(args: argparse.Namespace) -> int:
    from serial.tools import list_ports

    from drivers.diagnostics import check_rig, seen_cameras
    from drivers.rig import RigConfigError, load_rig_config

    try:
        config = load_rig_config(args.rig)
    except RigConfigError as exc:
        raise UserError(str(exc)) from exc
    cameras = seen_cameras()
    print("cameras: " + ("; ".join(cameras) if cameras else "none"))
    ports = [p.device for p in list_ports.comports()]
    print("serial ports: " + (", ".join(ports) if ports else "none"))
    print(f"rig {config.name!r} ({config.path}):")
    checks = check_rig(config)
    for c in checks:
        address = "" if c.address in ("sim", "none", "emulator") else f" {c.address}"
        print(f"  {c.device}{address}: {c.state}" + ("" if c.ok else f" ({c.advice})"))
    return 0 if all(c.ok for c in checks) else 1
