"""From a session's maps to its volume: the quality rules judged (core/pipeline/quality.py), the
metric volume, the subject's calibration into litres, the peak flow's maps at every frame, and the
values (core/pipeline/process.py runs them in that order)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from core.analysis.compartments import tidal_compartments
from core.analysis.optical_litres import OpticalLitres, subject_litres
from core.analysis.session_analysis import analyse_session
from core.analysis.values import peak_flow_spans_s
from core.calibration.spirometer import regression_features
from core.io.results import ResultsWriter
from core.io.session import SessionFile
from core.limits import Refusal
from core.pipeline.head_maps import HeadJob, HeadResult, HeadWorkers
from core.pipeline.plan import ProcessPlan
from core.pipeline.quality import (geometric_distance_refusal, maps_left_out_words, outline_refusal, session_refusal,
                                   shading_refusal, sides_shown, volume_refusal)
from core.reconstruction.photometric import CycleWindow
from core.volume.maps import REGIONS
from core.volume.metric import HeadDisplacements, MetricVolume, arm_in_outline, metric_volume, side_targets
from core.volume.sides import paired_tilts
from core.volume.steps import maps_in_steps


@dataclass
class SessionMaps:
    """What the session's maps pass left for the volume: per head, its job, its result (without the
    full maps, which are written) and the summaries the quality rules read."""
    jobs: dict[str, HeadJob] = field(default_factory=dict)
    made: dict[str, HeadResult] = field(default_factory=dict)
    displacements: dict[str, HeadDisplacements] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    mean_distance_mm: dict[str, float] = field(default_factory=dict)
    occluded: dict[str, np.ndarray] = field(default_factory=dict)
    out_of_view: dict[str, np.ndarray] = field(default_factory=dict)
    trunk_area_m2: dict[str, np.ndarray] = field(default_factory=dict)
    sheen: dict[str, float] = field(default_factory=dict)
    side_profiles: dict[str, tuple] = field(default_factory=dict)
    at_geometric_distance: bool = False  # made at the two heads' distances (core/pipeline/distance_pass.py)


@dataclass
class Verdict:
    """The quality rules on a session's maps: what they refuse, and which maps the volume keeps."""
    distance_refused: Refusal | None
    optical_refused: Refusal | None
    bent: Refusal | None  # the shading's refusal, which a subject calibration takes the scale of
    sides: dict[str, np.ndarray]  # per head, the maps whose sides no arm hides
    in_step: dict[str, np.ndarray]  # per head, the maps made while the subject stepped
    arm_in_outline: dict[str, np.ndarray]  # per head, the maps whose trunk outline took in an arm
    shown: dict[str, np.ndarray]  # per head, the maps the volume is made of


def judge(results: ResultsWriter, plan: ProcessPlan, maps: SessionMaps) -> Verdict:
    """Every quality rule on the maps, each refusal written to the results."""
    profiles = maps.side_profiles
    tilts = paired_tilts(*profiles.values()) if len(profiles) == 2 and maps.at_geometric_distance else np.zeros(0)
    if np.isfinite(tilts).any():
        results.attr("sides_tilt", float(np.nanmedian(tilts)))
    distance_refused = geometric_distance_refusal(maps.occluded) if plan.geometry else None
    if distance_refused is not None:
        results.refuse("distance", distance_refused)
    arm = {name: arm_in_outline(d.outline_excess) for name, d in maps.displacements.items()}
    refused = (session_refusal(maps.mean_distance_mm, maps.trunk_area_m2, maps.occluded, maps.out_of_view)
               or outline_refusal(arm))
    if refused is not None:
        results.refuse("optical", refused)
    sides = {name: sides_shown(maps.occluded[name]) for name in maps.displacements}
    in_step = {name: maps_in_steps(d.timestamp_ns, d.body_shift_mm) for name, d in maps.displacements.items()}
    shown = {name: sides[name] & ~in_step[name] & ~arm[name] for name in maps.displacements}
    return Verdict(distance_refused, refused, shading_refusal(maps.sheen, tilts), sides, in_step, arm, shown)


def write_displacement_sums(results: ResultsWriter, plan: ProcessPlan, maps: SessionMaps, verdict: Verdict) -> None:
    """/displacement_sums/<head>: the sums as they came, for other signals than the volume's."""
    if not all(d.sums for d in maps.displacements.values()):
        return
    targets, _ = side_targets(maps.displacements, plan.rig.baseline_mm)
    for name, d in maps.displacements.items():
        results.displacement_sums(name, d.timestamp_ns, d.sums, targets[name], verdict.shown[name],
                                  REGIONS + ("all",))


