"""What `process` will reconstruct, decided and checked before any map is made: the heads, their
light cycles, their binning and the passes the session needs (core/pipeline/process.py)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.analysis.values import PEAK_FLOW_REACH_S
from core.calibration.rig_profile import ProfileError, RigCalibration
from core.io.plausibility import head_intrinsics_problems
from core.io.session import SessionError, SessionFile
from core.reconstruction.binning import binned_head, working_binning
from core.reconstruction.photometric import CycleWindow, complete_cycles, windows_apart
from core.reconstruction.pipeline import ReconstructionSettings

# Work (maps times pixels) from which worker processes repay their start (docs/benchmarks.md, constants).
AUTO_WORKERS_PIXEL_MAPS = 5e6

# The first pass of a two-head `process` reconstructs a light cycle this often (docs/constants.md)
SURVEY_INTERVAL_S = 0.5


def survey_windows(windows: list[CycleWindow], frame_id: np.ndarray, frame_rate_hz: float) -> list[CycleWindow]:
    """Of a head's complete light cycles, those about SURVEY_INTERVAL_S apart."""
    return windows_apart(windows, frame_id, max(1, int(round(SURVEY_INTERVAL_S * frame_rate_hz))))


@dataclass(frozen=True)
class ProcessPlan:
    """A session's processing decided: which windows of which heads, at what binning, in which passes."""
    session_path: Path
    rig: object  # core.rig.Rig, with the calibration applied
    names: list[str]
    settings: ReconstructionSettings
    motion_compensation: str  # one of MOTION_MODES
    every: int  # frames between the session's maps
    maps_at: tuple[int, ...]  # frames whose full maps are kept
    factors: dict[str, int]  # each head's stream binning
    stream_heads: dict  # each head as its stream is binned
    complete: dict[str, list[CycleWindow]]  # each head's complete light cycles
    windows: dict[str, list[CycleWindow]]  # the cycles the session's maps are made of
    pseudo: dict[str, np.ndarray | None]  # each head's calibrated distant-light vectors, None if none
    geometry: bool  # the distance from the two heads' trunk widths and baseline (core/pipeline/distance_pass.py)
    survey: dict[str, list[CycleWindow]]  # the geometry's survey cycles
    dense_peak_flow: bool  # maps at every frame through each forced blow's peak flow (peak_flow_pass)
    peak_flow_windows: int  # as many as that pass will make if the session's volume is given

    @property
    def survey_count(self) -> int:
        return sum(len(w) for w in self.survey.values())

    @property
    def map_count(self) -> int:
        return sum(len(w) for w in self.windows.values())

    @property
    def total_windows(self) -> int:
        """Every cycle the passes reconstruct: the survey twice (distances, lights' outputs), the maps,
        the peak flow's."""
        return 2 * self.survey_count + self.map_count + self.peak_flow_windows

    def workers(self, asked: int | None) -> int:
        """Worker processes for `asked` (None: one per core when the work repays starting them)."""
        if asked is not None:
            return asked
        work = sum(len(self.windows[n]) * self.stream_heads[n].width * self.stream_heads[n].height for n in self.names)
        return (os.cpu_count() or 1) if work >= AUTO_WORKERS_PIXEL_MAPS else 1


def plan_process(session: SessionFile, session_path: str | os.PathLike, *, calibration: RigCalibration | None,
                 maps_at: list[int] | None, settings: ReconstructionSettings, heads: list[str] | None,
                 every: int | None, motion_compensation: str, volume_calibration, distance_from: str,
                 binning: int | None) -> ProcessPlan:
    """The plan of `process_session` (its arguments as it documents them); SessionError naming the
    session when it cannot be carried out."""
    if every is not None and every < 1:
        raise ValueError("every must be 1 or more")
    if distance_from not in ("heads", "photometric"):
        raise ValueError(f"distance_from must be 'heads' or 'photometric', got {distance_from!r}")
    rig = session.rig
    every = every or rig.cycle_length
    if calibration is not None:
        rig = _calibrated(rig, calibration, session_path)
    names = heads or session.heads
    for name in names:
        if name not in rig.heads:
            raise SessionError(f"{session_path} has no head {name!r} (heads: {', '.join(session.heads)})")
        if impossible := head_intrinsics_problems(rig.heads[name]):
            raise SessionError(f"{session_path}: the {name} head's intrinsics are impossible ({impossible[0]}): "
                               "no map can be made from them (the flow sensor's values: `photopft analyze`)")
    if not any(session.n_frames(name) for name in names):
        raise SessionError(f"{session_path} holds no camera frame: nothing to reconstruct")
    if binning is not None and binning < 1:
        raise ValueError("binning must be 1 or more")
    factors = {name: binning or working_binning(rig.heads[name]) for name in names}
    maps_at = sorted(set(maps_at or []))
    complete, windows = {}, {}
    for name in names:
        complete[name] = complete_cycles(session.light_index(name), session.frame_id(name), rig.cycle_length)
        windows[name] = _chosen(complete[name], session.frame_id(name), every, maps_at, name)
    pseudo = {}
    for name in names:
        vectors = calibration.heads[name].pseudo_light_vectors if calibration is not None else None
        pseudo[name] = None if vectors is not None and not np.any(vectors) else vectors
    geometry = (distance_from == "heads" and len(names) == 2 and bool(rig.baseline_mm)
                and settings.method == "near" and settings.distance == "photometric")
    survey = ({name: survey_windows(complete[name], session.frame_id(name), rig.frame_rate_hz) for name in names}
              if geometry else {})
    dense_peak_flow = volume_calibration is None and every == rig.cycle_length
    peak_flow_windows = 0
    if dense_peak_flow:
        blows = sum(1 for _, label in session.events() if label == "forced-start")
        span_frames = 2 * PEAK_FLOW_REACH_S * rig.frame_rate_hz * (1 - 1 / rig.cycle_length)
        peak_flow_windows = blows * len(names) * (1 + int(round(span_frames)))
    return ProcessPlan(Path(session_path), rig, list(names), settings, motion_compensation, every, tuple(maps_at),
                       factors, {name: binned_head(rig.heads[name], factors[name]) for name in names}, complete,
                       windows, pseudo, geometry, survey, dense_peak_flow, peak_flow_windows)


def _calibrated(rig, calibration: RigCalibration, session_path: str | os.PathLike):
    """The session's rig with the calibration's lights, if the calibration is for its sensors."""
    try:
        rig = calibration.apply(rig)
    except ProfileError as exc:
        raise SessionError(f"{session_path}: {exc}") from exc
    for name, head in rig.heads.items():
        cal = calibration.heads[name]
        if cal.extra.get("width") and (cal.extra["width"], cal.extra["height"]) != (head.width, head.height):
            raise SessionError(f"the calibration profile is for a {cal.extra['width']} x "
                               f"{cal.extra['height']} sensor, head {name} is {head.width} x {head.height}")
    return rig


def _chosen(complete: list[CycleWindow], frame_id: np.ndarray, every: int, maps_at: list[int],
            name: str) -> list[CycleWindow]:
    """The cycles `every` frames apart and those ending at the frames in `maps_at`, in order."""
    by_end = {w.newest: w for w in complete}
    missing = [i for i in maps_at if i not in by_end]
    if missing:
        raise SessionError(f"head {name}: no complete light cycle ends at frame(s) {missing}")
    chosen = windows_apart(complete, frame_id, every)
    chosen_ends = {w.newest for w in chosen}
    chosen += [by_end[i] for i in maps_at if i not in chosen_ends]
    return sorted(chosen, key=lambda w: w.newest)
