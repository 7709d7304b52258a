"""The live view: front and back height maps on a fixed, labelled scale, the volume curve of the
last 30 s, and the status of the rig. It only draws: `show(snapshot)` is called from the GUI's
timer with what the engine (app.engine) has ready."""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QGridLayout, QGroupBox, QHBoxLayout, QLabel, QPushButton, QScrollArea, QSlider,
                               QVBoxLayout, QWidget)

from app.engine.feeds import Snapshot
from app.engine.feeds import WINDOW_S
from core.analysis.optical_litres import ESTIMATE
from core.pipeline.quality import WORKING_RANGE_MM


HEIGHT_RANGE_MM = 40.0  # the maps' fixed scale: +-40 mm about the subject's mean surface


# The installed application compiles its reconstruction the first time a user starts it (numba's
# cache is the user's): the smoke test of a fresh install drew its first maps after 50 s on 2 cores,
# a started checkout with its cache after about 1 s (installer/smoke-test.sh, `photopft gui --smoke-test`)
FIRST_MAP_WAIT = ("waiting for the first map …\n(up to a minute on the first start after installing:\n"
                  "the reconstruction is being prepared)")


class HeadMapView(pg.GraphicsLayoutWidget):
    """One head's height map with its colour bar (mm)."""

    def __init__(self, head: str, parent=None) -> None:
        super().__init__(parent)
        self.head = head
        self.setBackground("w")
        plot = self.addPlot(title=f"{head.capitalize()} head: height (mm)")
        plot.setAspectLocked(True)
        plot.invertY(True)
        plot.hideAxis("left")
        plot.hideAxis("bottom")
        plot.setMouseEnabled(False, False)
        plot.setMenuEnabled(False)
        self.image = pg.ImageItem()
        plot.addItem(self.image)
        self.placeholder = pg.TextItem(FIRST_MAP_WAIT, color="k", anchor=(0.5, 0.5))
        plot.addItem(self.placeholder)
        self.placeholder.setPos(0.5, 0.5)  # the middle of the empty view, until the first map sets the range
        plot.setRange(xRange=(0.0, 1.0), yRange=(0.0, 1.0), padding=0.0)
        colours = pg.colormap.get("viridis")
        self.bar = pg.ColorBarItem(values=(-HEIGHT_RANGE_MM, HEIGHT_RANGE_MM), colorMap=colours, label="height (mm)",
                                   interactive=False, width=14)
        self.bar.setImageItem(self.image, insert_in=plot)
        self.plot = plot
        self._shown: np.ndarray | None = None

    def show_map(self, height_mm: np.ndarray | None) -> None:
        """Draw a new map; the one on screen is not drawn again (maps come slower than updates)."""
        if height_mm is None or height_mm is self._shown:
            return
        self._shown = height_mm
        if self.placeholder is not None:
            self.plot.removeItem(self.placeholder)
            self.placeholder = None
            self.plot.enableAutoRange()
        self.image.setImage(height_mm, autoLevels=False, levels=(-HEIGHT_RANGE_MM, HEIGHT_RANGE_MM))


VOLUME_STEPS_L = (0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0)  # half-ranges of the volume axis (L)


METRIC_PEN = pg.mkPen((200, 80, 20), width=2)
REFUSED_METRIC_PEN = pg.mkPen((150, 150, 150), width=2, style=Qt.PenStyle.DashLine)
# the legend in the title: inside the plot it covered the newest data
def litres_title(optical_litres: str, refused: bool = False) -> str:
    """The volume plot's title: the flow sensor, and what the optical litres are (calibrated on the
    subject, or an estimate), grey and dashed while `process` would refuse them."""
    optical = (f"<span style='color:#969696'>- - {optical_litres}: not valid, see Status</span>" if refused
               else f"<span style='color:#c85014'>━ {optical_litres}</span>")
    return f"Volume (L, BTPS), last 30 s: <span style='color:#141414'>━ flow sensor</span> &nbsp; {optical}"


LITRES_TITLE = litres_title(ESTIMATE)


