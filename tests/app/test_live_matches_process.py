"""What the operator sees is what the report says: a recorded session replayed through the live engine
gives the metric volume `photopft process` writes for it, from the same code path (cycle assembly,
binning, motion compensation, reconstruction, displacement tracking). The live view is causal (its
distances smoothed by what it has seen so far) and reconstructs the newest cycle when it falls
behind, so the curves agree within tens of mL, not to the digit."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from app.engine.live_rig import LiveRig
from app.engine.sources import replay_source
from core.analysis.optical_litres import POPULATION_GAIN
from core.io.session import SessionFile
from core.pipeline.process import process_session
from core.sim.breathing import Sway
from core.sim.simulate import SimConfig, simulate
from tests.waiting import wait_until

pytestmark = pytest.mark.slow


def test_the_live_volume_is_the_processed_volume(tmp_path):
    session = tmp_path / "s.h5"
    simulate(session, SimConfig(protocol="tidal", seconds=4.0, scale=0.1, seed=3, flow_sensor=None))
    process_session(session, tmp_path / "r.h5", workers=1)
    with h5py.File(tmp_path / "r.h5") as f, SessionFile(session) as s:
        first = min(int(s.timestamp_ns(h)[0]) for h in s.heads)
        processed_t = (f["metric_volume/timestamp_ns"][:] - first) / 1e9
        processed = f["metric_volume/volume_l"][:]
    # played at half speed: on a loaded machine (the CI's two test workers beside it) the engine made
    # 25 maps in 4 s at full speed; the comparison is of the path, not of the rate
    snapshot = replayed(session)
    # the checks `process` makes on the skin's shading and the maps' sides pass live too
    assert snapshot.optical_checked and snapshot.optical_refused is None
    settled = snapshot.metric_t_s > 0.5  # both heads' first maps in, the live distance settled
    live = snapshot.metric_volume_l[settled] / POPULATION_GAIN  # no calibration: the live estimate
    assert len(live) >= 30, len(live)  # a good share of the 4 s session's 88 cycles a head
    on_live_times = np.interp(snapshot.metric_t_s[settled], processed_t, processed)
    difference = (live - live.mean()) - (on_live_times - on_live_times.mean())
    # measured at half speed (2026-11-26): r 0.998, slope 1.00, rms 16 mL of a 1.04 L swing (104 live maps
    # after 0.5 s). On 2026-11-29 (the same session's processed volume now swings 0.62 L): r 0.996-0.997,
    # slope 1.05-1.08 on an idle machine (114-185 live maps; the processed volume 1.005 of the truth,
    # the live 1.05), 1.10 in CI beside the other worker: the live view's causal scale reads a few per
    # cent high on this torso, as `bench live` finds (docs/benchmarks.md, slope 1.04-1.06 against the truth)
    assert np.corrcoef(live, on_live_times)[0, 1] > 0.97
    assert 0.9 < np.polyfit(on_live_times, live, 1)[0] < 1.15
    assert np.sqrt(np.mean(difference ** 2)) < 0.06


def replayed(session, speed: float = 0.5):
    """The live engine's last snapshot of a whole replay of `session`."""
    with SessionFile(session) as s:
        last_ids = {h: int(s.frame_id(h)[-1]) for h in s.heads}
        cycle = s.rig.cycle_length
    rig = LiveRig(replay_source(session, speed=speed))
    rig.start()
    try:
        wait_until(lambda: rig.snapshot().replay_finished, 60, "the replay's end")
        # the reconstruction has caught up with the replay's last cycles
        wait_until(lambda: all(v.frame_id is not None and v.frame_id >= last_ids[h] - 2 * cycle
                               for h, v in rig.snapshot().heads.items()), 30, "the last cycles' maps")
        return rig.snapshot()
    finally:
        rig.stop()


def test_the_live_view_says_when_the_skin_does_not_follow_the_light_model(tmp_path):
    """Skin with a sheen (0.2 of white), which `process` refuses (tests/core/test_reconstruction.py):
    the live engine says so while the session runs, with the same reason."""
    session = tmp_path / "glossy.h5"
    simulate(session, SimConfig(protocol="tidal", seconds=3.0, scale=0.1, specular=0.2, clothing="skin",
                                flow_sensor=None, sway=Sway(0, 0, 0)))
    snapshot = replayed(session)
    assert snapshot.optical_checked
    assert "a sheen on the skin" in snapshot.optical_refused.reason, snapshot.optical_refused
