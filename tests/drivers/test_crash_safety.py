"""A recording killed with SIGKILL at a random moment: the file opens and holds all but the last second."""

from __future__ import annotations

import random
import resource
import signal
import subprocess
import sys
import time

import h5py
import numpy as np

from core.io.recovery import recover_session
from core.io.session import SessionFile, validate_session
from tests.waiting import wait_until


def test_sigkill_mid_recording_keeps_the_data(tmp_path):
    out = tmp_path / "killed.h5"
    process = subprocess.Popen([sys.executable, "-m", "app", "record", "-o", str(out), "--seconds", "30"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    # wait until recording has begun (the file exists and holds frames), then kill at a random moment
    seen = {}

    def recording() -> bool:
        try:
            with h5py.File(out, "r", swmr=True) as f:
                seen.update({h: f[f"heads/{h}/frames"].shape[0] for h in ("front", "back")})
        except (OSError, KeyError):
            return False
        return min(seen.values()) > 20

    wait_until(recording, 60, "20 frames of each head in the file")
    recorded_s = random.uniform(1.0, 3.0)
    time.sleep(recorded_s)  # the scenario: the kill falls at a random moment of the recording, not on a condition
    killed_at = time.monotonic()
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert "photopft recover" in validate_session(out)[0]  # the cut-off file says what to do
    kept = recover_session(out).kept
    assert out.with_name("killed.crashed.h5").exists()  # the original is kept
    assert validate_session(out) == [], validate_session(out)
    with SessionFile(out) as s:
        for head in ("front", "back"):
            n = s.n_frames(head)
            ids = s.frame_id(head).astype(int)
            assert np.all(np.diff(ids) >= 1)  # in order, none twice (a busy machine's simulated rig drops some)
            # everything that was in the file before the kill is kept, and at most about a second is lost:
            # counted in camera time (frame ids run at the rig's rate), since a busy machine's renderer skips frames
            covered_s = (ids[n - 1] - ids[seen[head] - 1]) / s.rig.frame_rate_hz
            assert n == kept[head] and n >= seen[head] and covered_s >= recorded_s - 1.5, (head, n, seen, recorded_s,
                                                                                            covered_s)
            last = s.frames(head)[n - 1]
            assert last.shape == s.rig.heads[head].shape and last.max() > 0
        adc, stamps = s.flow_samples()
        assert len(adc) > 500
        assert "recovered" in s.attrs
    with h5py.File(out, "r") as f:  # the copy is compressed as the recording was
        assert all("32001" in f[f"heads/{h}/frames"]._filters for h in ("front", "back"))
    assert time.monotonic() - killed_at < 60


def _file_size_limit(limit_bytes: int):
    def apply() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return apply


def test_a_full_disk_stops_the_recording_cleanly_and_keeps_the_data(tmp_path):
    """The file-size limit makes every write past 150 MB (a few seconds) fail as a full disk does. The
    recording asks for far longer than that takes: on a busy machine the simulated rig renders fewer
    frames a second, and a 20 s recording ended whole under the limit (2026-12-06)."""
    out = tmp_path / "full.h5"
    run = subprocess.run([sys.executable, "-m", "app", "record", "-o", str(out), "--seconds", "300"],
                         preexec_fn=_file_size_limit(150_000_000), capture_output=True, text=True, timeout=400)
    assert run.returncode == 1, run.stderr
    assert "the recording stopped" in run.stderr and f"photopft recover {out}" in run.stderr
    assert "Traceback" not in run.stderr
    kept = recover_session(out).kept
    assert validate_session(out) == []
    with SessionFile(out) as s:
        for head in ("front", "back"):
            assert kept[head] > 80 and s.frames(head)[kept[head] - 1].max() > 0
            assert np.all(np.diff(s.frame_id(head).astype(int)) >= 1)
        assert kept["flow"] > 500
