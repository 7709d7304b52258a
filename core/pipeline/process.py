"""`photopft process`: a session file in, a results file out (shared/spec/session-format.md)."""

from __future__ import annotations

import multiprocessing
import os
import queue
import time
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import h5py
import numba
import numpy as np

from core import __version__
from core.reconstruction.ambient import FlickerCorrection
from core.reconstruction.binning import binned_head, working_binning
from core.reconstruction.cycle import CycleFrame, cycle_frame, cycle_signal_of
from core.reconstruction.drift import light_gains_over_time
from core.analysis.optical_litres import OpticalLitres, subject_litres
from core.analysis.session_analysis import analyse_session
from core.calibration.spirometer import regression_features
from core.analysis.values import PEAK_FLOW_REACH_S, peak_flow_spans_s
from core.volume.metric import (WIDTH_SMOOTHING_S, HeadDisplacements, MetricVolume, metric_volume, on_maps_shown,
                                side_targets)
from core.analysis.compartments import tidal_compartments
from core.reconstruction.photometric import CycleWindow, complete_cycles, windows_apart
from core.rig import DARK
from core.io.outputs import atomic_output, stop_if_requested
from core.io.plausibility import head_intrinsics_problems
from core.reconstruction.pipeline import HeadMap, HeadReconstructor, ReconstructionSettings
from core.reconstruction.reflectance import RedundancyFit
from core.calibration.rig_profile import ProfileError, RigCalibration
from core.io.session import SessionError, SessionFile
from core.io.results import ResultsWriter
from core.volume.maps import REGIONS, DisplacementSums, DisplacementTracker, smooth_in_time
from core.volume.sides import paired_tilts, side_profile_mm
from core.volume.steps import maps_in_steps
from core.limits import Refusal
from core.pipeline.quality import (geometric_distance_refusal, maps_left_out_words, session_refusal, shading_refusal,
                                   sides_shown, volume_refusal)

# Work (maps times pixels) from which worker processes repay their start (docs/benchmarks.md, constants).
AUTO_WORKERS_PIXEL_MAPS = 5e6


@dataclass
class ProcessSummary:
    path: Path
    maps: dict[str, int]
    elapsed_s: float
    mean_distance_mm: dict[str, float]
    optical_refused: Refusal | None = None  # why no optical volume was written, when one was not
    # per head, the photometric fit's median distance less the two heads' geometric one, where that was used
    photometric_offset_mm: dict[str, float] = field(default_factory=dict)
    distance_refused: Refusal | None = None  # why the subject distance is not given, when it is not
    # per head, the median of its maps' sheen over the albedo (core/reconstruction/reflectance.py)
    sheen: dict[str, float] = field(default_factory=dict)


# The first pass of a two-head `process` (geometric_distances) reconstructs a light cycle this often:
# sway is slower than 0.25 Hz and the distances are smoothed over WIDTH_SMOOTHING_S (0.3 s; 2 survey maps a
# second sample it well: 0.5 s and 0.2 s gave the same volume, docs/history/volume-log.md "Axial sway read as breath")
SURVEY_INTERVAL_S = 0.5


def _survey_windows(windows: list[CycleWindow], frame_id: np.ndarray, frame_rate_hz: float) -> list[CycleWindow]:
    """Of a head's complete light cycles, those about SURVEY_INTERVAL_S apart."""
    return windows_apart(windows, frame_id, max(1, int(round(SURVEY_INTERVAL_S * frame_rate_hz))))