class VolumeView(pg.GraphicsLayoutWidget):
    """The volume curve (litres, last 30 s): the flow sensor and the metric optical volume, and the
    gradient volume (relative) under them."""

    def __init__(self, parent=None) -> None:
        super().__init__(parent)
        self.setBackground("w")
        self.litres = self.addPlot(title=LITRES_TITLE)
        self.litres.setLabel("left", "volume", units="L")
        self.litres.getAxis("left").enableAutoSIPrefix(False)
        self.litres.showGrid(y=True, alpha=0.3)
        self.litres.setMouseEnabled(False, False)
        self.flow_curve = self.litres.plot(pen=pg.mkPen((20, 20, 20), width=2), name="flow sensor")
        # 3000 points a curve in a few hundred pixels: draw each pixel column's extremes only
        self.flow_curve.setDownsampling(auto=True, method="peak")
        self.flow_curve.setClipToView(True)
        self.metric_curve = self.litres.plot(pen=METRIC_PEN)
        self._metric_refused: tuple[bool, str] = (False, ESTIMATE)
        self.nextRow()
        self.relative = self.addPlot(title="Optical, relative: the breathing's shape without litres")
        # a fixed time axis, now at the right: the curves move, the axes and the grid are drawn once
        # (a scrolling range rebuilt both axes' ticks and labels at every update)
        self.relative.setLabel("bottom", "time before now (s)")
        self.relative.setMouseEnabled(False, False)
        self.relative.setXLink(self.litres)
        self.litres.setXRange(-WINDOW_S, 0.0, padding=0)
        self._litres_range = 0.0
        self._set_litres_range(0.0)
        self.relative.setYRange(-1.05, 1.05)
        self.optical_curve = self.relative.plot(pen=pg.mkPen((40, 90, 200), width=2))
        self.relative.setToolTip("The gradient volume (thesis eq. 3.27), centred and scaled to ±1: "
                                 "the optical signal before any scale is put on it")
        self.ci.layout.setRowStretchFactor(0, 3)
        self.ci.layout.setRowStretchFactor(1, 1)

    def _set_litres_range(self, largest_l: float) -> None:
        """The volume axis in steps (VOLUME_STEPS_L), changed only when the curves need another step:
        its ticks and labels are drawn again only then."""
        needed = next((step for step in VOLUME_STEPS_L if largest_l * 1.05 <= step), VOLUME_STEPS_L[-1])
        if needed != self._litres_range:
            self._litres_range = needed
            self.litres.setYRange(-needed, needed, padding=0)

    def show_curves(self, s: Snapshot) -> None:
        refused = s.optical_refused is not None
        if (refused, s.optical_litres) != self._metric_refused:  # grey and dashed while `process` would refuse it
            self._metric_refused = (refused, s.optical_litres)
            self.metric_curve.setPen(REFUSED_METRIC_PEN if refused else METRIC_PEN)
            self.litres.setTitle(litres_title(s.optical_litres, refused))
        end = max(s.flow_t_s[-1] if len(s.flow_t_s) else 0.0, s.optical_t_s[-1] if len(s.optical_t_s) else 0.0)
        start = end - WINDOW_S
        largest_l = 0.0
        for curve, t_all, v_all in ((self.flow_curve, s.flow_t_s, s.flow_volume_l),
                                    (self.metric_curve, s.metric_t_s, s.metric_volume_l)):
            keep = t_all >= start
            t, v = t_all[keep], v_all[keep]
            if len(t) < 2:  # nothing in the window yet (no trunk in view, or the maps not yet scaled)
                curve.setData([], [])
            else:
                # display only: the line through the window's ends taken out, so a zero drift of the
                # sensor (or the optical volume's slow offsets) does not carry the curve off the plot
                trend = np.polyfit(t, v, 1) if len(t) > 100 else (0.0, float(np.median(v)))
                shown = v - np.polyval(trend, t)
                curve.setData(t - end, shown)
                largest_l = max(largest_l, float(np.max(np.abs(shown))))
        self._set_litres_range(largest_l)
        if len(s.optical_t_s) > 5:
            keep = s.optical_t_s >= start
            keep[:3] = False  # the first maps, before the distance is tracked
            values = s.optical[keep]
            if len(values) > 2:
                # thesis eq. 3.27, robust to a stray map: centred on the median, scaled by the 98th percentile
                centred = values - np.median(values)
                scale = float(np.percentile(np.abs(centred), 98)) or 1.0
                self.optical_curve.setData(s.optical_t_s[keep] - end, np.clip(centred / scale, -1.05, 1.05))


# A status line turns red, or back, only once its verdict has held this long: a value at its
# threshold (115.2 % against 115 %) would otherwise flicker between the two at every update.
VERDICT_HOLD_S = 1.5


class Settled:
    """Each line's verdict (warn or not) with hysteresis in time: a new verdict is shown once it has
    held VERDICT_HOLD_S; meanwhile the line keeps the verdict it shows, with its latest text."""

    def __init__(self, hold_s: float = VERDICT_HOLD_S) -> None:
        self.hold_s = hold_s
        self._shown: dict[str, tuple[str, bool, str]] = {}
        self._since: dict[str, float] = {}

    def choose(self, key: str, text: str, warn: bool, detail: str, now_s: float,
               text_follows: bool = False) -> tuple[str, bool, str]:
        """What the line shows now. `text_follows`: a measurement, whose text is always the latest and
        whose colour alone waits (a distance); otherwise the text is the verdict and waits with it."""
        shown = self._shown.get(key)
        if shown is None or shown[1] == warn:
            self._since.pop(key, None)
            self._shown[key] = (text, warn, detail)
            return self._shown[key]
        started = self._since.setdefault(key, now_s)
        if now_s - started >= self.hold_s:
            self._since.pop(key, None)
            self._shown[key] = (text, warn, detail)
        elif text_follows:
            self._shown[key] = (text, shown[1], detail)
        return self._shown[key]


