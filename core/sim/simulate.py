"""Simulate a whole session: build the rig and scene, render every frame, write the session file."""

from __future__ import annotations

import json
import queue
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from core.io.outputs import atomic_output, stop_if_requested
from core.rig import DARK, Head, Rig, thesis_rig
from core.io.session import SessionWriter, SubjectRecord
from core.sim import shapes
from core.sim.bodies import Body, body_surfaces
from core.sim.textures import fitzpatrick_albedo
from core.sim.breathing import MOUTHPIECE_OFF, RATE_HZ, ForcedBlow, Subject, Sway, Waveform, protocol_waveform
from core.sim.flowsensor import FlowSensorModel
from core.sim.makehuman import MeshBody, load_mesh_data
from core.sim.mesh_scene import MeshScene
from core.sim.render import CameraModel
from core.sim.surfaces import HeightField, mode_volumes_mm3, stretched_volume_mm3
from core.sim.scene import Digitiser, HeightFieldScene, Scene, SpherePlacement, SphereScene, noise_key

SCENES = ("torso", "plane", "vase", "relief", "sphere", "specular-sphere", "matte-sphere")
CALIBRATION_SCENES = ("specular-sphere", "matte-sphere")
CLOCK_START_NS = 1_000_000_000  # the session clock's value at the first frame
TRUTH_RATE_HZ = 200.0


@dataclass
class SimConfig:
    """Everything that defines a simulated session; defaults are the thesis rig and a healthy adult."""

    scene: str = "torso"
    # None: our own torso (shapes.torso); else a parametric body (core/sim/bodies.py) or a mesh body
    # of the test population (core/sim/makehuman.py)
    body: Body | MeshBody | None = None
    protocol: str = "full"
    seconds: float | None = None  # None: the protocol's natural length
    scale: float = 0.25
    seed: int = 1
    rig_seed: int | None = None  # draws the LEDs as built (None: seed); one rig for its calibration and its subjects
    noise_seed: int | None = None  # the camera noise's draw (None: seed); the rest of the scene keeps `seed`
    heads: tuple[str, ...] = ("front", "back")
    distance_mm: float = 2000.0  # front camera to the surface on its optical axis, at rest
    distance_back_mm: float = 2000.0
    sway: Sway | None = None  # None: the scene's default (torso: 50 mm axial, 15 mm lateral)
    subject: Subject = field(default_factory=Subject)
    blows: list[ForcedBlow] | None = None
    camera: CameraModel = field(default_factory=CameraModel)
    bit_depth: int = 12
    frame_rate_hz: float = 110.0
    clothing: str = "tshirt"
    specular: float = 0.0
    led_offset_mm: float = 0.0  # as built: each LED this far (random direction) from the drawing
    led_intensity_spread: float = 0.0  # as built: relative intensities 1 +- this (uniform)
    led_mu: float = 0.0  # LED anisotropy exponent (0: isotropic), axes along the optical axis
    led_mu_spread: float = 0.0  # as built: each LED's exponent led_mu +- this (uniform)
    led_tilt_deg: float = 0.0  # as built: each LED's axis up to this far from the optical axis
    led_drift: float = 0.0  # thermal drift: each LED's intensity 1 +- this, over periods of 3-10 minutes
    # the rig's time at the recording's first frame (s): its LEDs' drift and the room light go on from
    # there, so recordings made one after another on one rig (a wizard's captures) see one drift
    rig_clock_s: float = 0.0
    ambient_flicker: float = 0.0  # room light modulated +- this at twice the mains frequency
    mains_hz: float = 50.0
    lens_k1: float = 0.0  # radial distortion (OpenCV k1) of every camera; written to /rig, as a calibrated lens
    vignetting: float = 0.0  # the lenses' light loss at the corners; written to /rig, as a calibrated lens
    steps: int = 0  # the subject steps 20-50 mm (within 0.5 s) this many times
    arm_swing_mm: float = 0.0  # a body's arms move sideways by up to this (slowly), hiding and showing its sides
    skin_type: int | None = None  # Fitzpatrick I-VI of a body's bare skin (None: albedo 0.45)
    # a body's trunk stretched sideways as it breathes (its silhouette widens); False: its sides' motion
    # is a height change, cut near the sides, and the silhouette stays put (core/sim/bodies.py)
    widening: bool = False
    flow_sensor: FlowSensorModel | None = field(default_factory=FlowSensorModel)
    drop_rate: float = 0.0  # fraction of frames lost on the way (gaps in frame_id)
    # crossed linear polarisers on the LEDs and the lenses (polarised_camera, POLARISER_EXTINCTION): the
    # skin's surface reflection cut, every light dimmer; the sphere sessions are recorded with the lens's
    # polariser turned parallel, and render as without
    polarisers: bool = False
    truth_maps_at: list[int] | None = None  # frame indices; None: five spread over the session
    grid_step_mm: float = 1.0
    sphere_radius_mm: float = 75.0
    placements: int = 7
    placement_only: int | None = None  # render only this placement (one capture of a calibration wizard)
    placement_cycles: int = 3
    created: str | None = None
    compression: str | None = None

    @property
    def noise_draw(self) -> int:
        """The seed of the camera noise: noise_seed when given, else seed."""
        return self.seed if self.noise_seed is None else self.noise_seed


