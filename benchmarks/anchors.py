"""`photopft bench anchors`: what each reference of a map's displacement leaves of the breath and of its
noise, map by map as `photopft process` makes the maps.

`bench sides` reads a blow's top and bottom on pairs of maps registered at their true distance; here the
whole session is processed. For each subject of `bench population --subset`'s draws, both populations:
a tidal session of SECONDS with the world's sway and no steps, no flow sensor, simulated and processed as
`process` does; each head's displacement sums as they came from its maps (/displacement_sums, every map
shown) read three ways:
- levelled: referred to the level at the trunk's sides, each map's own (RimModel.level; /volume takes the
  session's level instead where each map's own is too noisy, core/volume/metric.py);
- less the neck: each pixel's displacement less the neck's (DisplacementSums.neck_mm);
- plain: no reference: each map's absolute depth as the two heads' trunk widths placed it.
Each read's slope on the true volume (least squares with an offset), the rms of the residual about it
and its map-to-map part (successive differences over the square root of 2), per head and both heads
summed (the back's maps on the front's times); and how many of a head's maps have no neck. The residual
is what no gain, the subject's calibration's included, takes out.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from benchmarks.common import SHARED

SIGNALS = ("levelled", "less the neck", "plain")
SECONDS = 20.0
HEADS = ("front", "back")
BOTH = "both"


@dataclass(frozen=True)
class AnchorRow:
    population: str
    body: str
    slope: dict[str, dict[str, float]]  # signal -> front, back, both -> slope on the true volume
    residual_l: dict[str, dict[str, float]]  # signal -> front, back, both -> rms about the slope
    map_to_map_l: dict[str, dict[str, float]]  # signal -> front, back, both -> its map-to-map part
    no_neck: dict[str, int]  # head -> maps without a neck
    maps: int  # the front head's
    seconds: float


def signal_series(sums: dict) -> dict[str, np.ndarray]:
    """Each read (SIGNALS) of one head's stored sums (ResultsFile.displacement_sums()[head]), litres on its maps."""
    from core.volume.maps import head_volume_l, neck_referred_volume_l, plain_volume_l

    k = list(sums["parts"]).index("all")
    return {"levelled": head_volume_l(sums["reference"][:, k], sums["current"][:, k], 1.0, 1.0),
            "less the neck": neck_referred_volume_l(sums["displaced"][:, k], sums["areas"][:, k], sums["neck_mm"]),
            "plain": plain_volume_l(sums["displaced"][:, k])}


def fit_to_truth(truth_l: np.ndarray, signal_l: np.ndarray) -> tuple[float, float, float]:
    """(slope, rms of the residual, its map-to-map part) of a signal regressed on the true volume with an
    offset, over the maps where both are finite; NaN with fewer than 10."""
    truth_l, signal_l = np.asarray(truth_l, dtype=float), np.asarray(signal_l, dtype=float)
    ok = np.isfinite(truth_l) & np.isfinite(signal_l)
    if ok.sum() < 10:
        return float("nan"), float("nan"), float("nan")
    slope, offset = np.polyfit(truth_l[ok], signal_l[ok], 1)
    residual = signal_l[ok] - (slope * truth_l[ok] + offset)
    return float(slope), float(np.sqrt(np.mean(residual ** 2))), float(np.std(np.diff(residual)) / np.sqrt(2.0))


def read_anchors(stored: dict[str, dict], truth_t_ns: np.ndarray, truth_l: np.ndarray
                 ) -> tuple[dict, dict, dict, dict[str, int], int]:
    """(slope, residual, map-to-map, maps without a neck, the front's maps) of each read of a session's
    stored displacement sums against its true volume (truth_t_ns, truth_l)."""
    slope: dict[str, dict[str, float]] = {s: {} for s in SIGNALS}
    residual: dict[str, dict[str, float]] = {s: {} for s in SIGNALS}
    map_to_map: dict[str, dict[str, float]] = {s: {} for s in SIGNALS}
    t_front = stored[HEADS[0]]["timestamp_ns"].astype(float)
    summed = {s: np.zeros(len(t_front)) for s in SIGNALS}
    for head in HEADS:
        t = stored[head]["timestamp_ns"].astype(float)
        truth = np.interp(t, truth_t_ns.astype(float), truth_l)
        for signal, values in signal_series(stored[head]).items():
            slope[signal][head], residual[signal][head], map_to_map[signal][head] = fit_to_truth(truth, values)
            good = np.isfinite(values)
            summed[signal] += (np.interp(t_front, t[good], values[good]) if good.sum() > 1
                               else np.full(len(t_front), np.nan))
    truth_front = np.interp(t_front, truth_t_ns.astype(float), truth_l)
    for signal in SIGNALS:
        fitted = fit_to_truth(truth_front, summed[signal])
        slope[signal][BOTH], residual[signal][BOTH], map_to_map[signal][BOTH] = fitted
    no_neck = {head: int(np.isnan(stored[head]["neck_mm"]).sum()) for head in HEADS}
    return slope, residual, map_to_map, no_neck, len(t_front)


