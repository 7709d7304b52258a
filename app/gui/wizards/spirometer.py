"""Spirometer calibration (engineer): the flow sensor against a reference flowmeter (thesis eq.
5.4), the thesis' volume regression from training sessions (eqs 5.1-5.3), the room's BTPS
conditions; saved as profiles, the previous ones kept."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QCheckBox, QDoubleSpinBox, QFileDialog, QFormLayout, QHBoxLayout, QLabel, QListWidget,
                               QPushButton, QTableWidget, QTableWidgetItem, QVBoxLayout, QWizard, QWizardPage)

from app.calibration_store import (FLOW_PROFILE, VOLUME_PROFILE, calibration_audit, calibration_dir, keep_previous,
                                   log_calibration)
from app.commands.reconstruction import regression_samples
from app.errors import UserError
from app.gui.errors import show_error
from app.records import RecordsError
from core.calibration.spirometer import CalibrationProfileError, fit_flow, fit_volume
from core.io.outputs import write_text_atomic
from core.io.session import now_iso
from core.sim.flowsensor import FlowSensorModel
from core.volume.flow_sensor import btps_factor


class RigFlowBench:
    """The rig's own flow sensor, read through the live engine while the pneumatic bench holds a
    steady flow."""

    label = "the rig's flow sensor"

    def __init__(self, engine) -> None:
        self.engine = engine

    def adc_mean(self, reference_lps: float, seconds: float = 2.0) -> float:
        return self.engine.flow_adc_mean(seconds)


class SimulatedFlowBench:
    """The simulated pneumatic bench: a steady flow through the simulated sensor, read for 2 s."""

    label = "the simulated flow bench (the simulated rig's sensor model; no hardware is read)"

    def __init__(self, seed: int = 1) -> None:
        self.model = FlowSensorModel()
        self.seed = seed
        self.reads = 0

    def adc_mean(self, reference_lps: float, seconds: float = 2.0) -> float:
        self.reads += 1
        t = np.arange(int(seconds * self.model.sample_rate_hz)) / self.model.sample_rate_hz
        counts = self.model.adc_counts(np.full(len(t), reference_lps * self.model.btps), t, self.seed + self.reads)
        return float(counts.mean())


class FlowPage(QWizardPage):
    def __init__(self, bench) -> None:
        super().__init__()
        self.bench = bench
        self.setTitle("Flow sensor")
        self.setSubTitle("Set a steady flow on the pneumatic bench, type the reference flowmeter's reading and "
                         "press Read (2 s). Cover the working range in both directions, and zero flow: at least "
                         f"three flows. Reading {getattr(bench, 'label', 'the flow sensor')}.")
        self.reference = QDoubleSpinBox(minimum=-15.0, maximum=15.0, value=0.0, suffix=" L/s", decimals=3,
                                        singleStep=0.5)
        self.read = QPushButton("Read")
        self.read.clicked.connect(self.read_flow)
        self.remove = QPushButton("Remove selected")
        self.remove.clicked.connect(self._remove)
        self.table = QTableWidget(0, 3)
        self.table.setHorizontalHeaderLabels(["Reference (L/s)", "ADC mean (counts)", "Residual (L/s)"])
        self.fit_label = QLabel("Read three or more steady flows.")
        self.fit_label.setWordWrap(True)
        self.plot = pg.PlotWidget(background="w", title="Residuals of the linear fit")
        self.plot.setLabel("bottom", "reference flow", units="L/s")
        self.plot.setLabel("left", "residual", units="L/s")
        self.plot.addLine(y=0, pen=pg.mkPen("k", width=1))
        self.plot.getAxis("left").enableAutoSIPrefix(False)
        self.points = pg.ScatterPlotItem(size=9, brush=pg.mkBrush(30, 30, 30))
        self.plot.addItem(self.points)
        row = QHBoxLayout()
        row.addWidget(QLabel("Reference flow"))
        row.addWidget(self.reference)
        row.addWidget(self.read)
        row.addWidget(self.remove)
        left = QVBoxLayout()
        left.addLayout(row)
        left.addWidget(self.table)
        left.addWidget(self.fit_label)
        layout = QHBoxLayout(self)
        layout.addLayout(left, 1)
        layout.addWidget(self.plot, 1)
        self.pairs: list[tuple[float, float]] = []
        self.calibration = None

    def read_flow(self) -> None:
        reference = self.reference.value()
        try:
            adc = self.bench.adc_mean(reference)
        except Exception as exc:  # a sensor that does not answer: said, the readings so far kept
            show_error(self, "The flow sensor could not be read.", f"{exc}. Check its cable and try again.")
            return
        self.pairs.append((reference, adc))
        self._refit()

    def _remove(self) -> None:
        rows = sorted({i.row() for i in self.table.selectedIndexes()}, reverse=True)
        for r in rows:
            del self.pairs[r]
        self._refit()

    def _refit(self) -> None:
        self.calibration = None
        residuals = [None] * len(self.pairs)
        if len(self.pairs) >= 3:
            flows, adcs = (np.array(x) for x in zip(*self.pairs))
            try:
                self.calibration = fit_flow(adcs, flows, created=now_iso(), sources=["flow bench"])
                residuals = self.calibration.residuals_lps
                c = self.calibration
                self.fit_label.setText(f"flow = {c.gain_lps:.6g} × ADC {c.offset_lps:+.4g} L/s; R² = {c.r_squared:.5f}; "
                                       f"{c.points} flows from {c.range_lps[0]:+.2f} to {c.range_lps[1]:+.2f} L/s.")
            except CalibrationProfileError as exc:
                self.fit_label.setText(f"<b>Not yet:</b> {exc}")
        else:
            self.fit_label.setText(f"{len(self.pairs)} of at least 3 flows read.")
        self.table.setRowCount(len(self.pairs))
        for r, ((flow, adc), residual) in enumerate(zip(self.pairs, residuals)):
            for c, text in enumerate((f"{flow:+.3f}", f"{adc:.1f}", "" if residual is None else f"{residual:+.4f}")):
                item = QTableWidgetItem(text)
                item.setFlags(item.flags() & ~Qt.ItemFlag.ItemIsEditable)
                self.table.setItem(r, c, item)
        self.table.resizeColumnsToContents()
        if self.calibration is not None:
            self.points.setData([f for f, _ in self.pairs], list(residuals))
        else:
            self.points.setData([], [])
        self.completeChanged.emit()

    def isComplete(self) -> bool:  # noqa: N802
        return self.calibration is not None


def fit_regression(files: list[Path]):
    """(calibration, features, volumes, None) of the thesis' regression on results files, or
    (None, None, None, why not)."""
    try:
        samples = [regression_samples(p) for p in files]
        features = np.vstack([s[0] for s in samples])
        volumes = np.concatenate([s[1] for s in samples])
        calibration = fit_volume(features, volumes, created=now_iso(), sessions=[s[2] for s in samples])
    except (UserError, CalibrationProfileError, OSError, KeyError) as exc:
        return None, None, None, str(exc)
    return calibration, features, volumes, None


class VolumePage(QWizardPage):
    def __init__(self) -> None:
        super().__init__()
        self.setTitle("Volume regression (thesis eqs 5.1-5.3)")
        self.setSubTitle("Fit the optical volume to the flow-sensor volume on processed training sessions "
                         "(results files of sessions with a flow sensor, at more than one distance).")
        self.enabled = QCheckBox("Fit a new volume regression (otherwise the one in force is kept)")
        self.enabled.setChecked(True)
        self.enabled.toggled.connect(self.completeChanged)
        self.add = QPushButton("Add results files…")
        self.add.clicked.connect(self._browse)
        self.list = QListWidget()
        self.label = QLabel("Add one or more results files.")
        self.label.setWordWrap(True)
        self.plot = pg.PlotWidget(background="w", title="Fitted against flow-sensor volume")
        self.plot.setLabel("bottom", "flow-sensor volume", units="L")
        self.plot.setLabel("left", "regression volume", units="L")
        self.points = pg.ScatterPlotItem(size=3, brush=pg.mkBrush(30, 30, 30, 120), pen=None)
        self.plot.addItem(self.points)
        left = QVBoxLayout()
        left.addWidget(self.enabled)
        left.addWidget(self.add)
        left.addWidget(self.list)
        left.addWidget(self.label)
        layout = QHBoxLayout(self)
        layout.addLayout(left, 1)
        layout.addWidget(self.plot, 1)
        self.files: list[Path] = []
        self.calibration = None

    def _browse(self) -> None:
        paths, _ = QFileDialog.getOpenFileNames(self, "Training results files", str(Path.home()), "Results (*.h5)")
        self.add_files([Path(p) for p in paths])

    def add_files(self, paths: list[Path]) -> None:
        """Fit the regression on every file so far: on a worker (the main window's jobs) when the
        wizard has one, so that reading the files does not freeze the window."""
        self.files += paths
        self.list.clear()
        self.list.addItems([p.name for p in self.files])
        self.calibration = None
        self.completeChanged.emit()
        files = list(self.files)
        start_job = getattr(self.wizard().parent() if self.wizard() else None, "start_job", None)
        if start_job is None:
            self._fitted(fit_regression(files))
            return
        self.label.setText(f"Fitting on {len(files)} file(s) …")
        start_job(lambda: fit_regression(files), "The volume regression", self._fitted)

    def _fitted(self, fitted) -> None:
        calibration, features, volumes, problem = fitted
        self.calibration = calibration
        if calibration is None:
            self.label.setText(f"<b>Cannot fit:</b> {problem}")
        else:
            c = calibration
            self.label.setText(f"r = {c.correlation:.4f}, R² = {c.r_squared:.4f} over {c.samples} samples from "
                               f"{len(self.files)} file(s).")
            keep = np.all(np.isfinite(features), axis=1)
            self.points.setData(volumes[keep][::5], c.volume_l(features[keep])[::5])
        self.completeChanged.emit()

    def isComplete(self) -> bool:  # noqa: N802
        return not self.enabled.isChecked() or self.calibration is not None


class ConditionsPage(QWizardPage):
    def __init__(self) -> None:
        super().__init__()
        self.setTitle("Room conditions (BTPS)")
        self.setSubTitle("The flow sensor measures at room conditions (ATPS); volumes are reported at body "
                         "conditions (BTPS). Enter today's room temperature, pressure and humidity.")
        self.temperature = QDoubleSpinBox(minimum=-10.0, maximum=45.0, value=23.0, suffix=" °C", decimals=1)
        self.pressure = QDoubleSpinBox(minimum=500.0, maximum=1100.0, value=1013.0, suffix=" hPa", decimals=1)
        self.humidity = QDoubleSpinBox(minimum=0.0, maximum=100.0, value=45.0, suffix=" %", decimals=0)
        self.factor = QLabel()
        form = QFormLayout(self)
        form.addRow("Room temperature", self.temperature)
        form.addRow("Barometric pressure", self.pressure)
        form.addRow("Relative humidity", self.humidity)
        form.addRow("BTPS factor", self.factor)
        for box in (self.temperature, self.pressure, self.humidity):
            box.valueChanged.connect(self._update)
        self._update()

    def _update(self) -> None:
        self.factor.setText(f"{self.btps():.4f}")

    def btps(self) -> float:
        return btps_factor(self.temperature.value(), self.pressure.value(), self.humidity.value())


class SpirometerCalibrationWizard(QWizard):
    def __init__(self, parent, bench=None, profile_dir: Path | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Spirometer calibration")
        self.profile_dir = profile_dir or calibration_dir()
        self.flow_page = FlowPage(bench or SimulatedFlowBench())
        self.volume_page = VolumePage()
        self.conditions_page = ConditionsPage()
        for page in (self.flow_page, self.volume_page, self.conditions_page):
            self.addPage(page)
        self.saved: list[Path] = []
        self.setMinimumSize(900, 560)

    def accept(self) -> None:
        self.profile_dir.mkdir(parents=True, exist_ok=True)
        flow = self.flow_page.calibration.to_json()
        c = self.conditions_page
        flow["room"] = {"temperature_c": c.temperature.value(), "pressure_hpa": c.pressure.value(),
                        "humidity_pct": c.humidity.value(), "btps_factor": c.btps()}
        try:
            audit = calibration_audit()
        except RecordsError as exc:
            show_error(self, "The calibration profiles cannot be saved.", str(exc))
            return
        try:
            target = self.profile_dir / FLOW_PROFILE
            kept = [keep_previous(target)]
            write_text_atomic(target, json.dumps(flow, indent=2) + "\n")
            self.saved = [target]
            volume = self.volume_page.calibration
            if self.volume_page.enabled.isChecked() and volume is not None:
                target = self.profile_dir / VOLUME_PROFILE
                kept.append(keep_previous(target))
                write_text_atomic(target, json.dumps(volume.to_json(), indent=2) + "\n")
                self.saved.append(target)
        except OSError as exc:
            show_error(self, "The calibration profiles cannot be saved.", f"{exc}. Check the folder's permissions.")
            return
        if audit is not None:
            with audit:
                for saved, previous in zip(self.saved, kept):
                    log_calibration(audit, "flow sensor" if saved.name == FLOW_PROFILE else "volume", saved,
                                    previous)
        super().accept()