@dataclass
class SimSummary:
    path: Path
    frames: dict[str, int]
    lost: dict[str, int]
    duration_s: float
    elapsed_s: float
    truth_volume_range_l: tuple[float, float]
    flow_samples: int


def as_built_heads(rig: Rig, config: SimConfig) -> dict[str, Head]:
    """The heads as built: LEDs off their drawn positions and intensities, as the config says."""
    rng = np.random.default_rng((config.seed if config.rig_seed is None else config.rig_seed) + 41)
    out = {}
    for name, head in rig.heads.items():
        positions = head.light_positions_mm.copy()
        if config.led_offset_mm > 0:
            directions = rng.standard_normal((4, 3))
            directions /= np.linalg.norm(directions, axis=1, keepdims=True)
            positions = positions + config.led_offset_mm * directions
        intensity = 1.0 + config.led_intensity_spread * rng.uniform(-1, 1, 4)
        axis = mu = None
        if config.led_mu > 0:
            tilt = np.radians(config.led_tilt_deg) * rng.uniform(0, 1, 4)
            azimuth = rng.uniform(0, 2 * np.pi, 4)
            axis = np.column_stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)])
            mu = config.led_mu + config.led_mu_spread * rng.uniform(-1, 1, 4)
        out[name] = replace(head, light_positions_mm=positions, light_intensity=intensity, light_axis=axis,
                            light_mu=mu)
    return out


class ArmSwing:
    """Slow sideways movements of both arms (mm outwards), a few each minute, within +-peak."""

    def __init__(self, peak_mm: float, seed: int) -> None:
        rng = np.random.default_rng(seed + 83)
        self.peak_mm = peak_mm
        self.freqs = rng.uniform(0.02, 0.15, 3)
        self.phases = rng.uniform(0, 2 * np.pi, 3)

    def at(self, t_s: float) -> float:
        wave = np.mean(np.sin(2 * np.pi * self.freqs * t_s + self.phases)) * np.sqrt(2.0)
        return float(self.peak_mm * np.clip(wave, -1.0, 1.0))


class Drift:
    """Slow thermal drift of every LED's output and the mains flicker of the room light."""

    def __init__(self, config: SimConfig) -> None:
        rng = np.random.default_rng(config.seed + 71)
        self.amplitude = config.led_drift
        self.start_s = config.rig_clock_s
        self.periods_s = rng.uniform(180.0, 600.0, 4)
        self.phases = rng.uniform(0, 2 * np.pi, 4)
        self.flicker = config.ambient_flicker
        self.flicker_hz = 2.0 * config.mains_hz
        self.flicker_phase = float(rng.uniform(0, 2 * np.pi))

    def head_at(self, head: Head, t_s: float) -> Head:
        if self.amplitude == 0:
            return head
        factor = 1.0 + self.amplitude * np.sin(2 * np.pi * (self.start_s + t_s) / self.periods_s + self.phases)
        return replace(head, light_intensity=head.light_intensity * factor)

    def relative_intensity(self, t_s: np.ndarray) -> np.ndarray:
        """(T, 4) each LED's output against its mean."""
        t = self.start_s + np.asarray(t_s, dtype=float)[:, None]
        return 1.0 + self.amplitude * np.sin(2 * np.pi * t / self.periods_s + self.phases)

    def ambient_at(self, t_s: float) -> float:
        phase = 2 * np.pi * self.flicker_hz * (self.start_s + t_s) + self.flicker_phase
        return 1.0 + self.flicker * float(np.sin(phase))


