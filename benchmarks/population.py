"""`photopft bench population`: the clinical values of a population of simulated subjects against
their truth, in a world as hard as a clinic.

Every subject has a body of its own (core/sim/bodies.py), a rig of its own (LEDs as built: up to
15 mm off the drawing, cos^mu falloff with tilted axes, spread and drift; mains flicker, lens
distortion, vignetting), a skin tone and sheen, a distance and a forced expiration that follows a
standard test waveform. As a user would, the rig's lights are calibrated from simulated sphere
sessions of that rig (no truth is used), the subject's protocol is recorded, processed and
analysed. The truth is read only to compare.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from app.args import WORLD_NAMES, finite, positive
from benchmarks.common import DOCS, SHARED, in_checkout, publish
from benchmarks.kept_session import keep_without_frames
from benchmarks.renders import RenderCache


# value key, label, unit, tolerance: absolute, relative (the "within 3 % or 50 mL")
VALUES = (("TV_l", "TV", "L", 0.050, 0.0), ("RR_bpm", "RR", "/min", 0.5, 0.0), ("VC_l", "VC", "L", 0.050, 0.03),
          ("FVC_l", "FVC", "L", 0.050, 0.03), ("FEV1_l", "FEV1", "L", 0.050, 0.03),
          ("FEV1_FVC", "FEV1/FVC", "", 0.03, 0.0), ("PEF_lps", "PEF", "L/s", 0.30, 0.10),
          ("distance_mm", "distance", "mm", 5.0, 0.0))
STANDARD_SETS = ("ISO26782", "ATS24")  # the standard blows the subjects' forced expirations follow
# a row's sources: the optical values calibrated on the subject, the uncalibrated optical estimate of the
# same session (the population's gain), the flow sensor (the calibration's part of the session only)
SOURCES = {"calibrated": "optical, calibrated", "estimate": "optical estimate", "flow": "flow sensor"}
COLOURS = {"calibrated": "tab:blue", "estimate": "tab:green", "flow": "tab:orange"}


@dataclass(frozen=True)


class VirtualSubject:
    index: int
    seed: int
    body: str  # 'random', a preset's name, or 'mesh:N' (the test population's body N)
    distance_mm: float
    skin_type: int
    specular: float
    led_offset_mm: float
    standard: str | None  # a .wf file, or None for the simulator's own blow model

    @property
    def body_name(self) -> str:
        """The body as `simulate --body` names it."""
        return self.body if self.body != "random" else f"random-{self.seed}"


def standard_blows(folder: Path | None) -> list[Path]:
    if folder is None or not folder.is_dir():
        return []
    return sorted(p for name in STANDARD_SETS for p in (folder / name).glob("*.wf"))


MAX_SHEEN = 0.3  # the population's skin sheen is drawn from 0 (matte) to this (oily skin)


def draw_subjects(count: int, seed: int, blows: list[Path], quick: bool = False,
                  max_sheen: float = MAX_SHEEN, bodies: str = "parametric") -> list[VirtualSubject]:
    """The population: random bodies, distances 1700-2300 mm, Fitzpatrick I-VI, skin sheen 0-max_sheen,
    LEDs 0-15 mm off the drawing, a standard blow each (in turn, from a shuffled list). `bodies`:
    "parametric" (the development population, core/sim/bodies.py) or "mesh" (the test population,
    core/sim/makehuman.py, with seeds of its own; the rest drawn alike)."""
    rng = np.random.default_rng(seed + 777)
    order = rng.permutation(len(blows)) if blows else []
    subjects = []
    for k in range(count):
        body = ("average-woman", "arms-close")[k % 2] if quick else "random"
        if bodies == "mesh":
            body = f"mesh:{MESH_SEEDS + 1000 * seed + k}"
        subjects.append(VirtualSubject(
            index=k, seed=1000 * seed + k, body=body,
            distance_mm=float(rng.uniform(1700, 2300)), skin_type=int(rng.integers(1, 7)),
            specular=float(rng.uniform(0.0, 1.0)) * max_sheen, led_offset_mm=float(rng.uniform(0.0, 15.0)),
            standard=str(blows[order[k % len(blows)]]) if blows else None))
    return subjects


BODIES = ("parametric", "mesh")  # the development population, the test population (docs/benchmarks.md)
MESH_SEEDS = 100_000  # the test population's bodies are drawn from seeds of their own, apart from the rest

# bench population --subset: a fixed subset of either population, quick enough to rerun between full runs
SUBSET_SUBJECTS = 8
SUBSET_SCALE = 0.25

WORLD = "clinic"  # the population's world (core/sim/simulate.py, WORLDS); clinic-polarised: behind crossed polarisers


def _config(subject: VirtualSubject, scale: float, world: str = WORLD, **changes):
    from core.sim.simulate import SimConfig, in_world

    config = in_world(SimConfig(scale=scale, seed=subject.seed, rig_seed=subject.seed), world)
    return replace(config, led_offset_mm=subject.led_offset_mm, specular=subject.specular,
                   skin_type=subject.skin_type, body=population_body(subject.body, subject.seed), clothing="skin",
                   **changes)


def session_config(subject: VirtualSubject, scale: float, world: str, protocol: str, seconds: float | None):
    """The subject's session as the bench renders it: its standard blow, its breathing's variability, and
    written as the recorder writes (Blosc LZ4, bit-shuffle): a subject's short protocol at the camera's
    full 1400 x 1024 is about 40 GB of raw frames, 17 GB compressed (docs/benchmarks.md, Compression)."""
    from core.analysis.spirometry import read_waveform
    from core.sim.breathing import ForcedBlow, standard_curve

    blows = None
    if subject.standard is not None:
        standard = read_waveform(subject.standard)
        curve = standard_curve(standard.volume_l, standard.rate_hz)
        blows = [ForcedBlow(effort=e, standard=curve) for e in (1.0, 0.97, 1.02)]
    config = _config(subject, scale, world, protocol=protocol, seconds=seconds, distance_mm=subject.distance_mm,
                     distance_back_mm=subject.distance_mm, blows=blows, compression=RECORDING_COMPRESSION)
    return replace(config, subject=replace(config.subject, rate_variability=0.15, sigh_every=12))


def population_body(name: str, seed: int):
    """A subject's body: a preset as it is, a random body with its arms held away from the trunk, as the
    guided session's positioning tells every patient (issue 74)."""
    from core.sim.bodies import body_named

    body = body_named(name, seed)
    return replace(body, arms="away") if name == "random" else body


