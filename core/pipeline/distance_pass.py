"""The subject's distance and the lights' outputs through a two-head session, from a survey of
photometric maps made before the session's maps (core/pipeline/process.py)."""

from __future__ import annotations

from typing import Callable

import numpy as np

from core.io.results import ResultsWriter
from core.io.session import SessionFile
from core.pipeline.head_maps import HeadJob, HeadWorkers
from core.reconstruction.drift import light_gains_over_time
from core.reconstruction.photometric import CycleWindow
from core.reconstruction.pipeline import ReconstructionSettings
from core.volume.maps import smooth_in_time
from core.volume.metric import WIDTH_SMOOTHING_S, HeadDisplacements, on_maps_shown, side_targets


def geometric_distances(surveyed: dict, baseline_mm: float) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Each head's subject distance (median depth, mm) over time from the two heads' geometry, as
    (timestamp_ns, distance_mm), from a first pass of photometric maps (HeadResult per head).

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
        shown = np.isfinite(distance)  # not a map whose sides an arm hides (process_head)
        if not shown.any():
            continue
        t = r.timestamp_ns.astype(float)[shown]
        out[name] = (t, smooth_in_time(t / 1e9, distance[shown], WIDTH_SMOOTHING_S))
    return out


def geometric_pass(results: ResultsWriter, jobs: list[HeadJob], baseline_mm: float, workers: HeadWorkers,
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


def light_gain_pass(results: ResultsWriter, session: SessionFile, rig, survey: dict[str, list[CycleWindow]],
                    plans: dict[str, list[CycleWindow]], geometric: dict, settings: ReconstructionSettings,
                    pseudo: dict, motion_compensation: str, binning: dict[str, int], workers: HeadWorkers,
                    progress: Callable[[float], None]) -> dict[str, np.ndarray]:
    """The lights' outputs through the session (core/reconstruction/drift.py): the survey's cycles made
    again at the two heads' distance, each read for its lights' outputs, smoothed; {head: (len(plans[head]), 4)
    factors of the intensities for each planned window}, written to /heads/<head>/light_gain."""
    jobs = []
    for name, (t, d) in geometric.items():
        stamps = session.timestamp_ns(name)
        at = np.array([stamps[w.newest] for w in survey[name]], dtype=float)
        jobs.append(HeadJob(session.path, rig, name, survey[name], settings, pseudo[name], motion_compensation,
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
