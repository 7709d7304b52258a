"""`photopft bench carry`: how the subject's calibration carries from its segment (quiet breathing and
a slow VC through the flow sensor) to the later manoeuvres, on true surfaces of both populations.

For each subject of `bench population --subset` (same draws, same world, its sway but no steps), the
true depth maps of both heads at times through the calibration segment, the quiet breathing after
the mouthpiece comes off, the second slow VC and each forced blow are read as regional optical signals
(each head's chest and abdomen, core/volume/subject_calibration.py, regional_signals); the subject's
calibration (`fit_subject_calibration`, as `process` fits it, on the true volume at the segment's
maps) then predicts the later manoeuvres: TV (the slope over the quiet breathing), VC, and each blow's
FVC and FEV1 (at the true blow's start and one second on; no back-extrapolation). Two signals:
- levelled: each head's displacement referred to the level at the trunk's sides (RimModel), as
  `process` reads it;
- plain: the displacement along each pixel's ray with no level, which needs each map's absolute
  depth to within a fraction of a millimetre: what the heads could give, not what `process` can;
- less the neck: the plain displacement less the neck's (DisplacementSums.neck_mm), which a shift
  of the whole map, its absolute depth's error included, leaves alone: what `process` could give on
  bodies whose necks move only with the whole body.
No noise and no reconstruction: it separates how a signal follows each body's breathing from the
noise the population bench adds. The truth is what is measured here; tuned on neither population.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from benchmarks.common import SHARED

SIGNALS = ("levelled", "plain", "less the neck")
VALUES = ("TV", "VC", "FVC", "FEV1")
CALIBRATION_MAPS = 48  # maps through the calibration segment (the fit takes at least MIN_FIT_MAPS)
TIDAL_MAPS = 16  # maps through the quiet breathing after the mouthpiece comes off
GRID_S = 0.01  # the truth searched on this grid for the manoeuvres' extremes


@dataclass(frozen=True)
class CarryRow:
    population: str
    body: str
    errors: dict[str, dict[str, float]]  # signal -> value -> relative error (0.02 = +2 %); FVC, FEV1 over the blows
    worst_blow: dict[str, dict[str, float]]  # signal -> FVC, FEV1 -> the largest error of one blow
    grouping: dict[str, str]  # signal -> the calibration's grouping
    residual_l: dict[str, float]
    seconds: float


def manoeuvre_times(scene, waveform) -> tuple[float, np.ndarray, np.ndarray, dict[str, tuple[float, ...]]]:
    """(mouthpiece off (s), the calibration's map times, the quiet breathing's after it, the marks:
    'VC' its highest and lowest volume after the mouthpiece is off; 'blow k' the blow's start (its
    highest volume), one second on and its lowest volume)."""
    from core.volume.subject_calibration import MOUTHPIECE_OFF

    events = sorted(waveform.events)
    off = next(t for t, label in events if label == MOUTHPIECE_OFF)
    ends = [t for t, label in events if label == "maneuver-end"]

    def end_after(start: float) -> float:
        return next((t for t in ends if t > start), waveform.duration_s)

    def extremes(a: float, b: float) -> tuple[np.ndarray, np.ndarray]:
        t = np.arange(a, b, GRID_S)
        return t, np.asarray(scene.truth_volume_l(t), dtype=float)

    marks: dict[str, tuple[float, ...]] = {}
    vc = [t for t, label in events if label == "vc-start" and t > off]
    if vc:
        t, v = extremes(vc[0], end_after(vc[0]))
        marks["VC"] = (float(t[np.argmax(v)]), float(t[np.argmin(v)]))
    for k, start in enumerate(t for t, label in events if label == "forced-start"):
        t, v = extremes(start - 1.0, end_after(start))
        top = float(t[np.argmax(v)])
        t, v = extremes(top, end_after(start))
        marks[f"blow {k + 1}"] = (top, top + 1.0, float(t[np.argmin(v)]))
    calibration = np.linspace(0.0, off, CALIBRATION_MAPS)
    tidal = np.linspace(off + 0.5, end_after(off), TIDAL_MAPS)
    return off, calibration, tidal, marks


def regional_series(scene, rig, config, digitisers, times: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
    """signal -> `<head> chest|abdomen` -> litres at `times` from the true depth maps, each head's
    distance the true one (the sway's axial part followed)."""
    from benchmarks.true_surfaces import true_trunk
    from core.volume.maps import DisplacementTracker, head_volume_l, neck_referred_volume_l, plain_volume_l
    from core.volume.subject_calibration import ABDOMEN, CHEST

    out: dict[str, dict[str, list[float]]] = {s: {} for s in SIGNALS}
    trackers = {name: DisplacementTracker(head) for name, head in rig.heads.items()}
    for t in times:
        axial = float(scene.sway_mm(np.array(t))[2])
        distances = {"front": config.distance_mm + axial, "back": config.distance_back_mm - axial}
        for name, head in rig.heads.items():
            _, maps = scene.render(head, float(t), 0, np.uint64(1), digitisers[name], want_maps=True)
            subject, trunk = true_trunk(maps.depth_mm, maps.normals)
            sums = trackers[name].add(np.where(trunk, maps.depth_mm, np.nan), trunk, subject, distances[name])
            for part, regions in (("chest", CHEST), ("abdomen", ABDOMEN)):
                inside = [r for r in regions if r in sums.reference]
                levelled = sum(head_volume_l(sums.reference[r], sums.current[r], 1.0, 1.0) for r in inside)
                plain = sum(plain_volume_l(sums.displaced[r]) for r in inside)
                necked = sum(neck_referred_volume_l(sums.displaced[r], sums.areas[r], sums.neck_mm) for r in inside)
                for signal, value in zip(SIGNALS, (levelled, plain, necked)):
                    out[signal].setdefault(f"{name} {part}", []).append(float(value) if inside else np.nan)
    return {s: {k: np.asarray(v, dtype=float) for k, v in series.items()} for s, series in out.items()}


def carry_errors(times: np.ndarray, truth_l: np.ndarray, signals: dict[str, np.ndarray], segment_s: tuple[float, float],
                 tidal: np.ndarray, marks: dict[str, tuple[float, ...]]):
    """The subject's calibration fitted on the segment's maps, and the relative errors of the values it
    predicts: ({value: error}, {FVC, FEV1: worst blow's}, the calibration)."""
    from core.volume.subject_calibration import fit_subject_calibration

    calibration = fit_subject_calibration(times, signals, times, truth_l, segment_s)
    predicted = calibration.volume_l(signals)
    at = {round(float(t), 6): i for i, t in enumerate(times)}

    def change(series: np.ndarray, a: float, b: float) -> float:
        return float(series[at[round(a, 6)]] - series[at[round(b, 6)]])

    quiet = np.isin(np.round(times, 6), np.round(tidal, 6))
    errors = {"TV": float(np.polyfit(truth_l[quiet], predicted[quiet], 1)[0]) - 1.0}
    if "VC" in marks:
        errors["VC"] = change(predicted, *marks["VC"]) / change(truth_l, *marks["VC"]) - 1.0
    blows = {"FVC": [], "FEV1": []}
    for name, times in marks.items():
        if name.startswith("blow"):
            top, second, bottom = times
            blows["FVC"].append(change(predicted, top, bottom) / change(truth_l, top, bottom) - 1.0)
            blows["FEV1"].append(change(predicted, top, second) / change(truth_l, top, second) - 1.0)
    worst = {}
    for value, found in blows.items():
        if found:
            errors[value] = float(np.mean(found))
            worst[value] = float(max(found, key=abs))
    return errors, worst, calibration


def carry_row(population: str, subject, scale: float, world: str) -> CarryRow:
    """One subject's true maps through its session, calibrated on its segment, each signal's errors."""
    from benchmarks.true_surfaces import subject_scene

    started = time.perf_counter()
    made = subject_scene(subject, scale, world, steps=0)  # the sway stays
    config, rig, scene, waveform, digitisers = made.config, made.rig, made.scene, made.waveform, made.digitisers
    off, calibration, tidal, marks = manoeuvre_times(scene, waveform)
    extra = sorted({t for times in marks.values() for t in times})
    times = np.concatenate([calibration, tidal, extra])
    order = np.argsort(times, kind="stable")
    times = times[order]
    truth = np.asarray(scene.truth_volume_l(times), dtype=float)
    series = regional_series(scene, rig, config, digitisers, times)
    errors, worst, grouping, residual = {}, {}, {}, {}
    for signal in SIGNALS:
        errors[signal], worst[signal], fitted = carry_errors(times, truth, series[signal], (0.0, off), tidal, marks)
        grouping[signal] = fitted.extra.get("grouping", "refused") + (" (refused)" if fitted.refused else "")
        residual[signal] = fitted.residual_l
    return CarryRow(population, made.body, errors, worst, grouping, residual, time.perf_counter() - started)


def _percent(x: float | None) -> str:
    return "" if x is None or not np.isfinite(x) else f"{100 * x:+.1f}"


def carry_table(rows: list[CarryRow]) -> str:
    lines = ["| population | body | signal | grouping | residual (mL) | TV % | VC % | FVC % (worst blow) | "
             "FEV1 % (worst blow) |", "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for signal in SIGNALS:
            e, w = row.errors[signal], row.worst_blow[signal]
            lines.append(f"| {row.population} | {row.body} | {signal} | {row.grouping[signal]} | "
                         f"{1000 * row.residual_l[signal]:.0f} | {_percent(e.get('TV'))} | {_percent(e.get('VC'))} | "
                         f"{_percent(e.get('FVC'))} ({_percent(w.get('FVC'))}) | "
                         f"{_percent(e.get('FEV1'))} ({_percent(w.get('FEV1'))}) |")
    lines.append("")
    for population in dict.fromkeys(r.population for r in rows):
        mine = [r for r in rows if r.population == population]
        for signal in SIGNALS:
            parts = []
            for value in VALUES:
                found = [r.worst_blow[signal].get(value, r.errors[signal].get(value)) for r in mine]
                found = np.abs([x for x in found if x is not None and np.isfinite(x)])
                if len(found):
                    within = int(np.sum(found <= 0.03))
                    parts.append(f"{value} within 3 % on {within} of {len(found)} (largest {100 * found.max():.1f} %)")
            lines.append(f"- {population}, {signal}: " + "; ".join(parts))
    return "\n".join(lines)


def run_carry_bench(subjects: int, scale: float, seed: int, world: str) -> tuple[str, list[CarryRow]]:
    from benchmarks.population import BODIES, draw_subjects, standard_blows

    blows = standard_blows(SHARED / "data" / "spirometry-waveforms")
    started = time.perf_counter()
    rows = [carry_row(population, subject, scale, world)
            for population in BODIES for subject in draw_subjects(subjects, seed, blows, bodies=population)]
    text = (f"{subjects} subjects of each population (`bench population --subset`'s draws), scale {scale}, world "
            f"{world} with its sway, no steps; true depth maps at {CALIBRATION_MAPS} times through the calibration "
            f"segment, {TIDAL_MAPS} through the quiet breathing after it and at each manoeuvre's marks; the subject's "
            "calibration as `process` fits it, on the true volume. Errors of the predicted values against the truth "
            "(FVC and FEV1: the mean over the blows, the worst blow in brackets; the summary counts each body's worst "
            "blow). {:.0f} s.\n\n".format(time.perf_counter() - started) + carry_table(rows))
    return text, rows


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench carry`: its arguments and what it runs."""
    from benchmarks.visible import add_subset_arguments, run_on_subsets

    p = what.add_parser("carry", help="how the subject's calibration carries to the later manoeuvres, on true "
                                      "surfaces of both populations")
    add_subset_arguments(p, "the simulated world")
    p.set_defaults(run=lambda args: run_on_subsets(args, "carry", "Calibration carried", run_carry_bench))