def _distance_errors(session: Path, results: Path, after_cycles: int) -> list[float]:
    """Median depth error on the subject (reconstructed against true depth) at the truth's maps
    that come after `after_cycles` light cycles: how far off the subject's distance is."""
    import h5py

    from core.io.session import SessionFile

    errors = []
    with SessionFile(session) as s, h5py.File(results, "r") as r:
        cycle = s.rig.cycle_length
        for head in s.heads:
            truth = s.truth()
            frames = list(truth[f"{head}/map_frame_index"][:])
            maps = r.get(f"heads/{head}/maps")
            if maps is None:
                continue
            ids = s.frame_id(head)
            made = {int(ids[int(p)]): i for i, p in enumerate(maps["frame_index"][:])}  # frame id -> map
            for k, frame in enumerate(frames):
                if frame < after_cycles * cycle or int(frame) not in made:
                    continue
                true_depth = truth[f"{head}/depth_mm"][k]
                depth = maps["depth_mm"][made[int(frame)]]
                both = np.isfinite(true_depth) & np.isfinite(depth)
                if both.sum() > 50:
                    errors.append(float(np.median(depth[both] - true_depth[both])))
    return errors


# The sphere sessions are rendered at no less than this scale: the light calibration reads the
# highlights of a 75 mm sphere and needs the pixels (ideal LEDs, subject 4 of seed 1: 12-17 mm off
# at scale 0.15, 1.4-3.7 mm at 0.3, 0.2-0.5 mm at 0.5; docs/benchmarks.md, lights). The rig's
# camera calibrates at its full 1400 x 1024 whatever the subject's scale here; the lights are in mm.
CALIBRATION_SCALE = 0.5
RECORDING_COMPRESSION = "blosc-lz4"


# The wizard's captures (app/gui/wizards/sphere.py): each place its own recording, the next one this long
# after the last (the sphere moved and held still), the LEDs switched on minutes before the first.
CAPTURE_INTERVAL_S = 15.0
LEDS_ON_BEFORE_S = 300.0
SPHERE_PLACES = 7


def sphere_sessions(subject: VirtualSubject, scale: float, folder: Path,
                    scenes: tuple[str, ...] = ("specular-sphere", "matte-sphere"),
                    world: str = WORLD) -> dict[str, list[Path]]:
    """The subject's rig's sphere captures at `scale`, {scene: paths}, as the calibration wizard records
    them: SPHERE_PLACES places of each sphere, one recording each, CAPTURE_INTERVAL_S apart on the rig's
    clock (its LEDs drift on from one to the next)."""
    import datetime as dt

    from core.calibration.light_sessions import CAPTURE_SECONDS
    from core.rig import thesis_rig
    from core.sim.simulate import simulate

    rig = thesis_rig(scale)
    hold = int(round(CAPTURE_SECONDS * rig.frame_rate_hz / rig.cycle_length))
    switched_on = dt.datetime.now(dt.timezone.utc).replace(microsecond=0)
    clock_s = LEDS_ON_BEFORE_S
    paths = sphere_paths(subject, scale, folder, scenes)
    for scene in scenes:
        for place, path in enumerate(paths[scene]):
            created = (switched_on + dt.timedelta(seconds=clock_s)).isoformat(timespec="seconds")
            simulate(path, _config(subject, scale, world, scene=scene, placement_only=place, placement_cycles=hold,
                                   steps=0, drop_rate=0.0, truth_maps_at=[], rig_clock_s=clock_s, created=created))
            clock_s += CAPTURE_INTERVAL_S
    return paths


def sphere_paths(subject: VirtualSubject, scale: float, folder: Path,
                 scenes: tuple[str, ...] = ("specular-sphere", "matte-sphere")) -> dict[str, list[Path]]:
    """Where sphere_sessions writes the subject's sphere captures, {scene: paths}."""
    return {scene: [folder / f"{subject.index}-{scene}-{scale:g}-{place + 1}.h5" for place in range(SPHERE_PLACES)]
            for scene in scenes}


def _render_subject(subject: VirtualSubject) -> dict:
    """A subject as a render's key holds it: its standard blow by name, not by where this checkout keeps it."""
    return {**asdict(subject), "standard": Path(subject.standard).name if subject.standard else None}


def _config_digest(config) -> str:
    import hashlib
    import pickle

    return hashlib.sha256(pickle.dumps(config)).hexdigest()[:16]


def lights_truth(session: Path) -> dict[str, dict[str, np.ndarray]]:
    """The lights as built, {head: {light_positions_mm, light_axis, light_mu}}, from a simulated session."""
    from core.io.session import SessionFile

    with SessionFile(session) as s:
        truth = s.truth()
        return {h: {k: truth[f"{h}/{k}"][:] for k in ("light_positions_mm", "light_axis", "light_mu")
                    if f"{h}/{k}" in truth} for h in s.heads}


LIGHTS_PROFILE, LIGHTS_TRUTH = "lights.json", "lights-truth.json"  # a kept light calibration's files


def calibrate_rig(subject: VirtualSubject, scale: float, folder: Path, world: str = WORLD,
                  renders: RenderCache | None = None) -> tuple[object, dict]:
    """The subject's rig calibrated as a user would (core/calibration/light_sessions.py) from its specular and
    matte sphere sessions at `scale`, and the truth of its lights (lights_truth). Raises what the
    wizard would show. With `renders`, the calibration is taken from there, or made from the sphere sessions
    kept there (rendered into it first where they are not) and kept."""
    from core.calibration.light_sessions import calibrate_lights

    if renders is not None:
        from benchmarks.renders import CALIBRATION_SOURCES, code_digest
        from core.calibration.rig_profile import load_profile

        what = {"kind": "sphere sessions", "subject": _render_subject(subject), "scale": scale, "world": world,
                "config": _config_digest(_config(subject, scale, world)), "places": SPHERE_PLACES,
                "interval_s": CAPTURE_INTERVAL_S, "leds_on_before_s": LEDS_ON_BEFORE_S}

        def calibrate(into: Path) -> None:
            kept, _ = renders.rendered(what, lambda folder: sphere_sessions(subject, scale, folder, world=world),
                                       source_commit())
            spheres = [p for paths in sphere_paths(subject, scale, kept).values() for p in paths]
            calibrate_lights(spheres)[0].save(into / LIGHTS_PROFILE)
            lights = {h: {k: v.tolist() for k, v in t.items()} for h, t in lights_truth(spheres[0]).items()}
            (into / LIGHTS_TRUTH).write_text(json.dumps(lights))

        calibrated = {"kind": "light calibration", "spheres": what, "code": code_digest(CALIBRATION_SOURCES)}
        kept, _ = renders.rendered(calibrated, calibrate, source_commit())
        lights = json.loads((kept / LIGHTS_TRUTH).read_text())
        return (load_profile(kept / LIGHTS_PROFILE),
                {h: {k: np.asarray(v) for k, v in t.items()} for h, t in lights.items()})
    spheres: list[Path] = []
    try:
        spheres = [p for paths in sphere_sessions(subject, scale, folder, world=world).values() for p in paths]
        return calibrate_lights(spheres)[0], lights_truth(spheres[0])
    finally:
        for path in spheres:
            path.unlink(missing_ok=True)