# Crossed polarisers (docs/simulator.md): the LED's polariser passes POLARISED_LED of its light; the
# skin's diffuse reflection, scattered under the surface, comes back unpolarised and the lens's
# polariser passes half of it, as of the room's light; the surface reflection keeps the LED's
# polarisation and the crossed lens polariser passes POLARISER_EXTINCTION of it (100:1, a plain film).
POLARISED_LED = 0.4
POLARISER_EXTINCTION = 0.01
UNPOLARISED_PASSED = 0.5  # the share of unpolarised light (diffuse, the room's) a polariser passes


def polarised_camera(camera: CameraModel) -> CameraModel:
    """The camera behind crossed polarisers: the LEDs' diffuse light at POLARISED_LED / 2, the room's
    and the backdrop's at half."""
    return replace(camera, white_level=camera.white_level * POLARISED_LED * UNPOLARISED_PASSED,
                   ambient_level=camera.ambient_level * UNPOLARISED_PASSED,
                   background_level=camera.background_level * UNPOLARISED_PASSED)


def polarised_specular(specular: float) -> float:
    """A surface's specular weight (relative to a white Lambertian surface) behind crossed
    polarisers, relative to the diffuse light that now reaches the camera (polarised_camera)."""
    return specular * POLARISER_EXTINCTION / UNPOLARISED_PASSED


WORLDS: dict[str, dict[str, float | bool]] = {
    "ideal": {},
    # the clinic: LEDs as built, room light, oily skin, a real lens, a subject who moves
    "clinic": {"led_offset_mm": 10.0, "led_intensity_spread": 0.10, "led_mu": 2.0, "led_mu_spread": 1.0,
               "led_tilt_deg": 10.0, "led_drift": 0.02, "ambient_flicker": 0.3, "specular": 0.15,
               "lens_k1": -0.08, "vignetting": 0.15, "steps": 2, "arm_swing_mm": 10.0, "drop_rate": 0.002},
}
# the clinic with crossed polarisers on the LEDs and lenses (the rig the glossy-skin refusal asks for)
WORLDS["clinic-polarised"] = dict(WORLDS["clinic"], polarisers=True)
# and bodies whose trunk widens as they breathe (the silhouette grows; SimConfig.widening)
WORLDS["clinic-widening"] = dict(WORLDS["clinic-polarised"], widening=True)


def in_world(config: SimConfig, world: str) -> SimConfig:
    """The config with a named world's realism switches set (see WORLDS)."""
    if world not in WORLDS:
        raise ValueError(f"unknown world {world!r}: one of {', '.join(WORLDS)}")
    return replace(config, **WORLDS[world])


def world_words(settings: dict[str, float | bool], leave_out: tuple[str, ...] = ()) -> str:
    """A world's settings (WORLDS) for a bench's table: each by name and value, a switch by name."""
    return ", ".join(k if v is True else f"{k} {v:g}" for k, v in settings.items() if k not in leave_out)


def world_json(config: SimConfig) -> str:
    """The simulated world's realism settings, for /truth."""
    keys = ("led_offset_mm", "led_intensity_spread", "led_mu", "led_mu_spread", "led_tilt_deg", "led_drift",
            "ambient_flicker", "mains_hz", "specular", "clothing", "skin_type", "lens_k1", "vignetting", "steps",
            "arm_swing_mm", "drop_rate", "polarisers", "widening", "distance_mm",
            "distance_back_mm", "scale", "seed")
    values = {k: getattr(config, k) for k in keys}
    return json.dumps(values, sort_keys=True)


def breathing_subject(config: SimConfig) -> Subject:
    """The subject who breathes: the config's, with a body's sex, age, stature and mass when it has one."""
    body = config.body
    if body is None:
        return config.subject
    return replace(config.subject, sex=body.sex, age_years=body.age_years, height_cm=body.height_cm,
                   weight_kg=body.weight_kg)


