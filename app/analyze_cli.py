"""`photopft analyze`: the pulmonary function values of a waveform file (and, later, of sessions)."""

from __future__ import annotations

import argparse
from pathlib import Path

from app.cli import UserError


def add_analyze(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("analyze", help="spirometric values of a waveform file",
                       description="Forced-expiration values (ATS/ERS 2019) of a volume-time or flow-time waveform "
                                   "file (.wf, see shared/data/spirometry-waveforms/README.md).")
    p.add_argument("--waveform", type=Path, required=True, help="a .wf file")
    p.set_defaults(run=run_analyze)


def run_analyze(args: argparse.Namespace) -> int:
    from core.spirometry import forced_values, read_waveform

    try:
        wave = read_waveform(args.waveform)
        v = forced_values(wave.volume_l, wave.rate_hz)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
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
