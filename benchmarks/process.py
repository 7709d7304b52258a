"""`photopft bench process`: the whole `photopft process`, as a user runs it, on a simulated
two-head session at the camera's resolution, timed end to end with 1, 2, ... worker processes."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from app.args import positive
from benchmarks.common import publish


def run_process_bench(seconds: float, scale: float, worker_counts: tuple[int, ...]) -> str:
    from core.io.session import SessionFile
    from core.sim.simulate import SimConfig, simulate

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        session = folder / "session.h5"
        simulate(session, SimConfig(protocol="tidal", seconds=seconds, scale=scale, seed=7))
        with SessionFile(session) as s:
            head = s.rig.heads["front"]
            frames = sum(s.n_frames(h) for h in s.heads)
            recorded_s = max((s.timestamp_ns(h)[-1] - s.timestamp_ns(h)[0]) / 1e9 for h in s.heads) \
                + 1.0 / s.rig.frame_rate_hz
        rows = []
        runs = [(workers, False) for workers in worker_counts] + [(max(worker_counts), True)]
        for workers, full in runs:
            out = folder / f"results-{workers}.h5"
            started = time.perf_counter()
            # the command as a user runs it, interpreter start-up and all
            code = subprocess.run([sys.executable, "-m", "app", "process", str(session), "-o", str(out), "--workers",
                                   str(workers)] + (["--full-resolution"] if full else []),
                                  stdout=subprocess.DEVNULL).returncode
            elapsed = time.perf_counter() - started
            if code != 0:
                raise RuntimeError(f"process with {workers} workers exited {code}")
            with SessionFile(session) as s, __import__("h5py").File(out, "r") as r:
                maps = sum(len(r[f"heads/{h}/frame_index"]) for h in s.heads)
            rows.append((workers, full, elapsed, maps))
            out.unlink()
    lines = [f"{seconds:g} s of tidal breathing, two heads of {head.width} x {head.height} pixels at "
             f"{frames / recorded_s / 2:.0f} frames/s ({frames} frames in all), `photopft process S.h5 -o R.h5 "
             f"--workers N` with every other setting at its default (each light cycle once, the stream binned to about "
             f"350 px wide as the live view does, masked integration, motion compensation, the metric volume), "
             f"and once with `--full-resolution` (the stream from every pixel), timed from the command's start to "
             f"its results file; {os.cpu_count()} cores.", "",
             "| workers | stream | wall time | maps | maps/s | × real time |", "|---|---|---|---|---|---|"]
    for workers, full, elapsed, maps in rows:
        lines.append(f"| {workers} | {'every pixel' if full else 'binned'} | {elapsed:.1f} s | {maps} | "
                     f"{maps / elapsed:.2f} | {elapsed / recorded_s:.1f} |")
    lines += ["", "Target (issue 25): at most 6 × real time on this 2-core machine."]
    return "\n".join(lines)


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench process`: its arguments and what it runs."""
    pr = what.add_parser("process", help="the whole `photopft process` at the camera's resolution, against real time")
    pr.add_argument("--seconds", type=positive, default=2.0)
    pr.add_argument("--scale", type=positive, default=1.0)
    pr.add_argument("--workers", default=None, help="worker counts to time, comma-separated (default 1,2,...,cores)")
    pr.add_argument("--no-write", action="store_true", help="print only")

    def run_process(args: argparse.Namespace) -> int:
        counts = (tuple(int(w) for w in args.workers.split(",")) if args.workers
                  else tuple(range(1, min(os.cpu_count() or 1, 2) + 1)))
        text = run_process_bench(args.seconds, args.scale, counts)
        return publish(args, "process", f"Process (`photopft bench process --seconds {args.seconds:g}"
                                         f"{'' if args.scale == 1 else f' --scale {args.scale:g}'}`)", text)

    pr.set_defaults(run=run_process)