def write_volume(results: ResultsWriter, session: SessionFile, plan: ProcessPlan, maps: SessionMaps,
                 verdict: Verdict, workers: HeadWorkers, peak_flow_progress: Callable[[float], None],
                 volume_calibration) -> Refusal | None:
    """/metric_volume and /volume (litres: the subject's calibration, or the thesis' regression when
    `volume_calibration` is given), /peak_flow_volume; returns why no optical volume was written, if
    none was."""
    refused, bent, shown = verdict.optical_refused, verdict.bent, verdict.shown
    displacements = maps.displacements
    metric = (metric_volume({n: d.of_maps(shown[n]) for n, d in displacements.items()}, plan.rig.baseline_mm)
              if all(maps.counts.values()) and refused is None and all(m.any() for m in shown.values()) else None)
    for name, level in (metric.levels.items() if metric is not None else ()):
        results.attr(f"level_{name}", level)  # the session's or each map's own (core/volume/metric.py)
    if metric is not None and (refused := volume_refusal(metric)) is not None:
        metric = None
        results.refuse("optical", refused)
    in_view = metric is not None and np.isfinite(metric.volume_l).all()  # a trunk in every head's view
    litres = gapped = None
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
    if in_view and plan.dense_peak_flow:
        peak_flow_pass(results, session, maps.jobs, maps.made, plan.complete, metric, workers, peak_flow_progress,
                       litres)
    if in_view:
        compartments = tidal_compartments(session, metric)
        left_out = maps_left_out_words(displacements, verdict.sides, verdict.in_step, verdict.arm_in_outline)
        if left_out:
            results.attr("maps_left_out", left_out)
        results.metric_volume(gapped.timestamp_ns, gapped.volume_l, gapped.scale_from, gapped.heads,
                              gapped.side_distance_mm, gapped.regions, compartments, gapped.head_regions)
    if volume_calibration is not None:
        write_regression_volume(results, plan.names, volume_calibration)
    elif in_view:
        results.volume(gapped.timestamp_ns, litres.volume_l(gapped), litres.method,
                       metric_scale_from=gapped.scale_from, **litres.attrs())
    return refused


# The volume at every frame is not smoothed: the analysis smooths a blow's maps as its noise needs (docs/constants.md)
PEAK_FLOW_SMOOTHING_S = 0.0


def peak_flow_pass(results: ResultsWriter, session: SessionFile, jobs: dict[str, HeadJob],
                   made: dict[str, HeadResult], complete: dict[str, list[CycleWindow]], metric: MetricVolume,
                   workers: HeadWorkers, progress: Callable[[float], None], litres: OpticalLitres) -> None:
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
        both = HeadDisplacements(t[order], [sums[i] for i in order])
        heads[r.name] = both.of_maps(sides_shown(occluded[order]) & ~arm_in_outline(both.outline_excess))
    if not all(len(h.timestamp_ns) for h in heads.values()):
        return
    dense = metric_volume({n: heads[n] for n in jobs}, jobs[next(iter(jobs))].rig.baseline_mm,
                          levels_of=metric.levels, smoothing_s=PEAK_FLOW_SMOOTHING_S)
    inside = np.zeros(len(dense.timestamp_ns), dtype=bool)
    for a, b in spans_ns:
        inside |= (dense.timestamp_ns >= a) & (dense.timestamp_ns <= b)
    results.peak_flow_volume(dense.timestamp_ns[inside], litres.volume_l(dense)[inside], spans_ns,
                             {n: len(j.windows) - 1 for n, j in new_jobs.items()})


def write_parameters(session_path: str | os.PathLike, results: ResultsWriter) -> None:
    """Pulmonary function values: from the flow sensor where the session has one (the reference
    instrument), else from /volume (the optical volume in litres); the `source` attribute says
    which. The optical values are also kept as attributes of /volume, beside the flow sensor's."""
    label = results.out["volume"].attrs.get("label") if results.has_volume() else None
    report = analyse_session(session_path, optical_volume=results.written_volume(),
                             optical_label=None if label is None else str(label),
                             optical_peak_flow=results.written_peak_flow_volume())
    if report.flow_refused is not None:
        results.refuse("flow", report.flow_refused)
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


def write_regression_volume(results: ResultsWriter, heads: list[str], calibration) -> None:
    """/volume from the thesis' regression (eqs 5.1-5.3) on the gradient volume, pixels and distance."""
    t, features = regression_features(lambda head, name: results.out[f"heads/{head}/{name}"][:], heads)
    results.volume(t, calibration.volume_l(features),
                   "thesis regression (eqs 5.1-5.3) on gradient volume, valid pixels and distance",
                   calibration_created=calibration.created, calibration_sessions=",".join(calibration.sessions))
