"""`photopft bench visible`: how much of a breath the two heads can see, and how much of it each optical
signal keeps, on true surfaces of both populations (no noise, no sway, no reconstruction of shading).

For each subject of `bench population --subset` (same draws, same world), the true depth and normal
maps of both heads at times spanning its slow VC are read three ways against the true volume change
(the slope of a line fit over those times):
- plain: every trunk pixel's displacement along its ray times its footprint, both heads summed (what
  the heads can see; the flanks are the rest);
- levelled: the same referred to the level at the trunk's sides (core/volume/maps.py, RimModel), as
  `process` reads it;
- levelled, integrated: the levelled signal on depth integrated from the true normals by the
  reconstruction's own integrator, anchored at the true median depth: what the integration's errors
  at the silhouette, where the level is read, do to it.
The truth is what is measured here; nothing is calibrated. Tuned on neither population.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np

from app.args import WORLD_NAMES, positive, positive_count
from benchmarks.common import SHARED, publish

SIGNALS = ("plain", "levelled", "levelled, integrated")
SPAN_MAPS = 13  # times from before the VC's lowest to after its highest volume
SPAN_MARGIN_S = 3.0


@dataclass(frozen=True)
class VisibleRow:
    population: str
    body: str
    range_l: float
    shares: dict[str, dict[str, float]]  # signal -> head (front, back, both) -> slope on the truth
    seconds: float


def signal_shares(depths: dict[str, list[np.ndarray]], normals: dict[str, list[np.ndarray]], heads: dict,
                  distances_mm: dict[str, float], truth_l: np.ndarray) -> dict[str, dict[str, float]]:
    """Each signal's slope on the true volume change, per head and summed, from true maps (H, W) per time;
    distances_mm: each head's distance to the subject, which does not sway here (the body frame's scale)."""
    from benchmarks.true_surfaces import true_trunk
    from core.reconstruction.integrate import depth_from_normals
    from core.volume.maps import DisplacementTracker, head_volume_l

    volumes = {s: {} for s in SIGNALS}
    for name, head in heads.items():
        levelled, integrated = DisplacementTracker(head), DisplacementTracker(head)
        series = {s: [] for s in SIGNALS}
        reference = None
        for depth, normal in zip(depths[name], normals[name]):
            subject, trunk = true_trunk(depth, normal)
            if reference is None:
                reference = (depth, trunk)
            both = trunk & reference[1]
            footprint = (depth / head.fx) * (depth / head.fy)
            series["plain"].append(float(np.sum((reference[0] - depth)[both] * footprint[both])) * 1e-6)
            sums = levelled.add(np.where(trunk, depth, np.nan), trunk, subject, distances_mm[name])
            series["levelled"].append(float(head_volume_l(sums.reference["all"], sums.current["all"], 1.0, 1.0)))
            rebuilt = depth_from_normals(normal, trunk, head.fx, head.fy, head.cx, head.cy,
                                         float(np.median(depth[trunk])))
            sums = integrated.add(np.where(trunk, rebuilt, np.nan), trunk & np.isfinite(rebuilt), subject,
                                  distances_mm[name])
            series["levelled, integrated"].append(
                float(head_volume_l(sums.reference["all"], sums.current["all"], 1.0, 1.0)))
        for s in SIGNALS:
            volumes[s][name] = np.asarray(series[s])
    change = truth_l - truth_l[0]
    out = {}
    for s in SIGNALS:
        per = {name: float(np.polyfit(change, v, 1)[0]) for name, v in volumes[s].items()}
        per["both"] = float(np.polyfit(change, sum(volumes[s].values()), 1)[0])
        out[s] = per
    return out


def visible_row(population: str, subject, scale: float, world: str, span_maps: int = SPAN_MAPS) -> VisibleRow:
    """One subject's true maps through its slow VC, read by each signal."""
    from benchmarks.true_surfaces import subject_scene
    from core.sim.breathing import Sway

    started = time.perf_counter()
    # the signals' share of a breath, not their sway: the world's sway and steps left out
    made = subject_scene(subject, scale, world, sway=Sway(0.0, 0.0, 0.0), steps=0)
    config, rig, scene, waveform, digitisers = made.config, made.rig, made.scene, made.waveform, made.digitisers
    low, high = vc_span_s(scene, waveform)
    times = np.linspace(max(0.0, low - SPAN_MARGIN_S), min(waveform.duration_s, high + SPAN_MARGIN_S), span_maps)
    depths = {name: [] for name in rig.heads}
    normals = {name: [] for name in rig.heads}
    for t in times:
        for name, head in rig.heads.items():
            _, maps = scene.render(head, float(t), 0, np.uint64(1), digitisers[name], want_maps=True)
            depths[name].append(maps.depth_mm)
            normals[name].append(maps.normals)
    truth_l = np.asarray(scene.truth_volume_l(times), dtype=float)
    distances = {"front": config.distance_mm, "back": config.distance_back_mm}
    shares = signal_shares(depths, normals, rig.heads, distances, truth_l)
    return VisibleRow(population, made.body, float(np.ptp(truth_l)), shares, time.perf_counter() - started)