class StatusPanel(QGroupBox):
    def __init__(self, heads: list[str], parent=None) -> None:
        super().__init__("Status", parent)
        grid = QGridLayout(self)
        self.labels: dict[str, QLabel] = {}
        rows = [(f"{h}_rate", f"{h.capitalize()} camera") for h in heads]
        rows += [(f"{h}_distance", f"{h.capitalize()} distance") for h in heads]
        rows += [("optical", "Optical volume"), ("recording", "Recording"), ("calibration", "Calibration"),
                 ("source", "Source")]
        for k, (key, title) in enumerate(rows):
            grid.addWidget(QLabel(f"<b>{title}</b>"), k, 0, Qt.AlignmentFlag.AlignTop)
            label = QLabel("–")
            label.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
            label.setWordWrap(True)
            grid.addWidget(label, k, 1)
            self.labels[key] = label
        grid.setRowStretch(len(rows), 1)
        self._shown: dict[str, tuple[str, bool, str]] = {}

    def set(self, key: str, text: str, warn: bool = False, detail: str = "") -> None:
        """Change a line (the details in its tooltip); an unchanged one is left alone (a style sheet
        re-polishes the label)."""
        if self._shown.get(key) == (text, warn, detail):
            return
        self._shown[key] = (text, warn, detail)
        label = self.labels[key]
        label.setText(text)
        label.setToolTip(detail)
        label.setStyleSheet("color: #b00020; font-weight: bold" if warn else "")


class ReplayBar(QWidget):
    """A replay's controls: pause or play, the position in the recording (drag to move), and its
    length. `control(action, position_s)` is the engine's replay_control."""

    STEPS_PER_S = 10

    def __init__(self, parent=None) -> None:
        super().__init__(parent)
        self.control = None
        self.play = QPushButton("Pause")
        self.play.setFixedWidth(90)
        self.play.clicked.connect(self._toggle)
        self.slider = QSlider(Qt.Orientation.Horizontal)
        self.slider.sliderReleased.connect(self._seek)
        self.position = QLabel("–")
        self.position.setMinimumWidth(130)
        layout = QHBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.play)
        layout.addWidget(self.slider, 1)
        layout.addWidget(self.position)
        self.paused = False

    def _toggle(self) -> None:
        if self.control is not None:
            self.control("resume" if self.paused else "pause")

    def _seek(self) -> None:
        if self.control is not None:
            self.control("seek", self.slider.value() / self.STEPS_PER_S)

    def show_position(self, position_s: float, length_s: float, paused: bool) -> None:
        self.paused = paused
        self.play.setText("Play" if paused else "Pause")
        self.slider.setMaximum(int(length_s * self.STEPS_PER_S))
        if not self.slider.isSliderDown():
            self.slider.setValue(int(position_s * self.STEPS_PER_S))
        shown = self.slider.value() / self.STEPS_PER_S if self.slider.isSliderDown() else position_s
        self.position.setText(f"{shown:.1f} s of {length_s:.1f} s" + (" (paused)" if paused else ""))


LOST_WINDOW_S = 10.0  # a camera's lost frames are judged over this much of the recent past
LOST_SHARE_WARN = 0.01  # red above this share of the window's frames


class LostFrames:
    """A camera's frames and lost frames over the last LOST_WINDOW_S, from cumulative counts."""

    def __init__(self) -> None:
        self.history: list[tuple[float, int, int]] = []  # (s, frames, lost)

    def recent(self, now_s: float, frames: int, lost: int) -> tuple[int, int]:
        self.history.append((now_s, frames, lost))
        while len(self.history) > 2 and self.history[1][0] < now_s - LOST_WINDOW_S:
            self.history.pop(0)
        _, frames0, lost0 = self.history[0]
        return frames - frames0, lost - lost0


SIMULATED_FULL_PACE_FPS = 100.0  # the simulated cameras keep the rig's 110 frames/s, or near it


def camera_status(fps: float, maps: int, recent_frames: int, recent_lost: int, lost: int,
                  simulated: bool) -> tuple[str, bool]:
    """A camera's status line and whether it is a fault. The simulated cameras skip frames the
    renderer cannot make in time (a real camera drops them the same way, but that is a fault)."""
    if simulated:
        fewer = "; fewer maps than the rig makes, so blows are read coarsely" if fps < SIMULATED_FULL_PACE_FPS else ""
        return (f"{fps:.0f} frames/s rendered ({lost} skipped: this computer's pace, not a fault{fewer}); "
                f"{maps} maps"), False
    share = recent_lost / max(recent_frames + recent_lost, 1)
    return (f"{fps:.0f} frames/s; {recent_lost} lost in the last {LOST_WINDOW_S:.0f} s ({lost} in all); "
            f"{maps} maps"), share > LOST_SHARE_WARN


