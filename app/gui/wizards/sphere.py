"""Sphere calibration (engineer): light positions from a specular sphere (thesis eqs 4.1-4.12,
all placements in one least-squares triangulation), their distances along the highlight rays
refined on the glossy sphere's own diffuse shading where it has one.

The sphere is captured at the centre of the view, then at two or more other places; each capture
shows the detected outline and highlights. The result lists each light's position, residual
(pass/fail against the threshold) and pseudo light vector; saving makes it the rig's calibration
profile and keeps the previous one. On the simulated rig a capture renders the simulated sphere
at the next place; on a real rig it records a second of the sphere.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt, QTimer
from PySide6.QtGui import QColor
from PySide6.QtWidgets import (QComboBox, QDoubleSpinBox, QFormLayout, QHBoxLayout, QLabel, QListWidget, QPushButton,
                               QTableWidget, QTableWidgetItem, QVBoxLayout, QWizard, QWizardPage)

from app.calibration_store import RIG_PROFILE, calibration_audit, calibration_dir, keep_previous, log_calibration
from app.gui.errors import show_error
from app.records import RecordsError
from core.calibration.light_sessions import (CAPTURE_SECONDS, DEFAULT_MAX_RESIDUAL_MM, advice, calibrate_lights,
                                             placement_images, specular_placements)
from core.calibration.rig_profile import ProfileError, load_profile
from core.calibration.sphere_geometry import CalibrationError, detect_sphere
from core.io.outputs import next_free_path
from core.io.session import SessionFile
from core.sim.simulate import simulate
from drivers.assembly import simulated_rig_config, simulated_sphere_config

MIN_CAPTURES = 3
# The matte sphere's shading places the lights only when each placement's distance can be told from
# theirs: measured on the simulated rig at 350 px (isotropic LEDs 8 mm off the drawing, the
# placements this wizard's simulated sphere takes), 3 places left them 5-14 mm off, 5 places 2-6 mm,
# 7 places 1.2-2.2 mm (the specular sphere alone 0.6-12 mm with 3, 3-6 mm with 7)
MIN_MATTE_CAPTURES = 7


def capture_simulated(folder: Path, index: int, scale: float, heads: tuple[str, ...], radius_mm: float,
                      finish: str = "specular", seed: int = 1) -> Path:
    """One placement of the simulated specular or matte sphere (index 0: the centre of the view), on the
    simulated rig that runs (its LEDs as built: drivers/assembly.py, simulated_sphere_config)."""
    path = next_free_path(folder / f"{finish}-{index + 1:02d}.h5")
    simulate(path, simulated_sphere_config(simulated_rig_config(heads, scale, seed), index, radius_mm, finish))
    return path


def capture_from_rig(window):
    """A capture on a real rig: CAPTURE_SECONDS of the sphere recorded from the live engine."""
    def capture(folder: Path, index: int, finish: str = "specular") -> Path:
        wizard = window.findChild(SphereCalibrationWizard)
        radius = wizard.intro.radius.value() if wizard is not None else 75.0
        path = next_free_path(folder / f"{finish}-{index + 1:02d}.h5")
        engine = window.engine
        engine.start_recording(path, None, kind="sphere-calibration",
                               root_attrs={"sphere_radius_mm": float(radius), "sphere_finish": finish})
        engine.mark("placement")
        time.sleep(CAPTURE_SECONDS)
        summary = engine.stop_recording()
        if summary.problems:
            raise OSError("; ".join(summary.problems))
        return path

    return capture


def detect_capture(path: Path, head_name: str):
    """(summed image, sphere fit, {light: highlight}, problems) of one capture's head; a matte sphere has
    no highlights."""
    with SessionFile(path) as session:
        radius = float(session.attrs["sphere_radius_mm"])
        if session.attrs.get("sphere_finish") == "matte":
            image = placement_images(session, head_name)[0].signal.sum(0)
            return image, detect_sphere(image, session.rig.heads[head_name], radius), {}, []
        result = specular_placements(session, head_name, radius)[0]
    return result.image, result.sphere, result.highlights, result.problems


class IntroPage(QWizardPage):
    def __init__(self) -> None:
        super().__init__()
        self.setTitle("Sphere calibration")
        self.setSubTitle("Light positions from the highlights of a polished (specular) sphere.")
        text = QLabel("1. Put the specular sphere on its stand at the centre of the view, at the patient's "
                      "distance, and keep the room dark.\n2. Capture it there, then at two or more other places "
                      "spread through the working volume (left and right, higher and lower, nearer and farther).\n"
                      "3. Each capture shows the sphere's outline and the four highlights: all four must be found.")
        text.setWordWrap(True)
        self.radius = QDoubleSpinBox(minimum=10.0, maximum=300.0, value=75.0, suffix=" mm", decimals=2)

        self.threshold = QDoubleSpinBox(minimum=0.5, maximum=100.0, value=DEFAULT_MAX_RESIDUAL_MM, suffix=" mm",
                                        decimals=1)
        form = QFormLayout(self)
        form.addRow(text)
        form.addRow("Sphere radius (from its certificate)", self.radius)
        form.addRow("Largest accepted residual per light", self.threshold)


class CapturePage(QWizardPage):
    """The captures of one sphere: the specular one (its highlights give the lights' directions; required)
    or the matte one (its shading places them along those directions; optional, recommended)."""

    def __init__(self, finish: str = "specular") -> None:
        super().__init__()
        self.finish = finish
        if finish == "matte":
            self.setTitle("Captures of the matte sphere (optional, recommended)")
            self.setSubTitle(f"The matte sphere at {MIN_MATTE_CAPTURES} or more places spread through the working "
                             "volume, the centre first: its shading places each light along its highlights' "
                             "direction. Next without captures skips it.")
        else:
            self.setTitle("Captures")
            self.setSubTitle("Capture at the centre first, then at two or more other places.")
        self.capture_button = QPushButton("Capture at the centre")
        self.capture_button.clicked.connect(self.capture)
        self.head = QComboBox()
        self.head.currentTextChanged.connect(self._show_selected)
        self.list = QListWidget()
        self.list.currentRowChanged.connect(self._show_selected)
        self.plot = pg.PlotWidget(background="w")
        self.plot.setAspectLocked(True)
        self.plot.invertY(True)
        self.image = pg.ImageItem()
        self.plot.addItem(self.image)
        self.outline = self.plot.plot(pen=pg.mkPen("r", width=2))
        self.spots = pg.ScatterPlotItem(size=14, pen=pg.mkPen("c", width=2), brush=None, symbol="o")
        self.plot.addItem(self.spots)
        self.labels: list[pg.TextItem] = []
        # where the sphere has been, over the head's whole field of view: spread them out
        self.placements = pg.PlotWidget(background="w", title="Placements so far")
        self.placements.setAspectLocked(True)
        self.placements.invertY(True)
        self.placements.hideAxis("bottom")
        self.placements.hideAxis("left")
        self.field = self.placements.plot(pen=pg.mkPen((120, 120, 120), width=1))
        self.placed = pg.ScatterPlotItem(size=12, pen=pg.mkPen("k"), brush=pg.mkBrush(30, 120, 200, 160))
        self.placements.addItem(self.placed)
        self.placements.setMaximumHeight(220)
        # the camera now, to place the sphere before capturing (a real rig's live engine)
        self.live = pg.PlotWidget(background="w", title="Live camera: place the sphere")
        self.live.setAspectLocked(True)
        self.live.invertY(True)
        self.live.hideAxis("bottom")
        self.live.hideAxis("left")
        self.live_image = pg.ImageItem()
        self.live.addItem(self.live_image)
        self.live.setMaximumHeight(240)
        self.live_note = QLabel()
        self.live_note.setWordWrap(True)
        self.preview_timer = QTimer(self)
        self.preview_timer.setInterval(300)
        self.preview_timer.timeout.connect(self._preview)
        left = QVBoxLayout()
        left.addWidget(self.capture_button)
        left.addWidget(QLabel("Head shown"))
        left.addWidget(self.head)
        left.addWidget(self.list, 1)
        left.addWidget(self.placements)
        left.addWidget(self.live)
        left.addWidget(self.live_note)
        layout = QHBoxLayout(self)
        layout.addLayout(left, 1)
        layout.addWidget(self.plot, 3)
        self.captures: list[Path] = []
        self.detections: list[dict] = []
        self.folder = Path(tempfile.mkdtemp(prefix=f"photopft-{finish}-sphere-"))

    def initializePage(self) -> None:  # noqa: N802
        if not self.head.count():
            self.head.addItems(self.wizard().heads)
        if self.wizard().preview is not None:
            self.live_note.setText("The newest light cycle of the head shown, about three times a second.")
            self.preview_timer.start()
        else:
            self.live.setVisible(False)
            self.live_note.setText("Simulated rig: each capture renders the simulated sphere at its next place; "
                                   "there is no camera to preview.")

    def cleanupPage(self) -> None:  # noqa: N802
        self.preview_timer.stop()

    def _preview(self) -> None:
        head = self.head.currentText()
        try:
            image = self.wizard().preview(head) if head else None
        except Exception as exc:  # the preview is a help; the captures do not need it
            self.preview_timer.stop()
            self.live_note.setText(f"No live picture: {exc}")
            return
        if image is not None:
            self.live_image.setImage(np.asarray(image, dtype=float), autoLevels=True)

    def capture(self) -> None:
        wizard = self.wizard()
        index = len(self.captures)
        self.capture_button.setEnabled(False)
        self.capture_button.setText("Capturing …")
        wizard.start_job(lambda: self._capture(index), f"Capture {index + 1}", self._captured,
                         failed=self.capture_failed)

    def _capture(self, index: int):
        wizard = self.wizard()
        path = wizard.capture(self.folder, index, self.finish)
        return path, {h: detect_capture(path, h) for h in wizard.heads}

    def _captured(self, result) -> None:
        path, detections = result
        self.captures.append(path)
        self.detections.append(detections)
        found = min(len(d[2]) for d in detections.values())
        where = "centre" if len(self.captures) == 1 else f"place {len(self.captures)}"
        if self.finish == "matte":
            self.list.addItem(f"{len(self.captures)}: {where}, sphere found")
        else:
            self.list.addItem(f"{len(self.captures)}: {where}, highlights found {found}/4"
                              + ("" if found == 4 else " (check the sphere and the lighting)"))
        self.list.setCurrentRow(self.list.count() - 1)
        self.capture_button.setText("Capture at another place")
        self.capture_button.setEnabled(True)
        self.completeChanged.emit()

    def capture_failed(self) -> None:
        self.capture_button.setText("Capture again")
        self.capture_button.setEnabled(True)

    def _show_selected(self, *_) -> None:
        row = self.list.currentRow()
        head = self.head.currentText()
        if row < 0 or not head or head not in self.detections[row]:
            return
        image, sphere, highlights, _ = self.detections[row][head]
        self.image.setImage(image, autoLevels=True)
        angle = np.linspace(0, 2 * np.pi, 200)
        cu, cv = sphere.centre_px
        self.outline.setData(cu + sphere.radius_px * np.cos(angle), cv + sphere.radius_px * np.sin(angle))
        self.spots.setData([h.uv[0] for h in highlights.values()], [h.uv[1] for h in highlights.values()])
        for label in self.labels:
            self.plot.removeItem(label)
        self.labels = []
        for light, h in highlights.items():
            # each label outward from the sphere's centre, beyond its highlight: close highlights'
            # labels no longer sit on each other
            direction = np.array([h.uv[0] - cu, h.uv[1] - cv])
            direction /= max(float(np.hypot(*direction)), 1e-9)
            label = pg.TextItem(f"L{light}", color=(0, 200, 220), anchor=(0.5, 0.5))
            label.setPos(h.uv[0] + 0.35 * sphere.radius_px * direction[0],
                         h.uv[1] + 0.35 * sphere.radius_px * direction[1])
            self.plot.addItem(label)
            self.labels.append(label)
        self._show_placements(head, image.shape)

    def _show_placements(self, head: str, shape: tuple[int, ...]) -> None:
        height, width = shape[:2]
        self.field.setData([0, width, width, 0, 0], [0, 0, height, height, 0])
        centres = [d[head][1].centre_px for d in self.detections if head in d]
        self.placed.setData([c[0] for c in centres], [c[1] for c in centres],
                            brush=[pg.mkBrush(200, 40, 40, 200) if k == self.list.currentRow() else
                                   pg.mkBrush(30, 120, 200, 160) for k in range(len(centres))])

    def isComplete(self) -> bool:  # noqa: N802
        if self.finish == "matte":  # none, or enough to tell each placement's distance from the lights'
            return len(self.captures) == 0 or len(self.captures) >= MIN_MATTE_CAPTURES
        if len(self.captures) < MIN_CAPTURES:
            return False
        return all(len(d[2]) == 4 for d in self.detections[0].values())  # the centre capture gives pseudo vectors


def previous_profile(path: Path):
    """(the light calibration in force, a sentence on it) for the comparison, (None, why) without one."""
    if not path.is_file():
        return None, "There is no earlier calibration to compare with."
    try:
        profile = load_profile(path)
    except ProfileError as exc:
        return None, f"The profile in force cannot be read ({exc}); nothing to compare with."
    return profile, (f"The last column compares with the profile in force of {profile.created[:10]}: a light that "
                     "moved by more than a few millimetres was knocked or refitted.")


class ResultPage(QWizardPage):
    def __init__(self) -> None:
        super().__init__()
        self.setTitle("Result")
        self.setSubTitle("Light positions in each head's camera frame; every residual must pass.")
        self.table = QTableWidget(0, 8)
        self.table.setHorizontalHeaderLabels(["Head", "Light", "Position (mm)", "± highlights (mm)", "Residual (mm)",
                                              "Pass", "Moved since the profile in force (mm)", "Pseudo light vector"])
        self.message = QLabel()
        self.message.setWordWrap(True)
        layout = QVBoxLayout(self)
        layout.addWidget(self.table)
        layout.addWidget(self.message)
        self.calibration = None
        self._runs = 0  # the newest calibration started: an older one's result is not shown

    def initializePage(self) -> None:  # noqa: N802

        wizard = self.wizard()
        captures = list(wizard.capture_page.captures) + list(wizard.matte_page.captures)
        self.calibration = None
        self.table.setRowCount(0)
        self._runs += 1
        run = self._runs
        self.message.setText(f"Calibrating the lights from {len(captures)} placements (a few seconds a head: the "
                             "highlights, then the spheres' shading) …")

        def work():
            try:
                # every light is solved, then judged here, so the table shows which fail
                return calibrate_lights(captures, max_residual_mm=float("inf"))
            except CalibrationError as exc:
                return exc

        wizard.start_job(work, "The light calibration", lambda result: self._calibrated(run, result),
                         failed=lambda: self._failed(run))

    def _failed(self, run: int) -> None:
        if run == self._runs:
            self.message.setText("<b>The calibration failed</b> (see the message). Go back and capture again.")

    def _calibrated(self, run: int, result) -> None:
        wizard = self.wizard()
        if run != self._runs or wizard is None:
            return
        threshold = wizard.intro.threshold.value()
        if isinstance(result, Exception):
            self.message.setText(f"<b>The calibration failed:</b> {result}. Go back and capture again.")
            self.completeChanged.emit()
            return
        calibration, reports = result
        rows = [(name, k, head) for name, head in calibration.heads.items() for k in range(4)]
        previous, previous_note = previous_profile(wizard.profile_dir / RIG_PROFILE)
        self.table.setRowCount(len(rows))
        for r, (name, k, head) in enumerate(rows):
            residual = float(head.residual_mm[k])
            moved = "–"
            if previous is not None and name in previous.heads:
                moved = f"{np.linalg.norm(head.light_positions_mm[k] - previous.heads[name].light_positions_mm[k]):.1f}"
            cells = [name, f"L{k}", ", ".join(f"{x:.1f}" for x in head.light_positions_mm[k]),
                     ", ".join(f"{x:.1f}" for x in head.light_position_sigma_mm[k]), f"{residual:.2f}",
                     "pass" if residual <= threshold else "FAIL", moved,
                     ", ".join(f"{x:+.3f}" for x in head.pseudo_light_vectors[k])]
            for c, text in enumerate(cells):
                item = QTableWidgetItem(text)
                item.setFlags(item.flags() & ~Qt.ItemFlag.ItemIsEditable)
                if c == 5:
                    item.setForeground(QColor("white"))
                    item.setBackground(QColor("#1b7f3b" if residual <= threshold else "#b00020"))
                self.table.setItem(r, c, item)
        self.comparison = previous_note
        notes = " ".join(_refinement_notes(reports)) + " " + previous_note
        self.table.resizeColumnsToContents()
        failed = [f"{name} L{k}" for name, k, head in rows if head.residual_mm[k] > threshold]
        if failed:
            self.message.setText(f"<b>{', '.join(failed)} fail</b> the {threshold:g} mm threshold: go back and "
                                 "capture at more places (spread wider), or check the sphere's radius. "
                                 + notes)
            self.completeChanged.emit()
            return
        self.calibration = calibration
        self.message.setText(f"All {len(rows)} lights pass (threshold {threshold:g} mm). {notes} "
                             "Finish saves the profile and puts it in force.")
        self.completeChanged.emit()

    def isComplete(self) -> bool:  # noqa: N802
        return self.calibration is not None


def _refinement_notes(reports) -> list[str]:
    """What placed each head's lights along their highlight rays, in the wizard's words."""
    notes = []
    for report in reports:
        how = f"refined on {report.refined_on}" if report.refined_on else "triangulated from the highlights only"
        if report.pattern_on:
            how = f"triangulated from the highlights, the LEDs' axes and falloff from {report.pattern_on}"
        notes.append(f"{report.head.capitalize()}: {how}" + "".join(f"; {p}" for p in report.problems) + ".")
    return notes + [f"{line}." for line in advice(reports)]


class SphereCalibrationWizard(QWizard):
    def __init__(self, parent, heads: tuple[str, ...] = ("front", "back"), scale: float = 0.25,
                 capture=None, start_job=None, profile_dir: Path | None = None, preview=None) -> None:
        super().__init__(parent)
        self.preview = preview  # head -> the camera's newest image (a real rig's engine.preview), or None
        self.setWindowTitle("Sphere calibration")
        self.heads = list(heads)
        self.scale = scale
        self._capture = capture
        self._start_job = start_job or getattr(parent, "start_job", None)
        self.profile_dir = profile_dir or calibration_dir()
        self.saved_to: Path | None = None
        self._jobs_running = 0  # captures and calibrations on the thread pool, which read the captures' folders
        self._closed = False
        self.intro = IntroPage()
        self.capture_page = CapturePage()
        self.matte_page = CapturePage("matte")
        self.result_page = ResultPage()
        for page in (self.intro, self.capture_page, self.matte_page, self.result_page):
            self.addPage(page)
        self.setMinimumSize(900, 600)

    def capture(self, folder: Path, index: int, finish: str = "specular") -> Path:
        if self._capture is not None:
            return self._capture(folder, index, finish)
        return capture_simulated(folder, index, self.scale, tuple(self.heads), self.intro.radius.value(), finish)

    def start_job(self, work, what: str, done, failed=None) -> None:
        """`work` on the main window's thread pool (here, without one), then `done` with its result on the
        GUI thread; `failed` (default: the capture page's) after the window has shown the failure. A job
        still running when the wizard is closed ends unseen: its result is dropped, its failure (the
        captures' folder it reads going with the wizard) is no error of the user's, and the folder
        goes when the last job has ended."""
        if self._start_job is None:
            done(work())
            return

        def guarded():
            try:
                return work()
            except Exception:
                if self._closed:
                    return None  # dropped below, like any result after closing
                raise

        def finished(result) -> None:
            self._job_ended()
            if not self._closed:
                done(result)

        def went_wrong(*_) -> None:
            self._job_ended()
            if not self._closed:
                (failed or self.capture_page.capture_failed)()

        self._jobs_running += 1
        job = self._start_job(guarded, what, finished)
        job.signals.failed.connect(went_wrong)

    def _job_ended(self) -> None:
        self._jobs_running -= 1
        if self._closed and self._jobs_running == 0:
            self._remove_captures()

    def _remove_captures(self) -> None:
        for page in (self.capture_page, self.matte_page):
            shutil.rmtree(page.folder, ignore_errors=True)

    def done(self, result: int) -> None:
        """Finish or Cancel: the captures' folder goes (the profile keeps each light's fit and residual),
        once no capture or calibration reads it any more."""
        self._closed = True
        for page in (self.capture_page, self.matte_page):
            page.preview_timer.stop()
        if self._jobs_running == 0:
            self._remove_captures()
        super().done(result)

    def accept(self) -> None:
        calibration = self.result_page.calibration
        self.profile_dir.mkdir(parents=True, exist_ok=True)
        target = self.profile_dir / RIG_PROFILE
        try:
            audit = calibration_audit()
        except RecordsError as exc:
            show_error(self, "The calibration profile cannot be saved.", str(exc))
            return
        try:
            kept = keep_previous(target)
            calibration.save(target)
        except OSError as exc:
            show_error(self, "The calibration profile cannot be saved.", f"{exc}. Check the folder's permissions.")
            return
        if audit is not None:
            with audit:
                log_calibration(audit, "lights (sphere wizard)", target, kept)
        self.saved_to = target
        self.previous = kept
        super().accept()