def vc_span_s(scene, waveform) -> tuple[float, float]:
    """The slow VC's lowest and highest true volume (s), the VC found by its event; else the session's."""
    t = np.arange(0.0, waveform.duration_s, 0.02)
    starts = [at for at, label in waveform.events if label == "vc-start"]
    if starts:
        ends = [at for at, label in waveform.events if label == "maneuver-end" and at > starts[0]]
        keep = (t >= starts[0]) & (t <= (ends[0] if ends else waveform.duration_s))
        t = t[keep]
    volume = scene.truth_volume_l(t)
    low, high = t[int(np.argmin(volume))], t[int(np.argmax(volume))]
    return (float(min(low, high)), float(max(low, high)))


def visible_table(rows: list[VisibleRow]) -> str:
    lines = ["| population | body | VC range (L) | " + " | ".join(f"{s}: front, back, both" for s in SIGNALS) + " |",
             "|---|---|---|" + "---|" * len(SIGNALS)]
    for row in rows:
        cells = [f"{row.shares[s]['front']:.2f}, {row.shares[s]['back']:.2f}, **{row.shares[s]['both']:.2f}**"
                 for s in SIGNALS]
        lines.append(f"| {row.population} | {row.body} | {row.range_l:.2f} | " + " | ".join(cells) + " |")
    lines.append("")
    for population in dict.fromkeys(r.population for r in rows):
        both = {s: np.array([r.shares[s]["both"] for r in rows if r.population == population]) for s in SIGNALS}
        lines.append(f"- {population} ({len(both[SIGNALS[0]])} bodies), both heads: " + "; ".join(
            f"{s} {b.mean():.2f} ({b.min():.2f} to {b.max():.2f})" for s, b in both.items()))
    from core.analysis.optical_litres import ESTIMATE_UNCERTAINTY, POPULATION_GAIN

    errors = estimate_errors(rows)
    lines.append("")
    lines.append(f"An uncalibrated estimate (the levelled, integrated signal times POPULATION_GAIN {POPULATION_GAIN:.2f}) "
                 "would read, before any noise or reconstruction error: " + "; ".join(
                     f"{p} {100 * e.min():+.0f} to {100 * e.max():+.0f} %" for p, e in errors.items())
                 + f". The largest, {100 * max(np.abs(e).max() for e in errors.values()):.0f} %, is the least "
                 f"uncertainty an estimate can be printed with (ESTIMATE_UNCERTAINTY {100 * ESTIMATE_UNCERTAINTY:.0f} %).")
    return "\n".join(lines)


def estimate_errors(rows: list[VisibleRow]) -> dict[str, np.ndarray]:
    """Per population, each body's error of the uncalibrated estimate on its true surfaces: the
    levelled, integrated share times POPULATION_GAIN, less one."""
    from core.analysis.optical_litres import POPULATION_GAIN

    out: dict[str, list[float]] = {}
    for row in rows:
        out.setdefault(row.population, []).append(POPULATION_GAIN * row.shares["levelled, integrated"]["both"] - 1.0)
    return {p: np.array(e) for p, e in out.items()}


def run_visible_bench(subjects: int, scale: float, seed: int, world: str) -> tuple[str, list[VisibleRow]]:
    from benchmarks.population import BODIES, draw_subjects, standard_blows

    blows = standard_blows(SHARED / "data" / "spirometry-waveforms")
    started = time.perf_counter()
    rows = []
    for population in BODIES:
        for subject in draw_subjects(subjects, seed, blows, bodies=population):
            rows.append(visible_row(population, subject, scale, world))
    text = (f"{subjects} subjects of each population (`bench population --subset`'s draws), scale {scale}, "
            f"world {world} without its sway, true maps at {SPAN_MAPS} times through the slow VC; each "
            "signal's slope on the true volume change. {:.0f} s.\n\n".format(time.perf_counter() - started)
            + visible_table(rows))
    return text, rows


def add_subset_arguments(p: argparse.ArgumentParser, world_help: str) -> None:
    """The arguments of a bench on true surfaces of both populations' subsets (visible, carry)."""
    from benchmarks.population import SUBSET_SCALE, SUBSET_SUBJECTS

    p.add_argument("--subjects", type=positive_count, default=SUBSET_SUBJECTS, help="subjects of each population")
    p.add_argument("--scale", type=positive, default=SUBSET_SCALE)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--world", choices=WORLD_NAMES, default="clinic-widening", help=world_help)
    p.add_argument("--no-write", action="store_true", help="print only")


def run_on_subsets(args: argparse.Namespace, name: str, title: str, bench, command: str | None = None,
                   flags: str = "") -> int:
    """`bench(subjects, scale, seed, world)` -> (text, rows), published under `name` with `title` followed by
    the command (`command`, default `name`), its arguments and `flags`; a missing body mesh one line."""
    from app.errors import UserError
    from core.sim.makehuman import MeshDataError, load_mesh_data

    try:
        load_mesh_data()  # the test population's bodies, read before the first subject rather than after the first half
        text, _ = bench(args.subjects, args.scale, args.seed, args.world)
    except MeshDataError as exc:  # the test population's bodies need ../shared/data/makehuman
        raise UserError(str(exc)) from exc
    return publish(args, name, f"{title} (`photopft bench {command or name} --subjects {args.subjects} "
                               f"--scale {args.scale}{flags}`)", text)


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench visible`: its arguments and what it runs."""
    p = what.add_parser("visible", help="how much of a breath the heads see, and each optical signal keeps, "
                                        "on true surfaces of both populations")
    add_subset_arguments(p, "the simulated world (its sway left out)")
    p.set_defaults(run=lambda args: run_on_subsets(args, "visible", "Visible share", run_visible_bench))
