"""The page the window opens on when the rig cannot start: what failed in plain words, each device
of the rig with its state and what to do, and the ways on (try again, the simulated rig, a
recorded session)."""

from __future__ import annotations

from pathlib import Path

from PySide6.QtGui import QColor
from PySide6.QtWidgets import (QHBoxLayout, QHeaderView, QLabel, QPushButton, QTableWidget, QTableWidgetItem,
                               QVBoxLayout, QWidget)

from drivers.diagnostics import check_rig
from drivers.rig import RigConfigError, load_rig_config


def device_checks(rig_config: Path | None):
    """The rig's devices, checked (drivers/diagnostics.py), or why the rig file cannot be read."""
    try:
        return check_rig(load_rig_config(rig_config)), ""
    except RigConfigError as exc:
        return [], f"The rig configuration cannot be read: {exc}"


class DiagnosticsPage(QWidget):
    def __init__(self, problem: str, rig_config: Path | None, retry, simulated, replay, parent=None) -> None:
        super().__init__(parent)
        layout = QVBoxLayout(self)
        title = QLabel("<h2>The rig could not start</h2>")
        self.problem = QLabel(problem)
        self.problem.setWordWrap(True)
        self.problem.setStyleSheet("color: #b00020; font-size: 14px")
        layout.addWidget(title)
        layout.addWidget(self.problem)
        self.table = QTableWidget(0, 4)
        self.table.setHorizontalHeaderLabels(["device", "address", "state", "what to do"])
        self.table.verticalHeader().setVisible(False)
        self.table.verticalHeader().setSectionResizeMode(QHeaderView.ResizeMode.ResizeToContents)
        self.table.setWordWrap(True)
        self.table.horizontalHeader().setStretchLastSection(True)
        self.note = QLabel()
        self.note.setWordWrap(True)
        layout.addWidget(QLabel(f"<b>Devices of {rig_config or 'the simulated rig'}</b>"))
        layout.addWidget(self.table, 1)
        layout.addWidget(self.note)
        buttons = QHBoxLayout()
        self.retry = QPushButton("Try again")
        self.retry.clicked.connect(retry)
        self.simulated = QPushButton("Use the simulated rig")
        self.simulated.clicked.connect(simulated)
        self.replay = QPushButton("Replay a recorded session…")
        self.replay.clicked.connect(replay)
        for b in (self.retry, self.simulated, self.replay):
            buttons.addWidget(b)
        buttons.addStretch(1)
        layout.addLayout(buttons)
        self.show_checks(rig_config)

    def show_checks(self, rig_config: Path | None) -> None:
        checks, note = device_checks(rig_config)
        self.table.setRowCount(len(checks))
        for row, c in enumerate(checks):
            for column, text in enumerate((c.device, c.address, c.state, c.advice)):
                item = QTableWidgetItem(text)
                if column == 2:
                    item.setForeground(QColor("#1b7f3b" if c.ok else "#b00020"))
                self.table.setItem(row, column, item)
        for column in (0, 1):
            self.table.resizeColumnToContents(column)
        self.table.setColumnWidth(2, 300)
        missing = [c.device for c in checks if not c.ok]
        self.note.setText(note or (f"Missing: {', '.join(missing)}. Fix it, then Try again." if missing else
                                   "Every device answers: Try again; if it fails again, the log file "
                                   "(Help in docs/installation.md) has the detail."))

