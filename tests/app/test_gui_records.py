"""The clinician's records window and the audit trail window, driven with pytest-qt offscreen on a
real SQLite file: interpretation, trend, comment, sign-off, amendment, bronchodilator pair, roles."""

from __future__ import annotations

from datetime import date, datetime, timezone

from PySide6.QtCore import QTimer
from PySide6.QtWidgets import QApplication

from app.gui.records_view import AuditWindow, RecordsWindow
from app.records import Records


def _visits(path, user="dr-lee"):
    records = Records(path, user=user)
    p = records.add_patient("Muster", "Max", "male", date(1966, 5, 1), 175.0, 80.0, patient_number="H-9")
    for day, fev1, fvc in ((1, 2.0, 4.0), (2, 2.6, 4.05)):
        (path.parent / f"s{day}.h5").write_bytes(f"recording {day}".encode())  # what a signature binds
        sid = records.add_session(p.id, path.parent / f"s{day}.h5", datetime(2026, 11, day, 9, tzinfo=timezone.utc))
        records.set_results(sid, None, {"flow sensor": {"FEV1_l": fev1, "FVC_l": fvc, "FEV1_FVC": fev1 / fvc,
                                                        "grade": "A"}})
    return records


def test_review_in_the_records_window(qtbot, tmp_path):
    records = _visits(tmp_path / "r.sqlite3")
    window = RecordsWindow(None, records)
    qtbot.addWidget(window)
    assert window.patients.count() == 1 and window.table.rowCount() == 2
    assert "Obstruction" in window.interpretation.text()  # the newest visit is chosen: FEV1/FVC 0.64
    litres = window.trend.litres.getPlotItem().listDataItems()
    assert [len(item.xData) for item in litres] == [2, 2]
    window.comment.setPlainText("Reversible obstruction.")
    window.save_comment.click()
    window.link.click()  # the only earlier visit is the pre-bronchodilator one
    window.sign.click()
    assert window.table.item(1, 6).text() == "signed by dr-lee"
    assert window.comment.isReadOnly() and not window.sign.isEnabled() and window.amend.isEnabled()
    window.amendment.setText("Repeat in 3 months.")
    window.amend.click()
    assert "Amendment by dr-lee" in window.signed.text() and "Post-bronchodilator visit of 2026-11-01" in \
        window.signed.text()
    assert records.pre_bronchodilator(records.history(1)[1].id).id == records.history(1)[0].id
    audit = AuditWindow(None, records)
    qtbot.addWidget(audit)
    assert "hash chain is whole" in audit.verdict.text()
    assert audit.table.item(0, 3).text() == "report amended" and audit.table.item(0, 1).text() == "dr-lee"
    records.close()


def test_a_refused_change_is_one_line_in_a_dialog(qtbot, tmp_path):
    path = tmp_path / "r.sqlite3"
    _visits(path).close()
    with Records(path, user="ed") as records:
        records.add_user("ed", "engineer", "ed-secret")
        records.authenticate("ed-secret")
        records.add_user("otto", "operator", "otto-secret")
    records = Records(path, user="otto")
    window = RecordsWindow(None, records)
    qtbot.addWidget(window)
    assert window.user.text() == "Acting as otto (operator)"
    seen: list[str] = []

    def close() -> None:
        dialog = QApplication.activeModalWidget()
        if dialog is None:
            QTimer.singleShot(20, close)
            return
        seen.append(dialog.informativeText())
        dialog.close()

    QTimer.singleShot(20, close)
    window.sign.click()
    assert seen and seen[0].startswith("report signed: otto is an operator; this needs the role clinician")
    assert window.table.item(1, 6).text() == "not signed"
    records.close()


def test_the_audit_window_shows_tampering(qtbot, tmp_path):
    from tests.app.test_audit import tamper

    path = tmp_path / "r.sqlite3"
    _visits(path).close()
    tamper(path, "DROP TRIGGER audit_log_no_update", "UPDATE audit_log SET details = '{}' WHERE id = 3")
    with Records(path, read_only=True) as records:
        audit = AuditWindow(None, records)
        qtbot.addWidget(audit)
        assert "tampered with: audit entry 3" in audit.verdict.text()
