"""The main window: the live view, menus and toolbar, and the engine it draws from."""

from __future__ import annotations

import gc
import logging
import resource
import sys
import time
import traceback
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import partial
from pathlib import Path
from typing import Callable

from PySide6.QtCore import QByteArray, QObject, QRunnable, QSettings, Qt, QThreadPool, QTimer, Signal
from PySide6.QtGui import QAction, QKeySequence
from PySide6.QtWidgets import QApplication, QDialog, QFileDialog, QLabel, QMainWindow, QMessageBox

from app.audit import UNREGISTERED, login_name
from app.calibration_store import calibration_audit, calibration_dir, syringe_status
from app.engine.feeds import EngineInfo
from app.engine.process import EngineProcess
from app.engine.sources import Source, replay_source, rig_source
from app.gui.cut_off import CutOffVisitsDialog
from app.gui.diagnostics_page import DiagnosticsPage
from app.gui.errors import file_problem, show_error
from app.gui.live_view import LiveView
from app.gui.processing import ProcessingPanel
from app.gui.profiles_view import ProfilesWindow
from app.gui.records_view import AuditWindow, RecordsWindow
from app.gui.settings_dialog import SettingsDialog
from app.gui.syringe_check import RigSyringe, SimulatedSyringe, SyringeCheckDialog
from app.gui.wizards.patient_session import PatientSessionWizard
from app.gui.wizards.sphere import SphereCalibrationWizard, capture_from_rig
from app.gui.wizards.spirometer import RigFlowBench, SimulatedFlowBench, SpirometerCalibrationWizard
from app.records import Records, RecordsError, default_path
from app.report_access import log_report, never_ask, report_for
from app.report_pdf import write_report
from app.session_processing import cut_off_visits
from core.io.session import SessionError

log = logging.getLogger("photopft.gui")

DISPLAY_INTERVAL_MS = 33  # about 30 display updates per second


def calibration_in_force(info: EngineInfo) -> str:
    """The calibrations in force on the source, and the age of the lights' (a replay: as recorded)."""
    stamps = {h.calibrated for h in info.rig.heads.values() if h.calibrated}
    if info.replay:
        return (f"as recorded (lights calibrated {min(stamps)[:10]})" if stamps
                else "as recorded (lights not calibrated)")

    text = info.calibration or "lights as the rig file gives them"
    if info.flow_calibration is not None:
        text += "; " + syringe_status(info.rig.name)[0]
    if stamps:
        try:
            days = (datetime.now(timezone.utc) - datetime.fromisoformat(min(stamps))).total_seconds() / 86400
        except ValueError:
            return text
        text += f" — lights {'calibrated today' if days < 1 else f'{days:.0f} days old'}"
        if days > 30:
            text += ": recalibrate (over 30 days)"
    return text


@dataclass(frozen=True)
class Stall:
    at_s: float  # since the monitor's last reset
    ms: float  # how much later than asked the timer ran
    busy_ms: float  # of which the GUI thread was on a CPU (drawing, Python, a garbage collection)
    preempted: int  # times the kernel took the CPU from the GUI thread meanwhile (involuntary switches)


def acting_user_text() -> str:
    """Who the records will say acted, and their role (roles are enforced once users are registered)."""
    name, role, enforced = login_name(), UNREGISTERED, False
    if default_path().exists():
        try:
            with Records(read_only=True) as records:
                role, enforced = records.actor.role, records.roles_enforced
        except RecordsError:
            pass
    if not enforced:
        return f"User: {name} (roles not enforced)"
    return f"User: {name} ({'not registered: may only look' if role == UNREGISTERED else role})"


def _thread_switches() -> int:
    try:
        return resource.getrusage(resource.RUSAGE_THREAD).ru_nivcsw
    except (AttributeError, OSError):  # RUSAGE_THREAD is Linux's
        return 0