def light_errors(calibration, lights: dict) -> dict[str, dict[str, list[float]]]:
    """Per head: each LED's position error (mm), and its axis (deg) and falloff exponent errors when
    the profile has them."""
    out = {}
    for h, truth in lights.items():
        fitted = calibration.heads[h]
        errors = {"position_mm": np.linalg.norm(fitted.light_positions_mm - truth["light_positions_mm"], axis=1).tolist()}
        if fitted.light_axis is not None and "light_axis" in truth:
            cosine = np.clip(np.sum(fitted.light_axis * truth["light_axis"], axis=1), -1.0, 1.0)
            errors["axis_deg"] = np.degrees(np.arccos(cosine)).tolist()
            errors["mu"] = np.abs(fitted.light_mu - truth["light_mu"]).tolist()
        out[h] = errors
    return out


def run_subject(subject: VirtualSubject, scale: float, protocol: str, folder: str, seconds: float | None,
                calibration_scale: float | None = None, world: str = WORLD, resume: bool = False,
                process_workers: int = 1, renders: RenderCache | None = None) -> dict:
    """One subject end to end; what each stage gave or why it refused. The lights are calibrated
    from sphere sessions at calibration_scale (default: scale, but no less than CALIBRATION_SCALE).
    With `resume`, `folder` is the subject's own and keeps each finished stage's output (the lights'
    profile, the session, the results) so that a run stopped midway goes on from the last one:
    a subject at the camera's full resolution takes longer than a working session.
    With `renders`, the sphere sessions and the subject's session are taken from there, or rendered
    into it (benchmarks/renders.py). With `resume`, the results are kept beside the folder
    (`<folder>.results.h5` for `<folder>.stages`)."""
    from core.pipeline.process import process_session
    from core.rig import thesis_rig
    from core.io.session import SessionFile
    from core.sim.simulate import simulate
    from core.calibration.rig_profile import ProfileError, load_profile

    started = time.perf_counter()
    work = Path(folder)
    work.mkdir(parents=True, exist_ok=True)
    stages_done = SubjectStages(work, {"subject": asdict(subject), "scale": scale, "world": world,
                                       "commit": source_commit()}) if resume else None
    out: dict = {"subject": asdict(subject), "stage_seconds": dict(stages_done.seconds) if stages_done else {}}
    stages = out["stage_seconds"]
    profile = work / f"{subject.index}-lights.json"
    calibration = None
    if stages_done and stages_done.has("calibrate lights"):
        try:
            calibration, lights = load_profile(profile), stages_done.lights()
        except ProfileError:  # a kept profile damaged since: every stage again
            stages_done.clear()
            stages.clear()
    if calibration is None:
        try:
            calibration, lights = calibrate_rig(subject, calibration_scale or max(scale, CALIBRATION_SCALE), work,
                                                world, renders)
        except Exception as exc:  # the bench reports a refusal, as a user would see it
            out["refused"] = f"light calibration: {exc}"
            return out
        stages["calibrate lights"] = time.perf_counter() - started
        if stages_done:
            calibration.save(profile)
            stages_done.finish("calibrate lights", stages, lights)
    out["led_error_mm"] = {h: e["position_mm"] for h, e in light_errors(calibration, lights).items()}
    for name, head in thesis_rig(scale).heads.items():  # lights in mm: the profile serves the subject's pixels too
        calibration.heads[name].extra.update(width=head.width, height=head.height)
    started = time.perf_counter() - sum(stages.values())
    session, results = work / f"{subject.index}-session.h5", work / f"{subject.index}-results.h5"
    config = session_config(subject, scale, world, protocol, seconds)
    if renders is not None:
        what = {"kind": "session", "subject": _render_subject(subject), "scale": scale, "world": world,
                "protocol": protocol, "seconds": seconds, "config": _config_digest(config)}
        kept, mark = renders.rendered(what, lambda into: simulate(into / session.name, config), source_commit())
        session = kept / session.name
        out["rendered_by"] = mark["commit"]
        stages["simulate subject"] = time.perf_counter() - started - sum(stages.values())
    elif not (stages_done and stages_done.has("simulate subject")):
        simulate(session, config)
        stages["simulate subject"] = time.perf_counter() - started - sum(stages.values())
        if stages_done:
            stages_done.finish("simulate subject", stages)
    with SessionFile(session) as s:
        cycle = s.rig.cycle_length
        ids = s.frame_id("front")
        wanted = {int(f) for h in s.heads for f in s.truth()[f"{h}/map_frame_index"][:]}
        # `process --maps-at` counts stored frames, the truth counts frame ids (frames get lost on the way):
        # the stored positions of the truth's frames whose whole cycle is there
        positions = {int(f): int(np.searchsorted(ids, f)) for f in wanted}
        map_frames = sorted(p for f, p in positions.items()
                            if p >= cycle - 1 and p < len(ids) and ids[p] == f and ids[p] - ids[p - cycle + 1] == cycle - 1)
    try:
        if not (stages_done and stages_done.has("process")):
            process_session(session, results, calibration=calibration, maps_at=map_frames, workers=process_workers)
            stages["process"] = time.perf_counter() - started - sum(stages.values())
            if stages_done:
                stages_done.finish("process", stages)
        out.update(read_results(session, results))
    except Exception as exc:
        out["refused"] = f"process: {exc}"
        return out
    stages["analyse"] = time.perf_counter() - started - sum(stages.values())
    out["seconds"] = sum(stages.values())
    if resume:  # the results kept beside the row, for reading other signals off them without processing again
        keep_without_frames(session, work.with_suffix(".session.h5"))
        os.replace(results, work.with_suffix(".results.h5"))
    for path in (results,) if renders is not None else (session, results):
        path.unlink(missing_ok=True)
    if stages_done:
        stages_done.clear()
        work.rmdir()
    return out


def read_results(session: Path, results: Path) -> dict:
    """A processed subject's row fields read off its session and results file by this commit's analysis:
    the truth, the flow sensor's and the optical values, the calibration, the groupings, the distances."""
    from core.analysis.optical_labels import calibrated_on_subject
    from core.analysis.session_analysis import analyse_session
    from core.io.results import ResultsFile, optical_inputs, optical_refusal
    from core.sim.truth import truth_values

    out: dict = {}
    report = analyse_session(session, **optical_inputs(results))
    truth = truth_values(session)
    out["truth"] = _numbers(truth.parameters())
    out["flow"] = _numbers(report.flow_sensor.parameters()) if report.flow_sensor is not None else {}
    out["optical"] = _numbers(report.optical.parameters()) if report.optical is not None else {}
    out["optical_label"] = report.optical_label
    calibrated = calibrated_on_subject(report.optical_label)
    out["calibrated"] = out["optical"] if calibrated else {}
    if calibrated:  # read over the span the calibrated values are read over: after the calibration
        truth = truth_values(session, report.optical_from_s)
        out["truth_calibrated"] = _numbers(truth.parameters())
    out["blows"] = blow_pairs(report.optical, truth)
    out["estimate"] = out["optical"] if report.optical is not None and not calibrated else {}
    out["optical_problems"] = list(report.optical.problems) if report.optical is not None else []
    out["optical_refused"] = optical_refusal(results)
    with ResultsFile(results) as r:
        out["distance_refused"] = r.distance_refused
        out["subject_calibration"] = {k: (v.tolist() if hasattr(v, "tolist") else v)
                                      for k, v in r.subject_calibration().items()}
        metric = r.metric_volume()
    if calibrated and metric is not None:  # the same session read as if it had no calibration
        out["estimate"] = _numbers(estimate_values(session, metric).parameters())
    out["groupings"] = grouping_values(session, results)
    out["distance_errors_mm"] = [] if out["distance_refused"] else _distance_errors(session, results, after_cycles=10)
    return out


