"""`photopft bench gui`: the live view's display rate, GUI-thread stalls, maps per second and
memory, in the real window on the simulated rig (offscreen unless a display is set)."""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def run_gui_bench(scale: float, seconds: float, record: bool) -> str:
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication

    from app.gui.main_window import MainWindow
    from app.live import simulated_source
    from core.session import SubjectRecord

    app = QApplication.instance() or QApplication([])
    window = MainWindow(simulated_source(scale=scale))
    window.show()
    folder = Path(tempfile.mkdtemp(prefix="photopft-bench-gui-"))
    f: dict = {"rss": []}

    def begin() -> None:
        heads = window.engine.snapshot().heads
        if not all(v.reconstructed > 0 for v in heads.values()):
            QTimer.singleShot(200, begin)
            return
        window.stalls.reset()
        f.update(t=time.monotonic(), updates=window.view.updates, maps={h: v.reconstructed for h, v in heads.items()},
                 frames={h: v.frames for h, v in heads.items()})
        f["rss"].append(_rss_mb())
        if record:
            window.engine.start_recording(folder / "bench.h5", SubjectRecord("BENCH", "male", 30.0, 175.0, 75.0),
                                          kind="simulation")
        sample.start(10000)
        QTimer.singleShot(int(seconds * 1000), end)

    def end() -> None:
        sample.stop()
        elapsed = time.monotonic() - f["t"]
        heads = window.engine.snapshot().heads
        f["rss"].append(_rss_mb())
        f.update(elapsed=elapsed, updates=(window.view.updates - f["updates"]) / elapsed,
                 stall=window.stalls.longest_ms,
                 maps={h: (v.reconstructed - f["maps"][h]) / elapsed for h, v in heads.items()},
                 fps={h: (v.frames - f["frames"][h]) / elapsed for h, v in heads.items()})
        f["summary"] = window.engine.stop_recording() if record else None
        window.close()
        app.quit()

    sample = QTimer()
    sample.timeout.connect(lambda: f["rss"].append(_rss_mb()))
    QTimer.singleShot(500, begin)
    app.exec()
    for path in folder.glob("*"):
        path.unlink()
    folder.rmdir()
    dropped = f["summary"].dropped_by_software if f["summary"] is not None else 0
    rows = [
        f"scale {scale:g}, {'recording' if record else 'live view only'}, {f['elapsed']:.0f} s, simulated rig "
        f"(its cameras rendered on the same cores), {os.cpu_count()} cores",
        "",
        "| display updates/s | GUI thread longest stall | maps/s per head | frames/s per head | dropped | memory |",
        "|---|---|---|---|---|---|",
        f"| {f['updates']:.1f} | {f['stall']:.0f} ms | "
        + ", ".join(f"{h} {r:.1f}" for h, r in f["maps"].items()) + " | "
        + ", ".join(f"{h} {r:.0f}" for h, r in f["fps"].items())
        + f" | {dropped} | {f['rss'][0]:.0f} -> {f['rss'][-1]:.0f} MB (peak {max(f['rss']):.0f}) |",
    ]
    return "\n".join(rows)
