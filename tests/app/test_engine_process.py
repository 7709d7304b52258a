"""The live engine in its own process (app.engine.process), as the GUI drives it, without Qt:
snapshots, a recording with its events, a source that cannot be opened, and an engine that dies."""

from __future__ import annotations

import os
import signal
from functools import partial

import h5py
import pytest

from app.engine.process import EngineError, EngineProcess
from app.engine.sources import replay_source, simulated_source
from core.io.recovery import recover_session
from core.io.session import SessionError, SubjectRecord, validate_session
from tests.waiting import wait_until

pytestmark = pytest.mark.slow

SUBJECT = SubjectRecord("ENGINE-1", "female", 40.0, 165.0, 60.0)


@pytest.fixture
def engine():
    e = EngineProcess(partial(simulated_source, scale=0.1))
    yield e
    e.stop()


def test_a_source_that_cannot_be_opened_raises_its_own_error(tmp_path):
    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"not hdf5")
    with pytest.raises(SessionError, match="broken.h5"):
        EngineProcess(partial(replay_source, broken))


def test_an_engine_that_dies_is_said_and_the_recording_so_far_is_kept(engine, tmp_path):
    path = tmp_path / "killed.h5"
    wait_until(lambda: all(v.frames > 0 for v in engine.snapshot().heads.values()), 120, "frames from each head")
    engine.start_recording(path, SUBJECT, kind="simulation")
    # killed once the file itself holds frames of each head (the recorder writes them out in batches)
    def on_disk() -> bool:
        try:
            with h5py.File(path, "r", swmr=True) as f:
                return min(f[f"heads/{h}/frames"].shape[0] for h in engine.info.heads) > 40
        except (OSError, KeyError):
            return False

    wait_until(on_disk, 60, "40 frames of each head in the file")
    os.kill(engine.pid, signal.SIGKILL)
    wait_until(lambda: any("capture engine stopped" in p for p in engine.snapshot().problems), 10, "the engine's death said")
    assert engine.stopped
    with pytest.raises(EngineError, match="stopped"):
        engine.stop_recording()
    kept = recover_session(path).kept
    assert validate_session(path) == [], validate_session(path)
    # killed while writing a head's dataset header, that head's frames are lost (checksum; the recovery
    # says so, tests/app/test_data_safety.py); every other part keeps what was recorded
    assert sum(n > 30 for n in kept.values()) >= len(kept) - 1
