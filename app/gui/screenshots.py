"""Screenshots of the main window, every wizard page and every dialog on the simulated rig, as the
operator sees the screen: `xvfb-run -a -s "-screen 0 1366x768x24" python -m app.gui.screenshots DIR`
(a real X server, the xcb platform). Each picture is the whole screen, so a window larger than the
screen shows cut off, as it would be; the main window fills the screen."""

from __future__ import annotations

import sys
import tempfile
import time
from datetime import datetime, timezone
from functools import partial
from pathlib import Path

from PySide6.QtCore import QTimer
from PySide6.QtWidgets import QApplication, QWidget

from app.engine.sources import rig_source, simulated_source
from app.gui.cut_off import CutOffVisitsDialog
from app.gui.login import LoginDialog
from app.gui.main_window import MainWindow
from app.gui.profiles_view import ProfilesWindow
from app.gui.records_view import AuditWindow, RecordsWindow
from app.gui.settings_dialog import SettingsDialog
from app.gui.syringe_check import SimulatedSyringe, SyringeCheckDialog
from app.gui.wizards.patient_session import PatientSessionWizard
from app.gui.wizards.sphere import SphereCalibrationWizard
from app.gui.wizards.spirometer import SpirometerCalibrationWizard
from app.records import Records
from app.session_processing import CUT_OFF, cut_off_visits


def _wait(app: QApplication, seconds: float, until=None) -> None:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        app.processEvents()
        if until is not None and until():
            return
        time.sleep(0.02)


def _grab(widget: QWidget, path: Path) -> None:
    """The whole screen with `widget` raised on it."""
    widget.raise_()
    widget.activateWindow()
    QApplication.processEvents()
    QApplication.primaryScreen().grabWindow(0).save(str(path))
    print(f"wrote {path}")


def _fill_screen(window: QWidget) -> None:
    """What a window manager's maximise does (Xvfb has none)."""
    area = QApplication.primaryScreen().availableGeometry()
    window.move(area.topLeft())
    window.resize(area.size())


def _records_windows(app, records, folder: Path, out: Path) -> None:
    """The records window on the patient just recorded, with two earlier visits made up for the
    picture (values only, no session files) so that the trend has points."""
    patient = records.find_patients("Nowak")[0]
    for year, fev1, fvc in ((2024, 2.95, 3.72), (2025, 2.81, 3.66)):
        sid = records.add_session(patient.id, folder / f"earlier-{year}.h5",
                                  datetime(year, 10, 14, 10, tzinfo=timezone.utc), operator="example")
        records.set_results(sid, None, {"flow sensor": {"FEV1_l": fev1, "FVC_l": fvc, "FEV1_FVC": fev1 / fvc,
                                                        "grade": "A"}})
    window = RecordsWindow(None, records)
    window.show()
    window.comment.setPlainText("Stable compared with last year.")
    window.save_comment.click()
    _wait(app, 0.5)
    _grab(window, out / "records-window.png")
    window.close()
    audit = AuditWindow(None, records)
    audit.show()
    _wait(app, 0.3)
    _grab(audit, out / "audit-trail.png")
    audit.close()