class StallMonitor:
    """How late the GUI thread's event loop runs a 10 ms timer: its longest stall, and the stalls
    longer than a display interval, each with what the GUI thread did meanwhile: a stall that is
    mostly busy time is work on the GUI thread; one that is not is a wait (for the GIL held by
    another thread of this process, or for a CPU the kernel gave to another process)."""

    def __init__(self, parent: QObject) -> None:
        self.longest_ms = 0.0
        self.long_stalls: list[Stall] = []
        self._last = time.perf_counter()
        self._last_cpu = time.thread_time()
        self._last_switches = _thread_switches()
        self._since = self._last
        self._timer = QTimer(parent)
        self._timer.setInterval(10)
        self._timer.timeout.connect(self._tick)
        self._timer.start()
        self._skip = 5  # the first ticks include start-up

    def _tick(self) -> None:
        now, cpu, switches = time.perf_counter(), time.thread_time(), _thread_switches()
        if self._skip:
            self._skip -= 1
        else:
            stall_ms = (now - self._last) * 1000.0 - 10.0
            self.longest_ms = max(self.longest_ms, stall_ms)
            if stall_ms > DISPLAY_INTERVAL_MS:
                self.long_stalls.append(Stall(self._last - self._since, stall_ms, (cpu - self._last_cpu) * 1000.0,
                                              switches - self._last_switches))
        self._last, self._last_cpu, self._last_switches = now, cpu, switches

    def reset(self) -> None:
        self.longest_ms = 0.0
        self.long_stalls = []
        self._since = time.perf_counter()
        self._skip = 5


class _JobSignals(QObject):
    done = Signal(object)
    failed = Signal(str, str)


class Job(QRunnable):
    """A one-shot job on the thread pool (a report, a file to process); its result comes back as
    a signal on the GUI thread."""

    def __init__(self, work, what: str) -> None:
        super().__init__()
        self.work = work
        self.what = what
        self.signals = _JobSignals()

    def run(self) -> None:
        try:
            self.signals.done.emit(self.work())
        except Exception as exc:  # every failure of a job reaches the user as a dialog
            self.signals.failed.emit(f"{self.what} failed: {exc}", traceback.format_exc())


# The GIL every 1 ms: the GUI thread waits at most this for it after a paint (docs/benchmarks.md, constants).
GIL_SWITCH_INTERVAL_S = 0.001


def tune_process_for_live_view() -> None:
    """Settings of the GUI process for a long live session (the engine has its own process,
    app.engine.process, and its own settings).

    - The GIL switch interval (above).
    - Python's full garbage collections walk every object the program has made; with Qt and
      pyqtgraph loaded that took tens of ms, all threads stopped. `gc.freeze()` moves what exists
      now (modules, widgets) out of their reach; called again once the first maps are drawn.
    """
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    gc.freeze()