BLOW_VALUES = ("FVC_l", "FEV1_l")
SAME_MARK_S = 0.05  # the optical curve and the truth are read at the same operator's marks


def blow_pairs(optical, truth) -> list[dict]:
    """Each forced blow the optical curve gave values for, beside the truth's values of the same blow
    (paired by the operator's mark): a session's FVC is the largest of its blows (ATS/ERS), and among
    readings with errors of their own the largest is also the one read most over, which the blows one by
    one separate from how each is read."""
    if optical is None or optical.forced is None or truth is None or truth.forced is None:
        return []
    pairs = []
    for blow in optical.forced.manoeuvres:
        same = [m for m in truth.forced.manoeuvres if abs(m.mark_s - blow.mark_s) <= SAME_MARK_S]
        if same:
            pairs.append({"mark_s": float(blow.mark_s),
                          "optical": {"FVC_l": float(blow.fvc_l), "FEV1_l": float(blow.fev1_l)},
                          "truth": {"FVC_l": float(same[0].fvc_l), "FEV1_l": float(same[0].fev1_l)}})
    return pairs


def blow_lines(rows: list[dict]) -> list[str]:
    """Each forced blow calibrated on the subject against the truth's reading of it, beside the session's
    value (its largest acceptable blow's); [] where no row has blows read so."""
    tolerances = {key: (absolute, relative) for key, _, _, absolute, relative in VALUES}
    labels = {key: label for key, label, *_ in VALUES}
    calibrated = [r for r in rows if r.get("calibrated") and r.get("blows")]
    if not calibrated:
        return []
    sessions = {label: bias for label, _, source, n, _, bias, *_ in agreement(calibrated)
                if source == "calibrated" and n}  # each value's session bias: its largest blow's
    cells = []
    for key in BLOW_VALUES:
        pairs = [(b["optical"][key], b["truth"][key]) for r in calibrated for b in r["blows"]]
        errors = np.array([m - t for m, t in pairs])
        share = np.mean([within(m, t, *tolerances[key]) for m, t in pairs])
        sd = errors.std(ddof=1) if len(errors) > 1 else float("nan")
        cells.append(f"{labels[key]} {errors.mean():+.3f} L (95 % limits {errors.mean() - 1.96 * sd:+.3f} to "
                     f"{errors.mean() + 1.96 * sd:+.3f}), {share:.0%} within tolerance"
                     + (f"; the session's (its largest blow's) {sessions[labels[key]]:+.3f}"
                        if labels[key] in sessions else ""))
    blows = sum(len(r["blows"]) for r in calibrated)
    return ["", f"Each forced blow calibrated on the subject ({blows} blows of {len(calibrated)} subjects), optical "
            "minus the truth's reading of the same blow: " + "; ".join(cells) + "."]


def reread_row(row: dict, results: Path, session: Path) -> dict:
    """A kept row read again by this commit's analysis off the results file kept beside it (`bench
    population --reread`): the same session and maps, the values as this commit reads them;
    `processed_by` names the commit that processed them."""
    started = time.perf_counter()
    fresh = read_results(session, results)
    for key in ("refused", "optical_refused", "distance_refused"):
        row.pop(key, None)
    return {**row, **fresh, "processed_by": row.get("processed_by", row.get("commit", "unknown")),
            "commit": source_commit(), "reread_seconds": time.perf_counter() - started}


def grouping_values(session: Path, results: Path) -> dict[str, dict]:
    """The session's optical values calibrated on the subject in each grouping of the regional signals
    (core/volume/subject_calibration.py, GROUPINGS) and as the calibration chooses ("chosen"), all read
    from the light cycles' maps alike (no maps at every frame through the blows): which grouping carries
    from the calibration to the later manoeuvres, measured on both populations. {} without a calibration."""
    from core.analysis.quiet_breathing import quiet_breathing_gain, with_quiet_breathing_gain
    from core.analysis.session_analysis import session_flow_volume
    from core.analysis.values import analyse_volume
    from core.io.results import ResultsFile
    from core.io.session import SessionFile
    from core.volume.subject_calibration import (GROUPINGS, calibration_segment, fit_subject_calibration,
                                                 regional_signals)

    with ResultsFile(results) as r:
        metric, head_regions = r.metric_volume(), r.head_regions()
    if metric is None or not head_regions:
        return {}
    with SessionFile(session) as s:
        start = s.start_ns()
        events = sorted(((t - start) / 1e9, label) for t, label in s.events())
        age = s.subject.age_years if s.subject is not None else None
        flow = session_flow_volume(s, events)
    segment = None if flow is None or flow.refused is not None else calibration_segment(events, float(flow.t_s[-1]))
    if segment is None:
        return {}
    t = (np.asarray(metric[0], dtype=np.int64) - start) / 1e9
    signals = regional_signals(head_regions)
    out = {}
    for name, groupings in [("chosen", tuple(GROUPINGS))] + [(g, (g,)) for g in GROUPINGS]:
        calibration = fit_subject_calibration(t, signals, flow.t_s, flow.volume_l, segment, groupings)
        curve = calibration.volume_l(signals)
        read = t >= segment[1]  # after the calibration, as the analysis reads the calibrated curve
        values = {} if calibration.refused else _numbers(with_quiet_breathing_gain(
            analyse_volume(t[read], curve[read], events, age, fitted=True),
            quiet_breathing_gain(flow.t_s, flow.volume_l, t, curve, events)).parameters())
        out[name] = {"values": values, "refused": calibration.refused and str(calibration.refused),
                     "gains": calibration.gains,
                     "grouping": calibration.extra.get("grouping"), "expected_error": calibration.expected_error}
    return out


def estimate_values(session: Path, metric: tuple[np.ndarray, np.ndarray]):
    """The optical values of a session's plain optical volume (/metric_volume) with the population's gain,
    as `process` gives them without a calibration on the subject (its PEF from the maps of every light
    cycle: the maps at every frame through the blows are the calibrated volume's)."""
    from core.analysis.optical_litres import POPULATION_GAIN
    from core.analysis.values import analyse_volume
    from core.io.session import SessionFile

    with SessionFile(session) as s:
        start = s.start_ns()
        events = sorted(((t - start) / 1e9, label) for t, label in s.events())
        age = s.subject.age_years if s.subject is not None else None
    t = (np.asarray(metric[0], dtype=np.int64) - start) / 1e9
    return analyse_volume(t, POPULATION_GAIN * np.asarray(metric[1], dtype=float), events, age, fitted=True)


