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
    from core.io.outputs import is_session_file
    from core.io.results import is_results_file, optical_refusal
    from core.reconstruction.process import process_session

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
    if OPTICAL not in stored and refused:
        stored[OPTICAL] = {"refused": refused}
    records.set_results(session_id, results, stored, status="processed")
    return ProcessedVisit(results, sources, refused)