class MainWindow(QMainWindow):
    def __init__(self, opener: Callable[[], Source], rig_config: Path | None = None,
                 engine_log: Path | None = None) -> None:
        """`opener`: a picklable callable that opens the source in the engine process (see
        app.engine.process), e.g. functools.partial(app.engine.sources.simulated_source, scale=0.5)."""
        super().__init__()
        tune_process_for_live_view()
        self._frozen_after_first_maps = False
        self.setWindowTitle("photopft")
        self.rig_config = rig_config
        self.settings = QSettings("photopft", "photopft")
        self.engine: EngineProcess | None = None
        self.engine_log = engine_log
        self.view: LiveView | None = None
        self.calibration_text = "session /rig (as recorded or as simulated)"
        self._jobs: list[Job] = []
        self._build_actions()
        self.status_label = QLabel()
        self.statusBar().addPermanentWidget(self.status_label)
        self.user_label = QLabel(acting_user_text())
        self.statusBar().addPermanentWidget(self.user_label)

        self.processing = ProcessingPanel(self)  # a visit processed after its recording (app/session_processing.py)
        self.processing.finished.connect(lambda _: self.statusBar().showMessage(self.processing.last_message, 15000))
        self.processing.problem.connect(lambda message: self.statusBar().showMessage(message, 15000))
        self.statusBar().addPermanentWidget(self.processing)
        self.stalls = StallMonitor(self)
        self.timer = QTimer(self)
        self.timer.setInterval(DISPLAY_INTERVAL_MS)
        self.timer.timeout.connect(self.refresh)
        self.info = None
        try:
            self.use_source(opener)
        except Exception as exc:  # the rig cannot start: the window opens on the diagnostics page
            log.exception("the source could not be opened")
            self.opener = opener
            self.show_diagnostics(str(exc))
        self.timer.start()
        geometry = self.settings.value("main/geometry")
        if isinstance(geometry, QByteArray):
            self.restoreGeometry(geometry)
        else:
            self.resize(1400, 860)
        state = self.settings.value("main/state")
        if isinstance(state, QByteArray):
            self.restoreState(state)

    # actions
    def _action(self, text: str, slot, shortcut: str | QKeySequence.StandardKey | None = None,
                tip: str = "") -> QAction:
        action = QAction(text, self)
        if shortcut is not None:
            action.setShortcut(QKeySequence(shortcut))
        action.setStatusTip(tip or text)
        action.triggered.connect(slot)
        return action

    def _build_actions(self) -> None:
        self.act_patient = self._action("&New patient session…", self.new_patient_session, "Ctrl+N",
                                        "Choose or add the patient, position, and record the protocol")
        self.act_open = self._action("&Open recorded session…", self.open_session, QKeySequence.StandardKey.Open,
                                     "Replay a session file through the live view")
        self.act_live = self._action("&Live rig", self.back_to_rig, "Ctrl+L", "Back to the rig's live view")
        self.act_report = self._action("&Export report…", self.export_report, "Ctrl+E",
                                       "Write the PDF report of a session or results file")
        self.act_sphere = self._action("&Sphere calibration…", self.sphere_calibration, None,
                                       "Light positions from a specular sphere (engineer)")
        self.act_spiro = self._action("S&pirometer calibration…", self.spirometer_calibration, None,
                                      "Flow sensor and volume calibration (engineer)")
        self.act_records = self._action("Patient &records…", self.open_records, "Ctrl+R",
                                        "Visits, trends, interpretation, comment and sign-off (clinician)")
        self.act_audit = self._action("&Audit trail…", self.open_audit, None,
                                      "Who did what when, with the check of its hash chain")
        self.act_syringe = self._action("3 L &syringe check…", self.syringe_check, None,
                                        "The daily check of the flow sensor with the 3 L syringe (operator)")
        self.act_profiles = self._action("&Profiles in force…", self.open_profiles, None,
                                         "The calibrations in force, the ones they replaced, and going back")
        self.act_settings = self._action("&Settings…", self.open_settings, "Ctrl+,")
        self.act_quit = self._action("&Quit", self.close, QKeySequence.StandardKey.Quit)
        menu = self.menuBar()
        session = menu.addMenu("&Session")
        for a in (self.act_patient, self.act_open, self.act_live, self.act_records, self.act_report):
            session.addAction(a)
        session.addSeparator()
        session.addAction(self.act_quit)
        calibrate = menu.addMenu("&Calibration")
        calibrate.addAction(self.act_sphere)
        calibrate.addAction(self.act_spiro)
        calibrate.addAction(self.act_syringe)
        calibrate.addSeparator()
        calibrate.addAction(self.act_profiles)
        tools = menu.addMenu("&Tools")
        tools.addAction(self.act_audit)
        tools.addAction(self.act_settings)
        toolbar = self.addToolBar("Main")
        toolbar.setObjectName("main-toolbar")
        for a in (self.act_patient, self.act_open, self.act_live, self.act_report):
            toolbar.addAction(a)

    # the engine
    def use_source(self, opener: Callable[[], Source]) -> None:
        """Run the live view on another source: the new engine starts first, so a source that
        cannot be opened leaves the current one running (and raises)."""
        self.opener = opener
        QApplication.setOverrideCursor(Qt.CursorShape.WaitCursor)  # the engine process starts in seconds
        try:
            engine = EngineProcess(opener, self.engine_log)
        finally:
            QApplication.restoreOverrideCursor()
        if self.engine is not None:
            self.engine.stop()
        self.engine = engine
        self.info = engine.info
        heads = list(self.info.heads)
        if self.view is None or self.view.heads != heads:
            self.view = LiveView(heads)
            self.setCentralWidget(self.view)
        self.view.simulated = self.info.simulated
        self.view.replay_bar.control = engine.replay_control if self.info.replay else None
        self.calibration_text = calibration_in_force(self.info)
        self.statusBar().showMessage(f"Showing {self.info.name}", 5000)

    def show_diagnostics(self, problem: str) -> None:
        self.diagnostics = DiagnosticsPage(problem, self.rig_config, self.retry_source,
                                           lambda: self.try_source(partial(rig_source, None)), self.open_session)
        self.setCentralWidget(self.diagnostics)
        self.view = None
        self.statusBar().showMessage("The rig could not start: see the devices", 10000)

    def retry_source(self) -> None:
        self.try_source(self.opener)

    def try_source(self, opener) -> None:
        try:
            self.use_source(opener)
        except Exception as exc:  # still not: the page says why, its checks redone
            log.exception("the source could not be opened")
            self.diagnostics.problem.setText(str(exc))
            self.diagnostics.show_checks(self.rig_config)

    def has_engine(self) -> bool:
        """An engine is running; otherwise the operator is told where to start one."""
        if self.engine is not None:
            return True
        show_error(self, "No rig is running.", "Try again on the diagnostics page, use the simulated rig, or replay "
                   "a recorded session.")
        return False

    def refresh(self) -> None:
        if self.engine is None or self.view is None:
            return
        snapshot = self.engine.snapshot()
        self.view.show(snapshot, self.calibration_text, self.info.name)
        if not self._frozen_after_first_maps and all(v.reconstructed for v in snapshot.heads.values()):
            gc.freeze()  # what the first maps made (numba's compiled code among it) is here to stay
            self._frozen_after_first_maps = True
        # the operator's status bar; the display's own timing (self.stalls) is for `photopft bench gui`
        self.status_label.setText("replay finished" if self.engine.replay_finished else "")

    # menu actions
    def new_patient_session(self) -> None:
        if not self.has_engine():
            return
        if self.info.replay:
            self.back_to_rig()
        wizard = PatientSessionWizard(self, self.engine)
        if wizard.exec() == PatientSessionWizard.DialogCode.Accepted and wizard.session_id is not None \
                and not getattr(self, "_shutting_down", False):
            patient = wizard.patient_page.patient()
            who = f"{patient.display_name}'s session" if patient else "the session"
            self.statusBar().showMessage(f"Saved {who} on record as {wizard.session_path}; processing it", 15000)
            self.processing.start(wizard.session_id, f"{who} ({wizard.session_path.name})")

    def open_session(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a recorded session", str(Path.home()),
                                              "Session files (*.h5)")
        if path:
            self.replay(Path(path))

    def replay(self, path: Path, speed: float = 1.0) -> None:
        try:
            self.use_source(partial(replay_source, path, speed))
        except (SessionError, OSError) as exc:
            what, todo = file_problem(path, exc)
            show_error(self, what, todo, str(exc))

    def back_to_rig(self) -> None:
        try:
            self.use_source(partial(rig_source, self.rig_config))
        except Exception as exc:  # the rig cannot be opened: said, and the view keeps what it has
            show_error(self, "The rig cannot be opened.", f"{exc}. Check the rig configuration in Settings.")

    def export_report(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Report of which session or results file?", str(Path.home()),
                                              "Session or results files (*.h5)")
        if not path:
            return
        output, _ = QFileDialog.getSaveFileName(self, "Save the report as", str(Path(path).with_suffix(".pdf")),
                                                "PDF (*.pdf)")
        if output:
            self.run_report(Path(path), Path(output))

    def run_report(self, path: Path, output: Path) -> Job:
        def work() -> Path:
            with Records() as records:
                data, _ = report_for(path, records, str(self.settings.value("reference/equations", "gli-global")),
                                     ask=never_ask)
                written = write_report(data, output, str(self.settings.value("report/page_size", "a4")))
                log_report(records, path, written, data.patient is not None)
            return written

        return self.start_job(work, f"The report of {path.name}",
                              lambda out: self.statusBar().showMessage(f"Report written: {out}", 10000))

    def start_job(self, work, what: str, done) -> Job:
        job = Job(work, what)
        job.signals.done.connect(done)
        job.signals.failed.connect(lambda message, detail: show_error(
            self, message, "Check the file and try again; the session file itself is unchanged.", detail))
        self._jobs.append(job)
        QThreadPool.globalInstance().start(job)
        return job

    def _may_calibrate(self) -> bool:
        """Only engineers calibrate where roles are enforced: said before the wizard's work starts."""
        try:
            records = calibration_audit()
        except RecordsError as exc:
            show_error(self, "You may not calibrate the rig.", str(exc))
            return False
        if records is not None:
            records.close()
        return True

    def sphere_calibration(self) -> None:
        if not self.has_engine():
            return
        if not self._may_calibrate():
            return
        heads = tuple(self.info.heads)
        scale = self.info.rig.heads["front"].width / 1400.0
        capture = None if self.info.simulated else capture_from_rig(self)
        wizard = SphereCalibrationWizard(self, heads, scale, capture=capture, profile_dir=self.profile_dir(),
                                         preview=None if self.info.simulated else self.engine.preview)
        if wizard.exec() and wizard.saved_to is not None:
            self.calibration_changed(f"Rig calibration saved and in force: {wizard.saved_to}")

    def spirometer_calibration(self) -> None:
        if self._on_the_rig("The spirometer is calibrated") and self._may_calibrate():
            bench = SimulatedFlowBench() if self.info.simulated else RigFlowBench(self.engine)
            wizard = SpirometerCalibrationWizard(self, bench, profile_dir=self.profile_dir())
            if wizard.exec() and wizard.saved:
                self.calibration_changed("Spirometer calibration saved and in force: "
                                         + ", ".join(p.name for p in wizard.saved))

    def _on_the_rig(self, what: str) -> bool:
        """A rig is running, not a replay; otherwise the operator is told where to go."""
        if not self.has_engine():
            return False
        if self.info.replay:
            show_error(self, f"{what} on the rig, not on a replay.", "Session > Live rig goes back to the rig first.")
            return False
        return True

    def profile_dir(self) -> Path:
        return calibration_dir(self.info.rig.name)

    def calibration_changed(self, message: str) -> None:
        """A profile saved or restored: the rig reopened with it (unless a replay is showing, which
        keeps the calibrations it was recorded with)."""
        if not self.info.replay:
            try:
                self.use_source(self.opener)
            except Exception as exc:  # the rig cannot be reopened with it: said, the view keeps what it has
                show_error(self, "The new calibration cannot be put in force.",
                           f"{exc}. Calibration > Profiles can put the previous one back.")
                return
        self.statusBar().showMessage(message, 10000)

    def syringe_check(self) -> None:
        if not self._on_the_rig("The syringe check is done"):
            return
        bench = SimulatedSyringe() if self.info.simulated else RigSyringe(self.engine)
        dialog = SyringeCheckDialog(self, bench, self.info.flow_calibration, self.info.rig.name, self.info.flow_from)
        if dialog.exec() and dialog.saved is not None:
            self.calibration_text = calibration_in_force(self.info)
            self.statusBar().showMessage(f"Syringe check logged: {dialog.saved['verdict']}", 10000)

    def open_profiles(self) -> None:
        if not self.has_engine():
            return
        window = ProfilesWindow(self, self.info.rig.name, self.info.calibration if not self.info.replay else "")
        window.exec()
        if window.restored is not None:
            self.calibration_changed(window.outcome)

    def open_records(self) -> None:
        try:
            records = Records()
        except RecordsError as exc:
            show_error(self, "The patient records cannot be opened.", str(exc))
            return
        with records:
            RecordsWindow(self, records, str(self.settings.value("reference/equations", "gli-global")),
                          processing=self.processing).exec()

    def open_audit(self) -> None:
        if not default_path().exists():
            show_error(self, "There is no audit trail yet.", "It starts with the first patient put on record.")
            return
        try:
            records = Records(read_only=True)
        except RecordsError as exc:
            show_error(self, "The audit trail cannot be opened.", str(exc))
            return
        with records:
            AuditWindow(self, records).exec()

    def open_settings(self) -> None:
        dialog = SettingsDialog(self.settings, self)
        if dialog.exec():
            rig = self.settings.value("rig/config", "")
            chosen = Path(rig) if rig else None
            if chosen != self.rig_config:
                self.rig_config = chosen
                if self.engine is None:
                    self.try_source(partial(rig_source, chosen))
                elif not self.info.replay and not self.engine.recording:
                    self.back_to_rig()

    def offer_cut_off_visits(self) -> None:
        """At start-up: visits whose recording never ended, with Recover and Discard."""
        try:
            if not default_path().exists():
                return
            with Records() as records:
                visits = cut_off_visits(records)
                if visits:
                    CutOffVisitsDialog(self, records, visits).exec()
        except RecordsError as exc:
            show_error(self, "The patient records cannot be opened.", str(exc))

    def shut_down(self, signum: int | None = None) -> None:
        """SIGTERM or SIGINT (app/gui/shutdown.py): every dialog closed (a recording in the patient
        session finished and its visit marked cancelled), the processing cancelled, the engine
        stopped, and the application quits with 0, asking nothing."""
        log.warning("signal %s: shutting down", signum)
        self._shutting_down = True
        for widget in QApplication.topLevelWidgets():
            if isinstance(widget, PatientSessionWizard) and widget.isVisible():
                widget.end_without_asking("cancelled")
            elif isinstance(widget, QDialog) and widget.isVisible():
                widget.reject()
        if self.processing.busy:
            self.processing.cancel()
        self.close()
        QApplication.instance().exit(0)

    def closeEvent(self, event) -> None:  # noqa: N802 - Qt naming
        if getattr(self, "_shutting_down", False) and self.engine is not None and self.engine.recording:
            self.engine.stop_recording()
        elif self.engine is not None and self.engine.recording:
            answer = QMessageBox.question(self, "photopft", "A recording is running. Stop it and quit? "
                                          "Everything recorded so far is kept.")
            if answer != QMessageBox.StandardButton.Yes:
                event.ignore()
                return
        self.settings.setValue("main/geometry", self.saveGeometry())
        self.settings.setValue("main/state", self.saveState())
        self.timer.stop()
        if self.engine is not None:
            self.engine.stop()
            self.engine = None
        QThreadPool.globalInstance().waitForDone(30000)
        super().closeEvent(event)