def geometric_distances(surveyed: dict, baseline_mm: float) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each head's subject distance (median depth, mm) over time from the two heads' geometry, as
    (timestamp_ns, distance_mm), from a first pass of photometric maps (_HeadResult per head).

    The photometric distance follows everything the light model leaves out: glossy skin put it
    800 mm short, LEDs 15 mm off hundreds of mm (docs/reconstruction.md), and even on matte skin
    with exact lights it scattered 1.5 mm from cycle to cycle and wandered 17 mm in 6 s. The two
    heads see the same trunk sides: their widths in pixels stand in the inverse ratio of their
    distances and the distances add up to the baseline (core/volume/metric.py, side_targets). Each
    map's shape (its median depth over its sides' depth) carries that to the map's median depth,
    smoothed over WIDTH_SMOOTHING_S. A head without a trunk in view gets none."""
    heads = {name: HeadDisplacements(r.timestamp_ns, r.sums) for name, r in surveyed.items()}
    if any(len(h.sums) == 0 for h in heads.values()):
        return {}
    targets, _ = side_targets(heads, baseline_mm)
    out = {}
    for name, r in surveyed.items():
        with np.errstate(invalid="ignore", divide="ignore"):
            distance = r.distance_mm * targets[name] / heads[name].side_mm
        shown = np.isfinite(distance)  # not a map whose sides an arm hides (_process_head)
        if not shown.any():
            continue
        t = r.timestamp_ns.astype(float)[shown]
        out[name] = (t, smooth_in_time(t / 1e9, distance[shown], WIDTH_SMOOTHING_S))
    return out


def _geometric_pass(results: ResultsWriter, jobs: list[_HeadJob], baseline_mm: float, workers: _HeadWorkers,
                    progress: Callable[[float], None]) -> tuple[dict, dict[str, float]]:
    """The first pass of a two-head `process`: the survey's photometric maps, each head's geometric
    distances (geometric_distances) and the photometric fit's median offset from them, written to
    /heads/<head>/photometric_survey."""
    surveyed = workers.run(jobs, progress)
    geometric = geometric_distances({r.name: r for r in surveyed}, baseline_mm)
    offsets = {}
    for r in surveyed:
        t, d = geometric.get(r.name, (np.zeros(0), np.zeros(0)))
        along = on_maps_shown(d, np.isin(r.timestamp_ns.astype(float), t))  # NaN on the maps left out for an arm
        if np.isfinite(r.distance_mm - along).any():
            offsets[r.name] = float(np.nanmedian(r.distance_mm - along))
        results.photometric_survey(r.name, r.timestamp_ns, r.distance_mm, along, offsets.get(r.name))
    return geometric, offsets


def _light_gain_pass(results: ResultsWriter, session: SessionFile, rig, survey: dict[str, list[CycleWindow]],
                     plans: dict[str, list[CycleWindow]], geometric: dict, settings: ReconstructionSettings,
                     pseudo: dict, motion_compensation: str, binning: dict[str, int], workers: "_HeadWorkers",
                     progress: Callable[[float], None]) -> dict[str, np.ndarray]:
    """The lights' outputs through the session (core/reconstruction/drift.py): the survey's cycles made
    again at the two heads' distance, each read for its lights' outputs, smoothed; {head: (len(plans[head]), 4)
    factors of the intensities for each planned window}, written to /heads/<head>/light_gain."""
    jobs = []
    for name, (t, d) in geometric.items():
        stamps = session.timestamp_ns(name)
        at = np.array([stamps[w.newest] for w in survey[name]], dtype=float)
        jobs.append(_HeadJob(session.path, rig, name, survey[name], settings, pseudo[name], motion_compensation,
                             (), np.interp(at, t, d), binning[name], 1))
    out = {}
    for r in workers.run(jobs, progress):
        stamps = session.timestamp_ns(r.name)
        planned = np.array([stamps[w.newest] for w in plans[r.name]], dtype=float) / 1e9
        measured_t = r.timestamp_ns.astype(float) / 1e9
        # the readings' outliers found and the smoothing made once, at the planned windows and the readings alike
        followed = light_gains_over_time(measured_t, r.light_gain, np.r_[planned, measured_t])
        out[r.name] = followed[:len(planned)]
        results.light_gain(r.name, r.timestamp_ns, r.light_gain, followed[len(planned):])
    return out


def trunk_area_m2(valid_pixels: np.ndarray, distance_mm: np.ndarray, head) -> np.ndarray:
    """The area of the subject a head's maps hold (m^2): valid pixels times each pixel's footprint at
    the map's distance."""
    return (np.asarray(valid_pixels, float) * (np.asarray(distance_mm, float) / head.fx)
            * (np.asarray(distance_mm, float) / head.fy) * 1e-6)


class DarkFeed:
    """A head's dark frames, handed to its FlickerCorrection (core/reconstruction/ambient.py) as the cycles move on:
    `flicker_of(window)` gives each frame's flicker, fitted on the dark frames around that cycle."""

    def __init__(self, frames: h5py.Dataset, light_index: np.ndarray, timestamp_ns: np.ndarray, mains_hz: float,
                 binning: int = 1) -> None:
        self.correction = FlickerCorrection(2.0 * mains_hz, binning=binning)
        self._frames = frames
        self._t = np.asarray(timestamp_ns, dtype=np.int64) / 1e9
        self._darks = np.flatnonzero(np.asarray(light_index) == DARK)
        self._dark_t = self._t[self._darks]
        self._next = 0

    def flicker_of(self, window: CycleWindow) -> Callable[[CycleFrame], np.ndarray | None]:
        t_cycle = float(self._t[window.newest])
        start, stop = self.correction.span(t_cycle)
        self._next = max(self._next, int(np.searchsorted(self._dark_t, start)))
        while self._next < len(self._darks) and self._dark_t[self._next] <= stop:
            j = int(self._darks[self._next])
            self.correction.add_dark(float(self._t[j]), self._frames[j])
            self._next += 1
        return lambda frame: self.correction.excess(frame.time_s, t_cycle)

    @property
    def flicker_share(self) -> float:
        """The room light's flicker as found (amplitude over the mean dark level, median over the
        fits); 0 when none stood above the dark frames' noise."""
        return float(np.median(self.correction.amplitudes)) if self.correction.amplitudes else 0.0


# How each light's frame is brought to its cycle's newest instant (core/reconstruction/cycle.py): a
# recorded session has the cycle after each one, so `process` interpolates towards it; the live view,
# which has only the frames so far, extrapolates from the cycle before (`photopft bench motion`).
MOTION_MODES = ("none", "extrapolated", "interpolated")


def motion_mode(motion_compensation: bool | str) -> str:
    """The mode of MOTION_MODES that `process`'s motion_compensation names: True interpolates, False is none."""
    mode = {True: "interpolated", False: "none"}.get(motion_compensation, motion_compensation)
    if mode not in MOTION_MODES:
        raise ValueError(f"motion_compensation must be one of {', '.join(MOTION_MODES)}, got {motion_compensation!r}")
    return mode


