"""`photopft process`: a session file in, a results file out (shared/spec/session-format.md).

The stages, in order: the plan (core/pipeline/plan.py), the survey of the subject's distance and the
lights' outputs (core/pipeline/distance_pass.py), each head's maps (core/pipeline/head_maps.py), the
quality rules, the volume and the values (core/pipeline/volume_stage.py)."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import h5py
import numpy as np

from core import __version__
from core.calibration.rig_profile import RigCalibration
from core.io.outputs import atomic_output
from core.io.results import ResultsWriter
from core.io.session import SessionFile
from core.limits import Refusal
from core.pipeline.distance_pass import geometric_pass, light_gain_pass
from core.pipeline.head_maps import HeadJob, HeadWorkers, motion_mode, trunk_area_m2
from core.pipeline.plan import SURVEY_INTERVAL_S, ProcessPlan, plan_process
from core.pipeline.volume_stage import (SessionMaps, judge, write_displacement_sums, write_parameters,
                                        write_volume)
from core.reconstruction.pipeline import ReconstructionSettings
from core.volume.metric import HeadDisplacements


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
    are made through each forced blow's peak flow too (peak_flow_pass, /peak_flow_volume).
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
    with SessionFile(session_path) as session:
        plan = plan_process(session, session_path, calibration=calibration, maps_at=maps_at, settings=settings,
                            heads=heads, every=every, motion_compensation=motion_mode(motion_compensation),
                            volume_calibration=volume_calibration, distance_from=distance_from, binning=binning)
        meter = _Progress(progress, plan.total_windows)
        with (atomic_output(output) as partial, h5py.File(partial, "w") as out,
              HeadWorkers(plan.workers(workers), len(plan.names)) as pool):
            results = ResultsWriter(out, session_path, f"photopft {__version__}", method=settings.method,
                                    integrator=settings.integrator,
                                    calibration=calibration.created if calibration is not None else "session /rig",
                                    motion_compensation=plan.motion_compensation != "none")
            results.attr("distance_from",
                         "two heads' trunk widths and baseline" if plan.geometry else "photometric fit")
            geometric, offsets, light_gains = _survey(results, session, plan, pool, meter)
            maps = _session_maps(results, session, plan, geometric, light_gains, pool, meter)
            verdict = judge(results, plan, maps)
            write_displacement_sums(results, plan, maps, verdict)
            refused = write_volume(results, session, plan, maps, verdict, pool,
                                   meter.of_pass(plan.peak_flow_windows), volume_calibration)
            write_parameters(session_path, results)
    if progress is not None:
        progress(1.0)
    return ProcessSummary(Path(output), maps.counts, time.perf_counter() - started, maps.mean_distance_mm, refused,
                          offsets, verdict.distance_refused, maps.sheen)


class _Progress:
    """The share of a session's windows done, over its passes."""

    def __init__(self, progress: Callable[[float], None] | None, total_windows: int) -> None:
        self._progress, self._total, self._done = progress, total_windows, 0

    def of_pass(self, windows: int) -> Callable[[float], None]:
        """A pass of `windows` windows reports the share of it done through this."""
        done = self._done

        def report(fraction: float) -> None:
            if self._progress is not None and self._total:
                self._progress((done + fraction * windows) / self._total)
        return report

    def advance(self, windows: int) -> None:
        self._done += windows


def _survey(results: ResultsWriter, session: SessionFile, plan: ProcessPlan, pool: HeadWorkers,
            meter: _Progress) -> tuple[dict, dict[str, float], dict[str, np.ndarray]]:
    """The two heads' distances over time, the photometric fit's offsets from them, and the lights'
    outputs at each planned window (core/pipeline/distance_pass.py); empty without the geometry."""
    if not plan.geometry:
        return {}, {}, {}
    jobs = [HeadJob(plan.session_path, plan.rig, name, plan.survey[name], plan.settings, plan.pseudo[name],
                    plan.motion_compensation, (), binning=plan.factors[name]) for name in plan.names]
    geometric, offsets = geometric_pass(results, jobs, plan.rig.baseline_mm, pool, meter.of_pass(plan.survey_count))
    meter.advance(plan.survey_count)
    light_gains = light_gain_pass(results, session, plan.rig, plan.survey, plan.windows, geometric, plan.settings,
                                  plan.pseudo, plan.motion_compensation, plan.factors, pool,
                                  meter.of_pass(plan.survey_count))
    meter.advance(plan.survey_count)
    return geometric, offsets, light_gains


def _session_maps(results: ResultsWriter, session: SessionFile, plan: ProcessPlan, geometric: dict,
                  light_gains: dict[str, np.ndarray], pool: HeadWorkers, meter: _Progress) -> SessionMaps:
    """Each head's maps of the planned windows, written to /heads/<head>, at the two heads' distances
    when the survey found them."""
    rig = plan.rig
    # the sides' agreement (core/volume/sides.py) is looked at on maps made at the geometric distance
    maps_per_survey = max(1, int(round(SURVEY_INTERVAL_S * rig.frame_rate_hz / plan.every)))
    maps = SessionMaps(at_geometric_distance=bool(geometric))
    for name in plan.names:
        distances_mm = None
        if name in geometric:
            stamps = session.timestamp_ns(name)
            t, d = geometric[name]
            distances_mm = np.interp(np.array([stamps[w.newest] for w in plan.windows[name]], dtype=float), t, d)
        maps.jobs[name] = HeadJob(plan.session_path, rig, name, plan.windows[name], plan.settings, plan.pseudo[name],
                                  plan.motion_compensation, plan.maps_at, distances_mm, plan.factors[name],
                                  maps_per_survey if geometric else 0, light_gains.get(name))
    for result in pool.run(list(maps.jobs.values()), meter.of_pass(plan.map_count)):
        name, head = result.name, rig.heads[result.name]
        maps.made[name] = replace(result, saved_normals=[], saved_depth=[])  # the full maps are written
        maps.side_profiles[name] = result.side_profiles
        results.head(name, {"timestamp_ns": result.timestamp_ns, "frame_index": result.frame_index,
                            "distance_mm": result.distance_mm, "gradient_volume": result.gradient_volume,
                            "valid_pixels": result.valid_pixels,
                            "occluded_side_share": result.occluded_side_share,
                            "side_out_of_view_share": result.side_out_of_view_share,
                            "sheen": result.sheen},
                     # binning: the stream's; valid_pixels count its bins
                     {"ambient_flicker": result.ambient_flicker, "binning": np.int64(plan.factors[name])},
                     result.saved_index, result.saved_normals, result.saved_depth, (head.height, head.width))
        maps.counts[name] = len(result.frame_index)
        maps.displacements[name] = HeadDisplacements(result.timestamp_ns, result.sums)
        maps.mean_distance_mm[name] = (float(np.nanmean(result.distance_mm)) if len(result.distance_mm)
                                       else float("nan"))
        maps.occluded[name] = result.occluded_side_share
        maps.out_of_view[name] = result.side_out_of_view_share
        maps.sheen[name] = float(np.nanmedian(result.sheen)) if np.isfinite(result.sheen).any() else float("nan")
        maps.trunk_area_m2[name] = trunk_area_m2(result.valid_pixels, result.distance_mm, plan.stream_heads[name])
    meter.advance(plan.map_count)
    return maps
