"""`photopft bench live`: the live view's metric optical volume (what the operator sees in orange)
against the simulated subject's true lung volume, on the simulated rig as the application runs it:
the slope and r of the one against the other, and the maps it came from."""

from __future__ import annotations

import argparse
import time

import numpy as np

from app.args import positive
from benchmarks.common import publish


def run_live_bench(seconds: float, scale: float, seed: int = 1) -> tuple[str, dict[str, float]]:
    from app.engine.live_rig import LiveRig
    from app.engine.sources import simulated_source

    source = simulated_source(scale=scale, seed=seed)
    engine = LiveRig(source)
    engine.start()
    try:
        time.sleep(seconds)
        snapshot = engine.snapshot()
        state = source.simulated
        t0 = engine._t0  # the first frame's stamp: the curves' zero
    finally:
        engine.stop()
    t, live = snapshot.metric_t_s, snapshot.metric_volume_l
    if t0 is None or len(t) < 20:
        raise RuntimeError(f"the live view made {len(t)} metric volume samples in {seconds:g} s: too few to compare")
    truth = state.waveform.at((t0 - state.start_ns) / 1e9 + t)
    slope, offset = np.polyfit(truth, live, 1)
    residual = live - (slope * truth + offset)
    figures = {"samples": float(len(t)), "per_s": len(t) / float(t[-1] - t[0]), "r": float(np.corrcoef(truth, live)[0, 1]),
               "slope": float(slope), "rms_l": float(np.sqrt(np.mean(residual ** 2))),
               "swing_true_l": float(np.ptp(truth)), "maps": float(sum(v.reconstructed for v in snapshot.heads.values()))}
    verdict = (f"refused: {snapshot.optical_refused}" if snapshot.optical_refused
               else "pass" if snapshot.optical_checked else "nothing to judge by yet")
    text = "\n".join([
        f"The simulated rig at scale {scale:g} (seed {seed}, tidal breathing with sway), the live engine as the window "
        f"runs it, {seconds:g} s; the live metric volume (both heads, no calibration) against the subject's true lung "
        "volume at the same instants; the live checks' verdict at the end.", "",
        "| samples | per second | r | slope | rms about the line (L) | true swing (L) | live checks |",
        "|---|---|---|---|---|---|---|",
        f"| {len(t)} | {figures['per_s']:.1f} | {figures['r']:.3f} | {figures['slope']:.3f} | {figures['rms_l']:.3f} | "
        f"{figures['swing_true_l']:.2f} | {verdict} |"])
    return text, figures


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench live`: its arguments and what it runs."""
    lv = what.add_parser("live", help="the live view's metric volume against the simulated subject's true volume")
    lv.add_argument("--seconds", type=positive, default=60.0)
    lv.add_argument("--scale", type=positive, default=0.25)
    lv.add_argument("--seed", type=int, default=1)
    lv.add_argument("--no-write", action="store_true", help="print only")

    def run_live(args: argparse.Namespace) -> int:
        text, _ = run_live_bench(args.seconds, args.scale, args.seed)
        return publish(args, f"live-{args.scale:g}", f"Live volume (`photopft bench live --seconds {args.seconds:g} "
                                                      f"--scale {args.scale:g}`)", text)

    lv.set_defaults(run=run_live)