def _torso_surfaces(config: SimConfig):
    specular = polarised_specular(config.specular) if config.polarisers else config.specular
    if config.body is None:
        return shapes.torso(config.grid_step_mm, config.clothing, config.seed, specular)
    skin = 0.45 if config.skin_type is None else fitzpatrick_albedo(config.skin_type)
    return body_surfaces(config.body, config.grid_step_mm, config.clothing, config.seed, skin_albedo=skin,
                         specular=specular, arm_motion=config.arm_swing_mm > 0, widening=config.widening)


def linear_volumes_mm3(surfaces: dict[str, HeightField]) -> np.ndarray:
    """Each mode's volume at unit amplitude (mm^3), both heads: its quadrature and its sideways stretch
    of the trunk at rest."""
    return sum(mode_volumes_mm3(s) + np.array([stretched_volume_mm3(s, np.eye(s.n_modes)[k], modes_too=False)
                                               for k in range(s.n_modes)]) for s in surfaces.values())


def widened_share(surfaces: dict[str, HeightField], amplitudes: np.ndarray,
                  linear_mm3: np.ndarray | None = None) -> float:
    """lambda such that the exact volume at lambda * amplitudes is the linear volume at amplitudes:
    a stretch widens the modes' own areas too (stretched_volume_mm3), a term in amplitude squared
    Q, so lambda^2 Q + lambda L - L = 0 (L the linear volume); 1 without a stretch."""
    if all(s.stretch_modes is None for s in surfaces.values()):
        return 1.0
    amplitudes = np.asarray(amplitudes, dtype=float)
    linear = float(amplitudes @ (linear_volumes_mm3(surfaces) if linear_mm3 is None else linear_mm3))
    quadratic = sum(stretched_volume_mm3(s, amplitudes) - stretched_volume_mm3(s, amplitudes, modes_too=False)
                    for s in surfaces.values())
    if quadratic == 0.0 or linear == 0.0:
        return 1.0
    root = np.sqrt(max(linear * linear + 4.0 * quadratic * linear, 0.0))
    return 2.0 * linear / (linear + np.sign(linear) * root)


def _torso_scene(config: SimConfig, waveform: Waveform, baseline: float) -> HeightFieldScene:
    surfaces = _torso_surfaces(config)
    subject = breathing_subject(config)
    shares = subject.compartment_shares()
    modes = surfaces["front"].mode_names
    names = tuple(n for n in modes if n in shares)  # the breathing modes; "arms" moves without volume
    breathing = np.array([modes.index(n) for n in names])
    linear_mm3 = linear_volumes_mm3(surfaces)
    per_mode_l = (linear_mm3 * 1e-6)[breathing]
    lags = np.array([subject.abdomen_lag_s if n == "abdomen" else 0.0 for n in names])
    share = np.array([shares[n] for n in names])
    swing = ArmSwing(config.arm_swing_mm, config.seed) if "arms" in modes else None

    def compartments(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=float)
        return np.stack([share[k] * waveform.at(np.clip(t - lags[k], 0, None)) for k in range(len(names))], -1)

    def amplitudes(t: float) -> np.ndarray:
        out = np.zeros(len(modes))
        out[breathing] = compartments(np.array(t)) / per_mode_l
        out *= widened_share(surfaces, out, linear_mm3)
        if swing is not None:
            out[modes.index("arms")] = swing.at(t)
        return out

    def flow(t: np.ndarray) -> np.ndarray:
        return sum(share[k] * waveform.flow_at(np.clip(t - lags[k], 0, None)) for k in range(len(names)))

    sway = config.sway if config.sway is not None else Sway(seed=config.seed)
    if config.steps:
        sway = replace(sway, steps=config.steps, steps_span_s=waveform.duration_s)
    probe = HeightFieldScene(surfaces, 0.0, baseline)
    z_mid = config.distance_mm + probe.on_axis_height_mm("front")
    baseline = z_mid + probe.on_axis_height_mm("back") + config.distance_back_mm
    scene = HeightFieldScene(surfaces, z_mid, baseline, amplitudes, sway.at, compartments, flow, waveform.events,
                             kind="simulation")
    scene.root_attrs = {"simulated_scene": "torso", "simulated_protocol": config.protocol,
                        "compartments": ",".join(names),
                        "simulated_body": "ours" if config.body is None else config.body.name}
    return scene


