"""What `photopft demo` prints after processing: the subject distance, the optical and flow sensor
volumes against the simulation's truth, and the key values side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from core.analysis.session_analysis import analyse_session
from core.analysis.values import grade_caveat
from core.io.results import ResultsFile, optical_inputs, optical_volume
from core.io.session import SessionFile
from core.volume.maps import gradient_volume_correlations


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
            caveat = grade_caveat(values)
            lines.append(f"  forced expirations: grade {values['grade']}, {values['acceptable_FVC']} of "
                         f"{values['manoeuvres']} acceptable" + (f"; {caveat}" if caveat else ""))
        lines += [f"  note: {problem}" for problem in report.flow_sensor.problems]
        if optical_values and np.isfinite(report.optical_from_s):
            lines.append(f"  note (optical): read from {report.optical_from_s:.1f} s, after the subject's calibration "
                         "(its quiet breathing and slow VC are the flow sensor's)")
        if optical_values:
            lines += [f"  note (optical): {problem}" for problem in report.optical.problems]
    return "\n".join(lines)
