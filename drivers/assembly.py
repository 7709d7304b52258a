"""The rig assembled from its configuration: cameras, sequencer, flow sensor, and the calibrations
in force. One place for the simulated rig and the real one, used by `record`, the live engine
and the wizards, so that every recording's /rig holds the lights and flow line the operator saw.
"""

from __future__ import annotations

import sys
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path

from core.calibration.rig_profile import load_profile as load_lights
from core.calibration.spirometer import CalibrationProfileError, FlowCalibration, load_profile as load_flow
from core.rig import Rig
from drivers.camera import AravisCamera, bandwidth_advice
from drivers.flowsensor import FlowSensor, FlowSensorEmulator
from drivers.light_phase import LightPhase
from drivers.rig import RigConfig, camera_head
from drivers.sequencer import Sequencer, SequencerEmulator
from drivers.simulated import SimCamera, SimFlowSensor, SimulatedRigState


@dataclass
class AssembledRig:
    rig: Rig  # with the light calibration in force applied
    cameras: dict
    flow: object | None
    flow_calibration: tuple[float, float] | None  # gain L/s per count, offset L/s (thesis eq. 5.4)
    lights: LightPhase
    simulated: object | None = None  # drivers.simulated.SimulatedRigState on the simulated rig
    lights_from: str = ""  # where the lights in force come from, in words for the status and the report
    flow_from: str = ""


# The simulated rig's LEDs as built: each this far from the drawing (a random direction) and its intensity
# 1 +- the spread, as the population bench's rigs are; a sphere calibration finds them
SIMULATED_LED_OFFSET_MM = 8.0
SIMULATED_LED_INTENSITY_SPREAD = 0.1


def simulated_rig_config(heads: tuple[str, ...] = ("front", "back"), scale: float = 0.25, seed: int = 1,
                         protocol: str = "tidal", seconds: float = 1800.0, frame_rate_hz: float = 110.0):
    """The simulated rig's scene (core.sim.simulate.SimConfig): the subject, and the heads and LEDs as built,
    which the sphere wizard's simulated captures share (simulated_sphere_config)."""
    # the simulator (numba kernels) only where the simulated rig needs it
    from core.sim.breathing import Subject, Sway
    from core.sim.simulate import SimConfig

    return SimConfig(scene="torso", protocol=protocol, seconds=seconds, scale=scale, seed=seed, heads=heads,
                     frame_rate_hz=frame_rate_hz, sway=Sway(seed=seed), subject=Subject(),
                     led_offset_mm=SIMULATED_LED_OFFSET_MM, led_intensity_spread=SIMULATED_LED_INTENSITY_SPREAD)


def simulated_sphere_config(rig_config, index: int, radius_mm: float, finish: str = "specular"):
    """One placement of the sphere wizard's simulated sphere (index 0: the centre of the view) on the
    simulated rig whose scene is `rig_config` (simulated_rig_config): the same heads and LEDs as built,
    so the lights it calibrates are the lights that then run."""
    return replace(rig_config, scene=f"{finish}-sphere", protocol="static", seconds=None, sway=None,
                   placement_only=index, sphere_radius_mm=radius_mm)


def simulated_rig(heads: tuple[str, ...] = ("front", "back"), scale: float = 0.25, seed: int = 1,
                  protocol: str = "tidal", seconds: float = 1800.0, frame_rate_hz: float = 110.0,
                  loop_cycles: int = 0, with_flow: bool = True, lights_known: bool = False) -> AssembledRig:
    """The simulated rig breathing a simulated subject; the reconstruction's lights those of the drawing
    (its LEDs as built lie SIMULATED_LED_OFFSET_MM off them) until a calibration is applied, or with
    `lights_known` the LEDs as built (a perfect sphere calibration: benches and tests of what comes
    after it). `loop_cycles`: that many light cycles rendered once and delivered over and over
    (drivers/simulated.py)."""
    config = simulated_rig_config(heads, scale, seed, protocol, seconds, frame_rate_hz)
    state = SimulatedRigState.build(config)
    cameras = {h: SimCamera(state, h, loop_cycles=loop_cycles) for h in heads}
    model = config.flow_sensor
    rig = state.rig
    if lights_known:
        rig = replace(rig, heads={n: replace(h, light_positions_mm=state.heads[n].light_positions_mm,
                                             light_intensity=state.heads[n].light_intensity)
                                  for n, h in rig.heads.items()})
    return AssembledRig(rig, cameras, SimFlowSensor(state) if with_flow else None,
                        (model.gain_lps, model.offset_lps), LightPhase(rig), simulated=state,
                        lights_from="the simulated rig's LEDs as built (known, as a perfect calibration)"
                        if lights_known else "the simulated rig's drawing (not calibrated: LEDs as built lie off it)",
                        flow_from="the simulated flow sensor's own line (not calibrated)")


