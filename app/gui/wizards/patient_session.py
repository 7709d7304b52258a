"""The patient session (operator): patient, positioning, the subject's calibration through the flow
sensor, then with the mouthpiece off tidal breathing, slow VC, forced expirations with ATS/ERS
feedback after each blow, review, save.

Recording starts when positioning passes and runs to the end; every manoeuvre is marked with the
protocol's events (tidal-start, vc-start, forced-start, maneuver-end, mouthpiece-off) so `photopft
process` and the report cut the curve exactly where the operator did. On the simulated rig the
simulated subject follows the prompts.
"""

from __future__ import annotations

import logging
import time
from datetime import date, datetime, timezone
from pathlib import Path

import numpy as np
from PySide6.QtCore import QDate, Qt, QTimer
from PySide6.QtWidgets import (QCheckBox, QComboBox, QDateEdit, QDoubleSpinBox, QFormLayout, QGroupBox, QHBoxLayout,
                               QLabel, QLineEdit, QListWidget, QListWidgetItem, QMessageBox, QPushButton, QSpinBox,
                               QTextEdit, QVBoxLayout, QWizard, QWizardPage)

from app.audit import login_name
from app.engine.protocol import LiveEngine
from app.gui.blow_screen import BlowScreen, predicted_fvc_l
from app.gui.errors import show_error
from app.gui.live_view import HeadMapView
from app.gui.volume_trace import SHOWN_S, VolumeTrace, plateau
from app.paths import data_dir
from app.records import Patient, Records, RecordsError
from app.report_data import main_table_rows, references_on, stored_interpretation
from core.analysis.protocol_feedback import (MAX_BLOWS, MAX_VC, MIN_TIDAL_BREATHS, forced_feedback, tidal_extension_s,
                                             vc_feedback)
from core.analysis.values import grade_caveat
from core.io.outputs import next_free_path
from core.io.session import SubjectRecord
from core.pipeline.quality import WORKING_RANGE_MM
from core.volume.subject_calibration import MOUTHPIECE_OFF

CENTRED_FRACTION = 0.12  # the subject's centre within 12 % of the image width of its centre


def _instructions(text: str) -> QLabel:
    label = QLabel(text)
    label.setWordWrap(True)
    label.setStyleSheet("font-size: 11pt")
    return label


class PatientPage(QWizardPage):
    def __init__(self, records: Records, operator: str = "") -> None:
        super().__init__()
        self.records = records
        self.setTitle("Patient")
        self.setSubTitle("Find the patient, or add a new one. Names stay in the records; the session file "
                         "carries only the pseudonym.")
        self.search = QLineEdit()
        self.search.setPlaceholderText("name, patient number or pseudonym")
        self.search.textChanged.connect(self._refresh)
        self.list = QListWidget()
        self.list.itemSelectionChanged.connect(self.completeChanged)
        new = QGroupBox("New patient")
        form = QFormLayout(new)
        self.family = QLineEdit()
        self.given = QLineEdit()
        self.number = QLineEdit()
        self.sex = QComboBox()
        self.sex.addItems(["female", "male"])
        self.birth = QDateEdit(QDate(1980, 1, 1))
        self.birth.setDisplayFormat("yyyy-MM-dd")
        self.birth.setCalendarPopup(True)
        self.height = QDoubleSpinBox(minimum=40.0, maximum=250.0, value=170.0, suffix=" cm", decimals=1)
        self.weight = QDoubleSpinBox(minimum=2.0, maximum=400.0, value=70.0, suffix=" kg", decimals=1)
        for label, widget in (("Family name", self.family), ("Given name", self.given),
                              ("Patient number", self.number), ("Sex (for the reference equations)", self.sex),
                              ("Date of birth", self.birth), ("Height", self.height), ("Weight", self.weight)):
            form.addRow(label, widget)
        self.add = QPushButton("Add patient")
        self.add.clicked.connect(self._add)
        form.addRow(self.add)
        self.front_only = QCheckBox("Front head only (the patient cannot stand in the rig)")
        self.operator = QLineEdit(operator or login_name())
        self.operator.setToolTip("Who runs this session: recorded in the session file and on the report")
        self.operator.textChanged.connect(self.completeChanged)
        who = QFormLayout()
        who.addRow("Operator", self.operator)
        layout = QHBoxLayout(self)
        left = QVBoxLayout()
        left.addLayout(who)
        left.addWidget(self.search)
        left.addWidget(self.list)
        left.addWidget(self.front_only)
        layout.addLayout(left, 1)
        layout.addWidget(new, 1)
        self._refresh()

    def _refresh(self) -> None:
        self.list.clear()
        for p in self.records.find_patients(self.search.text()):
            item = QListWidgetItem(f"{p.display_name}  ·  {p.patient_number or 'no number'}  ·  born "
                                   f"{p.birth_date.isoformat()}  ·  {p.pseudonym}")
            item.setData(Qt.ItemDataRole.UserRole, p.id)
            self.list.addItem(item)

    def _add(self) -> None:
        birth = self.birth.date()
        try:
            patient = self.records.add_patient(self.family.text(), self.given.text(), self.sex.currentText(),
                                               date(birth.year(), birth.month(), birth.day()), self.height.value(),
                                               self.weight.value(), self.number.text() or None)
        except RecordsError as exc:
            show_error(self, "The patient cannot be added.", f"{exc}. Correct it and add again.")
            return
        self.search.setText(patient.pseudonym)
        self._refresh()
        self.list.setCurrentRow(0)

    def patient(self) -> Patient | None:
        items = self.list.selectedItems()
        return self.records.patient(items[0].data(Qt.ItemDataRole.UserRole)) if items else None

    def isComplete(self) -> bool:  # noqa: N802 - Qt naming
        return self.patient() is not None and bool(self.operator.text().strip())


