"""`photopft bench sides`: how the two heads' distance, taken from their trunk widths, moves with a forced
blow, and what that does to each head's levelled change, on both populations' subsets.

Two heads at a known baseline see the same trunk sides, so their widths in pixels give each head's
distance (core/volume/maps.py, two_head_distances), and `process` scales every map to it. A head's
levelled signal sums its whole relief above the sides (10-25 L), which scales with the distance
cubed (relief and footprint), so a millimetre at 2 m is 15-40 mL. Here no steps and, unless --sway,
no sway: the true distance does not move, and any change of the widths' distance between a blow's
top and bottom is breathing read as distance. With --sway the world's sway (a translation) stays and
each map is registered at its true distance.

For each subject of `bench population --subset` (same draws), at each forced blow's highest and
lowest true volume, one light cycle of each head is rendered (no motion within it) and reconstructed
with the lights as built at the true distance (HeadReconstructor, `process`'s settings). Per blow:
the widths' front distance on the true and on the reconstructed maps at the top and the bottom, and
both heads' levelled change over the blow's true volume change (its gain) read four ways: on the true
maps, on the true normals integrated as the reconstruction integrates them, on the reconstruction at
the true distance, and on its maps scaled to the widths' distance; and the plain change (no level:
each pixel's displacement along its ray) on the true maps, on the reconstruction anchored at the true
map's median depth, and less the neck's displacement (DisplacementSums.neck_mm) on the true maps and
on the reconstruction. A body's mean gain is what its calibration takes out; each blow's gain about it
is what it cannot. Tuned on neither population: the truth is what is measured here.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from functools import partial

import numpy as np

from benchmarks.common import SHARED

HEADS = ("front", "back")


@dataclass(frozen=True)
class BlowSides:
    population: str
    body: str
    blow: str
    volume_change_l: float  # the blow's true volume change, top to bottom (its FVC)
    # where the widths put the front head's distance (mm), at the top and the bottom, on true and reconstructed maps
    front_mm: dict[str, tuple[float, float]]
    change_l: dict[str, dict[str, float]]  # READS and PLAIN_READS -> head -> change (L), top to bottom

    def gain(self, read: str) -> float:
        """Both heads' change read so over the blow's true volume change."""
        return sum(self.change_l[read].values()) / self.volume_change_l

    def moved_mm(self, maps: str) -> float:
        top, bottom = self.front_mm[maps]
        return bottom - top


# the true maps; the true normals integrated as the reconstruction integrates them; the reconstruction at the
# true distance; the same maps scaled to the widths' distance, as `process` scales them
READS = ("true maps", "true normals integrated", "true distance", "widths' distance")
# the same without a level: each pixel's displacement along its ray, both heads summed, on the true maps and
# on the reconstruction anchored at the true map's median depth (what no head measures: the anchor's own
# error moves a head's whole trunk, 0.1 L a millimetre); then less the neck's displacement
# (DisplacementSums.neck_mm), on the true maps and on the reconstruction at the true distance
PLAIN_READS = ("plain: true maps", "plain: true median depth", "plain, less the neck: true maps",
               "plain, less the neck: reconstructed")


def _changes(depths: list[np.ndarray], trunks: list[np.ndarray], subjects: list[np.ndarray], head,
             distances_mm: list[float]) -> tuple[float, float, float]:
    """(levelled, plain, less the neck) change (L) from the first map to the second, each registered at its
    distance (DisplacementTracker): levelled referred to the level at the trunk's sides (RimModel), plain each
    pixel's displacement along its ray with no level, and that less the neck's (neck_mm): a shift of the
    whole map, its anchor's error included, cancels; a neck or head that moves on its own does not."""
    from core.volume.maps import DisplacementTracker, head_volume_l, neck_referred_volume_l, plain_volume_l

    tracker = DisplacementTracker(head)
    levelled, plain, necked = [], [], []
    for depth, trunk, subject, distance in zip(depths, trunks, subjects, distances_mm):
        sums = tracker.add(np.where(trunk, depth, np.nan), trunk, subject, distance)
        levelled.append(head_volume_l(sums.reference["all"], sums.current["all"], 1.0, 1.0))
        plain.append(plain_volume_l(sums.displaced["all"]))
        necked.append(neck_referred_volume_l(sums.displaced["all"], sums.areas["all"], sums.neck_mm))
    return float(levelled[0] - levelled[1]), float(plain[0] - plain[1]), float(necked[0] - necked[1])