def _mesh_scene(config: SimConfig, waveform: Waveform) -> MeshScene:
    """A body of the mesh population (core/sim/makehuman.py), bare-skinned: the config's skin type
    and sheen when it has them, else the body's."""
    body = config.body
    specular = config.specular if config.specular else body.sheen
    specular = polarised_specular(specular) if config.polarisers else specular
    skin = fitzpatrick_albedo(config.skin_type if config.skin_type is not None else body.skin_type)
    sway = config.sway if config.sway is not None else Sway(seed=config.seed)
    if config.steps:
        sway = replace(sway, steps=config.steps, steps_span_s=waveform.duration_s)
    scene = MeshScene(body, load_mesh_data(), waveform, config.distance_mm, config.distance_back_mm, sway.at,
                      albedo=skin, specular=specular)
    scene.root_attrs["simulated_protocol"] = config.protocol
    return scene


def _object_scene(config: SimConfig) -> HeightFieldScene:
    builder = shapes.SHAPES[config.scene]
    surfaces = builder(config.grid_step_mm) if config.scene == "plane" else builder(config.grid_step_mm, seed=config.seed)
    probe = HeightFieldScene(surfaces, 0.0, 0.0)
    z_mid = config.distance_mm + probe.on_axis_height_mm("front")
    baseline = z_mid + probe.on_axis_height_mm("back") + config.distance_back_mm
    sway = config.sway.at if config.sway is not None else None
    scene = HeightFieldScene(surfaces, z_mid, baseline, sway=sway)
    scene.root_attrs = {"simulated_scene": config.scene}
    return scene


def sphere_placements(config: SimConfig, baseline: float, cycle_s: float) -> list[SpherePlacement]:
    """The centre of the view first (pseudo light vectors), then places spread through the working volume."""
    mid = config.distance_mm if len(config.heads) == 1 else baseline / 2.0
    rng = np.random.default_rng(config.seed + 53)
    spots = [(0.0, 0.0, 0.0), (-220, -150, -150), (220, 150, 150), (220, -150, 0), (-220, 150, 0),
             (0, -170, 150), (0, 170, -150), (-120, 0, 180), (120, 0, -180)]
    while len(spots) < max(config.placements, (config.placement_only or 0) + 1):
        spots.append((rng.uniform(-230, 230), rng.uniform(-170, 170), rng.uniform(-180, 180)))
    hold = config.placement_cycles * cycle_s
    chosen = list(enumerate(spots[: config.placements]))
    if config.placement_only is not None:
        chosen = [(0, spots[config.placement_only])]
    return [SpherePlacement(k * hold, np.array([x, y, mid + z], dtype=float)) for k, (x, y, z) in chosen]


def build_scene(config: SimConfig, rig: Rig) -> tuple[Scene, Waveform | None]:
    if config.scene not in SCENES:
        raise ValueError(f"unknown scene {config.scene!r}: one of {', '.join(SCENES)}")
    baseline = config.distance_mm + config.distance_back_mm + 230.0
    if config.scene == "torso":
        waveform = protocol_waveform(breathing_subject(config), config.protocol, config.seconds, config.seed, config.blows)
        if isinstance(config.body, MeshBody):
            return _mesh_scene(config, waveform), waveform
        return _torso_scene(config, waveform, baseline), waveform
    if config.scene in ("plane", "vase", "relief"):
        return _object_scene(config), None
    cycle_s = rig.cycle_length / rig.frame_rate_hz
    if config.scene == "sphere":
        centre = np.array([0.0, 0.0, config.distance_mm + 150.0])
        return SphereScene(150.0, [SpherePlacement(0.0, centre)], baseline, albedo=0.8, events=[(0.0, "static")]), None
    finish = "specular" if config.scene == "specular-sphere" else "matte"
    radius = config.sphere_radius_mm
    # A glossy highlight about two pixels in half-width: the LED's image through the lens' blur.
    footprint_rad = rig.heads["front"].pixel_size_mm / rig.heads["front"].focal_length_mm * 2.0 * 2000.0 / radius
    shininess = 2.0 * np.log(2.0) / (footprint_rad / 2.0) ** 2
    scene = SphereScene(radius, sphere_placements(config, baseline, cycle_s), baseline,
                        albedo=0.08 if finish == "specular" else 0.8,
                        specular=1.3 if finish == "specular" else 0.0, shininess=float(shininess),
                        kind="sphere-calibration")
    scene.root_attrs = {"sphere_radius_mm": float(radius), "sphere_finish": finish,
                        "simulated_scene": config.scene}
    return scene, None


