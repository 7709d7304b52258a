"""One measurement of the live view in the real window, shared by `photopft gui --smoke-test` and
`photopft bench gui`: from the first maps of every head, for a set time, optionally recording."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from app.memory import rss_mb
from drivers.recorder import RecordSummary


@dataclass
class LiveFigures:
    first_maps_s: float  # from the start of the measurement to every head's first map
    elapsed_s: float = 0.0
    updates_per_s: float = 0.0
    longest_stall_ms: float = 0.0
    maps_per_s: dict[str, float] = field(default_factory=dict)
    frames_per_s: dict[str, float] = field(default_factory=dict)
    rss_mb: list[float] = field(default_factory=list)  # GUI and engine processes: at the start, every 10 s, at the end
    gui_rss_mb: list[float] = field(default_factory=list)
    recording: RecordSummary | None = None


def measure_live_view(app, window, seconds: float, record_to: Path | None = None, subject=None,
                      kind: str = "simulation", first_maps_timeout_s: float = 300.0) -> LiveFigures:
    """Run the window's event loop until every head has a map (a cold numba cache compiles first),
    then measure for `seconds` (recording into `record_to` when given, with a tidal-start event),
    stop the recording, close the window and return the figures."""
    from PySide6.QtCore import QTimer

    waited = time.monotonic()
    figures = LiveFigures(first_maps_s=float("nan"))
    start: dict = {}
    sample = QTimer()

    def memory() -> None:
        gui = rss_mb()
        figures.gui_rss_mb.append(gui)
        figures.rss_mb.append(gui + rss_mb(window.engine.pid))

    sample.timeout.connect(memory)

    def begin() -> None:
        heads = window.engine.snapshot().heads
        if not all(v.reconstructed > 0 for v in heads.values()) and time.monotonic() - waited < first_maps_timeout_s:
            QTimer.singleShot(200, begin)
            return
        figures.first_maps_s = time.monotonic() - waited
        window.stalls.reset()
        start.update(t=time.monotonic(), updates=window.view.updates,
                     maps={h: v.reconstructed for h, v in heads.items()}, frames={h: v.frames for h, v in heads.items()})
        memory()
        if record_to is not None:
            window.engine.start_recording(record_to, subject, kind=kind)
            window.engine.mark("tidal-start")
        sample.start(10000)
        QTimer.singleShot(int(seconds * 1000), end)

    def end() -> None:
        sample.stop()
        elapsed = time.monotonic() - start["t"]
        heads = window.engine.snapshot().heads
        memory()
        figures.elapsed_s = elapsed
        figures.updates_per_s = (window.view.updates - start["updates"]) / elapsed
        figures.longest_stall_ms = window.stalls.longest_ms
        figures.maps_per_s = {h: (v.reconstructed - start["maps"][h]) / elapsed for h, v in heads.items()}
        figures.frames_per_s = {h: (v.frames - start["frames"][h]) / elapsed for h, v in heads.items()}
        if record_to is not None:
            figures.recording = window.engine.stop_recording()
        window.close()
        app.quit()

    QTimer.singleShot(500, begin)
    app.exec()
    return figures
