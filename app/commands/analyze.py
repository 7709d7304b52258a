"""`photopft analyze`: the pulmonary function values of a waveform file (and, later, of sessions)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from app.errors import UserError
from core.analysis import registry
from core.analysis.values import grade_caveat

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def add_analyze(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("analyze", help="pulmonary function values of a session or a waveform file",
                       description="Tidal, slow VC and forced-expiration values (ATS/ERS 2019, graded, with GLI "
                                   "predicted values) of a session file, or the forced-expiration values of a "
                                   "waveform file (.wf, see shared/data/spirometry-waveforms/README.md).")
    p.add_argument("session", type=Path, nargs="?",
                   help="a session file (.h5), or a results file of `photopft process` (adds the optical values)")
    p.add_argument("--waveform", type=Path, help="a .wf file instead of a session")
    p.add_argument("--equations", choices=("gli-global", "gli-2012"), default="gli-global",
                   help="reference equations (default GLI Global 2022)")
    p.add_argument("--json", action="store_true", help="the values, references and interpretation as JSON (a "
                                                       "session or results file), for scripts")
    p.set_defaults(run=run_analyze)


def run_analyze(args: argparse.Namespace) -> int:
    if args.waveform is None and args.session is None:
        raise UserError("give a session file or --waveform FILE.wf")
    if args.waveform is None:
        return run_analyze_session(args)
    from core.analysis.spirometry import forced_values, read_waveform

    try:
        wave = read_waveform(args.waveform)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    try:
        v = forced_values(wave.volume_l, wave.rate_hz)
    except ValueError as exc:
        raise UserError(f"{args.waveform}: {exc}") from exc
    expected = wave.expected
    rows = [("FVC", "L", v.fvc_l, expected.get("FVC")), ("FEV1", "L", v.fev1_l, expected.get("FEV1")),
            ("FEV0.75", "L", v.fev075_l, None), ("FEV6", "L", v.fev6_l, expected.get("FEV6")),
            ("FEV1/FVC", "%", 100 * v.fev1_fvc, expected.get("FEV1FVC")), ("PEF", "L/s", v.pef_lps, expected.get("PEF")),
            ("FEF25-75", "L/s", v.fef2575_lps, expected.get("FEF2575")), ("FET", "s", v.fet_s, expected.get("FET")),
            ("BEV", "L", v.bev_l, None)]
    print(f"{args.waveform.name}: {wave.group} {wave.name}, {'volume' if wave.kind == 'VT' else 'flow'}-time, "
          f"{wave.rate_hz:g} Hz, {len(wave.samples)} samples")
    print(f"  {'value':<9} {'measured':>10} {'expected':>10}")
    for name, unit, got, want in rows:
        shown = f"{want:10.3f}" if want is not None else " " * 10
        print(f"  {name:<9} {got:10.3f} {shown} {unit}")
    quality = "acceptable" if v.fvc_acceptable else ("FEV1 acceptable" if v.fev1_acceptable else "not acceptable")
    print(f"  ATS/ERS 2019: {quality}" + ("" if not v.problems else ": " + "; ".join(v.problems)))
    return 0


def _rows() -> tuple[registry.SpirometricValue, ...]:
    """The registry's values but the count of breaths analysed, which the report lists with the tidal values."""
    return tuple(v for v in registry.VALUES if v.key != "breaths")


def _plain(value):
    value = value.item() if hasattr(value, "item") else value
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _as_json(session: Path, results: Path | None, equations: str, report, named, sources) -> dict:
    from core.analysis.interpretation import interpret
    from core.io.results import optical_refusal

    main_name, main = sources[0]
    references = {}
    for key, name in ((v.key, v.reference) for v in registry.VALUES if v.reference):
        ref = report.references.get(name)
        if ref is not None:
            references[name] = {"predicted": ref.predicted, "lln": ref.lln}
            source = next((n for n, values in sources if key in values), None)  # a flow sensor that stopped
            if source is not None:  # at the mouthpiece's removal leaves FVC and FEV1 to the optical values
                value = float(dict(sources)[source][key])
                references[name].update(z=ref.zscore(value), percent_predicted=ref.percent(value), source=source)
    spirometry = next(((n, values) for n, values in sources if "FVC_l" in values), (main_name, main))
    grade = spirometry[1].get("grade")
    verdict = interpret({k: float(v) for k, v in spirometry[1].items() if k in ("FEV1_l", "FVC_l", "FEV1_FVC")},
                        report.references, str(grade) if grade is not None else None, spirometry[0])
    problems = {}
    for name, values in named:
        if values is not None:
            listed = list(values.problems)
            if values.forced is not None:
                listed += [f"blow {k}: {'; '.join(m.problems)}"
                           for k, m in enumerate(values.forced.manoeuvres, start=1) if m.problems]
            problems[name] = listed
    return {"session": str(session), "results": str(results) if results is not None else None,
            "equations": equations, "main_source": main_name,
            "values": {name: {k: _plain(v) for k, v in values.items()} for name, values in sources},
            "references": references, "reference_problem": report.reference_problem,
            "interpretation": {"pattern": verdict.pattern, "severity": verdict.severity, "summary": verdict.summary,
                               "z": verdict.z, "statements": verdict.statements},
            "optical_refused": optical_refusal(results) if results is not None else None,
            "optical_label": report.optical_label,
            "optical_read_from_s": report.optical_from_s if math.isfinite(report.optical_from_s) else None,
            "flow_refused": report.flow_refused and str(report.flow_refused),
            "flow_refused_code": report.flow_refused and report.flow_refused.code, "problems": problems}


