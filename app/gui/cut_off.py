"""Visits whose recording was cut off (the application or the machine died while recording), offered
at start-up: Recover (`photopft recover`, the original kept) or Discard (the file kept, the visit
no longer listed as one); app/session_processing.py does both."""

from __future__ import annotations

from PySide6.QtWidgets import (QAbstractItemView, QDialog, QDialogButtonBox, QHBoxLayout, QLabel, QPushButton,
                               QTableWidget, QTableWidgetItem, QVBoxLayout)

from app.records import Records, RecordsError
from app.session_processing import discard_visit, recover_visit


class CutOffVisitsDialog(QDialog):
    def __init__(self, parent, records: Records, visits: list) -> None:
        super().__init__(parent)
        self.setWindowTitle("Recordings that were cut off")
        self.records, self.visits = records, list(visits)
        layout = QVBoxLayout(self)
        layout.addWidget(QLabel("These recordings never ended: photopft or the computer stopped while they ran. "
                                "Recover keeps what was recorded (the original file is kept beside it); Discard "
                                "takes the visit off the patient's list (the file is kept).", wordWrap=True))
        self.table = QTableWidget(0, 3)
        self.table.setHorizontalHeaderLabels(["Patient", "Recorded", "File"])
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.verticalHeader().hide()
        layout.addWidget(self.table)
        self.outcome = QLabel(wordWrap=True)
        layout.addWidget(self.outcome)
        row = QHBoxLayout()
        self.recover = QPushButton("Recover", clicked=lambda: self._act("recover"))
        self.discard = QPushButton("Discard", clicked=lambda: self._act("discard"))
        row.addWidget(self.recover)
        row.addWidget(self.discard)
        row.addStretch(1)
        row.addWidget(QDialogButtonBox(QDialogButtonBox.StandardButton.Close, rejected=self.reject))
        layout.addLayout(row)
        self.resize(760, 360)
        self._fill()

    def _fill(self) -> None:
        self.table.setRowCount(len(self.visits))
        for k, visit in enumerate(self.visits):
            patient = self.records.patient(visit.patient_id)
            for j, text in enumerate((f"{patient.display_name} ({patient.pseudonym})",
                                      f"{visit.recorded:%Y-%m-%d %H:%M}", str(visit.session_path))):
                self.table.setItem(k, j, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        if self.visits:
            self.table.selectRow(0)
        for button in (self.recover, self.discard):
            button.setEnabled(bool(self.visits))

    def _act(self, what: str) -> None:
        rows = self.table.selectionModel().selectedRows()
        if not rows:
            return
        visit = self.visits[rows[0].row()]
        try:
            said = (recover_visit if what == "recover" else discard_visit)(self.records, visit.id)
        except RecordsError as exc:
            self.outcome.setText(f"<span style='color:#b00020'>{exc}</span>")
            return
        self.outcome.setText(said)
        self.visits.remove(visit)
        self._fill()