def anchor_row(population: str, subject, scale: float, world: str, seconds: float) -> AnchorRow:
    """One subject's tidal session simulated, processed and read (module doc)."""
    from benchmarks.population import session_config
    from core.io.results import ResultsFile
    from core.io.session import SessionFile
    from core.pipeline.process import process_session
    from core.sim.simulate import simulate

    started = time.perf_counter()
    config = replace(session_config(subject, scale, world, "tidal", seconds), steps=0, flow_sensor=None)
    with tempfile.TemporaryDirectory(prefix="photopft-anchors-") as folder:
        session, results = Path(folder) / "session.h5", Path(folder) / "results.h5"
        simulate(session, config)
        process_session(session, results)
        with ResultsFile(results) as r:
            stored = r.displacement_sums()
        with SessionFile(session) as s:
            truth_t, truth_l = s.truth()["timestamp_ns"][:], s.truth()["volume_l"][:]
    return AnchorRow(population, subject.body_name, *read_anchors(stored, truth_t, truth_l),
                     time.perf_counter() - started)


def _three(values: dict[str, float], digits: int = 3) -> str:
    return ", ".join(f"{values[k]:.{digits}f}" for k in (*HEADS, BOTH))


def anchors_table(rows: list[AnchorRow]) -> str:
    lines = ["| population | body | read | slope front, back, both | residual front, back, both (L) | "
             "map to map, both (L) | maps without a neck front, back (of) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        for s in SIGNALS:
            lines.append(f"| {r.population} | {r.body} | {s} | {_three(r.slope[s], 2)} | {_three(r.residual_l[s])} | "
                         f"{r.map_to_map_l[s][BOTH]:.3f} | {r.no_neck['front']}, {r.no_neck['back']} ({r.maps}) |")
    lines.append("")
    for population in dict.fromkeys(r.population for r in rows):
        mine = [r for r in rows if r.population == population]
        parts = [f"{s}: both heads' residual median {np.median([r.residual_l[s][BOTH] for r in mine]):.3f} L "
                 f"(map to map {np.median([r.map_to_map_l[s][BOTH] for r in mine]):.3f}), slope "
                 f"{min(r.slope[s][BOTH] for r in mine):.2f} to {max(r.slope[s][BOTH] for r in mine):.2f}"
                 for s in SIGNALS]
        lines.append(f"- {population} ({len(mine)} subjects): " + "; ".join(parts))
    return "\n".join(lines)


def run_anchors_bench(subjects: int, scale: float, seed: int, world: str,
                      seconds: float = SECONDS) -> tuple[str, list[AnchorRow]]:
    from benchmarks.population import BODIES, draw_subjects, standard_blows

    blows = standard_blows(SHARED / "data" / "spirometry-waveforms")
    started = time.perf_counter()
    rows = [anchor_row(population, subject, scale, world, seconds) for population in BODIES
            for subject in draw_subjects(subjects, seed, blows, bodies=population)]
    text = (f"{subjects} subjects of each population (`bench population --subset`'s draws), scale {scale}, world "
            f"{world} with its sway and without its steps, {seconds:g} s of tidal breathing without the flow "
            "sensor, processed as `photopft process` does; each read of the stored displacement sums regressed "
            "on the true volume. {:.0f} s.\n\n".format(time.perf_counter() - started) + anchors_table(rows))
    return text, rows


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench anchors`: its arguments and what it runs."""
    from app.args import positive
    from benchmarks.visible import add_subset_arguments, run_on_subsets

    p = what.add_parser("anchors", help="what the level, the neck or no reference leaves of the breath and its "
                                        "noise, map by map as `process` makes the maps, on both populations")
    add_subset_arguments(p, "the simulated world (its steps left out)")
    p.add_argument("--seconds", type=positive, default=SECONDS, help="tidal breathing simulated a subject")
    p.set_defaults(run=lambda args: run_on_subsets(args, "anchors", "Anchors, map by map",
                                                   partial(run_anchors_bench, seconds=args.seconds), "anchors",
                                                   f" --seconds {args.seconds:g}"))
