"""`photopft demo`: the main job on the simulated rig, start to finish."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from core.session import SessionFile, validate_session
from core.sim.flowsensor import btps_factor


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
        print(volume_summary(session))
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


def volume_summary(path: Path) -> str:
    lines = ["volume summary:"]
    with SessionFile(path) as s:
        if s.has_truth:
            truth = s.truth()
            t_truth = truth["timestamp_ns"][:]
            volume = truth["volume_l"][:]
            lines.append(f"  true volume (simulation): range {volume.min():+.3f} to {volume.max():+.3f} L, "
                         f"vital capacity {volume.max() - volume.min():.3f} L")
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
