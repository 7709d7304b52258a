"""A recorded visit processed and its values put on record: what the application runs in the
background when a recording ends, and again from the records window ("Process again").

The session is processed as `photopft process` does (process_session, one worker per core where it
repays), into `<session>-results.h5` beside it; the values of every source the report reads (the
flow sensor's, the optical ones) are stored on the visit, and the optical volume's refusal, where
it has one, with them, so the records say why there are no optical values.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from app.records import Records, RecordsError
from app.report_data import OPTICAL, build_report
from core.io.outputs import is_session_file
from core.io.recovery import recover_session
from core.io.results import is_results_file, optical_refusal
from core.io.session import SessionError
from core.pipeline.process import process_session

RESULTS_SUFFIX = "-results.h5"


class ProcessingCancelled(Exception):
    """The operator cancelled the processing; nothing was written."""


@dataclass(frozen=True)
class ProcessedVisit:
    results_path: Path
    sources: dict[str, dict]  # source -> the values stored
    optical_refused: str | None


def results_path_for(session_path: Path) -> Path:
    return session_path.with_name(session_path.stem + RESULTS_SUFFIX)


def process_visit(records: Records, session_id: int, progress: Callable[[float], None] | None = None,
                  cancelled: Callable[[], bool] | None = None) -> ProcessedVisit:
    """Process the visit's session and store its values; `cancelled` is asked at each step of the
    processing, and a True leaves nothing written (ProcessingCancelled)."""
    visit = records.session(session_id)
    session = visit.session_path
    if not session.is_file():
        raise RecordsError(f"{session}: the visit's session file is missing")
    results = results_path_for(session)
    if results.exists() and (is_session_file(results) or not is_results_file(results)):
        raise RecordsError(f"{results} is there and is not a results file of this visit: move it away first")

    def step(share: float) -> None:
        if cancelled is not None and cancelled():
            raise ProcessingCancelled(f"the processing of {session.name} was cancelled; nothing was written")
        if progress is not None:
            progress(share)

    process_session(session, results, progress=step, workers=None)
    data = build_report(results, with_maps=False)
    sources = {source: data.parameters(source) for source in data.sources}
    refused = optical_refusal(results)
    stored = dict(sources)
    if OPTICAL in stored and data.optical_label:  # what its litres are, wherever they are shown
        stored[OPTICAL] = {**stored[OPTICAL], "label": data.optical_label}
    if OPTICAL not in stored and refused:
        stored[OPTICAL] = {"refused": refused}
    records.set_results(session_id, results, stored, status="processed")
    return ProcessedVisit(results, sources, refused)


# A visit whose recording was cut off (the application or the machine died) stays "recording" until
# it is recovered or discarded; neither kind is offered as a bronchodilator pair's "pre" visit.
CUT_OFF = "recording"
NOT_A_VISIT = ("recording", "cancelled", "discarded")


def cut_off_visits(records: Records) -> list:
    """The visits left "recording" by a recording that never ended, oldest first."""
    return [v for p in records.find_patients("") for v in records.history(p.id) if v.status == CUT_OFF]


def recover_visit(records: Records, session_id: int) -> str:
    """`photopft recover` on the visit's file (the original kept as NAME.crashed.h5), the visit then
    marked recovered; a file that needs no recovery (it was closed, the application died after) is
    marked recorded. Returns what was done, in words."""
    visit = records.session(session_id)
    if not visit.session_path.exists():
        raise RecordsError(f"{visit.session_path}: the visit's session file is missing: discard the visit")
    try:
        recovery = recover_session(visit.session_path)
    except SessionError as exc:
        if "complete, valid session" not in str(exc):
            raise RecordsError(str(exc)) from exc
        records.set_results(session_id, None, visit.summary, status="recorded")
        return f"{visit.session_path.name} was complete: marked recorded"
    records.set_results(session_id, None, visit.summary, status="recovered")
    kept = ", ".join(f"{k} {v}" for k, v in recovery.kept.items())
    return f"{visit.session_path.name} recovered ({kept}); the original is kept as {recovery.original.name}"


def discard_visit(records: Records, session_id: int) -> str:
    """The visit marked discarded: its file stays where it is (a recording is never deleted)."""
    visit = records.session(session_id)
    records.set_results(session_id, None, visit.summary, status="discarded")
    return f"{visit.session_path.name} discarded from the visits (the file is kept)"
