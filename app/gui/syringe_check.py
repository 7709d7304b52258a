"""Calibration > 3 L syringe check (daily): the operator pumps the syringe through the flow sensor,
in and out, at different speeds; each stroke's volume from the flow line in force must lie within
3 % of 3 L (core/calibration/syringe.py). The result is logged for the rig and in the audit trail."""

from __future__ import annotations

import time
from contextlib import nullcontext

import numpy as np
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (QDialog, QDialogButtonBox, QHBoxLayout, QLabel, QPushButton, QTableWidget,
                               QTableWidgetItem, QVBoxLayout)

from app.calibration_store import log_syringe_check
from app.gui.errors import show_error
from app.records import RecordsError, existing_records
from core.calibration.syringe import SYRINGE_L, TOLERANCE, SyringeCheck, quiet_samples, syringe_strokes
from core.sim.flowsensor import FlowSensorModel


class RigSyringe:
    """The rig's own flow sensor, read through the live engine between Start and Stop."""

    label = "the rig's flow sensor"

    def __init__(self, engine) -> None:
        self.engine = engine
        self._since = 0

    def start(self) -> None:
        self._since = time.monotonic_ns()

    def stop(self) -> tuple[np.ndarray, np.ndarray]:
        return self.engine.flow_since(self._since)


class SimulatedSyringe:
    """A 3.000 L syringe pumped three times in and out (about 6, 1.5 and 0.6 s a stroke) through the
    simulated sensor model: what the simulated rig's daily check reads."""

    label = "a simulated 3 L syringe through the simulated sensor (no hardware is read)"

    def __init__(self, seed: int = 1) -> None:
        self.model = FlowSensorModel()
        self.seed = seed

    def start(self) -> None:
        pass

    def stop(self) -> tuple[np.ndarray, np.ndarray]:
        rate = self.model.sample_rate_hz
        parts = [np.zeros(int(rate))]
        for duration in (6.0, 1.5, 0.6):
            t = np.arange(int(duration * rate)) / rate
            shape = np.sin(np.pi * t / duration) * np.pi / (2 * duration) * SYRINGE_L  # integrates to 3 L
            parts += [shape, np.zeros(int(0.8 * rate)), -shape, np.zeros(int(0.8 * rate))]
        flow_atps = np.concatenate(parts)
        t = np.arange(len(flow_atps)) / rate
        counts = self.model.adc_counts(flow_atps * self.model.btps, t, self.seed)
        return counts, (t * 1e9).astype(np.int64)


def check_from_samples(adc: np.ndarray, stamps_ns: np.ndarray, gain_lps: float, offset_lps: float) -> SyringeCheck:
    """The strokes in the flow sensor's samples, by the flow line in force (ATPS: the syringe's gas
    is at room conditions, no BTPS factor)."""
    if len(adc) < 10:
        return SyringeCheck([])
    t = (np.asarray(stamps_ns, dtype=np.int64) - int(stamps_ns[0])) / 1e9
    flow = gain_lps * np.asarray(adc, dtype=float) + offset_lps
    quiet = quiet_samples(t, flow)
    if quiet.sum() > 100:  # zeroed on the pauses between strokes (a line: the sensor's zero drifts)
        flow = flow - np.polyval(np.polyfit(t[quiet], flow[quiet], 1), t)
    return SyringeCheck(syringe_strokes(t, flow))


class SyringeCheckDialog(QDialog):
    def __init__(self, parent, bench, flow_calibration: tuple[float, float] | None, rig_name: str,
                 flow_from: str) -> None:
        super().__init__(parent)
        self.setWindowTitle("3 L syringe check")
        self.bench = bench
        self.flow_calibration = flow_calibration
        self.rig_name = rig_name
        self.flow_from = flow_from
        self.check: SyringeCheck | None = None
        intro = QLabel(f"Connect the 3 L syringe to the flow sensor. Press Start, pump the syringe fully in and out "
                       f"three times (slowly, moderately, fast), then press Stop. Every stroke must read within "
                       f"{100 * TOLERANCE:.0f} % of {SYRINGE_L:g} L. Reading {bench.label}; flow line in force: "
                       f"{flow_from or 'none'}.")
        intro.setWordWrap(True)
        self.start = QPushButton("Start")
        self.start.clicked.connect(self._start)
        self.stop = QPushButton("Stop and check")
        self.stop.setEnabled(False)
        self.stop.clicked.connect(self._stop)
        self.table = QTableWidget(0, 4)
        self.table.setHorizontalHeaderLabels(["stroke", "volume (L)", "error", "peak flow (L/s)"])
        self.table.verticalHeader().setVisible(False)
        self.verdict = QLabel("not checked yet")
        self.verdict.setWordWrap(True)
        self.buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Save | QDialogButtonBox.StandardButton.Cancel)
        self.buttons.button(QDialogButtonBox.StandardButton.Save).setEnabled(False)
        self.buttons.accepted.connect(self._save)
        self.buttons.rejected.connect(self.reject)
        row = QHBoxLayout()
        row.addWidget(self.start)
        row.addWidget(self.stop)
        row.addStretch(1)
        layout = QVBoxLayout(self)
        layout.addWidget(intro)
        layout.addLayout(row)
        layout.addWidget(self.table, 1)
        layout.addWidget(self.verdict)
        layout.addWidget(self.buttons)
        self.saved: dict | None = None
        self.resize(620, 420)

    def _start(self) -> None:
        self.bench.start()
        self.start.setEnabled(False)
        self.stop.setEnabled(True)
        self.verdict.setText("Pump the syringe now: in and out, three times.")

    def _stop(self) -> None:
        self.stop.setEnabled(False)
        self.start.setEnabled(True)
        self.start.setText("Start again")
        if self.flow_calibration is None:
            show_error(self, "There is no flow line in force.", "Run the spirometer calibration first.")
            return
        try:
            adc, stamps = self.bench.stop()
        except Exception as exc:  # a sensor that does not answer: said, nothing logged
            show_error(self, "The flow sensor could not be read.", f"{exc}. Check its cable and try again.")
            return
        self.show_check(check_from_samples(adc, stamps, *self.flow_calibration))

    def show_check(self, check: SyringeCheck) -> None:
        self.check = check
        self.table.setRowCount(len(check.strokes))
        for row, s in enumerate(check.strokes):
            ok = abs(s.error(check.syringe_l)) <= TOLERANCE
            cells = (f"{row + 1} ({'in' if s.volume_l > 0 else 'out'})", f"{abs(s.volume_l):.3f}",
                     f"{100 * s.error(check.syringe_l):+.1f} %", f"{s.peak_flow_lps:.1f}")
            for column, text in enumerate(cells):
                item = QTableWidgetItem(text)
                if column == 2:
                    item.setForeground(QColor("#1b7f3b" if ok else "#b00020"))
                self.table.setItem(row, column, item)
        self.verdict.setText(check.verdict())
        self.verdict.setStyleSheet("color: #1b7f3b; font-weight: bold" if check.passed else
                                   "color: #b00020; font-weight: bold")
        self.buttons.button(QDialogButtonBox.StandardButton.Save).setEnabled(bool(check.strokes))

    def _save(self) -> None:
        try:
            records = existing_records(None, None, may="syringe check")
        except RecordsError as exc:
            show_error(self, "The check cannot be logged.", str(exc))
            return
        try:
            with records or nullcontext():
                self.saved = log_syringe_check(self.rig_name, self.check, self.flow_from, records)
        except OSError as exc:
            show_error(self, "The check cannot be logged.", f"{exc}. Check the folder's permissions.")
            return
        self.accept()
