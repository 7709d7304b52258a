"""`photopft demo`: the main job on the simulated rig, start to finish."""

from __future__ import annotations

import argparse
from pathlib import Path

import h5py
import numpy as np

from core.pipeline import ReconstructionSettings
from core.process import process_session
from core.session import SessionFile, validate_session
from core.flow import btps_factor


def add_demo(sub: argparse._SubParsersAction, run_simulate, describe_session) -> None:
    p = sub.add_parser("demo", help="simulate, check and summarise a full session on the simulated rig",
                       description="Simulate a subject (tidal breathing, slow VC, three forced expirations) on "
                                   "the simulated rig, validate the session file and print its volume summary.")
    p.add_argument("-o", "--output-dir", type=Path, default=Path("photopft-demo"))
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--seed", type=int, default=1)

    def run(args: argparse.Namespace) -> int:
        args.output_dir.mkdir(parents=True, exist_ok=True)
        session = args.output_dir / "session.h5"
        from app.cli import build_parser

        sim_args = build_parser().parse_args(["simulate", "-o", str(session), "--protocol", "full", "--seconds",
                                              str(args.seconds), "--scale", str(args.scale), "--seed",
                                              str(args.seed)])
        run_simulate(sim_args)
        problems = validate_session(session)
        if problems:
            print("the session file does not follow the spec:\n  " + "\n  ".join(problems))
            return 1
        print(describe_session(session))
        results = args.output_dir / "results.h5"
        print(f"reconstructing every 11th light cycle window (10 maps/s per head) into {results} ...")
        summary = process_session(session, results, every=11,
                                  settings=ReconstructionSettings(track=True))
        print(f"reconstructed {sum(summary.maps.values())} maps in {summary.elapsed_s:.0f} s")
        print(volume_summary(session, results))
        return 0

    p.set_defaults(run=run)


def flow_sensor_volume_l(s: SessionFile) -> tuple[np.ndarray, np.ndarray]:
    """(timestamp_ns, volume_l at BTPS) from the flow sensor's calibration in force, plain integration."""
    adc, t = s.flow_samples()
    flow = s.flow
    if flow.gain_lps is None:
        raise ValueError("the flow sensor is uncalibrated")
    attrs = flow.attrs
    factor = 1.0
    if flow.conditions == "ATPS" and "room_temperature_c" in attrs:
        factor = btps_factor(float(attrs["room_temperature_c"]), float(attrs["room_pressure_hpa"]),
                             float(attrs["room_humidity_pct"]))
    lps = (flow.gain_lps * adc + flow.offset_lps) * factor
    return t, np.cumsum(lps) / flow.sample_rate_hz


def _normalised(values: np.ndarray) -> np.ndarray:
    """Thesis eq. 3.27: (V - mean V) / max |V - mean V|."""
    centred = values - np.nanmean(values)
    return centred / np.nanmax(np.abs(centred))


def volume_summary(path: Path, results: Path | None = None) -> str:
    lines = ["volume summary:"]
    if results is not None:
        with h5py.File(results, "r") as r:
            heads = [h for h in ("front", "back") if h in r["heads"]]
            series = {h: (r[f"heads/{h}/timestamp_ns"][:], r[f"heads/{h}/distance_mm"][:],
                          r[f"heads/{h}/gradient_volume"][:]) for h in heads}
        for head, (_, distance, _) in series.items():
            lines.append(f"  {head}: subject distance {np.nanmedian(distance):.0f} mm (from "
                         f"{np.nanpercentile(distance, 2):.0f} to {np.nanpercentile(distance, 98):.0f} mm)")
        t = series[heads[0]][0]
        combined = sum(_normalised(np.interp(t, series[h][0], series[h][2])) for h in heads)
    with SessionFile(path) as s:
        if s.has_truth:
            truth = s.truth()
            t_truth = truth["timestamp_ns"][:]
            volume = truth["volume_l"][:]
            lines.append(f"  true volume (simulation): range {volume.min():+.3f} to {volume.max():+.3f} L, "
                         f"vital capacity {volume.max() - volume.min():.3f} L")
            if results is not None:
                r_gv = np.corrcoef(combined, np.interp(t, t_truth, volume))[0, 1]
                lines.append(f"  gradient volume (thesis eqs 3.26-3.27, {' and '.join(heads)} combined) against the "
                             f"true volume: r = {r_gv:.3f} (thesis Table 5.2: 0.98)")
        if s.flow is not None and s.flow.gain_lps is not None:
            t_flow, v_flow = flow_sensor_volume_l(s)
            lines.append(f"  flow sensor (BTPS, plain integration, zero drift not yet removed): range "
                         f"{v_flow.min():+.3f} to {v_flow.max():+.3f} L")
            if s.has_truth:
                v = np.interp(t_truth, t_flow, v_flow)
                r = np.corrcoef(v, volume)[0, 1]
                lines.append(f"  flow sensor against truth: r = {r:.4f}, largest difference "
                             f"{np.max(np.abs(v - volume)):.3f} L")
    return "\n".join(lines)