def _default_map_frames(n_frames: int, cycle: int) -> list[int]:
    ends = np.arange(cycle - 1, n_frames, cycle)
    if len(ends) == 0:
        return []
    return sorted(set(int(ends[int(round(k))]) for k in np.linspace(0, len(ends) - 1, min(5, len(ends)))))


def session_length_s(config: SimConfig, rig: Rig, waveform: Waveform | None, scene: Scene) -> float:
    if config.seconds is not None:
        return float(config.seconds)
    if waveform is not None:
        return waveform.duration_s
    if isinstance(scene, SphereScene):
        return len(scene.placements) * config.placement_cycles * rig.cycle_length / rig.frame_rate_hz
    return 2.0


def sim_digitisers(config: SimConfig, rig) -> dict[str, Digitiser]:
    """Each head's sensor: the full-resolution camera model, binned by 1 / scale (scale 0.5 reads
    2 x 2 pixels as one, as the rig does to fit a gigabit link); behind crossed polarisers but for the
    sphere sessions (SimConfig.polarisers)."""
    camera = config.camera
    if config.polarisers and config.scene not in CALIBRATION_SCENES:
        camera = polarised_camera(camera)
    return {h: Digitiser(camera.binned(1.0 / config.scale), config.bit_depth) for h in rig.heads}


