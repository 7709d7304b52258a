"""`photopft demo`: the main job on the simulated rig, start to finish."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.args import positive
from core.io.outputs import OutputError

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def add_demo(sub: argparse._SubParsersAction, run_simulate, describe_session) -> None:
    p = sub.add_parser("demo", help="simulate, check and summarise a full session on the simulated rig",
                       description="Simulate a subject (tidal breathing, slow VC, three forced expirations) on "
                                   "the simulated rig, validate the session file and print its volume summary.")
    p.add_argument("-o", "--output-dir", type=Path, default=Path("photopft-demo"))
    p.add_argument("--seconds", type=positive, default=60.0)
    p.add_argument("--scale", type=positive, default=0.25)
    p.add_argument("--seed", type=int, default=1)

    def run(args: argparse.Namespace) -> int:
        session = args.output_dir / "session.h5"
        if session.exists():
            raise OutputError(f"{session} exists (a demo was run there before, and a recorded session is never "
                              "replaced): choose another folder with -o")
        args.output_dir.mkdir(parents=True, exist_ok=True)
        # the work is imported when the verb runs: every verb's parser is built at start-up (app/cli.py)
        from app.commands.session import add_simulate
        from app.volume_summary import volume_summary
        from core.io.session import SessionFile, validate_session
        from core.pipeline.process import process_session
        from core.reconstruction.pipeline import ReconstructionSettings

        parser = argparse.ArgumentParser(prog="photopft")
        add_simulate(parser.add_subparsers())
        sim_args = parser.parse_args(["simulate", "-o", str(session), "--protocol", "full", "--seconds",
                                              str(args.seconds), "--scale", str(args.scale), "--seed",
                                              str(args.seed)])
        run_simulate(sim_args)
        problems = validate_session(session)
        if problems:
            print("the session file does not follow the spec:\n  " + "\n  ".join(problems))
            return 1
        print(f"{session}: valid photopft session (format version 1)")
        print(describe_session(session))
        results = args.output_dir / "results.h5"
        with SessionFile(session) as s:
            maps_per_s = s.rig.frame_rate_hz / s.rig.cycle_length
        # every light cycle, as `process` does: the peak flow needs a map at least every 50 ms
        print(f"reconstructing every light cycle ({maps_per_s:.0f} maps/s per head) into {results} ...")
        summary = process_session(session, results, workers=None, settings=ReconstructionSettings(track=True))
        print(f"reconstructed {sum(summary.maps.values())} maps in {summary.elapsed_s:.0f} s")
        print(volume_summary(session, results))
        return 0

    p.set_defaults(run=run)