class SubjectStages:
    """Which stages of one subject's run are done, in its own folder (`stages.json`), with the
    seconds each took and the truth of its lights. A folder left by another subject, scale, world
    or commit, or by a stage stopped midway, is cleared: only a whole stage of this very run is taken."""

    def __init__(self, folder: Path, stamp: dict):
        self.folder, self.stamp = folder, stamp
        folder.mkdir(parents=True, exist_ok=True)
        self.path = folder / "stages.json"
        try:
            state = json.loads(self.path.read_text())
        except (OSError, ValueError):
            state = {}
        if state.get("stamp") == stamp:
            self.state = {"stamp": stamp, "seconds": state.get("seconds", {}), "lights": state.get("lights", {})}
        else:
            self.clear()
        for stale in folder.glob(".*.partial*"):  # a stage stopped midway (atomic_output's temporary files)
            stale.unlink()
        for name, stage in (("session", "simulate subject"), ("results", "process")):  # whole, not marked done
            if not self.has(stage):
                for path in folder.glob(f"*-{name}.h5"):
                    path.unlink()

    @property
    def seconds(self) -> dict[str, float]:
        return self.state["seconds"]

    def has(self, stage: str) -> bool:
        return stage in self.state["seconds"]

    def lights(self) -> dict[str, dict[str, np.ndarray]]:
        return {h: {k: np.asarray(v) for k, v in truth.items()} for h, truth in self.state["lights"].items()}

    def finish(self, stage: str, seconds: dict[str, float], lights: dict | None = None) -> None:
        self.state["seconds"] = {**seconds}
        if lights is not None:
            self.state["lights"] = {h: {k: np.asarray(v).tolist() for k, v in t.items()} for h, t in lights.items()}
        _keep(self.path, self.state)

    def clear(self) -> None:
        """No stage done: the folder emptied."""
        self.state = {"stamp": self.stamp, "seconds": {}, "lights": {}}
        for path in self.folder.iterdir():
            path.unlink()


def _numbers(values: dict) -> dict[str, float]:
    return {k: float(v) for k, v in values.items() if isinstance(v, (int, float)) and np.isfinite(v)}


def within(value: float, truth: float, absolute: float, relative: float) -> bool:
    return abs(value - truth) <= max(absolute, relative * abs(truth))


def truth_for(row: dict, source: str) -> dict:
    """The truth a source's values are compared with: for the values calibrated on the subject, the truth
    read from the end of the calibration on, as they are (rows before 2026-12-07 have only the whole
    session's)."""
    if source == "calibrated" and "truth_calibrated" in row:
        return row["truth_calibrated"]
    return row.get("truth", {})


def _pairs(rows: list[dict], source: str, key: str) -> tuple[np.ndarray, np.ndarray, int]:
    """(measured, truth) over subjects that gave the value, and how many did not."""
    measured, truth, missing = [], [], 0
    for row in rows:
        if key == "distance_mm":
            if source != "calibrated":
                continue
            errors = row.get("distance_errors_mm") or []
            if errors:  # the subject's median depth as measured, at its worst map, and as it was
                true_distance = row["subject"]["distance_mm"]
                measured.append(true_distance + max(errors, key=abs))
                truth.append(true_distance)
            else:
                missing += 1
            continue
        true_value = truth_for(row, source).get(key)
        value = row.get(source, {}).get(key)
        if true_value is None:
            continue
        if value is None:
            missing += 1
            continue
        measured.append(value)
        truth.append(true_value)
    return np.array(measured), np.array(truth), missing


def _or_dash(value: float, spec: str) -> str:
    """A table cell: the value, or a dash where there is none (a subject refused before analysis)."""
    return format(value, spec) if np.isfinite(value) else "–"


def agreement(rows: list[dict]) -> list[tuple]:
    """Per value and source: n, refused, bias, 95 % limits of agreement, share within tolerance."""
    table = []
    for key, label, unit, absolute, relative in VALUES:
        for source in SOURCES:
            measured, truth, missing = _pairs(rows, source, key)
            if len(measured) == 0 and missing == 0:
                continue
            difference = measured - truth
            bias = float(difference.mean()) if len(difference) else float("nan")
            sd = float(difference.std(ddof=1)) if len(difference) > 1 else float("nan")
            share = (float(np.mean([within(m, t, absolute, relative) for m, t in zip(measured, truth)]))
                     if len(measured) else float("nan"))
            table.append((label, unit, source, len(measured), missing, bias, bias - 1.96 * sd, bias + 1.96 * sd,
                          share, absolute, relative))
    return table


def bland_altman_pngs(rows: list[dict], folder: Path, stem: str) -> list[Path]:
    """One Bland-Altman plot per value (difference against mean; optical and flow sensor)."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    folder.mkdir(parents=True, exist_ok=True)
    written = []
    for key, label, unit, absolute, relative in VALUES:
        fig, ax = plt.subplots(figsize=(5.0, 3.6), dpi=110)
        plotted = False
        refused_note = []
        for source, colour in COLOURS.items():
            measured, truth, missing = _pairs(rows, source, key)
            if missing and source != "flow":  # the flow sensor stops at the mouthpiece's removal
                refused_note.append(f"{SOURCES[source]}: no value for "
                                    f"{missing} of {len(measured) + missing} subjects")
            if len(measured) == 0:
                continue
            plotted = True
            mean = truth if key == "distance_mm" else 0.5 * (measured + truth)
            difference = measured - truth
            name = SOURCES[source]
            ax.scatter(mean, difference, s=14, color=colour, label=name)
            if len(difference) > 1:
                bias, sd = difference.mean(), difference.std(ddof=1)
                for level, style in ((bias, "-"), (bias - 1.96 * sd, "--"), (bias + 1.96 * sd, "--")):
                    ax.axhline(level, color=colour, linestyle=style, linewidth=0.8)
        if not plotted:
            plt.close(fig)
            continue
        ax.axhline(absolute, color="grey", linestyle=":", linewidth=0.8)
        ax.axhline(-absolute, color="grey", linestyle=":", linewidth=0.8)
        suffix = f" ({unit})" if unit else ""
        ax.set_xlabel(("the subject's true distance" if key == "distance_mm" else f"mean of measured and true {label}")
                      + suffix)
        ax.set_ylabel(f"measured − true{suffix}")
        ax.set_title(f"{label}: Bland-Altman, {len(rows)} subjects", fontsize=10)
        if refused_note:  # under the axes, where no point can lie
            fig.text(0.01, 0.01, "; ".join(refused_note), fontsize=7, color="dimgrey")
        ax.legend(fontsize=8)
        fig.tight_layout(rect=(0.0, 0.04 if refused_note else 0.0, 1.0, 1.0))
        path = folder / f"{stem}-{label.replace('/', '_')}.png"
        fig.savefig(path)
        plt.close(fig)
        written.append(path)
    return written


def _kept(folder: Path | None, subject: VirtualSubject, scale: float, world: str = WORLD) -> Path | None:
    mesh = "-mesh" if subject.body.startswith("mesh:") else ""
    return None if folder is None else folder / f"subject-{subject.seed}-{scale:g}{_world_suffix(world)}{mesh}.json"


def _stages_folder(folder: Path | None, subject: VirtualSubject, scale: float, world: str = WORLD) -> Path | None:
    kept = _kept(folder, subject, scale, world)
    return None if kept is None else kept.with_suffix(".stages")


def _world_suffix(world: str) -> str:
    return "" if world == WORLD else f"-{world}"


def _keep(path: Path | None, row: dict) -> None:
    """A finished subject's row, written whole (temporary file renamed) so that a run stopped midway
    resumes from it."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".part")
    partial.write_text(json.dumps(row))
    partial.replace(path)


