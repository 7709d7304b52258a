"""`photopft gui`: the desktop application."""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path


def add_gui(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gui", help="the desktop application (live view, patient sessions, calibrations)",
                       description="Runs on the simulated rig unless --rig names a real one.")
    p.add_argument("--rig", type=Path, help="rig configuration (default resources/rigs/simulated.toml)")
    p.add_argument("--session", type=Path, help="replay this recorded session in the live view")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed (1 = real time)")
    p.add_argument("--scale", type=float, help="simulated rig: sensor scale (default the rig config's)")
    p.add_argument("--smoke-test", type=float, metavar="SECONDS",
                   help="record a simulated session for SECONDS in the real window, process it, write its report, "
                        "print the figures and exit (0 when everything worked)")
    p.set_defaults(run=run_gui)


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def run_gui(args: argparse.Namespace) -> int:
    from PySide6.QtCore import QTimer
    from PySide6.QtWidgets import QApplication

    from app.cli import UserError
    from app.gui.errors import install_excepthook, setup_logging
    from app.gui.main_window import MainWindow
    from app.live import replay_source, rig_source

    setup_logging()
    app = QApplication.instance() or QApplication(sys.argv[:1])
    app.setApplicationName("photopft")
    app.setOrganizationName("photopft")
    try:
        source = replay_source(args.session, args.speed) if args.session else rig_source(args.rig, args.scale)
    except Exception as exc:  # the rig or file cannot be opened: one clear line, before any window
        raise UserError(f"cannot start: {exc}") from exc
    window = MainWindow(source, args.rig)
    install_excepthook(lambda: window)
    window.show()
    if args.smoke_test is None:
        return app.exec()
    return _smoke_test(app, window, args.smoke_test)


def _smoke_test(app, window, seconds: float) -> int:
    """Record on the simulated rig in the real window, then process and report the recording."""
    from PySide6.QtCore import QTimer

    from core.session import SubjectRecord, validate_session

    folder = Path(tempfile.mkdtemp(prefix="photopft-smoke-"))
    session = folder / "smoke.h5"
    figures: dict = {}

    def begin() -> None:
        window.stalls.reset()
        figures["rss_start"] = _rss_mb()
        figures["updates_start"] = window.view.updates
        figures["maps_start"] = {h: v.reconstructed for h, v in window.engine.snapshot().heads.items()}
        figures["t_start"] = time.monotonic()
        window.engine.start_recording(session, SubjectRecord("SMOKE-0001", "male", 30.0, 175.0, 75.0),
                                      kind="simulation")
        window.engine.mark("tidal-start")

    def finish() -> None:
        elapsed = time.monotonic() - figures["t_start"]
        snapshot = window.engine.snapshot()
        figures["elapsed"] = elapsed
        figures["updates"] = (window.view.updates - figures["updates_start"]) / elapsed
        figures["maps"] = {h: (v.reconstructed - figures["maps_start"][h]) / elapsed
                           for h, v in snapshot.heads.items()}
        figures["stall"] = window.stalls.longest_ms
        figures["rss_end"] = _rss_mb()
        figures["summary"] = window.engine.stop_recording()
        window.close()
        app.quit()

    waited = time.monotonic()

    def when_ready() -> None:
        """Start once both heads show maps (the first start of an installed app compiles first)."""
        heads = window.engine.snapshot().heads
        if all(v.reconstructed > 0 for v in heads.values()) or time.monotonic() - waited > 300:
            print(f"smoke test: first maps after {time.monotonic() - waited:.1f} s", flush=True)
            begin()
            QTimer.singleShot(int(seconds * 1000), finish)
        else:
            QTimer.singleShot(200, when_ready)

    QTimer.singleShot(500, when_ready)
    app.exec()
    summary = figures["summary"]
    print(f"smoke test: {figures['elapsed']:.1f} s recorded in the window: "
          + ", ".join(f"{h} {n} frames" for h, n in summary.frames.items())
          + f", {summary.dropped_by_software} dropped")
    print("  maps reconstructed per second: " + ", ".join(f"{h} {r:.1f}" for h, r in figures["maps"].items()))
    print(f"  display updates per second: {figures['updates']:.1f}; GUI thread longest stall "
          f"{figures['stall']:.0f} ms; memory {figures['rss_start']:.0f} -> {figures['rss_end']:.0f} MB")
    problems = validate_session(session)
    ok = not problems and not summary.problems and all(r > 0 for r in figures["maps"].values()) \
        and figures["updates"] > 0
    if problems or summary.problems:
        print("  problems: " + "; ".join(problems + summary.problems))
        return 1
    from core.process import process_session
    from app.report_data import build_report
    from app.report_pdf import write_report

    results = folder / "smoke-results.h5"
    processed = process_session(session, results, every=11)
    report = write_report(build_report(results), folder / "smoke-report.pdf")
    print(f"  processed {sum(processed.maps.values())} maps in {processed.elapsed_s:.1f} s; report {report}")
    return 0 if ok else 1