def blow_sides(population: str, body: str, name: str, times: tuple[float, float], scene, rig, digitisers,
               distances_mm: dict[str, tuple[float, float]]) -> BlowSides:
    """One blow's top and bottom read each way (module doc); distances_mm: each head's true distance at
    the two times (the world's sway along the axis, where it has one)."""
    from benchmarks.true_surfaces import true_trunk
    from core.reconstruction.integrate import depth_from_normals
    from core.reconstruction.pipeline import HeadReconstructor, trunk_mask
    from core.volume.maps import trunk_width_px, two_head_distances

    maps: dict[str, dict[str, tuple[list, list, list]]] = {"true": {}, "integrated": {}, "reconstructed": {}}
    for head_name in HEADS:
        head = rig.heads[head_name]
        reconstructor = HeadReconstructor(head)
        for kind in maps:
            maps[kind][head_name] = ([], [], [])
        for k, t in enumerate(times):
            frames = []
            for light in (0, 1, 2, 3, -1):  # -1: the dark frame
                key = np.uint64(7919 * (k + 1) + 104729 * (light + 2) + (0 if head_name == "front" else 1))
                image, true_maps = scene.render(head, float(t), light, key, digitisers[head_name], want_maps=True)
                frames.append(image.astype(float))
            dark = frames[-1]
            subject, trunk = true_trunk(true_maps.depth_mm, true_maps.normals)
            for store, value in zip(maps["true"][head_name], (true_maps.depth_mm, trunk, subject)):
                store.append(value)
            integrated = depth_from_normals(true_maps.normals, trunk, head.fx, head.fy, head.cx, head.cy,
                                            distances_mm[head_name][k])
            for store, value in zip(maps["integrated"][head_name],
                                    (integrated, trunk & np.isfinite(integrated), subject)):
                store.append(value)
            made = reconstructor.reconstruct(np.stack([f - dark for f in frames[:4]]), None, dark,
                                             distance_mm=distances_mm[head_name][k])
            trunk = trunk_mask(made.mask, np.nan_to_num(made.normals)) & np.isfinite(made.depth_mm)
            for store, value in zip(maps["reconstructed"][head_name], (made.depth_mm, trunk, made.mask)):
                store.append(value)
    widths_mm = {}
    for kind, by_head in ((k, maps[k]) for k in ("true", "reconstructed")):
        widths = {h: np.array([trunk_width_px(d, tr, rig.heads[h]) for d, tr, _ in zip(*by_head[h])]) for h in HEADS}
        front, back = two_head_distances(widths["front"], widths["back"], rig.baseline_mm)
        widths_mm[kind] = {"front": front, "back": back}
    change: dict[str, dict[str, float]] = {read: {} for read in READS + PLAIN_READS}
    for h in HEADS:
        at = list(distances_mm[h])
        change[READS[0]][h], change[PLAIN_READS[0]][h], change[PLAIN_READS[2]][h] = _changes(
            *maps["true"][h], rig.heads[h], at)
        change[READS[1]][h], _, _ = _changes(*maps["integrated"][h], rig.heads[h], at)
        depths, trunks, subjects = maps["reconstructed"][h]
        change[READS[2]][h], _, change[PLAIN_READS[3]][h] = _changes(depths, trunks, subjects, rig.heads[h], at)
        anchored = [d * np.median(true[both]) / np.median(d[both]) for d, true, both in
                    ((d, true, tr & np.isfinite(true)) for d, true, tr in zip(depths, maps["true"][h][0], trunks))]
        _, change[PLAIN_READS[1]][h], _ = _changes(anchored, trunks, subjects, rig.heads[h],
                                                   [float(np.nanmedian(d)) for d in anchored])
        # each map scaled about the camera as `process` scales it: by its widths' distance over the sides' true
        # one (the true maps' widths' distance at the top, moved since by the true distance's sway)
        sides = widths_mm["true"][h][0] + (np.asarray(at) - at[0])
        ratio = widths_mm["reconstructed"][h] / sides
        scaled = [d * r for d, r in zip(depths, ratio)]
        change[READS[3]][h], _, _ = _changes(scaled, trunks, subjects, rig.heads[h], [a * r for a, r in zip(at, ratio)])
    front = {kind: (float(w["front"][0]), float(w["front"][1])) for kind, w in widths_mm.items()}
    volume = np.asarray(scene.truth_volume_l(np.asarray(times, dtype=float)), dtype=float)
    return BlowSides(population, body, name, float(volume[0] - volume[1]), front, change)


