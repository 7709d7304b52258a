"""Exports: a pseudonymised copy of a session for research, and CSV of the volume curves and values.

The research copy keeps everything needed to reprocess the session (frames, rig, flow, events,
truth) and replaces what could link it back to the clinic: the subject's clinic pseudonym becomes
a study pseudonym (HMAC-SHA256 of it under the study's secret key, so the same patient gets the
same study id across sessions and nobody without the key can go back), the recording time keeps
only its date, the age is rounded to whole years, and the operator's name is dropped.
"""

from __future__ import annotations

import csv
import hashlib
import hmac
import os
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from app.report_data import FLOW_SENSOR, OPTICAL, ReportData
from core.io.outputs import atomic_output
from core.io.session import SessionError, now_iso, validate_session

DROPPED_ROOT_ATTRS = ("operator", "recovered")


def study_pseudonym(clinic_id: str, study_key: bytes) -> str:
    return "R-" + hmac.new(study_key, clinic_id.encode("utf-8"), hashlib.sha256).hexdigest()[:12].upper()


def research_copy(session_path: str | os.PathLike, output: str | os.PathLike, study_key: bytes,
                  study: str = "") -> Path:
    """Write the pseudonymised copy; returns its path. The copy is validated before it is kept."""
    session_path, output = Path(session_path), Path(output)
    if len(study_key) < 16:
        raise ValueError("the study key must be at least 16 bytes (keep it with the study, not with the data)")
    if output.resolve() == session_path.resolve():
        raise ValueError("the research copy must not overwrite the session")
    problems = validate_session(session_path)
    if problems:
        raise SessionError(f"{session_path} is not a valid session file: {problems[0]}")
    with atomic_output(output) as partial:
        _write_research_copy(session_path, partial, study_key, study)
        problems = validate_session(partial)
        if problems:
            raise SessionError(f"the research copy came out invalid ({problems[0]}); nothing was written")
    return output


def _date_only(iso: str) -> str:
    return datetime.fromisoformat(iso).astimezone(timezone.utc).replace(hour=0, minute=0, second=0,
                                                                        microsecond=0).isoformat()


def _write_research_copy(session_path: Path, partial: Path, study_key: bytes, study: str) -> None:
    """Every attribute that could lead back is written once, already changed: an attribute written and
    then overwritten would leave its old bytes in the file."""
    with h5py.File(session_path, "r") as src, h5py.File(partial, "w", libver="latest") as dst:
        for key, value in src.attrs.items():
            if key not in DROPPED_ROOT_ATTRS + ("created",):
                dst.attrs[key] = value
        dst.attrs["created"] = _date_only(str(src.attrs["created"]))
        dst.attrs["pseudonymised"] = now_iso()
        dst.attrs["study"] = study
        for name in src:
            if name == "subject":
                subject = dst.create_group("subject")
                for key, value in src["subject"].attrs.items():
                    if key == "id":
                        value = study_pseudonym(str(value.decode() if isinstance(value, bytes) else value), study_key)
                    elif key == "age_years":
                        value = float(np.round(float(value)))
                    subject.attrs[key] = value
            elif name == "rig":
                rig = dst.create_group("rig")
                for key, value in src["rig"].attrs.items():
                    rig.attrs[key] = value
                for head in src["rig"]:
                    group = rig.create_group(head)
                    for key, value in src["rig"][head].attrs.items():
                        group.attrs[key] = _date_only(str(value)) if key == "calibrated" else value
            else:
                src.copy(src[name], dst, name)


def volume_csv(data: ReportData, output: str | os.PathLike, rate_hz: float = 100.0) -> Path:
    """The volume curves (litres, BTPS) on one time base: seconds from the session's first frame."""
    output = Path(output)
    names = [s for s in (OPTICAL, FLOW_SENSOR) if s in data.curves]
    if not names:
        raise ValueError(f"{data.session_path} has no volume curve in litres to export")
    start = min(float(data.curves[n][0][0]) for n in names)
    end = max(float(data.curves[n][0][-1]) for n in names)
    grid = np.arange(start, end, 1.0 / rate_hz)
    columns = []
    for n in names:
        t, v = data.curves[n]
        values = np.interp(grid, t, v)
        values[(grid < t[0]) | (grid > t[-1])] = np.nan
        columns.append(values)
    with atomic_output(output) as partial, open(partial, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["time_s"] + [f"{n.replace(' ', '_')}_volume_l" for n in names])
        for k, t in enumerate(grid):
            writer.writerow([f"{t:.3f}"] + ["" if not np.isfinite(c[k]) else f"{c[k]:.4f}" for c in columns])
    return output


def values_csv(data: ReportData, output: str | os.PathLike) -> Path:
    """One row per value and source, with the predicted value, LLN, z-score and percent predicted."""
    output = Path(output)
    with atomic_output(output) as partial, open(partial, "w", newline="", encoding="utf-8") as f:
        writer = csv.writer(f)
        writer.writerow(["parameter", "unit", "source", "value", "predicted", "lln", "z", "percent_predicted",
                         "equations"])
        for row in list(data.rows) + list(data.tidal_rows):
            for source, value in row.values.items():
                ref = row.reference
                writer.writerow([row.key, row.unit, source, f"{value:.6g}",
                                 f"{ref.predicted:.6g}" if ref else "", f"{ref.lln:.6g}" if ref else "",
                                 f"{row.z(source):.4f}" if ref else "", f"{row.percent(source):.2f}" if ref else "",
                                 data.equations if ref else ""])
        for source in data.sources:
            p = data.parameters(source)
            for key in ("grade", "grade_FEV1", "grade_FVC", "acceptable_FEV1", "acceptable_FVC", "manoeuvres",
                        "starts_not_judged", "coughs_not_judged"):
                if key in p:
                    writer.writerow([key, "", source, p[key], "", "", "", "", ""])
    return output
