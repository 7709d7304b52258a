"""SIGTERM and SIGINT end the application cleanly (issue 77, requirement 5): a recording in a patient
session is finished and its visit marked, the engine process stopped, no dialog, exit 0."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from functools import partial
from pathlib import Path

import pytest
from PySide6.QtWidgets import QApplication

from app.gui.main_window import MainWindow
from app.gui.shutdown import ShutdownSignals
from app.engine.sources import simulated_source
from app.records import Records
from core.io.session import validate_session
from tests.waiting import wait_until

pytestmark = pytest.mark.slow


def test_sigterm_during_a_recording_finishes_it_and_asks_nothing(qtbot, tmp_path, monkeypatch):
    from app.gui.wizards.patient_session import PatientSessionWizard

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    window = MainWindow(partial(simulated_source, scale=0.1))
    qtbot.addWidget(window)
    engine = window.engine
    records = Records(tmp_path / "records.sqlite3")
    wizard = PatientSessionWizard(None, engine, records, sessions_dir=tmp_path / "sessions")
    qtbot.addWidget(wizard)
    wizard.show()
    page = wizard.currentPage()
    page.family.setText("Kowalski")
    page.sex.setCurrentText("male")
    page.add.click()
    wizard.next()
    qtbot.waitUntil(wizard.currentPage().isComplete, timeout=30000)
    wizard.next()
    assert engine.recording
    signals = ShutdownSignals(window, window.shut_down)
    try:
        os.kill(os.getpid(), signal.SIGTERM)
        qtbot.waitUntil(lambda: window.engine is None and not wizard.isVisible(), timeout=30000)
    finally:
        signals.restore()
    assert signals.received == [signal.SIGTERM]
    assert QApplication.activeModalWidget() is None  # nothing waits for an answer
    assert not engine.recording and validate_session(wizard.session_path) == []
    (patient,) = records.find_patients("Kowalski")
    (visit,) = records.history(patient.id)
    assert visit.status == "cancelled" and visit.session_path == wizard.session_path
    records.close()


def _children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text().split()
        out += [int(c) for c in text]
    return out


def _engine_started(pid: int) -> bool:
    """True once a spawned multiprocessing child runs (a `uname` run by an import is no engine)."""
    for child in _children(pid):
        try:
            if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes():
                return True
        except OSError:
            pass
    return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_the_application_exits_0_on_a_signal(tmp_path, sig):
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen", XDG_DATA_HOME=str(tmp_path / "data"),
               XDG_CONFIG_HOME=str(tmp_path / "config"), XDG_STATE_HOME=str(tmp_path / "state"))
    gui = subprocess.Popen([sys.executable, "-m", "app", "gui", "--scale", "0.1"], env=env,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        # the engine process is started when the window is up
        wait_until(lambda: _engine_started(gui.pid) or gui.poll() is not None, 120, "the window's engine")
        assert _engine_started(gui.pid), "the window did not start its engine"
        engine = _children(gui.pid)
        gui.send_signal(sig)
        out, err = gui.communicate(timeout=60)
    finally:
        if gui.poll() is None:
            gui.kill()
    assert gui.returncode == 0, err
    assert "Something went wrong" not in err and "Traceback" not in err

    def alive(pid: int) -> bool:
        try:
            return "zombie" not in Path(f"/proc/{pid}/status").read_text().lower()
        except OSError:
            return False

    # the engine and multiprocessing's helper end with the application
    wait_until(lambda: not any(alive(pid) for pid in engine), 15, "the engine's processes to end")