def hardware_rig(config: RigConfig, stack: ExitStack) -> AssembledRig:
    """The rig's cameras, flow sensor and sequencer, opened and configured; the sequencer armed,
    started by the returned LightPhase once the cameras wait for its triggers."""
    settings = config.camera
    cameras, heads = {}, {}
    for head, identifier in config.cameras.items():
        camera = AravisCamera(identifier, name=f"{head} ({identifier})")
        stack.callback(camera.close)
        camera.configure(settings)
        _, _, width, height = camera.region()
        advice = bandwidth_advice(width, height, 8 if settings.pixel_format == "Mono8" else 12, settings.frame_rate_hz)
        if advice:
            print(f"warning: {head} camera: {advice}", file=sys.stderr)
        cameras[head] = camera
        heads[head] = camera_head(head, config.optics.get(head, {}), camera.sensor_size, camera.region(),
                                  settings.binning, 8 if settings.pixel_format == "Mono8" else 12)
    rig = Rig(config.name, heads, frame_rate_hz=settings.frame_rate_hz, mains_hz=config.mains_hz)
    port = config.sequencer_port
    sequencer = None
    if port != "sim":
        if port == "emulator":
            emulator = stack.enter_context(SequencerEmulator())
            port = emulator.port
        sequencer = Sequencer(port)
        stack.callback(sequencer.close)
        sequencer.configure(rig.sequence, int(settings.exposure_us), settings.frame_rate_hz)
        sequencer.arm()
        stack.callback(sequencer.stop)
    flow = None
    if config.flow_port is not None:
        port = config.flow_port
        if port == "emulator":
            emulator = stack.enter_context(FlowSensorEmulator())
            port = emulator.port
        flow = FlowSensor(port)
        stack.callback(flow.close)
    calibration = (config.flow_gain_lps, config.flow_offset_lps) if config.flow_gain_lps is not None else None
    return AssembledRig(rig, cameras, flow, calibration, LightPhase(rig, first_trigger=0, sequencer=sequencer),
                        lights_from="the rig file's drawing (not calibrated: run the sphere calibration)",
                        flow_from=f"the rig file of {config.name}" if calibration else "")


def assemble_rig(config: RigConfig, stack: ExitStack, scale: float | None = None, seconds: float = 1800.0,
                 light_profile: Path | None = None, flow_profile: Path | None = None,
                 loop_cycles: int = 0) -> AssembledRig:
    """The rig a configuration names, with the calibrations in force: `light_profile` and
    `flow_profile` (the calibration wizards' profiles in force), else the rig file's own
    `calibration` and flow line. Raises ProfileError or CalibrationProfileError for a profile that
    cannot be used, the device errors for a device that cannot be opened."""
    if config.simulated:
        sim = config.simulation
        assembled = simulated_rig(tuple(config.cameras), scale or float(sim.get("scale", 0.25)),
                                  int(sim.get("seed", 1)), sim.get("protocol", "tidal"), seconds,
                                  config.camera.frame_rate_hz, loop_cycles,
                                  with_flow=config.flow_port is not None)
    else:
        assembled = hardware_rig(config, stack)
    lights = light_profile or config.calibration
    if lights is not None:
        profile = load_lights(lights)
        assembled.rig = assembled.lights.rig = profile.apply(assembled.rig)
        assembled.lights_from = f"{Path(lights).name} of {profile.created[:16].replace('T', ' ')}"
    if flow_profile is not None and assembled.flow is not None:
        flow = load_flow(flow_profile)
        if not isinstance(flow, FlowCalibration):
            raise CalibrationProfileError(f"{flow_profile}: a volume calibration, not a flow sensor's")
        assembled.flow_calibration = (flow.gain_lps, flow.offset_lps)
        assembled.flow_from = f"{Path(flow_profile).name} of {flow.created[:16].replace('T', ' ')}"
    return assembled
