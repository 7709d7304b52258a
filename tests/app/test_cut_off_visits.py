"""Visits whose recording was cut off (issue 77, requirement 7): offered at start-up with Recover and
Discard, never offered as a bronchodilator pair's pre visit."""

from __future__ import annotations

from datetime import date, datetime, timezone

import pytest

from app.gui.cut_off import CutOffVisitsDialog
from app.records import Records, RecordsError
from app.session_processing import cut_off_visits


@pytest.fixture()
def visits(small_session, tmp_path):
    """(records, ids): a visit cut off mid-file, one whose file was closed but never marked, and a
    later complete visit, all of one patient."""
    from tests.app.test_data_safety import _crashed_copy

    whole = small_session.read_bytes()
    cut = _crashed_copy(small_session, tmp_path / "cut.h5")  # the recorder died while it wrote
    closed = tmp_path / "closed.h5"
    closed.write_bytes(whole)
    later = tmp_path / "later.h5"
    later.write_bytes(whole)
    records = Records(tmp_path / "records.sqlite3", user="otto")
    p = records.add_patient("Nowak", "Ewa", "female", date(1974, 3, 2), 164.0, 68.0, pseudonym="P-CUT")
    ids = [records.add_session(p.id, path, datetime(2026, 12, 4, hour, tzinfo=timezone.utc), status=status)
           for path, hour, status in ((cut, 9, "recording"), (closed, 10, "recording"), (later, 11, "recorded"))]
    yield records, ids
    records.close()


def test_cut_off_visits_are_recovered_or_discarded_from_the_dialog(visits, qtbot):
    records, (cut, closed, later) = visits
    assert [v.id for v in cut_off_visits(records)] == [cut, closed]
    with pytest.raises(RecordsError, match="is recording: recover it first"):
        records.link_bronchodilator(cut, later)
    dialog = CutOffVisitsDialog(None, records, cut_off_visits(records))
    qtbot.addWidget(dialog)
    assert dialog.table.rowCount() == 2 and "Nowak, Ewa (P-CUT)" == dialog.table.item(0, 0).text()
    dialog.recover.click()
    assert "cut.h5 recovered (" in dialog.outcome.text() and "cut.crashed.h5" in dialog.outcome.text()
    assert records.session(cut).status == "recovered" and records.session(cut).session_path.exists()
    assert (records.session(cut).session_path.parent / "cut.crashed.h5").exists()  # the original is kept
    dialog.recover.click()  # the closed file needs no recovery
    assert "closed.h5 was complete: marked recorded" in dialog.outcome.text()
    assert dialog.table.rowCount() == 0 and not dialog.recover.isEnabled()
    assert cut_off_visits(records) == []
    records.link_bronchodilator(cut, later)  # a recovered visit is a visit


def test_a_discarded_visit_keeps_its_file_and_is_no_pre_candidate(visits, qtbot):
    from app.gui.records_view import RecordsWindow

    records, (cut, closed, later) = visits
    dialog = CutOffVisitsDialog(None, records, cut_off_visits(records))
    qtbot.addWidget(dialog)
    dialog.discard.click()
    assert "cut.h5 discarded from the visits (the file is kept)" in dialog.outcome.text()
    assert records.session(cut).status == "discarded" and records.session(cut).session_path.exists()
    window = RecordsWindow(None, records)
    qtbot.addWidget(window)
    window.table.selectRow(2)  # the later visit: its candidates for "pre"
    offered = [window.pre.itemData(k) for k in range(window.pre.count())]
    assert cut not in offered and closed not in offered  # discarded, and still cut off
