"""The simulated rig's devices: cameras that render the simulated subject, and its flow sensor.

They behave like the real ones in time: frames and samples come at their rate on the session
clock (paced in real time by default), with frame ids and sample counters.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from core.analysis.reference import ReferenceUnavailable, reference
from core.rig import thesis_rig
from drivers.camera import CameraSettings, CameraStats, Frame, frame_due_within
from drivers.flowsensor import FlowBlock


@dataclass
class SimulatedRigState:
    """What the simulated devices share: the scene, the heads as built, the clock's start."""

    config: object  # core.sim.simulate.SimConfig
    rig: object  # core.rig.Rig
    scene: object
    heads: dict
    digitisers: dict
    start_ns: int
    waveform: object = None  # core.sim.breathing.Waveform of a torso scene

    @classmethod
    def build(cls, config, realtime_start_ns: int | None = None) -> "SimulatedRigState":
        # the simulator (numba kernels) only where the simulated rig needs it
        from core.sim.simulate import as_built_heads, build_scene, sim_digitisers

        rig = replace(thesis_rig(config.scale, tuple(config.heads), config.bit_depth, config.frame_rate_hz),
                      mains_hz=config.mains_hz)
        scene, waveform = build_scene(config, rig)
        if len(rig.heads) == 2:
            rig = replace(rig, baseline_mm=float(scene.baseline_mm))
        heads = as_built_heads(rig, config)
        digitisers = sim_digitisers(config, rig)
        return cls(config, rig, scene, heads, digitisers, realtime_start_ns or time.monotonic_ns(), waveform)

    def now_s(self) -> float:
        return (time.monotonic_ns() - self.start_ns) / 1e9

    def follow(self, sex: str, age_years: float, height_cm: float, weight_kg: float, subject_id: str = "") -> None:
        """The simulated subject becomes the registered patient: sex, age, height and weight, and lung
        volumes at the GLI Global predicted values the report uses, so a demonstration reads near
        100 % of predicted; the quiet breathing is theirs from half a second on. The body's shape
        stays the one the scene was built with."""
        # the simulator (numba kernels) only where the simulated rig needs it
        from core.sim.breathing import Subject, tidal

        age = min(max(float(age_years), 3.0), 100.0)
        height = min(max(float(height_cm), 90.0), 230.0)
        try:
            fvc = reference("FVC", sex, age, height).predicted
            fev1 = reference("FEV1", sex, age, height).predicted
        except ReferenceUnavailable:  # outside the equations' range: the simulator's own predictions
            fvc = fev1 = None
        subject = Subject(id=subject_id or self.config.subject.id, sex=sex, age_years=age, height_cm=height,
                          weight_kg=float(weight_kg), fvc_l=fvc, fev1_l=fev1)
        self.config = replace(self.config, subject=subject)
        if self.waveform is not None:
            rng = np.random.default_rng(self.config.seed + int(self.now_s() * 1000))
            quiet = tidal(subject, 600.0, rng)
            self.waveform.splice(self.now_s() + 0.5, quiet[:1], quiet[1:])

    def perform(self, manoeuvre: str, blow=None) -> float:
        """The simulated subject does what the operator asks, from now: "vc" (slow vital capacity)
        or "forced" (a forced expiration, `blow` a core.sim.breathing.ForcedBlow), then breathes quietly.
        Returns the seconds until the manoeuvre is over."""
        # the simulator (numba kernels) only where the simulated rig needs it
        from core.sim.breathing import RATE_HZ, ForcedBlow, forced, slow_vc, tidal

        if self.waveform is None:
            raise ValueError("this simulated scene does not breathe")
        rng = np.random.default_rng(self.config.seed + int(self.now_s() * 1000))
        subject = self.config.subject
        if manoeuvre == "vc":
            samples, _ = slow_vc(subject, rng, lead_count=0)
        elif manoeuvre == "forced":
            samples, _ = forced(subject, blow or ForcedBlow(), rng, lead_count=0)
        else:
            raise ValueError(f"unknown manoeuvre {manoeuvre!r}: vc or forced")
        self.waveform.splice(self.now_s() + 0.3, samples, tidal(subject, 600.0, rng))
        return 0.3 + len(samples) / RATE_HZ


