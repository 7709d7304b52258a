"""`photopft emulate`: the rig's serial devices on pseudo-terminals, for demos and tests."""

from __future__ import annotations

import argparse
import time

from app.args import finite, positive

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def add_emulate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("emulate", help="run a serial device emulator on a pseudo-terminal",
                       description="Serve a device's protocol (docs/protocols.md) on a new pseudo-terminal and print "
                                   "its path; runs until interrupted (or for --seconds).")
    p.add_argument("device", choices=("sequencer", "flowsensor"))
    p.add_argument("--seconds", type=positive, help="stop after this long")
    p.add_argument("--corrupt-rate", type=finite, default=0.0, help="flow sensor: share of frames with a bad byte")
    p.add_argument("--drop-rate", type=finite, default=0.0, help="flow sensor: share of frames lost")
    p.set_defaults(run=run_emulate)


def run_emulate(args: argparse.Namespace) -> int:
    from drivers.flowsensor import FlowSensorEmulator
    from drivers.sequencer import SequencerEmulator

    emulator = (SequencerEmulator() if args.device == "sequencer"
                else FlowSensorEmulator(corrupt_rate=args.corrupt_rate, drop_rate=args.drop_rate))
    with emulator:
        print(f"{args.device} emulator on {emulator.port}", flush=True)
        end = time.monotonic() + args.seconds if args.seconds else None
        while end is None or time.monotonic() < end:
            time.sleep(0.1)
    return 0
