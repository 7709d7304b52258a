"""`photopft demo`: the main job on the simulated rig, start to finish."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from app.args import positive
from core.io.outputs import OutputError
from core.reconstruction.pipeline import ReconstructionSettings
from core.pipeline.process import process_session
from core.io.results import ResultsFile, optical_inputs, optical_volume
from core.io.session import SessionFile, validate_session
from core.analysis.session_analysis import analyse_session
from core.volume.maps import gradient_volume_correlations


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
        from app.commands.session import add_simulate

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


def volume_summary(path: Path, results: Path | None = None) -> str:
    lines = ["volume summary:"]
    optical = optical_volume(results) if results is not None else None
    if results is not None:
        with ResultsFile(results) as r:
            heads = r.heads
            series = {h: (r.series(h, "timestamp_ns"), r.series(h, "distance_mm"), r.series(h, "gradient_volume"))
                      for h in heads}
            distance_refused = r.distance_refused
        if distance_refused:
            lines.append(f"  no subject distance: {distance_refused}")
        else:
            for head, (_, distance, _) in series.items():
                lines.append(f"  {head}: subject distance {np.nanmedian(distance):.0f} mm (from "
                             f"{np.nanpercentile(distance, 2):.0f} to {np.nanpercentile(distance, 98):.0f} mm)")
    truth_volume = None
    with SessionFile(path) as s:
        if s.has_truth:
            truth = s.truth()
            truth_volume = truth["volume_l"][:]
            t_truth = truth["timestamp_ns"][:]
            volume = truth["volume_l"][:]
            lines.append(f"  true volume (simulation): range {volume.min():+.3f} to {volume.max():+.3f} L, "
                         f"vital capacity {volume.max() - volume.min():.3f} L")
            if results is not None:
                r_gv = gradient_volume_correlations({h: (series[h][0], series[h][2]) for h in heads}, t_truth,
                                                    volume)["combined"]
                lines.append(f"  gradient volume (thesis eqs 3.26-3.27, {' and '.join(heads)} combined) against the "
                             f"true volume: r = {r_gv:.3f} (thesis Table 5.2: 0.98)")
                if optical is not None:
                    measured = np.isfinite(optical[1])  # not a map left out for an arm against the trunk
                    true_at = np.interp(optical[0], t_truth, volume)[measured]
                    slope = np.polyfit(true_at - true_at[0], optical[1][measured], 1)[0]
                    lines.append(f"  optical volume in litres against the true volume: "
                                 f"r = {np.corrcoef(optical[1][measured], true_at)[0, 1]:.4f}, slope {slope:.3f}")
    report = analyse_session(path, **optical_inputs(results))
    if report.flow_volume is not None:
        t_flow, v_flow = report.flow_volume
        lines.append(f"  flow sensor (BTPS, zero drift removed): range {v_flow.min():+.3f} to {v_flow.max():+.3f} L")
        if truth_volume is not None:
            with SessionFile(path) as s:
                start = int(min(s.timestamp_ns(h)[0] for h in s.heads))
            v = np.interp((t_truth - start) / 1e9, t_flow, v_flow)
            lines.append(f"  flow sensor against the true volume: r = {np.corrcoef(v, volume)[0, 1]:.4f}, largest "
                         f"difference {np.max(np.abs(v - volume)):.3f} L")
        values = report.flow_sensor.parameters()
        optical_values = report.optical.parameters() if report.optical is not None else {}
        lines.append("key values: flow sensor" + (f", {report.optical_label}" if optical_values else "") + ":")
        shown = [("TV", "TV_l", "L"), ("RR", "RR_bpm", "/min"), ("VC", "VC_l", "L"), ("FVC", "FVC_l", "L"),
                 ("FEV1", "FEV1_l", "L"), ("FEV1/FVC", "FEV1_FVC", ""), ("PEF", "PEF_lps", "L/s")]
        for label, key, unit in shown:
            if key in values:
                ref = report.references.get({"FVC_l": "FVC", "FEV1_l": "FEV1", "FEV1_FVC": "FEV1_FVC"}.get(key, ""))
                extra = (f"  (predicted {ref.predicted:.2f}, LLN {ref.lln:.2f}, z {ref.zscore(values[key]):+.2f})"
                         if ref is not None else "")
                beside = f" {optical_values[key]:7.3f}" if key in optical_values else ""
                lines.append(f"  {label:<9} {values[key]:7.3f}{beside} {unit}{extra}")
        if "grade" in values:
            lines.append(f"  forced expirations: grade {values['grade']}, {values['acceptable_FVC']} of "
                         f"{values['manoeuvres']} acceptable")
        lines += [f"  note: {problem}" for problem in report.flow_sensor.problems]
        if optical_values:
            lines += [f"  note (optical): {problem}" for problem in report.optical.problems]
    return "\n".join(lines)