# How far a simulated camera's frames may fall behind the clock before it skips ahead. A real
# camera keeps time and drops what it cannot deliver; a renderer slower than the frame rate (scale
# 0.5 on two cores, or 0.25 on a busy machine) would otherwise stamp its frames ever further in the
# past, away from the flow sensor's samples and the operator's event marks, and the live view's
# optical curve would drift out of the window the flow sensor's curve sets. Skipped frames are
# lost frames (gaps in the ids), as on a real rig.
MAX_LAG_S = 0.1


@dataclass
class SimCamera:
    """A head of the simulated rig behind the Camera protocol.

    `loop_cycles`: render that many light cycles once, at start, and deliver them over and over at
    the rig's rate (ids and timestamps run on). For measuring the recorder at a rate the renderer
    cannot reach on the same cores; the images repeat, so such a recording is not for reconstruction.
    """

    state: SimulatedRigState
    head: str
    realtime: bool = True
    loop_cycles: int = 0
    name: str = ""
    stats: CameraStats = field(default_factory=CameraStats)

    def __post_init__(self) -> None:
        self.name = self.name or f"sim-{self.head}"
        self._next = 0
        self._running = False
        self._loop: list[np.ndarray] = []

    def configure(self, settings: CameraSettings) -> None:
        """The simulated sensor keeps the rig's size and rate; settings are accepted as given."""

    def start(self) -> None:
        if self.loop_cycles and not self._loop:
            self._loop = [self._render(i) for i in range(self.loop_cycles * self.state.rig.cycle_length)]
        self._running = True

    def _render(self, i: int) -> np.ndarray:
        # the simulator (numba kernels) only where the simulated rig needs it
        from core.sim.scene import noise_key

        s = self.state
        head = s.heads[self.head]
        light = s.rig.sequence[i % s.rig.cycle_length]
        image, _ = s.scene.render(head, i / s.rig.frame_rate_hz, light,
                                  noise_key(s.config.noise_draw, self.head, i, head.width * head.height), s.digitisers[self.head])
        return image

    def grab(self, timeout_s: float = 0.5) -> Frame | None:
        if not self._running:
            return None
        s = self.state
        period_ns = 1e9 / s.rig.frame_rate_hz
        due = s.start_ns + int(round(self._next * period_ns))
        if self.realtime:
            now = time.monotonic_ns()
            n = s.rig.cycle_length
            if now - due > MAX_LAG_S * 1e9 and self._next % n == 0:
                # Behind: skip to the light cycle under way, as a camera drops frames; whole cycles
                # only, so that a renderer slower than the rig still delivers complete cycles to
                # reconstruct (one frame skipped here and there would leave none).
                self._next = int((now - s.start_ns) // period_ns) // n * n
                due = s.start_ns + int(round(self._next * period_ns))
            if not frame_due_within((due - now) / 1e9, timeout_s):
                return None
        i = self._next
        image = self._loop[i % len(self._loop)] if self._loop else self._render(i)
        self._next += 1
        frame = Frame(image, i, due)
        self.stats.count(frame)
        return frame

    def stop(self) -> None:
        self._running = False

    def close(self) -> None:
        self.stop()


@dataclass
class SimFlowSensor:
    """The simulated pneumotachometer: the subject's true flow through the sensor model, 1000 samples/s."""

    state: SimulatedRigState
    realtime: bool = True

    def __post_init__(self) -> None:
        self.model = self.state.config.flow_sensor
        self._next = 0
        self.lost_samples = 0

    @property
    def sample_rate_hz(self) -> float:
        return self.model.sample_rate_hz

    def start(self) -> None:
        self._next = 0

    def read(self) -> FlowBlock:
        now = time.monotonic_ns()
        rate = self.model.sample_rate_hz
        due = int((now - self.state.start_ns) * rate / 1e9) if self.realtime else self._next + 100
        counter = np.arange(self._next, max(self._next, due), dtype=np.int64)
        self._next = int(counter[-1]) + 1 if len(counter) else self._next
        t = counter / rate
        adc = self.model.adc_counts(self.state.scene.truth_flow_lps(t), t, self.state.config.seed + int(self._next))
        stamps = self.state.start_ns + np.round(counter * 1e9 / rate).astype(np.int64)
        return FlowBlock(adc, counter, stamps, 0)

    def stop(self) -> None:
        pass

    def close(self) -> None:
        pass