def neighbour_cycles(windows_by_id: dict[int, CycleWindow], newest_id: int, cycle_length: int,
                     mode: str) -> tuple[CycleWindow | None, CycleWindow | None]:
    """(the cycle before, the cycle after) a window whose newest frame has id newest_id, as `mode` uses
    them; the last cycle of a recording, which has none after it, is extrapolated."""
    if mode == "none":
        return None, None
    previous = windows_by_id.get(newest_id - cycle_length)
    following = windows_by_id.get(newest_id + cycle_length) if mode == "interpolated" else None
    return previous, following


def cycle_signal(frames: h5py.Dataset, window: CycleWindow, previous: CycleWindow | None, max_value: int,
                 cache: dict[int, CycleFrame], frame_id: np.ndarray, timestamp_ns: np.ndarray,
                 flicker: Callable[[CycleFrame], np.ndarray | None] | None = None, binning: int = 1,
                 following: CycleWindow | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window's signal from a session's frames (core/reconstruction/cycle.py, as the live view makes it): with
    `previous` (the cycle one period earlier) motion-compensated, or with `following` too (the cycle one
    period later) interpolated towards it; `flicker` (DarkFeed.flicker_of,
    binned alike) the room light's flicker in a frame; `cache` keeps each frame read."""
    def frame(i: int) -> CycleFrame:
        if i not in cache:
            cache[i] = cycle_frame(frames[i], binning, max_value, timestamp_ns[i] / 1e9, int(frame_id[i]))
        return cache[i]

    return cycle_signal_of([frame(i) for i in window.lit], frame(window.dark),
                           [frame(i) for i in previous.lit] if previous is not None else None, flicker,
                           [frame(i) for i in following.lit] if following is not None else None)


def process_session(session_path: str | os.PathLike, output: str | os.PathLike, *,
                    calibration: RigCalibration | None = None, maps_at: list[int] | None = None,
                    settings: ReconstructionSettings | None = None, heads: list[str] | None = None,
                    every: int | None = None, motion_compensation: bool | str = True, volume_calibration=None,
                    progress: Callable[[float], None] | None = None, workers: int | None = 1,
                    distance_from: str = "heads", binning: int | None = None) -> ProcessSummary:
    """Reconstruct every complete light cycle of each head: windows of one cycle's frames, sliding
    by `every` frames (default: the cycle's length, each cycle once; 1: a map at every frame).
    distance_from: "heads" (two heads and a baseline: each map scaled to the distance the two
    heads' trunk widths give, `geometric_distances`; one head: as "photometric") or
    "photometric" (each head's own photometric fit, core/reconstruction/distance.py).
    With a map every light cycle (`every` the cycle's length) and a metric volume, maps at every frame
    are made through each forced blow's peak flow too (_peak_flow_pass, /peak_flow_volume).
    `workers` > 1 reconstructs the heads in that many processes at once (one head each, at most);
    None: one per core when the work repays starting them (AUTO_WORKERS_PIXEL_MAPS).
    `binning`: the stream reconstructed on binning x binning bins; None: each head binned to about
    WORKING_WIDTH_PX wide, as the live view does (core/reconstruction/binning.py); 1: every pixel. Maps asked for
    in `maps_at` keep every pixel either way. `motion_compensation` (MOTION_MODES; True: "interpolated")
    brings each light's frame to its cycle's newest instant.

    Maps "at frame i" come from the newest complete cycle ending at frame i; frames asked for
    in `maps_at` that end no complete cycle are reported as an error.
    """
    started = time.perf_counter()
    settings = settings or ReconstructionSettings()
    if every is not None and every < 1:
        raise ValueError("every must be 1 or more")
    if distance_from not in ("heads", "photometric"):
        raise ValueError(f"distance_from must be 'heads' or 'photometric', got {distance_from!r}")
    motion_compensation = motion_mode(motion_compensation)
    with SessionFile(session_path) as session:
        rig = session.rig
        every = every or rig.cycle_length
        if calibration is not None:
            try:
                rig = calibration.apply(rig)
            except ProfileError as exc:
                raise SessionError(f"{session_path}: {exc}") from exc
            for name, head in rig.heads.items():
                cal = calibration.heads[name]
                if cal.extra.get("width") and (cal.extra["width"], cal.extra["height"]) != (head.width, head.height):
                    raise SessionError(f"the calibration profile is for a {cal.extra['width']} x "
                                       f"{cal.extra['height']} sensor, head {name} is {head.width} x {head.height}")
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
        stream_heads = {name: binned_head(rig.heads[name], factors[name]) for name in names}
        maps_at = sorted(set(maps_at or []))
        counts, distances, displacements, occluded, out_of_view, areas, sheen = {}, {}, {}, {}, {}, {}, {}
        with atomic_output(output) as partial, h5py.File(partial, "w") as out, ExitStack() as stack:
            results = ResultsWriter(out, session_path, f"photopft {__version__}", method=settings.method,
                                    integrator=settings.integrator,
                                    calibration=calibration.created if calibration is not None else "session /rig",
                                    motion_compensation=motion_compensation != "none")
            total_windows = 0
            plans, complete = {}, {}
            for name in names:
                windows = complete[name] = complete_cycles(session.light_index(name), session.frame_id(name),
                                                           rig.cycle_length)
                by_end = {w.newest: w for w in windows}
                missing = [i for i in maps_at if i not in by_end]
                if missing:
                    raise SessionError(f"head {name}: no complete light cycle ends at frame(s) {missing}")
                chosen = windows_apart(windows, session.frame_id(name), every)
                chosen_ends = {w.newest for w in chosen}
                chosen += [by_end[i] for i in maps_at if i not in chosen_ends]
                chosen.sort(key=lambda w: w.newest)
                plans[name] = chosen
                total_windows += len(chosen)
            pseudo = {}
            for name in names:
                vectors = calibration.heads[name].pseudo_light_vectors if calibration is not None else None
                pseudo[name] = None if vectors is not None and not np.any(vectors) else vectors
            geometry = (distance_from == "heads" and len(names) == 2 and bool(rig.baseline_mm)
                        and settings.method == "near" and settings.distance == "photometric")
            results.attr("distance_from", "two heads' trunk widths and baseline" if geometry else "photometric fit")
            survey = {}
            if geometry:
                survey = {name: _survey_windows(complete[name], session.frame_id(name), rig.frame_rate_hz)
                          for name in names}
                survey_windows = sum(len(w) for w in survey.values())
                total_windows += 2 * survey_windows  # the photometric survey, the lights' outputs
            # the maps at every frame through each forced blow's peak flow (_peak_flow_pass), as many as it
            # will make if the session's volume is given: each head's reference again and the frames of the
            # span that the session's maps leave out
            peak_flow_windows = 0
            dense_peak_flow = volume_calibration is None and every == rig.cycle_length
            if dense_peak_flow:
                blows = sum(1 for _, label in session.events() if label == "forced-start")
                span_frames = 2 * PEAK_FLOW_REACH_S * rig.frame_rate_hz * (1 - 1 / rig.cycle_length)
                peak_flow_windows = blows * len(names) * (1 + int(round(span_frames)))
                total_windows += peak_flow_windows
            if workers is None:
                work = sum(len(plans[n]) * stream_heads[n].width * stream_heads[n].height for n in names)
                workers = (os.cpu_count() or 1) if work >= AUTO_WORKERS_PIXEL_MAPS else 1
            done_before = 0

            def overall(fraction_of_pass: float, pass_windows: int) -> None:
                if progress is not None and total_windows:
                    progress((done_before + fraction_of_pass * pass_windows) / total_windows)

            pool = stack.enter_context(_HeadWorkers(workers, len(names)))  # both passes, and the peak flow's
            geometric, offsets, light_gains = {}, {}, {}
            if geometry:
                jobs = [_HeadJob(Path(session_path), rig, name, survey[name], settings, pseudo[name],
                                 motion_compensation, (), binning=factors[name]) for name in names]
                geometric, offsets = _geometric_pass(results, jobs, rig.baseline_mm, pool,
                                                     lambda f: overall(f, survey_windows))
                done_before = survey_windows
                light_gains = _light_gain_pass(results, session, rig, survey, plans, geometric, settings, pseudo,
                                               motion_compensation, factors, pool,
                                               lambda f: overall(f, survey_windows))
                done_before += survey_windows
            jobs = []
            # the sides' agreement (core/volume/sides.py) is looked at on maps made at the geometric distance
            maps_per_survey = max(1, int(round(SURVEY_INTERVAL_S * rig.frame_rate_hz / every)))
            for name in names:
                distances_mm = None
                if name in geometric:
                    stamps = session.timestamp_ns(name)
                    t, d = geometric[name]
                    distances_mm = np.interp(np.array([stamps[w.newest] for w in plans[name]], dtype=float), t, d)
                jobs.append(_HeadJob(Path(session_path), rig, name, plans[name], settings, pseudo[name],
                                     motion_compensation, tuple(maps_at), distances_mm, factors[name],
                                     maps_per_survey if geometric else 0, light_gains.get(name)))
            pass_windows = sum(len(plans[n]) for n in names)
            profiles, made = {}, {}
            for result in pool.run(jobs, lambda f: overall(f, pass_windows)):
                made[result.name] = replace(result, saved_normals=[], saved_depth=[])  # the full maps are written
                profiles[result.name] = result.side_profiles
                name, head = result.name, rig.heads[result.name]
                results.head(name, {"timestamp_ns": result.timestamp_ns, "frame_index": result.frame_index,
                                    "distance_mm": result.distance_mm, "gradient_volume": result.gradient_volume,
                                    "valid_pixels": result.valid_pixels,
                                    "occluded_side_share": result.occluded_side_share,
                                    "side_out_of_view_share": result.side_out_of_view_share,
                                    "sheen": result.sheen},
                             # binning: the stream's; valid_pixels count its bins
                             {"ambient_flicker": result.ambient_flicker, "binning": np.int64(factors[name])},
                             result.saved_index, result.saved_normals, result.saved_depth,
                             (head.height, head.width))
                counts[name] = len(result.frame_index)
                displacements[name] = HeadDisplacements(result.timestamp_ns, result.sums)
                distances[name] = (float(np.nanmean(result.distance_mm)) if len(result.distance_mm)
                                   else float("nan"))
                occluded[name] = result.occluded_side_share
                out_of_view[name] = result.side_out_of_view_share
                sheen[name] = float(np.nanmedian(result.sheen)) if np.isfinite(result.sheen).any() else float("nan")
                areas[name] = trunk_area_m2(result.valid_pixels, result.distance_mm, stream_heads[name])
            done_before += pass_windows
            tilts = paired_tilts(*profiles.values()) if len(profiles) == 2 and geometric else np.zeros(0)
            if np.isfinite(tilts).any():
                results.attr("sides_tilt", float(np.nanmedian(tilts)))
            distance_refused = geometric_distance_refusal(occluded) if geometry else None
            if distance_refused is not None:
                results.refuse("distance", distance_refused)
            refused = session_refusal(distances, areas, occluded, out_of_view)
            if refused is not None:
                results.refuse("optical", refused)
            bent = shading_refusal(sheen, tilts)
            sides = {name: sides_shown(occluded[name]) for name in displacements}
            in_step = {name: maps_in_steps(d.timestamp_ns, d.body_shift_mm) for name, d in displacements.items()}
            shown = {name: sides[name] & ~in_step[name] for name in displacements}
            if all(d.sums for d in displacements.values()):  # the sums as they came, for other signals
                targets, _ = side_targets(displacements, rig.baseline_mm)
                for name, d in displacements.items():
                    results.displacement_sums(name, d.timestamp_ns, d.sums, targets[name], shown[name],
                                              REGIONS + ("all",))
            metric = (metric_volume({n: d.of_maps(shown[n]) for n, d in displacements.items()}, rig.baseline_mm)
                      if all(counts.values()) and refused is None and all(m.any() for m in shown.values()) else None)
            for name, level in (metric.levels.items() if metric is not None else ()):
                results.attr(f"level_{name}", level)  # the session's or each map's own (core/volume/metric.py)
            if metric is not None and (refused := volume_refusal(metric)) is not None:
                metric = None
                results.refuse("optical", refused)
            in_view = metric is not None and np.isfinite(metric.volume_l).all()  # a trunk in every head's view
            litres = None
            if in_view:
                first = next(iter(displacements))
                gapped = metric.with_gaps(displacements[first].timestamp_ns,
                                          {n: (d.timestamp_ns, shown[n]) for n, d in displacements.items()})
                litres = subject_litres(session, gapped)
                results.subject_calibration(litres.calibration, litres.not_calibrated)
            if bent is not None and litres is not None and litres.calibrated:  # a scale the calibration takes
                results.attr("shading_note", f"{bent.reason}; the subject's calibration takes the scale this changes")
            elif bent is not None:
                in_view, metric = False, None
                if refused is None:
                    refused = bent
                    results.refuse("optical", bent)
            if in_view and dense_peak_flow:
                _peak_flow_pass(results, session, {job.name: job for job in jobs}, made, complete, metric, pool,
                                lambda f: overall(f, peak_flow_windows), litres)
            if in_view:
                compartments = tidal_compartments(session, metric)
                metric = gapped
                left_out = maps_left_out_words(displacements, sides, in_step)
                if left_out:
                    results.attr("maps_left_out", left_out)
                results.metric_volume(metric.timestamp_ns, metric.volume_l, metric.scale_from, metric.heads,
                                      metric.side_distance_mm, metric.regions, compartments, metric.head_regions)
            if volume_calibration is not None:
                _write_regression_volume(results, out, names, volume_calibration)
            elif in_view:
                results.volume(metric.timestamp_ns, litres.volume_l(metric), litres.method,
                               metric_scale_from=metric.scale_from, **litres.attrs())
            _write_parameters(session_path, results)
    if progress is not None:
        progress(1.0)
    return ProcessSummary(Path(output), counts, time.perf_counter() - started, distances, refused, offsets,
                          distance_refused, sheen)


# The volume at every frame is not smoothed: the analysis smooths a blow's maps as its noise needs (docs/constants.md)
PEAK_FLOW_SMOOTHING_S = 0.0


def _peak_flow_pass(results: ResultsWriter, session: SessionFile, jobs: dict[str, "_HeadJob"],
                    made: dict[str, "_HeadResult"], complete: dict[str, list[CycleWindow]], metric: MetricVolume,
                    workers: "_HeadWorkers", progress: Callable[[float], None], litres: "OpticalLitres") -> None:
    """/peak_flow_volume: maps at every frame through each forced blow's peak flow (peak_flow_spans_s on
    the session's volume), beside the session's maps, and the metric volume of the two together there,
    unsmoothed (PEAK_FLOW_SMOOTHING_S). Error-free, one map a light cycle reads PEF within 10 % on 78 %
    of the standard waveforms, one map a frame on 95 %; with 0-35 mL of noise a map, as the analysis
    reads them, 92 % and 96 % of those it gives (docs/history/volume-log.md, "Peak flow"). Each head's new maps
    follow its reference map (made again first), distances and lights' outputs as the session's maps
    have them; the volume takes the levels /metric_volume took. `progress` gets the share of its maps made."""
    t0 = int(metric.timestamp_ns[0])
    events = [((int(ts) - t0) / 1e9, label) for ts, label in session.events()]
    spans_s = peak_flow_spans_s((metric.timestamp_ns - t0) / 1e9, metric.volume_l, events)
    if not spans_s:
        return
    spans_ns = [(t0 + int(a * 1e9), t0 + int(b * 1e9)) for a, b in spans_s]
    new_jobs = {}
    for name, job in jobs.items():
        stamps = session.timestamp_ns(name)
        planned = {w.newest for w in job.windows}
        inside = [w for w in complete[name] if w.newest not in planned
                  and any(a <= stamps[w.newest] <= b for a, b in spans_ns)]
        first = next((i for i, s in enumerate(made[name].sums) if np.isfinite(s.reference.get("all", np.nan))), None)
        if not inside or first is None:
            return
        windows = [job.windows[first]] + inside
        planned_s = made[name].timestamp_ns.astype(float) / 1e9
        at_s = np.array([stamps[w.newest] for w in windows], dtype=float) / 1e9

        def along(values: np.ndarray | None) -> np.ndarray | None:
            if values is None:
                return None
            values = np.asarray(values, dtype=float)
            columns = values.reshape(len(values), -1).T
            return np.stack([np.interp(at_s, planned_s, c) for c in columns], axis=-1).reshape(len(at_s), *values.shape[1:])

        new_jobs[name] = replace(job, windows=windows, maps_at=(), distances_mm=along(job.distances_mm),
                                 profile_every=0, light_gains=along(job.light_gains))
    heads = {}
    for r in workers.run(list(new_jobs.values()), progress):
        main = made[r.name]
        t = np.concatenate([main.timestamp_ns, r.timestamp_ns[1:]])
        sums = list(main.sums) + list(r.sums[1:])
        occluded = np.concatenate([main.occluded_side_share, r.occluded_side_share[1:]])
        order = np.argsort(t, kind="stable")
        shown = sides_shown(occluded[order])
        heads[r.name] = HeadDisplacements(t[order], [sums[i] for i in order]).of_maps(shown)
    if not all(len(h.timestamp_ns) for h in heads.values()):
        return
    dense = metric_volume({n: heads[n] for n in jobs}, jobs[next(iter(jobs))].rig.baseline_mm,
                          levels_of=metric.levels, smoothing_s=PEAK_FLOW_SMOOTHING_S)
    inside = np.zeros(len(dense.timestamp_ns), dtype=bool)
    for a, b in spans_ns:
        inside |= (dense.timestamp_ns >= a) & (dense.timestamp_ns <= b)
    results.peak_flow_volume(dense.timestamp_ns[inside], litres.volume_l(dense)[inside], spans_ns,
                             {n: len(j.windows) - 1 for n, j in new_jobs.items()})


@dataclass(frozen=True)
class _HeadJob:
    """One head's share of `process_session`, picklable for a worker process."""
    session_path: Path
    rig: object  # core.rig.Rig
    name: str
    windows: list[CycleWindow]
    settings: ReconstructionSettings
    pseudo_light_vectors: np.ndarray | None
    motion_compensation: str  # one of MOTION_MODES
    maps_at: tuple[int, ...]
    distances_mm: np.ndarray | None = None  # each window's subject distance, when known from elsewhere
    binning: int = 1  # the stream reconstructed on binning x binning bins (maps_at frames at full resolution)
    profile_every: int = 0  # every so many maps, the trunk's sides along its height (side_profile_mm); 0 none
    # (len(windows), 4) the lights' outputs at each window as factors of the rig's intensities
    # (light_gains_over_time); None: the intensities as calibrated
    light_gains: np.ndarray | None = None


@dataclass
class _HeadResult:
    name: str
    timestamp_ns: np.ndarray
    frame_index: np.ndarray
    distance_mm: np.ndarray
    gradient_volume: np.ndarray
    valid_pixels: np.ndarray
    occluded_side_share: np.ndarray
    side_out_of_view_share: np.ndarray
    sheen: np.ndarray
    saved_index: list[int]
    saved_normals: list[np.ndarray]
    saved_depth: list[np.ndarray]
    sums: list
    ambient_flicker: float = 0.0  # DarkFeed.flicker_share
    # (n, 4) every job.profile_every maps the lights' outputs against the intensities solved with (NaN between)
    light_gain: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    # (timestamp_ns, side_profile_mm) every job.profile_every maps
    side_profiles: tuple[np.ndarray, list] = field(default_factory=lambda: (np.zeros(0, np.int64), []))


def _process_head(job: _HeadJob, tick: Callable[[], None]) -> _HeadResult:
    """Reconstructs one head's windows in order (the running distance and the displacement tracker
    follow the stream); `tick` after each."""
    rig, name = job.rig, job.name
    full_head = rig.heads[name]
    head = binned_head(full_head, job.binning)
    reconstructor = HeadReconstructor(head, job.pseudo_light_vectors, job.settings)
    full_reconstructor = None  # the maps asked for at full resolution, when the stream is binned
    tracker = DisplacementTracker(head)
    rows: dict[str, list] = {"timestamp_ns": [], "frame_index": [], "distance_mm": [], "gradient_volume": [],
                             "valid_pixels": [], "occluded_side_share": [], "side_out_of_view_share": [], "sheen": []}
    saved_index, saved_normals, saved_depth, sums, gains = [], [], [], [], []
    profile_times, profiles = [], []
    near = job.settings.method == "near"  # the sheen's fit needs the near lights' per-pixel irradiance
    with SessionFile(job.session_path) as session:
        frames = session.frames(name)
        stamps = session.timestamp_ns(name)
        ids = session.frame_id(name)
        all_windows = {int(ids[w.newest]): w for w in complete_cycles(session.light_index(name), ids,
                                                                       rig.cycle_length)}
        cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        darks = DarkFeed(frames, session.light_index(name), stamps, rig.mains_hz, job.binning)
        for number, window in enumerate(job.windows):
            stop_if_requested()
            for stale in [k for k in cache if k < window.newest - 2 * rig.cycle_length]:
                del cache[stale]
            previous, following = neighbour_cycles(all_windows, int(ids[window.newest]), rig.cycle_length,
                                                   job.motion_compensation)
            signal, saturated, dark = cycle_signal(frames, window, previous, head.max_value, cache, ids, stamps,
                                                   darks.flicker_of(window), job.binning, following)
            known = job.distances_mm[number] if job.distances_mm is not None else np.nan
            if job.light_gains is not None:
                reconstructor.intensity_factors = job.light_gains[number]
            result = reconstructor.reconstruct(signal, saturated, dark, float(known) if np.isfinite(known) else None)
            rows["timestamp_ns"].append(stamps[window.newest])
            rows["frame_index"].append(window.newest)
            rows["distance_mm"].append(result.distance_mm)
            rows["gradient_volume"].append(result.gradient_volume)
            rows["valid_pixels"].append(int(result.mask.sum()))
            for key in ("occluded_side_share", "side_out_of_view_share"):
                rows[key].append(result.extra.get(key, np.nan))
            looked_at = job.profile_every and number % job.profile_every == 0
            redundancy = (reconstructor.redundancy(signal, saturated, result) if looked_at and near
                          else RedundancyFit.none())
            rows["sheen"].append(redundancy.sheen)
            gains.append(redundancy.light_gain)
            if sides_shown(rows["occluded_side_share"][-1]):
                sums.append(tracker.add(result.depth_mm, result.mask, result.silhouette, known))
            else:  # an arm hides the sides the map is referred to: left out (MAX_HIDDEN_MAPS), nor the reference
                sums.append(DisplacementSums(float("nan"), float("nan"), {}, {}))
            if looked_at:
                profile_times.append(stamps[window.newest])
                profiles.append(side_profile_mm(result.depth_mm, result.mask, result.silhouette, head))
            if window.newest in job.maps_at:
                full = result
                if job.binning > 1:
                    full_reconstructor = full_reconstructor or HeadReconstructor(full_head, job.pseudo_light_vectors,
                                                                                 job.settings)
                    full_reconstructor.intensity_factors = reconstructor.intensity_factors
                    full_darks = DarkFeed(frames, session.light_index(name), stamps, rig.mains_hz)
                    full = full_reconstructor.reconstruct(
                        *cycle_signal(frames, window, previous, head.max_value, {}, ids, stamps,
                                      full_darks.flicker_of(window), following=following),
                        float(result.distance_mm))
                saved_index.append(window.newest)
                saved_normals.append(full.normals.astype(np.float32))
                saved_depth.append(full.depth_mm.astype(np.float32))
            tick()
    return _HeadResult(name, np.asarray(rows["timestamp_ns"], dtype=np.int64),
                       np.asarray(rows["frame_index"], dtype=np.int64),
                       np.asarray(rows["distance_mm"], dtype=np.float64),
                       np.asarray(rows["gradient_volume"], dtype=np.float64),
                       np.asarray(rows["valid_pixels"], dtype=np.int64),
                       np.asarray(rows["occluded_side_share"], dtype=np.float64),
                       np.asarray(rows["side_out_of_view_share"], dtype=np.float64),
                       np.asarray(rows["sheen"], dtype=np.float64), saved_index, saved_normals,
                       saved_depth, sums, darks.flicker_share,
                       light_gain=np.asarray(gains, dtype=np.float64).reshape(-1, 4),
                       side_profiles=(np.asarray(profile_times, dtype=np.int64), profiles))


_worker_ticks = None  # in a worker process: the queue its progress goes to


def use_threads(threads: int) -> None:
    """The calling thread's numba kernels, and the DCTs that follow them (core/reconstruction/integrate.py),
    on `threads` cores: at least one, at most numba's pool. Per thread: a live head's reconstruction
    thread, a worker process, a Dask task each take their share of the cores."""
    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))