def simulate(path: str | Path, config: SimConfig, progress: Callable[[float], None] | None = None) -> SimSummary:
    """Render the session described by `config` into a session file at `path`."""
    started = time.perf_counter()
    rig = replace(thesis_rig(config.scale, tuple(config.heads), config.bit_depth, config.frame_rate_hz),
                  mains_hz=config.mains_hz)
    if config.lens_k1 or config.vignetting:
        rig = replace(rig, heads={n: replace(h, dist_coeffs=np.array([config.lens_k1, 0, 0, 0, 0]),
                                             vignetting=config.vignetting)
                                  for n, h in rig.heads.items()})
    drift = Drift(config)
    scene, waveform = build_scene(config, rig)
    if len(rig.heads) == 2:
        rig = replace(rig, baseline_mm=float(scene.baseline_mm))
    true_heads = as_built_heads(rig, config)
    duration = session_length_s(config, rig, waveform, scene)
    n_frames = int(round(duration * rig.frame_rate_hz))
    if n_frames < rig.cycle_length:
        raise ValueError(f"{duration:.3f} s is shorter than one light cycle")
    period_ns = rig.frame_period_ns
    map_frames = set(config.truth_maps_at if config.truth_maps_at is not None
                     else _default_map_frames(n_frames, rig.cycle_length))
    bad = [i for i in map_frames if not 0 <= i < n_frames]
    if bad:
        raise ValueError(f"truth map frames {bad} outside 0-{n_frames - 1}")
    rng = np.random.default_rng(config.seed + 61)
    kept = rng.random(n_frames) >= config.drop_rate
    digitisers = sim_digitisers(config, rig)

    subject = None
    if scene.kind in ("simulation", "patient"):
        s = breathing_subject(config)
        subject = SubjectRecord(s.id, s.sex, s.age_years, s.height_cm, s.weight_kg)
    root = dict(scene.root_attrs)
    root["simulated_seed"] = int(config.seed)
    block = rig.cycle_length * 11
    maps: dict[str, dict[int, object]] = {h: {} for h in rig.heads}

    with atomic_output(path) as partial, SessionWriter(partial, kind=scene.kind, rig=rig, subject=subject,
                                                       created=config.created, root_attrs=root,
                                                       compression=config.compression) as writer:
        for t, label in scene.events:
            writer.add_event(CLOCK_START_NS + int(round(t * 1e9)), label)
        errors: list[BaseException] = []
        jobs: queue.Queue = queue.Queue(maxsize=4)

        def write_loop() -> None:
            while (job := jobs.get()) is not None:
                if not errors:
                    try:
                        writer.append_frames(*job)
                    except BaseException as exc:  # reported on the main thread
                        errors.append(exc)

        thread = threading.Thread(target=write_loop, name="session-writer", daemon=True)
        thread.start()
        try:
            for start in range(0, n_frames, block):
                stop_if_requested()
                indices = [i for i in range(start, min(start + block, n_frames))]
                for name, head in true_heads.items():
                    frames, ids, lights, stamps = [], [], [], []
                    for i in indices:
                        light = rig.sequence[i % rig.cycle_length]
                        key = noise_key(config.noise_draw, name, i, head.width * head.height)
                        t_i = i / rig.frame_rate_hz
                        frame, rendered = scene.render(drift.head_at(head, t_i), t_i, light, key,
                                                       replace(digitisers[name], ambient_scale=drift.ambient_at(t_i)),
                                                       want_maps=i in map_frames)
                        if rendered is not None:
                            maps[name][i] = rendered
                        if kept[i]:
                            frames.append(frame)
                            ids.append(i)
                            lights.append(light)
                            stamps.append(CLOCK_START_NS + int(round(i * period_ns)))
                    if frames:
                        jobs.put((name, np.stack(frames), lights, stamps, ids))
                if errors:
                    break
                if progress is not None:
                    progress(min(1.0, (start + block) / n_frames))
        finally:
            jobs.put(None)
            thread.join()
        if errors:
            raise errors[0]

        truth_t = np.arange(0.0, duration, 1.0 / TRUTH_RATE_HZ)
        truth_heads = {}
        for name, head in true_heads.items():
            indices = sorted(maps[name])
            truth_heads[name] = {
                "light_positions_mm": head.light_positions_mm,
                "map_frame_index": np.array(indices, dtype=np.int64),
                "normals": np.stack([maps[name][i].normals for i in indices]).astype(np.float32)
                if indices else np.zeros((0, head.height, head.width, 3), np.float32),
                "depth_mm": np.stack([maps[name][i].depth_mm for i in indices]).astype(np.float32)
                if indices else np.zeros((0, head.height, head.width), np.float32),
            }
            truth_heads[name]["light_intensity"] = head.light_intensity
            if head.light_axis is not None:
                truth_heads[name]["light_axis"] = head.light_axis
                truth_heads[name]["light_mu"] = head.light_mu
            if drift.amplitude:
                truth_heads[name]["light_drift"] = drift.relative_intensity(truth_t)
        extra = {"sway_mm": scene.sway_mm(truth_t), "flow_lps": scene.truth_flow_lps(truth_t)}
        if isinstance(scene, (HeightFieldScene, MeshScene)) and scene.compartment_volumes_l(truth_t) is not None:
            extra["compartment_volume_l"] = scene.compartment_volumes_l(truth_t)
        truth_volume = scene.truth_volume_l(truth_t)
        truth_attrs = {"world": world_json(config)}
        if config.body is not None and config.scene == "torso":
            truth_attrs["body"] = config.body.as_json()
        writer.write_truth(CLOCK_START_NS + np.round(truth_t * 1e9).astype(np.int64), truth_volume, truth_heads,
                           extra, truth_attrs)

        flow_samples = 0
        if config.flow_sensor is not None and scene.kind == "simulation" and waveform is not None:
            sensor = config.flow_sensor
            # the mouthpiece comes off: the flow sensor records the subject's calibration only
            flow_end_s = min([duration] + [t for t, label in scene.events if label == MOUTHPIECE_OFF])
            t = np.arange(0.0, flow_end_s, 1.0 / sensor.sample_rate_hz)
            adc = sensor.adc_counts(scene.truth_flow_lps(t), t, config.seed)
            writer.configure_flow(sample_rate_hz=sensor.sample_rate_hz, adc_bits=sensor.adc_bits, sensor=sensor.sensor,
                                  conditions="ATPS", gain_lps=sensor.gain_lps, offset_lps=sensor.offset_lps,
                                  extra_attrs=sensor.file_attrs())
            writer.append_flow(adc, CLOCK_START_NS + np.round(t * 1e9).astype(np.int64))
            flow_samples = len(adc)

    n_kept = int(kept.sum())
    return SimSummary(Path(path), {h: n_kept for h in rig.heads}, {h: n_frames - n_kept for h in rig.heads},
                      duration, time.perf_counter() - started,
                      (float(truth_volume.min()), float(truth_volume.max())), flow_samples)


__all__ = ["SimConfig", "SimSummary", "simulate", "build_scene", "SCENES", "CALIBRATION_SCENES", "RATE_HZ", "DARK"]
