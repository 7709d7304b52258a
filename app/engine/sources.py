"""Where the live engine's frames come from: the rig's cameras (simulated or real, with the calibrations
in force) or a recorded session played back (drivers/replay.py)."""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from app.calibration_store import in_force
from core.io.session import SessionError, SessionFile
from core.rig import Rig
from drivers.assembly import assemble_rig, simulated_rig
from drivers.light_phase import LightPhase, RecordedLights
from drivers.replay import FileCamera, FileFlow, ReplayClock
from drivers.rig import load_rig_config


@dataclass
class Source:
    """Where frames come from: the rig's cameras (simulated or real) or a recorded file."""
    rig: Rig
    cameras: dict
    flow: object | None
    lights: LightPhase | RecordedLights  # which light lit each frame (drivers/light_phase.py)
    flow_calibration: tuple[float, float] | None
    name: str
    conditions: str = "ATPS"
    room: tuple[float, float, float] = (23.0, 1013.0, 50.0)  # temperature C, pressure hPa, humidity %
    replay: bool = False
    closers: list[Callable[[], None]] = field(default_factory=list)
    simulated: object | None = None  # drivers.simulated.SimulatedRigState: a subject that follows prompts
    compression: str = "blosc-lz4"  # the frames' lossless filter when recording (the rig file's [recording])
    calibration: str = ""  # the calibrations in force, in words (drivers/assembly.py)
    flow_from: str = ""  # where the flow line in force comes from (drivers/assembly.py)
    replay_clock: ReplayClock | None = None  # a replay's position, pause and seek


def simulated_source(scale: float = 0.25, heads: tuple[str, ...] = ("front", "back"), seed: int = 1,
                     protocol: str = "tidal", seconds: float = 1800.0, loop_cycles: int = 0) -> Source:
    """The simulated rig, breathing quietly, its LEDs as built known (a perfect sphere calibration) and
    its flow sensor as built (benches and tests; the application opens it through rig_source, with the
    calibrations in force).
    `loop_cycles`: that many light cycles rendered once and delivered over and over
    (drivers/simulated.py), for measuring the live view at a rate the renderer cannot reach on the
    same cores."""
    return _source(simulated_rig(heads, scale, seed, protocol, seconds, loop_cycles=loop_cycles, lights_known=True),
                   f"simulated rig (scale {scale:g})")


def _source(assembled, name: str, closers: list | None = None) -> Source:
    return Source(assembled.rig, assembled.cameras, assembled.flow, assembled.lights, assembled.flow_calibration,
                  name, closers=closers or [], simulated=assembled.simulated,
                  calibration=f"lights: {assembled.lights_from}"
                  + (f"; flow sensor: {assembled.flow_from}" if assembled.flow_from else ""),
                  flow_from=assembled.flow_from)


def replay_source(path: str | Path, speed: float = 1.0) -> Source:
    """A recorded session played through the live view at real speed (or `speed` times it)."""
    session = SessionFile(path)
    recorded = [h for h in session.heads if session.n_frames(h)]
    if not recorded:
        session.close()
        raise SessionError(f"{path} holds no camera frame to replay")
    first = int(min(session.timestamp_ns(h)[0] for h in recorded))
    last = int(max(session.timestamp_ns(h)[-1] for h in recorded))
    clock = ReplayClock(first, speed, last)
    cameras = {h: FileCamera(session, h, clock) for h in session.heads}
    lights = {h: dict(zip(session.frame_id(h).tolist(), session.light_index(h).tolist())) for h in session.heads}
    flow = FileFlow(session, clock) if session.flow is not None and session.flow.gain_lps is not None else None
    calibration = (session.flow.gain_lps, session.flow.offset_lps) if flow is not None else None
    conditions = session.flow.conditions if session.flow is not None else "ATPS"
    room = (23.0, 1013.0, 50.0)
    if session.flow is not None:
        a = session.flow.attrs
        room = (float(a.get("room_temperature_c", 23.0)), float(a.get("room_pressure_hpa", 1013.0)),
                float(a.get("room_humidity_pct", 50.0)))
    source = Source(session.rig, cameras, flow, RecordedLights(lights),
                    calibration, f"replay of {Path(path).name}" + (f" at {speed:g}x" if speed != 1 else ""),
                    conditions, room, replay=True, closers=[session.close])
    source.replay_clock = clock
    return source


def rig_source(config_path: str | Path | None = None, scale: float | None = None) -> Source:
    """The rig a configuration names (resources/rigs/simulated.toml by default), with the
    calibration profiles in force for it (app/calibration_store.py)."""
    config = load_rig_config(config_path)
    profiles = in_force(config.name)
    stack = ExitStack()
    try:
        assembled = assemble_rig(config, stack, scale, light_profile=profiles.lights, flow_profile=profiles.flow)
    except Exception:
        stack.close()
        raise
    name = (f"{config.name} (simulated, scale {scale or float(config.simulation.get('scale', 0.25)):g})"
            if config.simulated else config.name)
    source = _source(assembled, name, [stack.close])
    source.compression = config.compression
    return source