def subject_sides(population: str, subject, scale: float, world: str, sway: bool = False) -> list[BlowSides]:
    """Each forced blow of one subject's clinical session, without its steps and, unless `sway`, its sway."""
    from benchmarks.carry import manoeuvre_times
    from benchmarks.true_surfaces import subject_scene
    from core.sim.breathing import Sway

    made = subject_scene(subject, scale, world, steps=0, **({} if sway else {"sway": Sway(0.0, 0.0, 0.0)}))
    config, rig, scene, digitisers, body = made.config, made.rig, made.scene, made.digitisers, made.body
    _, _, _, marks = manoeuvre_times(scene, made.waveform)
    rows = []
    for name, times in marks.items():
        if not name.startswith("blow"):
            continue
        axial = np.array([float(scene.sway_mm(np.array(t))[2]) for t in (times[0], times[2])])
        distances = {"front": tuple(config.distance_mm + axial), "back": tuple(config.distance_back_mm - axial)}
        rows.append(blow_sides(population, body, name, (times[0], times[2]), scene, rig, digitisers, distances))
    return rows


def sides_table(rows: list[BlowSides]) -> str:
    lines = ["| population | body | blow | FVC (L) | true maps' levelled change front, back (L) | "
             "widths' front distance moved, true maps (mm) | reconstructed maps (mm) | "
             + " | ".join(READS + PLAIN_READS) + " |",
             "|---|---|---|---|---|---|---|" + "---|" * len(READS + PLAIN_READS)]
    for r in rows:
        true = r.change_l[READS[0]]
        lines.append(f"| {r.population} | {r.body} | {r.blow} | {r.volume_change_l:.2f} | {true['front']:.3f}, "
                     f"{true['back']:.3f} | {r.moved_mm('true'):+.1f} | {r.moved_mm('reconstructed'):+.1f} | "
                     + " | ".join(f"{r.gain(read):.3f}" for read in READS + PLAIN_READS) + " |")
    lines.append("")
    for population in dict.fromkeys(r.population for r in rows):
        mine = [r for r in rows if r.population == population]
        moved = {m: np.array([r.moved_mm(m) for r in mine]) for m in ("true", "reconstructed")}
        parts = [f"- {population} ({len(mine)} blows): the widths' distance moved {moved['true'].mean():+.1f} mm "
                 f"(sd {moved['true'].std():.1f}) on true maps, {moved['reconstructed'].mean():+.1f} mm "
                 f"(sd {moved['reconstructed'].std():.1f}) on reconstructed ones"]
        for read in READS + PLAIN_READS:
            gains = np.array([r.gain(read) for r in mine])
            # each blow's gain over its body's mean gain: what a calibration on the subject cannot take out
            own = np.concatenate([gains[index] / gains[index].mean() - 1.0 for index in
                                  ([k for k, r in enumerate(mine) if r.body == body]
                                   for body in dict.fromkeys(r.body for r in mine))])
            parts.append(f"{read}: gain {gains.mean():.3f} ({gains.min():.3f} to {gains.max():.3f}), "
                         f"each blow about its body's mean sd {100 * own.std():.1f} %")
        lines.append("; ".join(parts))
    return "\n".join(lines)


def run_sides_bench(subjects: int, scale: float, seed: int, world: str,
                    sway: bool = False) -> tuple[str, list[BlowSides]]:
    from benchmarks.population import BODIES, draw_subjects, standard_blows

    blows = standard_blows(SHARED / "data" / "spirometry-waveforms")
    started = time.perf_counter()
    rows = [row for population in BODIES for subject in draw_subjects(subjects, seed, blows, bodies=population)
            for row in subject_sides(population, subject, scale, world, sway)]
    scene = ("with its sway (a translation; each map at its true distance), without its steps" if sway
             else "without its sway and steps")
    truth = "it moves with the sway only" if sway else "it does not move"
    text = (f"{subjects} subjects of each population (`bench population --subset`'s draws), scale {scale}, world "
            f"{world} {scene}; at each forced blow's top and bottom one light cycle a head, "
            "reconstructed with the lights as built. The widths' distance: the two heads' trunk widths and the "
            f"baseline (two_head_distances), front head; truth: {truth}. Each read's gain: both heads' "
            "levelled change over the blow's true volume change (a body's mean gain is what its calibration takes "
            "out, each blow's about it what it cannot). {:.0f} s.\n\n".format(time.perf_counter() - started)
            + sides_table(rows))
    return text, rows


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench sides`: its arguments and what it runs."""
    from benchmarks.visible import add_subset_arguments, run_on_subsets

    p = what.add_parser("sides", help="how the two heads' distance from their trunk widths moves with a forced blow, "
                                      "and how much of a blow each optical signal keeps, on both populations")
    add_subset_arguments(p, "the simulated world (its steps left out)")
    p.add_argument("--sway", action="store_true", help="keep the world's sway (a translation), each map at its "
                                                        "true distance")
    p.set_defaults(run=lambda args: run_on_subsets(args, "sides-sway" if args.sway else "sides",
                                                   "Distance from the sides" + (", with sway" if args.sway else ""),
                                                   partial(run_sides_bench, sway=args.sway), "sides",
                                                   " --sway" if args.sway else ""))