class PositioningPage(QWizardPage):
    """The live view behind shows the maps; here, the checks that must pass before recording."""

    def __init__(self, engine: LiveEngine) -> None:
        super().__init__()
        self.engine = engine
        self.setTitle("Positioning")
        self.setSubTitle("Ask the patient to stand still between the heads, arms slightly away from the body, "
                         "facing the front head. Recording starts when every check passes and you press Next.")
        self.checks = QLabel()
        self.checks.setTextFormat(Qt.TextFormat.RichText)
        self.maps_row = QHBoxLayout()
        self.maps: dict = {}
        layout = QVBoxLayout(self)
        layout.addWidget(_instructions("Move the patient until both lines read OK: the distance within the "
                                       "working range, the body centred in the picture and the arms held "
                                       "away from the trunk (an arm against it hides the side the volume "
                                       "is measured from)."))
        layout.addLayout(self.maps_row, 1)
        layout.addWidget(self.checks)
        self.passed = False
        self.timer = QTimer(self)
        self.timer.timeout.connect(self._check)

    def initializePage(self) -> None:  # noqa: N802

        for head in self.wizard().heads():
            if head not in self.maps:
                self.maps[head] = HeadMapView(head)
                self.maps_row.addWidget(self.maps[head])
        for head, view in self.maps.items():
            view.setVisible(head in self.wizard().heads())
        self.timer.start(200)

    def cleanupPage(self) -> None:  # noqa: N802
        self.timer.stop()

    def _check(self) -> None:
        snapshot = self.engine.snapshot()
        lines, ok = [], True
        heads = self.wizard().heads()
        for head in heads:
            view = snapshot.heads.get(head)
            if head in self.maps and view is not None:
                self.maps[head].show_map(view.height_mm)
            if view is None or view.height_mm is None:
                lines.append(f"{head}: waiting for the first map")
                ok = False
                continue
            low, high = WORKING_RANGE_MM
            distance_ok = low <= view.distance_mm <= high
            columns = np.nonzero(np.isfinite(view.height_mm).any(axis=0))[0]
            width = view.height_mm.shape[1]
            centre = 0.5 * (columns[0] + columns[-1]) if len(columns) else np.nan
            centred = bool(len(columns)) and abs(centre - (width - 1) / 2) <= CENTRED_FRACTION * width
            arms_away = not view.arm_against_trunk
            ok = ok and bool(distance_ok and centred and arms_away)
            lines.append(f"<b>{head.capitalize()}</b>: distance {view.distance_mm:.0f} mm "
                         f"{'OK' if distance_ok else f'<span style=color:#b00020>outside {low:.0f}–{high:.0f} mm</span>'}"
                         f"; centred {'OK' if centred else '<span style=color:#b00020>move the patient to the centre</span>'}"
                         f"; arms {'away OK' if arms_away else '<span style=color:#b00020>against the trunk: hold them away from the body</span>'}")
        self.checks.setText("<br>".join(lines))
        if ok != self.passed:
            self.passed = ok
            self.completeChanged.emit()

    def isComplete(self) -> bool:  # noqa: N802
        return self.passed

    def validatePage(self) -> bool:  # noqa: N802
        self.timer.stop()
        if self.engine.recording:  # Back to positioning and Next again: the recording goes on, one file
            return True
        return self.wizard().start_recording()


