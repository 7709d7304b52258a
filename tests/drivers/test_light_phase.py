"""Which light lit each frame (drivers/light_phase.py): the trigger count, confirmed by the images."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from core.io.session import SessionFile, SubjectRecord
from core.sim.simulate import SimConfig
from drivers.camera import CameraStats, Frame
from drivers.light_phase import LightPhase, LightPhaseError
from drivers.recorder import Recorder
from drivers.simulated import SimCamera, SimulatedRigState


@pytest.fixture(scope="module")
def state() -> SimulatedRigState:
    return SimulatedRigState.build(SimConfig(protocol="tidal", seconds=30.0, scale=0.1, seed=2))


class JoinedCamera:
    """A simulated head whose camera joined the running sequence at trigger `joined_at` and numbers
    its frames as a GigE Vision camera does (block ids from 1), losing the frames in `lost` (by
    trigger). `lights` holds the true light of each delivered frame id."""

    def __init__(self, state: SimulatedRigState, head: str, joined_at: int, lost: set[int] = frozenset()) -> None:
        self.inner = SimCamera(state, head, realtime=False)
        self.joined_at, self.lost = joined_at, set(lost)
        self.sequence = state.rig.sequence
        self.lights: dict[int, int] = {}
        self.stats = CameraStats()
        self.name = head

    def configure(self, settings) -> None:
        pass

    def start(self) -> None:
        self.inner.start()
        self.inner._next = self.joined_at

    def grab(self, timeout_s: float = 0.5) -> Frame | None:
        frame = self.inner.grab(timeout_s)
        while frame.frame_id in self.lost:
            frame = self.inner.grab(timeout_s)
        block_id = frame.frame_id - self.joined_at + 1
        self.lights[block_id] = self.sequence[frame.frame_id % len(self.sequence)]
        out = Frame(frame.image, block_id, frame.timestamp_ns)
        self.stats.count(out)
        return out

    def stop(self) -> None:
        self.inner.stop()

    def close(self) -> None:
        self.inner.close()


def _feed(phase: LightPhase, camera: JoinedCamera, head: str, frames: int) -> list[Frame]:
    out = []
    for _ in range(frames):
        frame = camera.grab()
        phase.observe(head, frame.frame_id, frame.image)
        out.append(frame)
    return out


def test_the_trigger_count_gives_each_frame_its_light_and_a_lost_frame_is_a_gap(state):
    assert state.rig.sequence == (0, 1, 2, 3, -1)
    phase = LightPhase(state.rig, first_trigger=7)  # the head's first frame (id 100) was trigger 7
    lights = [phase.light_of("front", i) for i in (100, 101, 102, 104, 105, 106)]  # frame 103 lost
    assert lights == [2, 3, -1, 1, 2, 3]


@pytest.mark.parametrize("joined_at", [1, 2, 3, 4, 5 * 11 + 3])
def test_a_camera_that_joined_mid_sequence_is_realigned_by_its_images(state, joined_at):
    """The counted phase says the first frame was trigger 0; the camera joined later, and lost
    frames on the way: the first check, before anything is recorded, puts every light right."""
    camera = JoinedCamera(state, "front", joined_at, lost={joined_at + 7, joined_at + 13, joined_at + 14})
    phase = LightPhase(state.rig, first_trigger=0)
    camera.start()
    frames = _feed(phase, camera, "front", 60)
    assert phase.ready("front")
    assert [phase.light_of("front", f.frame_id) for f in frames] == [camera.lights[f.frame_id] for f in frames]
    assert any("realigned at the start" in n for n in phase.summary())


def test_a_phase_that_is_right_is_confirmed_and_says_nothing(state):
    camera = JoinedCamera(state, "back", joined_at=0)
    phase = LightPhase(state.rig, first_trigger=0)
    camera.start()
    frames = _feed(phase, camera, "back", 40)
    assert [phase.light_of("back", f.frame_id) for f in frames] == [camera.lights[f.frame_id] for f in frames]
    assert phase.summary() == []


def test_a_phase_that_slips_mid_recording_is_realigned_and_said(state):
    """A frame counted twice (the phase slips by one) is found within a few cycles and realigned."""
    camera = JoinedCamera(state, "front", joined_at=0)
    phase = LightPhase(state.rig, first_trigger=0)
    camera.start()
    _feed(phase, camera, "front", 30)
    camera.joined_at -= 1  # from here each block id is one more than the trigger says
    frames = _feed(phase, camera, "front", 60)
    assert [phase.light_of("front", f.frame_id) for f in frames[-15:]] == [camera.lights[f.frame_id]
                                                                            for f in frames[-15:]]
    assert any("realigned there" in n for n in phase.summary())


def test_leds_wired_in_another_order_stop_with_the_reason(state):
    """The rig says LED 0 is at the upper left; the images show it lighting from the lower right."""
    head = state.rig.heads["front"]
    swapped = replace(head, light_positions_mm=head.light_positions_mm[[2, 1, 0, 3]])
    rig = replace(state.rig, heads={"front": swapped})
    camera = JoinedCamera(state, "front", joined_at=0)
    phase = LightPhase(rig, first_trigger=0)
    camera.start()
    with pytest.raises(LightPhaseError, match="images show the LEDs firing as"):
        _feed(phase, camera, "front", 20)


def test_images_that_cannot_tell_leave_the_counted_phase_and_say_so(state):
    """A test pattern (or nobody in front of the head): no dark frame stands out."""
    rng = np.random.default_rng(1)
    phase = LightPhase(state.rig, first_trigger=3)
    for frame_id in range(1, 41):
        phase.observe("front", frame_id, rng.integers(100, 110, size=(64, 64)).astype(np.uint16))
    assert phase.ready("front")
    assert phase.light_of("front", 1) == state.rig.sequence[3]
    assert any("could not confirm the light phase" in n for n in phase.summary())


def test_the_recorder_writes_the_lights_the_images_confirm(state, tmp_path):
    """Recorded from a camera that joined at trigger 3 and lost frames: every frame's light in
    the file is the light that lit it."""
    camera = JoinedCamera(state, "front", joined_at=3, lost={9, 10, 30})
    rig = replace(state.rig, heads={"front": state.rig.heads["front"]}, baseline_mm=None)
    recorder = Recorder(tmp_path / "joined.h5", rig, {"front": camera}, LightPhase(rig, first_trigger=0),
                        subject=SubjectRecord("P-1", "male", 30, 175, 75), kind="simulation")
    summary = recorder.run(0.5)
    assert summary.problems == [] and any("realigned at the start" in n for n in summary.notices)
    with SessionFile(tmp_path / "joined.h5") as session:
        ids = session.frame_id("front").astype(int)
        assert len(ids) > 20
        np.testing.assert_array_equal(session.light_index("front"), [camera.lights[i] for i in ids])
