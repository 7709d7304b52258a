"""One contract, two engines: the in-process LiveRig and the EngineProcess answer the GUI's calls
(app/engine/protocol.py, LiveEngine) alike, on the simulated rig."""

from __future__ import annotations

import time
from functools import partial

import numpy as np
import pytest

from app.engine.live_rig import LiveRig
from app.engine.process import EngineProcess
from app.engine.protocol import LiveEngine
from app.engine.sources import simulated_source
from core.io.session import SessionFile, SubjectRecord, validate_session
from tests.waiting import wait_until

pytestmark = pytest.mark.slow

SUBJECT = SubjectRecord("CONTRACT-1", "female", 40.0, 165.0, 60.0)


def _in_process():
    rig = LiveRig(simulated_source(scale=0.1))
    rig.start()
    return rig


def _own_process():
    return EngineProcess(partial(simulated_source, scale=0.1))


@pytest.fixture(params=[_in_process, _own_process], ids=["in-process", "own-process"])
def engine(request):
    e = request.param()
    yield e
    e.stop()


def test_both_engines_show_maps_and_record_a_session_with_its_events(engine, tmp_path):
    assert isinstance(engine, LiveEngine)
    assert engine.info.heads == ("front", "back") and engine.info.simulated and not engine.info.replay
    assert engine.rig.heads.keys() == {"front", "back"} and not engine.replay_finished
    wait_until(lambda: all(v.reconstructed > 0 for v in engine.snapshot().heads.values()), 120, "a map from each head")
    snapshot = engine.snapshot()
    assert all(v.height_mm is not None and v.height_mm.shape == engine.rig.heads[h].shape
               for h, v in snapshot.heads.items())  # each map travels once, and stays
    assert np.isfinite(engine.flow_adc_mean(1.0))
    assert engine.preview("front") is not None
    path = tmp_path / "s.h5"
    before = time.monotonic_ns()
    engine.start_recording(path, SUBJECT, kind="simulation")
    assert engine.recording
    wait_until(lambda: min(engine.snapshot().recorded_frames.values(), default=0) > 0, 30, "frames recorded")
    mark = engine.mark("tidal-start")
    assert engine.perform("forced") > 1.0  # the simulated subject follows the prompt
    wait_until(lambda: engine.flow_reaches(mark + 500_000_000), 30, "flow samples 0.5 s past the mark")
    assert engine.recorded_values(30.0) is not None
    counts, stamps = engine.flow_since(mark)
    assert len(counts) == len(stamps) > 0
    summary = engine.stop_recording()
    assert not engine.recording and min(summary.frames.values()) >= 5
    assert validate_session(path) == [], validate_session(path)
    with SessionFile(path) as s:
        for head in s.heads:  # the frames span the recording in camera time (a busy machine's renderer skips some)
            ids = s.frame_id(head).astype(int)
            assert (ids[-1] - ids[0]) / s.rig.frame_rate_hz >= summary.elapsed_s - 0.6, (head, ids, summary.elapsed_s)
        assert [(t, label) for t, label in s.events()] == [(mark, "tidal-start")]
        # the stamp crossed over unchanged, on the monotonic clock (not compared with the frames' stamps:
        # on a loaded machine the simulated cameras' nominal stamps fall seconds behind it)
        assert before < mark