CALIBRATION_QUIET_S = 20.0  # the calibration's quiet breathing before its slow VC (issue 75)


def on_the_flow_sensor(traces: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The optical curve moved to the flow sensor's level (its mean over their common times), for drawing
    the two together: each has its own zero."""
    if "optical" not in traces or "flow sensor" not in traces:
        return traces
    (t_opt, v_opt), (t_flow, v_flow) = traces["optical"], traces["flow sensor"]
    t_opt, v_opt = np.asarray(t_opt, float), np.asarray(v_opt, float)
    common = (t_opt >= t_flow[0]) & (t_opt <= t_flow[-1]) & np.isfinite(v_opt) if len(t_flow) else np.zeros(0, bool)
    if not common.any():
        return traces
    shift = float(np.mean(np.interp(t_opt[common], t_flow, v_flow) - v_opt[common]))
    return {**traces, "optical": (t_opt, v_opt + shift)}


class CalibrationPage(QWizardPage):
    """The subject's calibration: quiet breathing and one slow VC through the flow sensor while both heads
    run; the optical signals are fitted to the flow sensor's volume (core/volume/subject_calibration.py)
    and the operator sees the fit, its residual and expected error, and repeats it where it is refused.
    Next marks `mouthpiece-off`: from there the cameras alone give the litres. A patient who cannot use
    a mouthpiece skips it: the optical litres are then an estimate with the population's uncertainty."""

    def __init__(self, engine: LiveEngine) -> None:
        super().__init__()
        self.engine = engine
        self.setTitle("Calibration through the flow sensor")
        self.setSubTitle(f"Mouthpiece in and nose clip on. The patient breathes quietly for "
                         f"{CALIBRATION_QUIET_S:.0f} s, then does one slow vital capacity: slowly all the way in, "
                         "slowly all the way out until nothing more comes out, back to normal breathing.")
        self.start = QPushButton("Start calibration")
        self.start.clicked.connect(self._start)
        self.vc = QPushButton("Start slow VC")
        self.vc.setEnabled(False)
        self.vc.clicked.connect(self._begin_vc)
        self.end = QPushButton("End slow VC")
        self.end.setEnabled(False)
        self.end.clicked.connect(self._end_vc)
        self.skip = QCheckBox("The patient cannot use a mouthpiece: no calibration (the litres are estimates)")
        self.skip.toggled.connect(self._skipped)
        self.result = QLabel("not started")
        self.result.setWordWrap(True)
        self.trace = VolumeTrace(self)
        buttons = QHBoxLayout()
        for button in (self.start, self.vc, self.end):
            buttons.addWidget(button)
        layout = QVBoxLayout(self)
        layout.addLayout(buttons)
        layout.addWidget(self.trace, 1)
        layout.addWidget(self.result)
        layout.addWidget(self.skip)
        self.calibration = None
        self.mouthpiece_off = False  # marked: the flow sensor's samples end there
        self._vc_started = False
        self._start_ns = 0
        self._quiet_until = 0.0
        self.timer = QTimer(self)
        self.timer.setInterval(200)
        self.timer.timeout.connect(self._tick)

    def _start(self) -> None:
        self.calibration = None
        self._vc_started = False
        self.trace.status.setText("the flow sensor's volume and the optical one (not calibrated yet), since the start")
        self._start_ns = self.engine.mark("tidal-start")
        self._quiet_until = time.monotonic() + CALIBRATION_QUIET_S
        self.start.setEnabled(False)
        self.vc.setEnabled(False)
        self.result.setText(f"quiet breathing: {CALIBRATION_QUIET_S:.0f} s")
        self.result.setStyleSheet("")
        self.timer.start()
        self.completeChanged.emit()

    def _tick(self) -> None:
        try:
            self.trace.show_traces(on_the_flow_sensor(self.engine.blow_trace(self._start_ns, before_s=0.0)))
        except Exception as exc:  # the curve is feedback; the recording goes on without it
            self.trace.status.setText(f"live curve stopped: {exc}")
        left = self._quiet_until - time.monotonic()
        if left > 0:
            self.result.setText(f"quiet breathing: {left:.0f} s left")
        elif not self._vc_started and self._quiet_until:
            self.result.setText("now the slow VC: press Start slow VC as the patient begins")
            self.vc.setEnabled(True)

    def _begin_vc(self) -> None:
        self._vc_started = True
        self.engine.mark("vc-start")
        self.last_duration_s = self.engine.perform("vc")
        self.vc.setEnabled(False)
        self.end.setEnabled(True)
        self.result.setText("slow VC: press End slow VC once the patient is back to normal breathing")

    def _end_vc(self) -> None:
        self._end_ns = self.engine.mark("maneuver-end")
        self._asked = time.monotonic()
        self.end.setEnabled(False)
        self.result.setText("fitting the optical signals to the flow sensor …")
        self._when_flow_arrives()

    def _when_flow_arrives(self) -> None:
        if not self.engine.flow_reaches(self._end_ns) and time.monotonic() - self._asked < 10.0:
            QTimer.singleShot(100, self._when_flow_arrives)
            return
        self.timer.stop()
        self._quiet_until = 0.0
        try:
            calibration = self.engine.calibrate_on_subject(self._start_ns)
        except Exception as exc:  # said; the operator may repeat it or go on without
            calibration = None
            refused = f"the calibration failed: {exc}"
        else:
            refused = calibration.refused
        self.start.setText("Repeat calibration")
        self.start.setEnabled(True)
        self.vc.setEnabled(False)
        if calibration is not None and "fit_t_s" in calibration.extra:  # the fit over the flow sensor's curve
            traces = self.engine.blow_trace(self._start_ns, before_s=0.0)
            traces["optical"] = (calibration.extra["fit_t_s"], calibration.extra["fit_l"])
            self.trace.show_traces(on_the_flow_sensor(traces))
            self.trace.status.setText("the flow sensor's volume and the optical signals fitted to it")
        if refused is None:
            self.calibration = calibration
            self.result.setText(
                f"Calibrated: the optical signals follow the flow sensor within {1000 * calibration.residual_l:.0f} mL "
                f"({100 * calibration.residual_l / calibration.range_l:.1f} % of its {calibration.range_l:.2f} L); "
                f"expected error {100 * calibration.expected_error:.1f} %. Take the mouthpiece out and the nose clip "
                "off, then Next.")
            self.result.setStyleSheet("color: #006400")
        else:
            self.result.setText(f"Not calibrated: {refused}")
            self.result.setStyleSheet("color: #b00020")
        self.completeChanged.emit()

    def _skipped(self, skipped: bool) -> None:
        for button in (self.start, self.vc, self.end):
            button.setEnabled(not skipped and button is self.start)
        if skipped:
            self.timer.stop()
        self.completeChanged.emit()

    def isComplete(self) -> bool:  # noqa: N802
        return self.calibration is not None or self.skip.isChecked()

    def validatePage(self) -> bool:  # noqa: N802
        if not self.mouthpiece_off:  # once: Back and Next again does not take it off twice
            self.engine.mark(MOUTHPIECE_OFF)
            self.mouthpiece_off = True
            self.start.setEnabled(False)
            self.skip.setEnabled(False)
        return True


class TimedPage(QWizardPage):
    """Tidal breathing: a set time of quiet breathing, counted down."""

    def __init__(self, engine: LiveEngine) -> None:
        super().__init__()
        self.engine = engine
        self.setTitle("Tidal breathing")
        self.setSubTitle("Mouthpiece out: ask the patient to breathe quietly and normally, mouth closed.")
        self.seconds = QSpinBox(minimum=10, maximum=600, value=60, suffix=" s")
        self.start = QPushButton("Start tidal breathing")
        self.start.clicked.connect(self._start)
        self.remaining = QLabel("not started")
        form = QFormLayout(self)
        form.addRow("Duration", self.seconds)
        form.addRow(self.start)
        form.addRow("Remaining", self.remaining)
        self.trace = VolumeTrace(self, window_s=SHOWN_S)
        form.addRow(self.trace)
        self.done = False
        self._mark_ns = 0
        self._ticks = 0
        self.extended_s = 0.0
        self.timer = QTimer(self)
        self.timer.timeout.connect(self._tick)

    def _start(self) -> None:
        self._mark_ns = self.engine.mark("tidal-start")
        self.ends_at = time.monotonic() + self.seconds.value()
        self.extended_s = 0.0
        self.start.setEnabled(False)
        self.seconds.setEnabled(False)
        self.timer.start(200)

    def _show_breathing(self) -> None:
        """The curve five times a second; breaths, TV and RR so far every 2 s (they analyse the
        whole recording)."""
        try:
            self.trace.show_traces(self.engine.blow_trace(self._mark_ns, before_s=0.0))
        except Exception as exc:  # the curve is feedback; the recording goes on without it
            self.trace.status.setText(f"live curve stopped: {exc}")
            return
        self._ticks += 1
        if self._ticks % 10 == 1:
            values = self.engine.recorded_values(self.wizard().age_years())
            tidal = values.tidal if values is not None else None
            calibrated = self.wizard().calibration_page.calibration is not None
            self.trace.status.setText(
                f"{tidal.breaths} breaths so far; TV {tidal.tidal_volume_l:.2f} L, RR "
                f"{tidal.respiratory_rate_bpm:.0f}/min" if tidal is not None else
                "no breath counted yet" if values is not None or calibrated else
                "breaths are counted when the session is processed (no calibration on the subject)")

    def _tick(self) -> None:
        self._show_breathing()
        left = self.ends_at - time.monotonic()
        if left > 0:
            extra = f" (extended: {self._note})" if self.extended_s else ""
            self.remaining.setText(f"{left:.0f} s{extra}")
            return
        breaths = self._breaths()
        extension = tidal_extension_s(breaths, self.extended_s)
        if extension:
            self.extended_s += extension
            self.ends_at = time.monotonic() + extension
            self._note = f"{breaths} breath{'s' if breaths != 1 else ''} so far, {MIN_TIDAL_BREATHS} needed"
            return
        self.timer.stop()
        self.engine.mark("maneuver-end")
        self.remaining.setText("done" if breaths is None or breaths >= MIN_TIDAL_BREATHS else
                               f"done, with only {breaths} breaths: the tidal values rest on few breaths")
        self.done = True
        self.completeChanged.emit()

    def _breaths(self) -> int | None:
        """Tidal breaths in the recording so far, from the flow sensor (None without one: counted
        when the session is processed)."""
        values = self.engine.recorded_values(self.wizard().age_years())
        if values is None:
            return None
        return int(values.tidal.breaths) if values.tidal is not None else 0

    def isComplete(self) -> bool:  # noqa: N802
        return self.done


class ManoeuvrePage(QWizardPage):
    """One kind of manoeuvre, started and ended by the operator (the simulated subject follows)."""

    def __init__(self, engine: LiveEngine, kind: str) -> None:
        super().__init__()
        self.engine = engine
        self.kind = kind
        forced = kind == "forced"
        self.setTitle("Forced expirations" if forced else "Slow vital capacity")
        self.setSubTitle(
            "Breathe quietly; then a full, fast inspiration to the top, and blast out as hard and fast as "
            "possible, and keep going until nothing more comes out (at least 6 s). At least three blows."
            if forced else
            "Breathe quietly; then slowly breathe all the way in, then slowly all the way out until nothing "
            "more comes out, then back to normal breathing.")
        self.begin = QPushButton("Start blow" if forced else "Start slow VC")
        self.begin.clicked.connect(self._begin)
        self.end = QPushButton("End blow" if forced else "End manoeuvre")
        self.end.setEnabled(False)
        self.end.clicked.connect(self._end)
        self.reject = QPushButton("Reject the last one (do it again)")
        self.reject.setToolTip("The last manoeuvre is left out of every value (marked in the recording)")
        self.reject.setEnabled(False)
        self.reject.clicked.connect(self._reject_last)
        self.feedback = QTextEdit(readOnly=True)
        self.trace = None if forced else VolumeTrace(self)
        buttons = QHBoxLayout()
        buttons.addWidget(self.begin)
        buttons.addWidget(self.end)
        buttons.addWidget(self.reject)
        self.layout_ = QVBoxLayout(self)
        self.layout_.addLayout(buttons)
        if self.trace is not None:
            self.layout_.addWidget(self.trace, 1)
            self.feedback.setMaximumHeight(110)
        self.layout_.addWidget(self.feedback)
        self.count = 0
        self.assessed = 0
        self._lines: list[str] = []
        self.finished = False
        self.screen = None  # the forced-blow screen, made when the page shows (it needs the patient)
        self.trace_timer = QTimer(self)
        self.trace_timer.setInterval(100)
        self.trace_timer.timeout.connect(self._trace)
        self._mark_ns = 0

    def initializePage(self) -> None:  # noqa: N802

        if self.kind != "forced" or self.screen is not None:
            return
        patient = self.wizard().patient_page.patient()
        self.screen = BlowScreen(self.wizard().age_years(), predicted_fvc_l(patient))
        self.layout_.insertWidget(1, self.screen, 1)
        self.feedback.setMaximumHeight(90)
        wizard = self.wizard()
        room = wizard.screen().availableGeometry()  # a 1366 x 768 screen: the buttons stay on it
        wizard.resize(min(max(wizard.width(), 1150), room.width() - 20), min(max(wizard.height(), 860), room.height() - 40))
        if wizard.y() + wizard.height() > room.bottom() or wizard.x() + wizard.width() > room.right():
            wizard.move(room.left() + max(0, (room.width() - wizard.width()) // 2), room.top())

    def _begin(self) -> None:
        self._mark_ns = self.engine.mark("forced-start" if self.kind == "forced" else "vc-start")
        self.last_duration_s = self.engine.perform(self.kind)
        self.begin.setEnabled(False)
        self.reject.setEnabled(False)
        self.end.setEnabled(True)
        self.trace_timer.start()

    def _trace(self) -> None:
        """The blow so far on the forced-blow screen, the slow VC's curve and plateau on its page (ten
        times a second)."""
        try:
            traces = self.engine.blow_trace(self._mark_ns)
        except Exception as exc:  # the screen is feedback; the recording goes on without it
            self.trace_timer.stop()
            (self.screen.status if self.screen is not None else self.trace.status).setText(
                f"live curves stopped: {exc}")
            return
        if self.screen is not None:
            self.screen.show_live(traces)
            return
        self.trace.show_traces(traces)
        main = self.trace.main_trace(traces)
        if main is not None:
            reached_s, change = plateau(*main)
            self.trace.status.setText(
                f"plateau reached at {reached_s:.1f} s (under 25 mL over a second at the lowest volume)"
                if reached_s is not None else
                f"no plateau yet ({change * 1000:.0f} mL in the last second; under 25 mL at the bottom needed)"
                if change == change else "no plateau yet")

    def _end(self) -> None:
        self._end_ns = self.engine.mark("maneuver-end")
        self._asked = time.monotonic()
        self.count += 1
        self.end.setEnabled(False)
        self.begin.setEnabled(False)
        self.feedback.setPlainText("\n".join(self._lines + [f"{'Blow' if self.kind == 'forced' else 'Slow VC'} "
                                                             f"{self.count}: analysing …"]))
        self._when_flow_arrives()

    def _when_flow_arrives(self) -> None:
        """The flow sensor's samples reach the recording a little after the frames that stamp the
        events (seconds on a busy machine): the blow is judged once they cover it."""
        if not self.engine.flow_reaches(self._end_ns) and time.monotonic() - self._asked < 10.0:
            QTimer.singleShot(100, self._when_flow_arrives)
            return
        self.trace_timer.stop()
        self._trace()  # the whole manoeuvre, to its end
        self._lines.append(self._assess())
        self.feedback.setPlainText("\n".join(self._lines))
        self.assessed = self.count
        self.begin.setEnabled(self.count < (MAX_BLOWS if self.kind == "forced" else MAX_VC) and not self.finished)
        self.reject.setEnabled(self.count > 0)
        self.completeChanged.emit()

    def _assess(self) -> str:
        age_years = self.wizard().age_years()
        values = self.engine.recorded_values(age_years)
        if values is None:
            if self.screen is not None:
                self.screen.finish_blow(None)
            return f"{self.title()} {self.count}: recorded (no flow sensor: feedback comes with the report)."
        if self.kind != "forced":
            return self._assess_vc(values)
        if self.screen is not None:
            self.screen.finish_blow(values.forced)
        feedback = forced_feedback(values, self.count, age_years)
        self.finished = feedback.finished
        return feedback.text

    def _assess_vc(self, values) -> str:
        feedback = vc_feedback(values, self.count, predicted_fvc_l(self.wizard().patient_page.patient()))
        self.finished = feedback.finished
        return feedback.text

    def _reject_last(self) -> None:
        """The operator saw the last manoeuvre go wrong: it is marked rejected (left out of every
        value, in the report too) and may be done again."""
        self.engine.mark("maneuver-rejected")
        self.count -= 1
        self.assessed = self.count
        self._lines[-1] += " Rejected by the operator."
        self.reject.setEnabled(False)
        self.finished = False
        if self.screen is not None:
            self.screen.reject_last()
            values = self.engine.recorded_values(self.wizard().age_years())
            if values is not None and values.forced is not None:
                self.screen.show_grade(values.forced)
        self.feedback.setPlainText("\n".join(self._lines))
        self.begin.setEnabled(True)
        self.completeChanged.emit()

    def isComplete(self) -> bool:  # noqa: N802
        if self.end.isEnabled() or self.assessed < self.count:
            return False
        if self.kind == "forced":
            return self.finished or self.count >= MAX_BLOWS
        return self.finished


def review_html(parameters: dict, problems: list[str], patient: Patient | None, source: str) -> str:
    """The values of `source` as the report names them, with predicted values, z-scores and the
    ERS/ATS 2022 interpretation, which names the source."""
    now = datetime.now(timezone.utc)
    references = references_on(patient, now, "gli-global") if patient else {}
    rows = ["<tr><th align=left>Value</th><th>Unit</th><th>Measured</th><th>Predicted</th><th>LLN</th><th>z</th></tr>"]
    for row in main_table_rows():
        if row.key not in parameters:
            continue
        value = float(parameters[row.key])
        ref = references.get(row.reference) if row.reference else None
        extra = (f"<td align=right>{ref.predicted:.2f}</td><td align=right>{ref.lln:.2f}</td>"
                 f"<td align=right>{ref.zscore(value):+.2f}</td>") if ref else "<td></td><td></td><td></td>"
        rows.append(f"<tr><td>{row.name}</td><td>{row.unit}</td><td align=right>{value:.{row.decimals}f}</td>"
                    f"{extra}</tr>")
    html = "<table cellspacing=0 cellpadding=3>" + "".join(rows) + "</table>"
    if "grade" in parameters:
        caveat = grade_caveat(parameters)
        html += (f"<p>ATS/ERS 2019 grade <b>{parameters['grade']}</b>: {parameters['acceptable_FEV1']} acceptable "
                 f"FEV1 and {parameters['acceptable_FVC']} acceptable FVC of {parameters['manoeuvres']} blows"
                 + (f"; {caveat}" if caveat else "") + ".</p>")
    if patient is not None:
        verdict = stored_interpretation(patient, parameters, now, source)
        html += f"<p><b>{verdict.summary}</b> (ERS/ATS 2022)<br>" + "<br>".join(verdict.statements) + "</p>"
    html += "".join(f"<p>Note: {p}</p>" for p in problems)
    return html


class ReviewPage(QWizardPage):
    def __init__(self, engine: LiveEngine) -> None:
        super().__init__()
        self.engine = engine
        self.setTitle("Review and save")
        self.setSubTitle("The recording stops when you press Finish; the session is put on the patient's record "
                         "and its report can be exported from the Session menu.")
        self.summary = QTextEdit(readOnly=True)
        QVBoxLayout(self).addWidget(self.summary)

    def initializePage(self) -> None:  # noqa: N802
        values = self.engine.recorded_values(self.wizard().age_years())
        if values is None:
            self.summary.setPlainText("No calibration on the subject: the values come with processing and the "
                                      "report (optical estimates).")
            return
        self.summary.setHtml("<p>From the live optical volume, calibrated on the subject; the report's values come "
                             "from processing the recording.</p>"
                             + review_html(values.parameters(), values.problems, self.wizard().patient_page.patient(),
                                           "live optical, calibrated on the subject"))


class PatientSessionWizard(QWizard):
    def __init__(self, parent, engine: LiveEngine, records: Records | None = None,
                 sessions_dir: Path | None = None, operator: str = "") -> None:
        super().__init__(parent)
        self.setWindowTitle("Patient session")
        self.engine = engine
        self.records = records or Records()
        self.sessions_dir = sessions_dir or data_dir() / "sessions"
        self.session_path: Path | None = None
        self.session_id: int | None = None
        self.patient_page = PatientPage(self.records, operator)
        self.addPage(self.patient_page)
        self.addPage(PositioningPage(engine))
        self.calibration_page = CalibrationPage(engine)
        self.addPage(self.calibration_page)
        self.addPage(TimedPage(engine))
        self.addPage(ManoeuvrePage(engine, "vc"))
        self.addPage(ManoeuvrePage(engine, "forced"))
        self.addPage(ReviewPage(engine))
        self.setOption(QWizard.WizardOption.NoBackButtonOnStartPage)
        self.setMinimumSize(760, 520)

    def heads(self) -> list[str]:
        heads = list(self.engine.info.heads)
        return ["front"] if self.patient_page.front_only.isChecked() else heads

    def age_years(self) -> float | None:
        p = self.patient_page.patient()
        return p.age_years(date.today()) if p else None

    @property
    def operator(self) -> str:
        return self.patient_page.operator.text().strip()

    def start_recording(self) -> bool:
        patient = self.patient_page.patient()
        now = datetime.now(timezone.utc)
        self.sessions_dir.mkdir(parents=True, exist_ok=True)
        self.session_path = next_free_path(self.sessions_dir / f"{patient.pseudonym}-{now:%Y%m%d-%H%M%S}.h5")
        subject = SubjectRecord(**patient.subject_attrs(now))
        kind = "simulation" if self.engine.info.simulated else "patient"
        try:
            self.records.check_permitted("session recorded")  # before the engine records anything
        except RecordsError as exc:
            show_error(self, "The recording cannot start.", str(exc))
            return False
        try:
            self.engine.start_recording(self.session_path, subject, kind=kind, heads=self.heads(),
                                        root_attrs={"operator": self.operator} if self.operator else None)
            self.session_id = self.records.add_session(patient.id, self.session_path, now, operator=self.operator,
                                                       rig=self.engine.rig.name, status="recording")
        except (OSError, ValueError) as exc:
            show_error(self, "The recording cannot start.", f"{exc}. Check the disk and the rig, then try again.")
            return False
        return True

    def _stop(self, status: str, quiet: bool = False) -> None:
        if not self.engine.recording:
            return
        try:  # the flow sensor's values while it was on; after the mouthpiece came off they come with processing
            values = None if self.calibration_page.mouthpiece_off else self.engine.recorded_values(self.age_years())
        except Exception:  # values are a convenience here; the recording is what matters
            values = None
        summary = self.engine.stop_recording()
        if self.session_id is not None:
            self.records.set_results(self.session_id, None, {"flow sensor": values.parameters()} if values else {},
                                     status=status)
        if summary.problems and quiet:
            logging.getLogger(__name__).error("the recording stopped with a problem: %s", "; ".join(summary.problems))
        elif summary.problems:
            show_error(self, "The recording stopped with a problem.", "; ".join(summary.problems))

    def accept(self) -> None:
        self._stop("recorded")
        super().accept()

    def reject(self) -> None:
        if self.engine.recording and not self._confirm_cancel():
            return
        self._stop("cancelled")
        super().reject()

    def end_without_asking(self, status: str) -> None:
        """The application is shutting down: the recording finished, the visit marked, no question."""
        self._stop(status, quiet=True)
        super().reject()

    def _confirm_cancel(self) -> bool:
        """Cancel during a recording asks first: what was recorded is kept either way, marked cancelled."""
        answer = QMessageBox.question(
            self, "Cancel the session?",
            "Stop the recording and end this patient session?\n\nWhat was recorded so far is kept in the "
            "patient's record, marked as cancelled.",
            QMessageBox.StandardButton.Yes | QMessageBox.StandardButton.No, QMessageBox.StandardButton.No)
        return answer == QMessageBox.StandardButton.Yes
