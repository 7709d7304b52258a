"""Who gets which report: the identified PDF (name, date of birth, hospital number from the records)
is a clinician's, as FHIR and GDT are; anyone else gets the pseudonymous one. Every report written
is in the audit trail, with whether it named the patient."""

from __future__ import annotations

from pathlib import Path

from app import auth
from app.records import Records, RecordsError
from app.report_data import ReportData, build_report


def never_ask(user: str) -> str:
    """For work off the GUI thread: a password is asked at sign-in, never from there."""
    raise auth.AuthenticationError(f"{user} has not signed in")


def report_for(path: Path, records: Records | None, equations: str = "gli-global", with_maps: bool = True,
               ask=None) -> tuple[ReportData, str | None]:
    """(the report's data, why the patient's identity was left out or None). With no records, or a
    patient not on record, the report is pseudonymous anyway (None)."""
    data = build_report(path, records=records, equations=equations, with_maps=with_maps)
    if data.patient is None or records is None:
        return data, None
    try:
        records.check_permitted("export identified")
        records.require_password("export identified", ask)
    except RecordsError as exc:
        data.patient = None
        why = f"the patient's name is left out: {exc}"
        data.notes.append(f"Pseudonymous report: {why}.")
        return data, why
    return data, None


def log_report(records: Records | None, source: Path, output: Path, identified: bool) -> None:
    if records is not None:
        records.log("report written", str(Path(source).resolve()),
                    {"pdf": str(Path(output).resolve()), "identified": identified})