def run_analyze_session(args: argparse.Namespace) -> int:
    """A session file (flow sensor and truth), or a results file (its session, and its optical volume)."""
    from app.report_data import open_inputs
    from core.io.results import optical_inputs, optical_refusal
    from core.io.session import SessionError
    from core.analysis.session_analysis import analyse_session
    from core.sim.truth import truth_values

    try:
        session, results = open_inputs(args.session)
        report = analyse_session(session, args.equations, **optical_inputs(results))
        truth = truth_values(session)
        # an optical curve calibrated on the subject is read after its calibration: its truth so too
        truth_as_optical = (truth_values(session, report.optical_from_s)
                            if truth is not None and math.isfinite(report.optical_from_s) else None)
    except (SessionError, ValueError, OSError, KeyError) as exc:
        raise UserError(str(exc) if str(args.session) in str(exc) else f"{args.session}: {exc}") from exc
    named = (("flow sensor", report.flow_sensor), ("optical", report.optical), ("truth (simulation)", truth),
             (f"truth from {report.optical_from_s:.1f} s", truth_as_optical))
    sources = [(name, values.parameters()) for name, values in named if values]
    if not sources and report.flow_refused:
        raise UserError(f"{args.session}: the flow sensor's values are refused: {report.flow_refused}")
    if not sources:
        raise UserError(f"{args.session} has neither a flow sensor recording nor a simulation truth to analyse; "
                        "the optical volume comes with `photopft process` (analyse its results file)")
    if args.json:
        print(json.dumps(_as_json(session, results, args.equations, report, named, sources), indent=2,
                         ensure_ascii=False))
        return 0
    header = f"  {'value':<9} {'unit':<6}" + "".join(f"{name:>20}" for name, _ in sources)
    header += f"{'predicted':>11}{'LLN':>8}{'z':>7}{'% pred':>8}"
    print(f"{session}: values from the {sources[0][0]}; reference {args.equations} (z and % predicted of the "
          "first source that gives the value)")
    print(header)
    for row in _rows():
        key, label, unit = row.key, row.label, row.unit
        if not any(key in values for _, values in sources):
            continue
        cells = "".join(f"{values[key]:>20.3f}" if key in values else f"{'':>20}" for _, values in sources)
        ref = report.references.get(row.reference or "")
        extra = ""
        first = next((values[key] for _, values in sources if key in values), None)
        if ref is not None and first is not None:
            extra = f"{ref.predicted:>11.3f}{ref.lln:>8.3f}{ref.zscore(first):>7.2f}{ref.percent(first):>8.0f}"
        print(f"  {label:<9} {unit:<6}{cells}{extra}")
    for name, values in sources:
        if "grade" in values:
            caveat = grade_caveat(values)
            print(f"  {name}: grade {values['grade']} (FEV1 {values['grade_FEV1']}, FVC {values['grade_FVC']}), "
                  f"{values['acceptable_FEV1']} acceptable FEV1 and {values['acceptable_FVC']} acceptable FVC of "
                  f"{values['manoeuvres']} blows" + (f"; {caveat}" if caveat else ""))
    if report.reference_problem:
        print(f"  no predicted values: {report.reference_problem}")
    if report.optical_label:
        print(f"  optical: {report.optical_label}")
    if report.optical is not None and math.isfinite(report.optical_from_s):
        print(f"  optical: read from {report.optical_from_s:.1f} s, after the subject's calibration (before it, "
              "the flow sensor's)")
    if results is not None and (refused := optical_refusal(results)):
        print(f"  optical values refused: {refused}")
    if report.flow_refused:
        print(f"  flow sensor values refused: {report.flow_refused}")
    for name, values in named:
        if values is not None:
            for problem in values.problems:
                print(f"  {name}: {problem}")
            if values.forced is not None:
                for k, m in enumerate(values.forced.manoeuvres, start=1):
                    if m.problems:
                        print(f"  {name}, blow {k}: " + "; ".join(m.problems))
    return 0