def main(out: Path) -> int:
    out.mkdir(parents=True, exist_ok=True)
    app = QApplication.instance() or QApplication(sys.argv[:1])
    window = MainWindow(partial(simulated_source, scale=0.25))
    _fill_screen(window)
    window.show()
    _wait(app, 60, lambda: all(v.reconstructed > 3 for v in window.engine.snapshot().heads.values()))
    _wait(app, 8)  # the volume curve fills
    _grab(window, out / "main-window.png")

    folder = Path(tempfile.mkdtemp(prefix="photopft-shots-"))
    records = Records(folder / "records.sqlite3")
    wizard = PatientSessionWizard(window, window.engine, records, sessions_dir=folder)
    wizard.show()
    page = wizard.currentPage()
    page.family.setText("Nowak")
    page.given.setText("Ewa")
    page.number.setText("H-1234")
    page.sex.setCurrentText("female")
    page.height.setValue(166)
    page.weight.setValue(61)
    page.add.click()
    _wait(app, 0.5)
    _grab(wizard, out / "patient-1-patient.png")
    wizard.next()
    _wait(app, 20, wizard.currentPage().isComplete)
    _grab(wizard, out / "patient-2-positioning.png")
    wizard.next()
    calibration = wizard.currentPage()  # the subject's calibration through the flow sensor
    calibration.start.click()
    _wait(app, 60, calibration.vc.isEnabled)
    calibration.vc.click()
    _wait(app, calibration.last_duration_s + 0.8)
    calibration.end.click()
    _wait(app, 30, calibration.start.isEnabled)
    _wait(app, 0.5)
    _grab(wizard, out / "patient-2b-calibration.png")
    wizard.next()
    tidal = wizard.currentPage()
    tidal.seconds.setValue(10)
    tidal.start.click()
    _wait(app, 4)
    _grab(wizard, out / "patient-3-tidal.png")
    _wait(app, 75, tidal.isComplete)  # ten seconds hold too few breaths: the page extends itself
    wizard.next()
    for name in ("vc", "forced"):
        page = wizard.currentPage()
        while not page.isComplete():
            page.begin.click()
            if name == "forced" and page.count == 1:  # the second blow, as the operator sees it happen
                _wait(app, 0.45 * page.last_duration_s)
                _grab(wizard, out / "patient-5-forced-during-blow.png")
                _wait(app, 0.55 * page.last_duration_s + 0.8)
            else:
                _wait(app, page.last_duration_s + 0.8)
            page.end.click()
            _wait(app, 15, lambda: page.assessed == page.count)
        _grab(wizard, out / f"patient-{4 if name == 'vc' else 5}-{name}.png")
        wizard.next()
    _wait(app, 0.5)
    _grab(wizard, out / "patient-6-review.png")
    wizard.accept()
    # processed in the background as after Finish, the progress in the main window
    window.processing.start(wizard.session_id, "Ewa Nowak's session", records.path)
    _wait(app, 3)
    _grab(window, out / "main-window-processing.png")
    _wait(app, 1800, lambda: not window.processing.busy)
    print(window.processing.last_message)

    _records_windows(app, records, folder, out)
    _dialogs(app, window, records, folder, out)

    sphere = SphereCalibrationWizard(window, ("front", "back"), 0.25, profile_dir=folder / "cal")
    sphere.show()
    _wait(app, 0.3)
    _grab(sphere, out / "sphere-1-intro.png")
    for count, name in ((4, "sphere-2-captures.png"), (7, "sphere-2-matte.png")):  # specular, then matte
        sphere.next()
        page = sphere.currentPage()
        for k in range(count):
            page.capture()
            _wait(app, 60, lambda: len(page.captures) == k + 1)
        _wait(app, 0.5)
        _grab(sphere, out / name)
    sphere.next()
    result = sphere.currentPage()
    _wait(app, 120, lambda: result.table.rowCount() > 0)
    _wait(app, 0.5)
    _grab(sphere, out / "sphere-3-result.png")
    sphere.reject()

    spiro = SpirometerCalibrationWizard(window, profile_dir=folder / "cal")
    spiro.show()
    flow = spiro.currentPage()
    for reference in (-8.0, -4.0, -1.0, 0.0, 1.0, 4.0, 8.0):
        flow.reference.setValue(reference)
        flow.read.click()
    _wait(app, 0.5)
    _grab(spiro, out / "spirometer-1-flow.png")
    spiro.next()
    volume = spiro.currentPage()
    training = sorted(Path(p) for p in sys.argv[2:])
    if training:
        volume.add_files(training)
        _wait(app, 120, lambda: not volume.label.text().startswith("Fitting"))  # on a worker
    _wait(app, 0.5)
    _grab(spiro, out / "spirometer-2-volume.png")
    if not volume.isComplete():
        volume.enabled.setChecked(False)
    spiro.next()
    _wait(app, 0.3)
    _grab(spiro, out / "spirometer-3-conditions.png")
    spiro.reject()
    QTimer.singleShot(0, window.close)
    _wait(app, 1)
    records.close()
    _diagnostics(app, folder, out)
    return 0


def _dialogs(app, window, records, folder: Path, out: Path) -> None:
    """Sign-in, settings, profiles, the syringe check and the cut-off recordings offered at start-up."""
    login = LoginDialog(window, "dr.keller", "Signing a report needs a clinician's password.")
    login.show()
    _wait(app, 0.3)
    _grab(login, out / "sign-in.png")
    login.reject()
    settings = SettingsDialog(window.settings, window)
    settings.show()
    _wait(app, 0.3)
    _grab(settings, out / "settings.png")
    settings.reject()
    profiles = ProfilesWindow(window, window.info.rig.name, window.calibration_text)
    profiles.show()
    _wait(app, 0.3)
    _grab(profiles, out / "profiles.png")
    profiles.reject()
    syringe = SyringeCheckDialog(window, SimulatedSyringe(), window.info.flow_calibration, window.info.rig.name,
                                 window.info.flow_from)
    syringe.show()
    syringe.start.click()
    _wait(app, 12)
    syringe.stop.click()
    _wait(app, 0.5)
    _grab(syringe, out / "syringe-check.png")
    syringe.reject()
    patient = records.find_patients("Nowak")[0]
    records.add_session(patient.id, folder / "cut-off.h5", datetime(2026, 11, 30, 9, 5, tzinfo=timezone.utc),
                        operator="example", status=CUT_OFF)
    cut_off = CutOffVisitsDialog(window, records, cut_off_visits(records))
    cut_off.show()
    _wait(app, 0.3)
    _grab(cut_off, out / "cut-off-recordings.png")
    cut_off.reject()


def _diagnostics(app, folder: Path, out: Path) -> None:
    """The window on a rig whose front camera and sequencer are not connected."""
    rig = folder / "clinic.toml"
    rig.write_text('name = "clinic"\n[camera]\n[heads.front]\ncamera = "192.168.10.21"\n[heads.back]\n'
                   'camera = "192.168.10.22"\n[sequencer]\nport = "/dev/ttyACM0"\n[flowsensor]\nport = "emulator"\n')
    window = MainWindow(partial(rig_source, rig), rig)
    _fill_screen(window)
    window.show()
    _wait(app, 0.5)
    _grab(window, out / "diagnostics.png")
    window.close()


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("docs/images")))
