"""`photopft gui`: the desktop application."""

from __future__ import annotations

import argparse
import sys
import tempfile
from functools import partial
from pathlib import Path

from app.args import finite, positive

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def add_gui(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gui", help="the desktop application (live view, patient sessions, calibrations)",
                       description="Runs on the simulated rig unless --rig names a real one.")
    p.add_argument("--rig", type=Path, help="rig configuration (default resources/rigs/simulated.toml)")
    p.add_argument("--session", type=Path, help="replay this recorded session in the live view")
    p.add_argument("--speed", type=finite, default=1.0, help="replay speed (1 = real time)")
    p.add_argument("--scale", type=positive, help="simulated rig: sensor scale (default the rig config's)")
    p.add_argument("--smoke-test", type=finite, metavar="SECONDS",
                   help="record a simulated session for SECONDS in the real window, process it, write its report, "
                        "print the figures and exit (0 when everything worked)")
    p.set_defaults(run=run_gui)


def signed_in() -> bool:
    """True when nobody need sign in (no users with passwords in the records) or someone did."""
    from PySide6.QtWidgets import QDialog

    from app.audit import login_name
    from app.auth import use_asker
    from app.gui.login import LoginDialog, ask_in_dialog, login_needed

    use_asker(ask_in_dialog)
    return not login_needed() or LoginDialog(None, login_name()).exec() == QDialog.DialogCode.Accepted


def lock_when_idle(window) -> None:
    """Where someone signed in: the lock after the settings' security/idle_minutes without input."""
    from PySide6.QtCore import QSettings

    from app.auth import proven_user
    from app.gui.login import IDLE_MINUTES, IdleLock

    if proven_user():
        minutes = float(QSettings().value("security/idle_minutes", IDLE_MINUTES))
        window.idle_lock = IdleLock(window, minutes, window.close)


def run_gui(args: argparse.Namespace) -> int:
    from PySide6.QtWidgets import QApplication

    from app.gui.errors import setup_logging
    from app.gui.shutdown import ShutdownSignals

    setup_logging()
    app = QApplication.instance() or QApplication(sys.argv[:1])
    app.setApplicationName("photopft")
    app.setOrganizationName("photopft")
    # from here on SIGTERM and SIGINT end the application with 0 (a signal before the window is
    # made is acted on once it is)
    shutdown = ShutdownSignals(app, _close_dialogs) if args.smoke_test is None else None
    try:
        return _run_window(app, args, shutdown)
    finally:
        if shutdown is not None:
            shutdown.restore()


def _close_dialogs(signum: int) -> None:
    """A signal before the window is made: the sign-in dialog, if up, goes."""
    from PySide6.QtWidgets import QApplication

    dialog = QApplication.activeModalWidget()
    if dialog is not None:
        dialog.reject()


def _run_window(app, args: argparse.Namespace, shutdown) -> int:
    from PySide6.QtCore import QTimer

    from app.errors import UserError
    from app.gui.errors import ENGINE_LOG, install_excepthook
    from app.gui.main_window import MainWindow
    from app.engine.sources import replay_source, rig_source
    from app.logs import log_file

    if args.smoke_test is None and (not signed_in() or shutdown.received):
        return 0
    rig = args.rig or settings_rig()
    opener = partial(replay_source, args.session, args.speed) if args.session else \
        partial(rig_source, rig, args.scale)
    try:
        window = MainWindow(opener, rig, engine_log=log_file(ENGINE_LOG))
    except Exception as exc:  # the rig or file cannot be opened: one clear line, and no window
        raise UserError(f"cannot start: {exc}") from exc
    failed: list[bool] = []

    def give_up() -> None:  # the smoke test: an unexpected error ends it, with the traceback on stderr
        failed.append(True)
        window.close()
        app.exit(1)

    install_excepthook(lambda: window, give_up if args.smoke_test is not None else None)
    window.show()
    if args.smoke_test is None:
        lock_when_idle(window)
        QTimer.singleShot(0, window.offer_cut_off_visits)
        shutdown.on_signal = window.shut_down
        app.processEvents()  # a signal that came while the window was made is read here
        if shutdown.received:
            if not getattr(window, "_shutting_down", False):
                window.shut_down(shutdown.received[0])
            return 0
        return app.exec()
    if window.engine is None:
        raise UserError(f"cannot start: {window.diagnostics.problem.text()}")
    return _smoke_test(window, args.smoke_test, failed)


def settings_rig() -> Path | None:
    """The rig configuration chosen in Settings (None: the simulated rig)."""
    from PySide6.QtCore import QSettings

    chosen = str(QSettings("photopft", "photopft").value("rig/config", "") or "")
    return Path(chosen) if chosen else None


# The smoke test's window goes on up to this much longer until every head has made a map in it: on a
# loaded machine (CI, the tests beside it) a head made one map in 2.3 s and the other none
SMOKE_MAPS_GRACE_S = 30.0


def _smoke_test(window, seconds: float, failed: list[bool]) -> int:
    """Record on the simulated rig in the real window, then process and report the recording.
    `failed` holds an entry once an unexpected error has ended the window's event loop."""
    from app.gui.measure import measure_live_view
    from core.io.session import SubjectRecord, validate_session

    folder = Path(tempfile.mkdtemp(prefix="photopft-smoke-"))
    session = folder / "smoke.h5"
    f = measure_live_view(window, seconds, session, SubjectRecord("SMOKE-0001", "male", 30.0, 175.0, 75.0),
                          until_every_head_maps_s=SMOKE_MAPS_GRACE_S)
    if failed:
        print("smoke test: an unexpected error ended it (its traceback above, and in the log)")
        return 1
    summary = f.recording
    print(f"smoke test: first maps after {f.first_maps_s:.1f} s; {f.elapsed_s:.1f} s recorded in the window: "
          + ", ".join(f"{h} {n} frames" for h, n in summary.frames.items())
          + f", {summary.dropped_by_software} dropped")
    print("  maps reconstructed per second: " + ", ".join(f"{h} {r:.1f}" for h, r in f.maps_per_s.items()))
    print(f"  display updates per second: {f.updates_per_s:.1f}; GUI thread longest stall "
          f"{f.longest_stall_ms:.0f} ms; memory {f.rss_mb[0]:.0f} -> {f.rss_mb[-1]:.0f} MB")
    problems = validate_session(session)
    ok = not problems and not summary.problems and all(r > 0 for r in f.maps_per_s.values()) \
        and f.updates_per_s > 0
    if problems or summary.problems:
        print("  problems: " + "; ".join(problems + summary.problems))
        return 1
    from app.report_data import build_report
    from app.report_pdf import write_report
    from core.pipeline.process import process_session

    results = folder / "smoke-results.h5"
    processed = process_session(session, results, every=11)
    report = write_report(build_report(results), folder / "smoke-report.pdf")
    print(f"  processed {sum(processed.maps.values())} maps in {processed.elapsed_s:.1f} s; report {report}")
    return 0 if ok else 1