def run_population_bench(subjects: int, scale: float, seed: int, quick: bool, workers: int,
                         standards: Path | None, images: Path | None,
                         max_sheen: float = MAX_SHEEN, keep: Path | None = None, world: str = WORLD,
                         bodies: str = "parametric", renders: RenderCache | None = None,
                         reread: bool = False) -> tuple[str, list[dict]]:
    """The bench's table and rows. With `keep`, each finished subject's row is kept there and a
    later run with the same arguments takes it instead of running the subject again. With `renders`,
    the subjects' rendered sessions are taken from there or kept there (benchmarks/renders.py). With
    `reread`, no subject is run: each kept row whose results file is kept beside it is read again by
    this commit's analysis (reread_row) and kept so, and the table is made of the kept rows."""
    from app.progress import Progress
    from core.pipeline.head_maps import use_threads
    from core.sim.simulate import WORLDS

    started = time.perf_counter()
    blows = standard_blows(standards)
    population = draw_subjects(subjects, seed, blows, quick, max_sheen, bodies)
    protocol, seconds = ("short", 8.0) if quick else ("clinical", None)
    calibration_scale = scale if quick else max(scale, CALIBRATION_SCALE)
    done: dict[int, dict] = {}
    for s in population:
        path = _kept(keep, s, scale, world)
        if path is not None and path.is_file():
            row = json.loads(path.read_text())
            if row.get("subject") == asdict(s):
                done[s.index] = _reread_kept(row, path) if reread else row
    if reread:
        population = [s for s in population if s.index in done]
    with tempfile.TemporaryDirectory() as tmp, Progress("bench population") as progress:
        # with `keep`, each subject's finished stages are kept beside its row until the row is written;
        # one subject at a time processes its two heads at once (a Pool's workers cannot start their own)
        count = max(1, min(workers, len(population) - len(done)))
        jobs = [((s, scale, protocol, _stages_folder(keep, s, scale, world) or tmp, seconds, calibration_scale, world,
                  keep is not None, 2 if count == 1 else 1, renders), _kept(keep, s, scale, world))
                for s in population if s.index not in done]
        progress(len(done) / len(population), f"{len(done)} of {len(population)} subjects")
        if count > 1:
            # a Pool, not an executor: leaving the block (done, or Ctrl-C / SIGTERM) terminates the workers
            # instead of waiting for the subjects they are on
            # each worker's numba kernels on its share of the cores: two workers of two threads each on two
            # cores took 15.8 s to simulate and 14.6 s to process a 2 s subject at scale 0.5, one thread each
            # 14.8 and 12.8 s (2026-11-27)
            with get_context("spawn").Pool(count, use_threads, (max(1, (os.cpu_count() or 1) // count),)) as pool:
                for row in pool.imap_unordered(_run_job, jobs):
                    done[row["subject"]["index"]] = row
                    progress(len(done) / len(population), f"{len(done)} of {len(population)} subjects")
        else:
            for job in jobs:
                row = _run_job(job)
                done[row["subject"]["index"]] = row
                progress(len(done) / len(population), f"{len(done)} of {len(population)} subjects")
    rows = [done[s.index] for s in population]
    resumed = len(population) - len(jobs)
    elapsed = time.perf_counter() - started
    describe_bodies(rows)
    stem = population_section(scale, max_sheen, world, bodies)
    pngs = bland_altman_pngs(rows, images, stem) if images is not None else []
    return _table(rows, scale, seed, quick, blows, elapsed, workers, pngs, WORLDS[world], max_sheen,
                  calibration_scale, resumed, bodies), rows


def population_section(scale: float, max_sheen: float, world: str, bodies: str = "parametric") -> str:
    """The bench's name in docs/benchmarks.md and its plots' stem."""
    return (f"population-{scale:g}" + ("" if max_sheen == MAX_SHEEN else f"-sheen{max_sheen:g}") + _world_suffix(world)
            + ("-mesh" if bodies == "mesh" else ""))


def _reread_kept(row: dict, path: Path) -> dict:
    """A kept row read again off the results file kept beside it (`<row>.results.h5`) and its session,
    as rendered or else the copy without frames kept beside it (`<row>.session.h5`, made here where an
    older run kept none), and kept so; the row as it was where there is no results file (refused before
    processing) or no session."""
    from core.io.errors import SessionError
    from core.io.results import session_of_results

    results, copy = path.with_suffix(".results.h5"), path.with_suffix(".session.h5")
    if not results.is_file():
        return row
    try:
        try:
            session = session_of_results(results)
        except SessionError:
            if not copy.is_file():
                raise
            session = copy
        if not copy.is_file():
            keep_without_frames(session, copy)
        fresh = reread_row(row, results, session)
    except SessionError as exc:
        print(f"{path.name}: not read again, kept as processed at {row.get('commit', 'unknown')}: {exc}",
              file=sys.stderr)
        return row
    _keep(path, fresh)
    return fresh


def _run_job(job: tuple) -> dict:
    arguments, kept = job
    row = run_subject(*arguments)
    row["commit"] = source_commit()
    _keep(kept, row)
    return row


@functools.cache


def source_commit() -> str:
    """The checkout's commit the subject was run with (kept rows may come from several), "-dirty" after it
    where the checkout had changes. Read once a process, when it first runs a subject and imports the code:
    a worker keeps the code it loaded, and the checkout read at each row's end named commits made while a
    long run went on (2026-12-02: rows labelled with two later commits ran the code of the run's start)."""
    import subprocess

    try:
        return subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=7"],
                              cwd=Path(__file__).resolve().parents[1],
                              capture_output=True, text=True, timeout=10).stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


# What `process` refuses the optical values for (core/pipeline/quality.py, core/volume/metric.py),
# by words its reasons hold; the first match names a reason
REFUSAL_KINDS = (("an arm lies against the trunk", "an arm against the trunk"),
                 ("runs out of the image", "the trunk out of the image"),
                 ("outside the rig's working range", "a distance outside the working range"),
                 ("no subject distance", "no distance"),
                 ("cm^2 of the subject", "too little of the trunk"),
                 ("its shading puts the subject", "the shading against the heads' geometry"),  # rows before 2026-11-27
                 ("does not follow the light model: a sheen", "a sheen on the skin"),
                 ("the maps are bent", "bent maps"),
                 ("jumps away and back", "jumps"),
                 ("noise from map to map", "a noisy curve"),
                 ("and its depth in this head's maps", "a head's scale"))


def refusal_kind(reason: str) -> str:
    """A short name for why the optical values were refused (REFUSAL_KINDS), or "other"."""
    return next((kind for words, kind in REFUSAL_KINDS if words in reason), "other")


def refusal_tally(rows: list[dict]) -> str:
    """How many subjects' optical values were refused, for what, most first: "4 for an arm ..., 2 for ..."."""
    from collections import Counter

    counts = Counter(refusal_kind(r["optical_refused"]) for r in rows if r.get("optical_refused"))
    return ", ".join(f"{n} for {kind}" for kind, n in sorted(counts.items(), key=lambda kv: (-kv[1], kv[0])))


def _table(rows: list[dict], scale: float, seed: int, quick: bool, blows: list[Path], elapsed: float,
           workers: int, pngs: list[Path], world: dict, max_sheen: float = MAX_SHEEN,
           calibration_scale: float | None = None, resumed: int = 0, bodies: str = "parametric") -> str:
    from core.rig import thesis_head
    from core.sim.simulate import world_words

    head = thesis_head(scale=scale)
    sphere = thesis_head(scale=calibration_scale or scale)
    refused = [r for r in rows if "refused" in r]
    lines = [f"{len(rows)} simulated subjects (seed {seed}{', quick' if quick else ''}), two heads of {head.width} x "
             f"{head.height} pixels; protocol: {'its first 8 s' if quick else 'the clinical one: 20 s tidal (irregular, sighs) and one slow VC through the flow sensor (the subject calibration), then with the mouthpiece off 10 s tidal, one slow VC, three forced blows'}; "
             f"blows following {'the standard waveforms (' + ', '.join(STANDARD_SETS) + f', {len(blows)} files)' if blows else 'the simulator own model (no standard waveforms found)'}, "
             "scaled to each subject's predicted FVC. The world: "
             + ("the test population: MakeHuman body meshes ray-cast (core/sim/makehuman.py; no method tuned on them)"
                if bodies == "mesh" else "the development population: random parametric bodies (core/sim/bodies.py)")
             + ", distance 1700-2300 mm, "
             f"Fitzpatrick I-VI, skin sheen 0-{max_sheen:g}, LEDs 0-15 mm off the drawing, and the clinic's "
             + world_words(world, leave_out=("led_offset_mm", "specular"))
             + (" (crossed polarisers on the LEDs and lenses; the sphere sessions without)" if world.get("polarisers") else "")
             + f". Lights calibrated from each rig's simulated sphere sessions (specular and matte, {sphere.width} x "
             f"{sphere.height} pixels); processed with "
             "`photopft process` defaults. Optical, calibrated: the subject's own calibration; optical estimate: the same "
             "session's plain optical volume with the population's gain (core/analysis/optical_litres.py). "
             "Truth read only to compare.", "",
             "| value | source | n | refused | bias | 95 % limits of agreement | within tolerance |",
             "|---|---|---|---|---|---|---|"]
    for label, unit, source, n, missing, bias, low, high, share, absolute, relative in agreement(rows):
        tolerance = f"{absolute:g} {unit}".strip() + (f" or {relative:.0%}" if relative else "")
        limits = f"{low:+.3f} to {high:+.3f}" if n > 1 else "one value: no limits"
        given = (f"{bias:+.3f} | {limits} | {share:.0%} (±{tolerance})" if n
                 else f"no value given | | (±{tolerance})")
        lines.append(f"| {label}{f' ({unit})' if unit else ''} | {SOURCES[source]} | "
                     f"{n} | {missing} | {given} |")
    lines += ["", "Distance: the worst median depth error on the subject over the truth's maps after 10 cycles, per subject; "
              "refused where `process` gives no distance (`/@distance_refused`).",
              "", "| # | body | sex, age, height, BMI | arms | distance (mm) | skin | sheen | blow | LED error (mm, worst) | "
              "optical TV / truth (L) | optical FVC / truth (L) | calibration: residual (mL), expected error | distance error (mm) |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        s = row["subject"]
        body = row.get("body", {})
        led = max((max(v) for v in row.get("led_error_mm", {}).values()), default=float("nan"))
        truth, optical = truth_for(row, "calibrated" if row.get("calibrated") else "optical"), row.get("optical", {})
        errors = row.get("distance_errors_mm") or []
        cells = [(f"{optical[k]:.3f}" if k in optical else "none") + (f" / {truth[k]:.3f}" if k in truth else "")
                 for k in ("TV_l", "FVC_l")]
        cells.append(calibration_cell(row.get("subject_calibration") or {}))
        lines.append(f"| {s['index']} | {body.get('name', s['body'])} | {body.get('sex', '?')}, "
                     f"{body.get('age_years', float('nan')):.0f} y, {body.get('height_cm', float('nan')):.0f} cm, "
                     f"{body.get('bmi', float('nan')):.1f} | {body.get('arms', '?')} | {s['distance_mm']:.0f} | "
                     f"{s['skin_type']} | {s['specular']:.2f} | {Path(s['standard']).stem if s['standard'] else 'model'} | "
                     f"{_or_dash(led, '.1f')} | "
                     f"{' | '.join(cells)} | {_or_dash(max(errors, key=abs) if errors else float('nan'), '+.1f')} |"
                     + (f" refused: {row['refused']}" if "refused" in row else "")
                     + (f" optical refused: {row['optical_refused']}" if row.get("optical_refused") else "")
                     + (f" distance refused: {row['distance_refused']}" if row.get("distance_refused") else "")
                     + (f" optical: {'; '.join(row['optical_problems'])}" if row.get("optical_problems")
                        and not row.get("optical_refused") else ""))
    subject_seconds = [r["seconds"] for r in rows if "seconds" in r]
    tally = refusal_tally(rows)
    lines += ["", f"{len(refused)} of {len(rows)} subjects refused before analysis"
              + (f"; optical values refused {tally}" if tally else "")
              + f"; calibrated on the subject: {sum(bool(r.get('calibrated')) for r in rows)}"
              + f". Run time {elapsed:.0f} s with "
              f"{workers} subject(s) at once on {os.cpu_count()} cores"
              + (f" ({resumed} subjects kept from an earlier run of the same bench)" if resumed else "")
              + (f"; subjects processed at commit(s) "
                 f"{', '.join(sorted({r.get('processed_by', r.get('commit', 'unknown')) for r in rows}))}")
              + (f", read again at {', '.join(sorted({r['commit'] for r in rows if 'processed_by' in r}))} "
                 "(`--reread`)" if any("processed_by" in r for r in rows) else "")
              + (f", rendered at {', '.join(sorted({r['rendered_by'] for r in rows if 'rendered_by' in r}))}"
                 if any("rendered_by" in r for r in rows) else "")
              + (f"; {np.median(subject_seconds):.0f} s per subject (median)." if subject_seconds else ".")]
    lines += blow_lines(rows)
    lines += grouping_lines(rows)
    if pngs:
        lines += ["", "Bland-Altman plots: " + ", ".join(f"![{p.stem}](images/{p.name})" for p in pngs)]
    return "\n".join(lines)


GROUPING_VALUES = ("TV_l", "VC_l", "FVC_l", "FEV1_l", "FEV1_FVC")


def grouping_lines(rows: list[dict]) -> list[str]:
    """The subject's calibration in each grouping of the regional signals against the truth: per grouping
    and value, the subjects given, the median and the worst error (%) and the share within tolerance."""
    from core.volume.subject_calibration import GROUPINGS

    fitted = [r for r in rows if r.get("groupings")]
    if not fitted:
        return []
    tolerances = {key: (absolute, relative) for key, _, _, absolute, relative in VALUES}
    labels = {key: label for key, label, *_ in VALUES}
    lines = ["", f"The subject's calibration in each grouping of the regional signals (core/volume/subject_calibration.py), "
             f"{len(fitted)} subjects with one; every value read from the light cycles' maps alike, so the chosen "
             "grouping's PEF and FEV1 here may differ from the table above. Error: optical minus truth, % of the truth.",
             "", "| grouping | " + " | ".join(f"{labels[k]}: n, median, worst, within" for k in GROUPING_VALUES) + " |",
             "|---|" + "---|" * len(GROUPING_VALUES)]
    for grouping in ("chosen", *GROUPINGS):
        cells = []
        for key in GROUPING_VALUES:
            pairs = [(r["groupings"][grouping]["values"][key], truth_for(r, "calibrated")[key]) for r in fitted
                     if key in r["groupings"].get(grouping, {}).get("values", {}) and key in truth_for(r, "calibrated")]
            if not pairs:
                cells.append("none")
                continue
            errors = np.array([100 * (m - t) / t for m, t in pairs])
            share = np.mean([within(m, t, *tolerances[key]) for m, t in pairs])
            cells.append(f"{len(pairs)}, {np.median(errors):+.1f}, {errors[np.argmax(np.abs(errors))]:+.1f}, {share:.0%}")
        lines.append(f"| {grouping} | " + " | ".join(cells) + " |")
    return lines


def calibration_cell(calibration: dict) -> str:
    """A subject's calibration in the table: its residual and expected error, or why there is none."""
    if "residual_l" in calibration and "refused" not in calibration:
        return f"{1000 * calibration['residual_l']:.0f}, {100 * calibration.get('expected_error', float('nan')):.1f} %"
    return str(calibration.get("refused") or calibration.get("not_calibrated") or "none")


def describe_bodies(rows: list[dict]) -> None:
    """Fill each row's body description (done in the parent: the body is a pure function of the seed)."""
    for row in rows:
        s = row["subject"]
        b = population_body(s["body"], s["seed"])
        row["body"] = {**json.loads(b.as_json()), "bmi": b.bmi}


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench population`: its arguments and what it runs."""
    po = what.add_parser("population", help="clinical values of simulated subjects in a clinic-like world, "
                                            "against the truth (Bland-Altman)")
    po.add_argument("--subjects", type=int, default=30)
    po.add_argument("--scale", type=positive, default=0.5)
    po.add_argument("--seed", type=int, default=1)
    po.add_argument("--quick", action="store_true", help="two small subjects and 14 s each (what the tests run)")
    po.add_argument("--workers", type=int, default=None, help="subjects at once (default: one per core)")
    po.add_argument("--waveforms", type=Path, default=SHARED / "data" / "spirometry-waveforms",
                    help="the standard test waveforms the blows follow (default ../shared/data/spirometry-waveforms)")
    po.add_argument("--max-sheen", type=finite, default=None,
                    help="skin sheen drawn from 0 to this (default 0.3; 0: matte skin)")
    po.add_argument("--world", choices=tuple(w for w in WORLD_NAMES if w != "ideal"), default="clinic-widening",
                    help="the clinic's rig, or the same behind crossed polarisers on the LEDs and lenses, or that "
                         "with bodies whose trunk widens as they breathe (clinic-widening, the default)")
    po.add_argument("--bodies", choices=("parametric", "mesh"), default="parametric",
                    help="the development population (parametric trunks, the default) or the test population "
                         "(MakeHuman body meshes from ../shared/data/makehuman, ray-cast; no method is tuned on it)")
    po.add_argument("--keep", type=Path, default=None,
                    help="keep each finished subject here (its row, its results file and its session without "
                         "the frames, to read it again without processing or renders) and, run again, go on "
                         "from them (long runs)")
    po.add_argument("--renders", type=Path, default=None, metavar="DIR",
                    help="keep the subjects' rendered sessions here and reuse them while the simulator's code is "
                         "unchanged: a rerun after a change to the reconstruction or the analysis costs "
                         "calibration and processing only")
    po.add_argument("--renders-max-gb", type=positive, default=40.0,
                    help="the renders kept at most (GB); the least recently used are removed first")
    po.add_argument("--subset", action="store_true",
                    help=f"the fixed subset for use between full runs: the population's first {SUBSET_SUBJECTS} "
                         f"subjects at scale {SUBSET_SCALE:g} (overrides --subjects and --scale)")
    po.add_argument("--reread", action="store_true",
                    help="run no subject: read each subject kept in --keep again off the results file kept "
                         "beside its row, with this commit's analysis (after a change to the analysis only), "
                         "and make the table of the kept rows")
    po.add_argument("--no-write", action="store_true", help="print only")

    def run_population(args: argparse.Namespace) -> int:
        from app.errors import UserError

        if args.subjects < 1:
            raise UserError("--subjects must be 1 or more")
        if args.keep is not None and args.keep.exists() and not args.keep.is_dir():
            raise UserError(f"{args.keep}: --keep must be a folder (the finished subjects are kept in it), this is a file")
        if args.subset:
            args.subjects, args.scale = SUBSET_SUBJECTS, SUBSET_SCALE
        if args.reread and (args.keep is None or not args.keep.is_dir()):
            raise UserError(f"--reread reads the subjects kept in --keep FOLDER again"
                            f"{'' if args.keep is None else f': {args.keep} is not a folder'}")
        if args.renders is not None and args.renders.exists() and not args.renders.is_dir():
            raise UserError(f"{args.renders}: --renders must be a folder (the rendered sessions are kept in it), "
                            "this is a file")
        subjects = 2 if args.quick else args.subjects
        workers = max(1, min(subjects, args.workers or os.cpu_count() or 1))
        images = None if args.no_write or not in_checkout() else DOCS.parent / "images"
        sheen = MAX_SHEEN if args.max_sheen is None else args.max_sheen
        renders = RenderCache(args.renders, args.renders_max_gb * 1e9) if args.renders is not None else None
        text, _ = run_population_bench(subjects, args.scale, args.seed, args.quick, workers, args.waveforms, images,
                                       sheen, args.keep, args.world, args.bodies, renders, args.reread)
        suffix = ("" if sheen == MAX_SHEEN else f" --max-sheen {sheen:g}") + (
            "" if args.world == WORLD else f" --world {args.world}") + (
            " --bodies mesh" if args.bodies == "mesh" else "")
        section = population_section(args.scale, sheen, args.world, args.bodies)
        return publish(args, section, f"Population (`photopft bench population --subjects {subjects} --scale "
                                       f"{args.scale:g} --seed {args.seed}{suffix}`)", text)

    po.set_defaults(run=run_population)