def _start_worker(ticks, threads: int) -> None:
    global _worker_ticks
    _worker_ticks = ticks
    use_threads(threads)


def _process_head_in_worker(job: _HeadJob) -> _HeadResult:
    return _process_head(job, lambda: _worker_ticks.put(1))


class _HeadWorkers:
    """Where `process_session` reconstructs its heads: here (workers <= 1), or in spawned worker
    processes (fork is unsafe once OpenMP threads run), each with its share of the cores, started
    once for both of its passes: a worker takes about 2 s to start (imports, numba's cached kernels),
    and a pool per pass spent that twice."""

    def __init__(self, workers: int, heads: int) -> None:
        self._count = min(workers, heads)
        self._pool = None
        self._ticks = None

    def __enter__(self) -> "_HeadWorkers":
        if self._count > 1:
            context = multiprocessing.get_context("spawn")
            self._ticks = context.Queue()
            self._pool = context.Pool(self._count, initializer=_start_worker,
                                      initargs=(self._ticks, max(1, (os.cpu_count() or 1) // self._count)))
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()

    def run(self, jobs: list[_HeadJob], progress: Callable[[float], None]) -> list[_HeadResult]:
        """Each job's head reconstructed; `progress` gets the share of their windows done."""
        done = 0
        total = sum(len(job.windows) for job in jobs)

        def tick(count: int = 1) -> None:
            nonlocal done
            done += count
            if total:
                progress(done / total)

        if self._pool is None or len(jobs) <= 1:
            return [_process_head(job, tick) for job in jobs]
        pending = self._pool.map_async(_process_head_in_worker, jobs, chunksize=1)
        while not pending.ready():
            stop_if_requested()
            try:
                tick(self._ticks.get(timeout=0.2))
            except queue.Empty:
                pass
        return pending.get()


def maps_at(session_path: str | os.PathLike, head_name: str, frame_indices: list[int], *,
            settings: ReconstructionSettings | None = None, motion_compensation: bool | str = True,
            distances_mm: list[float] | None = None, light_gains: np.ndarray | None = None) -> list[HeadMap]:
    """Maps of one head at the given frames (each the newest complete cycle ending at or before
    it), by the same reconstruction `process_session` runs, for reports and reviews.
    distances_mm: the subject's distance at each frame as `process` measured it (processed_distance_mm);
    without it, or where it is NaN, each map's distance is the photometric fit's, which the
    lights' and the skin's errors move by tens to hundreds of millimetres (docs/reconstruction.md).
    light_gains: (len(frame_indices), 4) the lights' outputs `process` followed at those frames
    (processed_light_gains); None: the intensities as calibrated."""
    settings = settings or ReconstructionSettings()
    mode = motion_mode(motion_compensation)
    with SessionFile(session_path) as session:
        rig = session.rig
        if head_name not in rig.heads:
            raise SessionError(f"{session_path} has no head {head_name!r}")
        head = rig.heads[head_name]
        ids = session.frame_id(head_name)
        windows = complete_cycles(session.light_index(head_name), ids, rig.cycle_length)
        if not windows:
            raise SessionError(f"head {head_name}: no complete light cycle in {session_path}")
        ends = np.array([w.newest for w in windows])
        by_id = {int(ids[w.newest]): w for w in windows}
        frames = session.frames(head_name)
        reconstructor = HeadReconstructor(head, None, settings)
        lights, stamps = session.light_index(head_name), session.timestamp_ns(head_name)
        out = []
        known = list(distances_mm) if distances_mm is not None else [float("nan")] * len(frame_indices)
        for number, (index, distance) in enumerate(zip(frame_indices, known)):
            if light_gains is not None:
                reconstructor.intensity_factors = np.asarray(light_gains[number], dtype=float)
            window = windows[max(0, int(np.searchsorted(ends, index, side="right")) - 1)]
            previous, following = neighbour_cycles(by_id, int(ids[window.newest]), rig.cycle_length, mode)
            darks = DarkFeed(frames, lights, stamps, rig.mains_hz)  # a feed per frame asked: they come in any order
            signal, saturated, dark = cycle_signal(frames, window, previous, head.max_value, {}, ids, stamps,
                                                   darks.flicker_of(window), following=following)
            out.append(reconstructor.reconstruct(signal, saturated, dark,
                                                 float(distance) if np.isfinite(distance) else None))
    return out


def _write_parameters(session_path: str | os.PathLike, results: ResultsWriter) -> None:
    """Pulmonary function values: from the flow sensor where the session has one (the reference
    instrument), else from /volume (the optical volume in litres); the `source` attribute says
    which. The optical values are also kept as attributes of /volume, beside the flow sensor's."""
    label = results.out["volume"].attrs.get("label") if results.has_volume() else None
    report = analyse_session(session_path, optical_volume=results.written_volume(),
                             optical_label=None if label is None else str(label),
                             optical_peak_flow=results.written_peak_flow_volume())
    if report.optical is not None:
        results.volume_parameters(report.optical.parameters())
    if report.flow_sensor is not None:
        results.parameters("flow sensor", report.flow_sensor.parameters(), report.flow_volume)
    elif report.optical is not None:
        results.parameters(f"optical: {results.out['volume'].attrs['method']}", report.optical.parameters())
    else:
        results.parameters("none: " + (f"the flow sensor's values refused ({report.flow_refused})"
                                       if report.flow_refused else "no flow sensor")
                           + " and no optical volume in litres", {})



def _write_regression_volume(results: ResultsWriter, out: h5py.File, heads: list[str], calibration) -> None:
    """/volume from the thesis' regression (eqs 5.1-5.3) on the gradient volume, pixels and distance."""
    t, features = regression_features(lambda head, name: out[f"heads/{head}/{name}"][:], heads)
    results.volume(t, calibration.volume_l(features),
                   "thesis regression (eqs 5.1-5.3) on gradient volume, valid pixels and distance",
                   calibration_created=calibration.created, calibration_sessions=",".join(calibration.sessions))