MIN_VOLUME_HEIGHT_PX = 220  # the volume curves' plot, whatever the screen: the operator reads breaths off it


class LiveView(QWidget):
    def __init__(self, heads: list[str], parent=None, simulated: bool = False) -> None:
        super().__init__(parent)
        self.heads = heads
        self.simulated = simulated
        self.lost = {h: LostFrames() for h in heads}
        self.settled = Settled()
        self.maps = {h: HeadMapView(h) for h in heads}
        self.volume = VolumeView()
        self.status = StatusPanel(heads)
        self.status.setMinimumWidth(260)
        # on a small screen (1366 x 768) the status scrolls and the maps shrink: the volume curve keeps its height
        status_scroll = QScrollArea()
        status_scroll.setWidget(self.status)
        status_scroll.setWidgetResizable(True)
        status_scroll.setFrameShape(QScrollArea.Shape.NoFrame)
        status_scroll.setMinimumWidth(280)
        status_scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        self.volume.setMinimumHeight(MIN_VOLUME_HEIGHT_PX)
        top = QHBoxLayout()
        for h in heads:
            top.addWidget(self.maps[h], 1)
        top.addWidget(status_scroll)
        self.replay_bar = ReplayBar()
        self.replay_bar.setVisible(False)
        layout = QVBoxLayout(self)
        layout.addLayout(top, 1)  # the maps scale down; the litres are what the operator reads
        layout.addWidget(self.volume, 1)
        layout.addWidget(self.replay_bar)
        self.updates = 0

    def show(self, s: Snapshot, calibration: str, source: str) -> None:  # noqa: A003 - Qt naming
        replay = bool(np.isfinite(s.replay_length_s))
        if self.replay_bar.isVisible() != replay:
            self.replay_bar.setVisible(replay)
        if replay:
            self.replay_bar.show_position(s.replay_position_s, s.replay_length_s, s.replay_paused)
        # with two heads each one's distance comes from both trunk widths: an arm in one view spoils both
        # (docs/history/volume-log.md, "An arm against the trunk moves the two heads' distances")
        arms = [h for h, view in s.heads.items() if view.arm_against_trunk] if len(s.heads) == 2 else []
        for h, view in s.heads.items():
            if h in self.maps:
                self.maps[h].show_map(view.height_mm)
            recent_frames, recent_lost = self.lost[h].recent(s.elapsed_s, view.frames, view.lost)
            self.status.set(f"{h}_rate", *camera_status(view.fps, view.reconstructed, recent_frames, recent_lost,
                                                         view.lost, self.simulated))
            low, high = WORKING_RANGE_MM
            ok = low <= view.distance_mm <= high
            text = (f"{view.distance_mm:.0f} mm (working range {low:.0f}–{high:.0f} mm)" if np.isfinite(view.distance_mm)
                    else "no subject seen")
            arm = view.arm_against_trunk
            if arms and np.isfinite(view.distance_mm):  # as `process`, which gives no distance then
                text = (f"not measured: an arm against the trunk ({arms[0]} view) hides the sides it is measured "
                        "from: arms away from the body")
            elif arm:
                text += "; an arm against the trunk hides its side: arms away from the body"
            self.status.set(f"{h}_distance", *self.settled.choose(f"{h}_distance", text, not ok or bool(arms) or arm,
                                                                   "", s.elapsed_s, text_follows=True))
        if s.optical_refused is not None:
            line = (f"not valid now: {s.optical_refused.action or 'ask the patient to stand still'}", True,
                    str(s.optical_refused))
        else:
            line = ("valid" if s.optical_checked else "not checked yet: both heads must see the trunk"
                    if len(self.heads) == 2 else "not checked: the checks take two heads", False,
                    "the skin's shading and the maps' sides pass the checks" if s.optical_checked else "")
        self.status.set("optical", *self.settled.choose("optical", *line, s.elapsed_s))
        if s.recording is not None:
            frames = ", ".join(f"{h} {n}" for h, n in s.recorded_frames.items())
            self.status.set("recording", f"{s.recording.name}: {frames} frames written, {s.dropped} dropped",
                            warn=s.dropped > 0)
        else:
            self.status.set("recording", "not recording")
        if s.problems:
            self.status.set("recording", "; ".join(s.problems[-2:]), warn=True)
        syringe_due = "syringe check: none today" in calibration and not self.simulated
        self.status.set("calibration", calibration, warn=syringe_due or "syringe check: FAILED" in calibration)
        self.status.set("source", source)
        self.volume.show_curves(s)
        self.updates += 1
