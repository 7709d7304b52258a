"""A visit processed in the background and its values on record (issue 77, requirement 1): the
records window's "Process again" runs process on the visit's session, stores the flow sensor's and
the optical values (or why there are none) beside each other, and a cancel leaves nothing written."""

from __future__ import annotations

from datetime import date, datetime, timezone

import numpy as np
import pytest

from app.records import Records
from app.session_processing import ProcessingCancelled, process_visit, results_path_for
from core.sim.breathing import Subject
from core.sim.simulate import SimConfig, simulate


@pytest.fixture(scope="module")
def visit(tmp_path_factory):
    """(records, session id, session): 8 s of quiet breathing on record, not yet processed."""
    folder = tmp_path_factory.mktemp("visit")
    session = folder / "P-PROC-20261204.h5"
    subject = Subject(id="P-PROC", sex="female", age_years=40.0, height_cm=166.0, weight_kg=60.0)
    simulate(session, SimConfig(protocol="tidal", seconds=8.0, scale=0.05, seed=4, subject=subject))
    path = folder / "records.sqlite3"
    with Records(path, user="otto") as r:
        patient = r.add_patient("Doe", "Jane", "female", date(1986, 1, 1), 166.0, 60.0, pseudonym="P-PROC")
        sid = r.add_session(patient.id, session, datetime(2026, 12, 4, 9, tzinfo=timezone.utc), status="recorded")
    return path, sid, session


def test_a_cancelled_processing_writes_nothing(visit):
    path, sid, session = visit
    with Records(path, user="otto") as r, pytest.raises(ProcessingCancelled, match="cancelled; nothing was written"):
        process_visit(r, sid, cancelled=lambda: True)
    assert not results_path_for(session).exists()
    assert not any(p.name.endswith(".partial.h5") for p in session.parent.iterdir())
    with Records(path, read_only=True) as r:
        assert r.session(sid).status == "recorded"


def test_process_again_in_the_records_window_stores_both_sources(visit, qtbot):
    from app.gui.records_view import RecordsWindow

    path, sid, session = visit
    records = Records(path, user="otto")
    window = RecordsWindow(None, records)
    qtbot.addWidget(window)
    assert "No values stored for this visit" in window.values.text()
    with qtbot.waitSignal(window.processing.finished, timeout=300_000) as done:
        window.process_again.click()
        assert not window.processing.isHidden() and "Processing P-PROC-20261204.h5" in window.processing.label.text()
    outcome = done.args[0]
    assert outcome.results_path == results_path_for(session) and outcome.results_path.exists()
    visit_now = records.session(sid)
    assert visit_now.status == "processed" and visit_now.results_path == outcome.results_path
    assert "TV_l" in visit_now.summary["flow sensor"]
    optical = visit_now.summary["optical"]  # values, or why the optical volume was refused
    assert ("TV_l" in optical) != ("refused" in optical)
    text = window.values.text()
    assert "flow sensor" in text
    assert (optical.get("label") or "") in text and ("refused" in optical or "optical" in optical["label"])
    assert window.processing.isHidden()
    records.close()


def test_every_export_from_the_records_window_is_audited_and_refused_to_an_operator(visit, qtbot, tmp_path):
    import json

    from app import auth
    from app.gui.records_view import RecordsWindow

    shared, sid, session = visit
    path = tmp_path / "records.sqlite3"  # a copy: the users added below stay out of the other tests' records
    path.write_bytes(shared.read_bytes())
    records = Records(path, user="otto")
    window = RecordsWindow(None, records)
    qtbot.addWidget(window)
    outputs = {"pdf": tmp_path / "r.pdf", "fhir": tmp_path / "b.json", "fhir-identified": tmp_path / "i.json",
               "gdt": tmp_path / "x.gdt", "csv": tmp_path / "csv"}
    said = {kind: window.export_to(kind, out) for kind, out in outputs.items()}  # roles not enforced yet
    assert all(said.values()), said
    assert json.loads(outputs["fhir-identified"].read_text())["entry"][0]["resource"]["name"][0]["family"] == "Doe"
    assert (outputs["csv"] / "values.csv").exists()
    trail = [(e.action, e.details) for e in records.audit_trail()]
    assert sum(action == "export" for action, _ in trail) == 4
    assert [d["identified"] for a, d in trail if a == "report written"] == [True]
    with Records(path, user="ed") as admin:
        admin.add_user("ed", "engineer", "ed-secret")
        admin.authenticate("ed-secret")
        admin.add_user("otto", "operator", "otto-secret")
    auth.prove("otto", 0.0)
    seen: list[str] = []
    from tests.app.test_gui import _close_when_shown

    _close_when_shown(qtbot, seen)
    assert window.export_to("gdt", tmp_path / "y.gdt") is None
    qtbot.waitUntil(lambda: bool(seen))
    assert "export identified: otto is an operator" in seen[0] and not (tmp_path / "y.gdt").exists()
    records.close()


def test_the_slow_vc_plateau_is_the_lowest_second_that_holds():
    from app.gui.volume_trace import plateau

    t = np.arange(0.0, 14.0, 0.01)
    v = np.interp(t, [0, 2, 4, 9, 11, 14], [0.0, 0.0, 3.0, -1.5, -1.5, 0.5])  # in, out to a plateau, back
    reached_s, _ = plateau(t, v)
    assert reached_s == pytest.approx(10.0, abs=0.05)  # one second into the bottom
    assert plateau(t[t < 9.5], v[t < 9.5])[0] is None  # still breathing out
    quiet = 0.25 * np.sin(2 * np.pi * t / 4)
    assert plateau(t, quiet)[0] is None  # quiet breathing's pauses are no plateau
