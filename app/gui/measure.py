"""One measurement of the live view in the real window, shared by `photopft gui --smoke-test` and
`photopft bench gui`: from the first maps of every head (and a warm-up after them), for a set
time, optionally recording."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from PySide6.QtCore import QEventLoop, QTimer

from app.memory import rss_mb
from drivers.recorder import RecordSummary

if TYPE_CHECKING:
    from app.gui.main_window import Stall


@dataclass
class LiveFigures:
    first_maps_s: float  # from the start of the measurement to every head's first map
    elapsed_s: float = 0.0
    updates_per_s: float = 0.0
    longest_stall_ms: float = 0.0
    long_stalls: list[Stall] = field(default_factory=list)  # at_s: s into the measurement
    maps_per_s: dict[str, float] = field(default_factory=dict)
    frames_per_s: dict[str, float] = field(default_factory=dict)
    # GUI and engine processes: at the start of the measurement, every 10 s, at the end
    rss_mb: list[float] = field(default_factory=list)
    rss_first_maps_mb: float = float("nan")  # both processes when every head had its first map
    gui_rss_mb: list[float] = field(default_factory=list)
    recording: RecordSummary | None = None


def measure_live_view(window, seconds: float, record_to: Path | None = None, subject=None,
                      kind: str = "simulation", first_maps_timeout_s: float = 300.0, warmup_s: float = 0.0,
                      until_every_head_maps_s: float = 0.0) -> LiveFigures:
    """Run an event loop of its own until every head has a map (a cold numba cache compiles first),
    then for `warmup_s` more (the live view before a recording, as while the operator positions
    the patient: the engine's buffers and the drawing reach their working size), then measure for
    `seconds` (recording into `record_to` when given, with a tidal-start event), and up to
    `until_every_head_maps_s` longer until every head has made a map within the measurement (a short
    window on a loaded machine may see none from a head that makes one every second or two), stop
    the recording, close the window and return the figures."""
    waited = time.monotonic()
    figures = LiveFigures(first_maps_s=float("nan"))
    start: dict = {}
    sample = QTimer()

    def both_mb() -> float:
        return rss_mb() + rss_mb(window.engine.pid)

    def memory() -> None:
        figures.gui_rss_mb.append(rss_mb())
        figures.rss_mb.append(both_mb())

    sample.timeout.connect(memory)

    def begin() -> None:
        heads = window.engine.snapshot().heads
        mapped = all(v.reconstructed > 0 for v in heads.values())
        if not mapped and not window.engine.stopped and time.monotonic() - waited < first_maps_timeout_s:
            QTimer.singleShot(200, begin)  # a stopped engine sends no maps: not waited for
            return
        if mapped:  # else first_maps_s stays NaN: none came
            figures.first_maps_s = time.monotonic() - waited
            figures.rss_first_maps_mb = both_mb()
        QTimer.singleShot(int(warmup_s * 1000), measure)

    def measure() -> None:
        heads = window.engine.snapshot().heads
        window.stalls.reset()
        start.update(t=time.monotonic(), updates=window.view.updates,
                     maps={h: v.reconstructed for h, v in heads.items()}, frames={h: v.frames for h, v in heads.items()})
        memory()
        if record_to is not None:
            window.engine.start_recording(record_to, subject, kind=kind)
            window.engine.mark("tidal-start")
        sample.start(10000)
        QTimer.singleShot(int(seconds * 1000), end)

    def every_head_mapped() -> bool:
        heads = window.engine.snapshot().heads
        return all(v.reconstructed > start["maps"][h] for h, v in heads.items())

    def end() -> None:
        if (not window.engine.stopped and not every_head_mapped()
                and time.monotonic() - start["t"] < seconds + until_every_head_maps_s):
            QTimer.singleShot(200, end)
            return
        sample.stop()
        elapsed = time.monotonic() - start["t"]
        heads = window.engine.snapshot().heads
        memory()
        figures.elapsed_s = elapsed
        figures.updates_per_s = (window.view.updates - start["updates"]) / elapsed
        figures.longest_stall_ms = window.stalls.longest_ms
        figures.long_stalls = list(window.stalls.long_stalls)
        figures.maps_per_s = {h: (v.reconstructed - start["maps"][h]) / elapsed for h, v in heads.items()}
        figures.frames_per_s = {h: (v.frames - start["frames"][h]) / elapsed for h, v in heads.items()}
        if record_to is not None:
            figures.recording = window.engine.stop_recording()
        window.close()
        loop.quit()

    QTimer.singleShot(500, begin)
    loop = QEventLoop()  # its own loop, not the application's: a measurement leaves the application as it was
    loop.exec()
    return figures
