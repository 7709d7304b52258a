"""`photopft bench tidal`: the population's quiet breathing read as an optical volume reads it.

Each subject of `bench population` (the same seed draws the same bodies) breathes the 20 s of quiet
breathing that opens its protocol (core.sim.breathing.tidal, the bench's irregular rate and sighs). The
curve is sampled one map a light cycle, each map the mean volume over its cycle (benchmarks.blows),
with white noise of a given size a map, and its tidal values read as the session analysis reads them
(core.analysis.values.tidal_values_of). The table gives, per noise, the tidal volume's and the rate's
bias and 95 % limits of agreement against the same reading of the noise-free curve, and the share
within issue 27's tolerances (50 mL, 0.5/min); beside the rate as read now (breath_period_s, from
mid-inspiration to mid-inspiration), the rate read between end-expiratory minima, as it was before.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

import numpy as np

from benchmarks.common import noises_ml, publish
from benchmarks.blows import maps_of
from benchmarks.population import WORLD, _config, draw_subjects
from core.analysis.values import Breath, quiet_breaths, tidal_breaths, tidal_values_of
from core.sim.breathing import RATE_HZ, TIDAL_SECONDS, tidal
from core.sim.simulate import breathing_subject


TIDAL_S = TIDAL_SECONDS["short"]  # the population bench's protocol opens with it


@dataclass


class Reading:
    """One subject's quiet breathing, one noise draw: (tidal volume L, rate /min, breaths) of the
    noise-free curve and of the sampled one, and both rates read between minima."""

    noise_l: float
    truth: tuple[float, float, int]
    optical: tuple[float, float, int]
    between_minima: tuple[float, float]


def _rate_between_minima(breaths: list[Breath]) -> float:
    return 60.0 / float(np.mean([b[1] + b[2] for b in breaths]))


def _read(t_s: np.ndarray, volume_l: np.ndarray) -> tuple[tuple[float, float, int], float] | None:
    breaths = tidal_breaths([(t_s, volume_l)])
    values = tidal_values_of(breaths)
    if values is None:
        return None
    return ((values.tidal_volume_l, values.respiratory_rate_bpm, values.breaths),
            _rate_between_minima(quiet_breaths(breaths)))


def readings(subjects: int, seed: int, noise_l: list[float], draws: int) -> list[Reading]:
    out = []
    for subject in draw_subjects(subjects, seed, []):
        config = _config(subject, 0.25, WORLD)
        breather = replace(breathing_subject(config), rate_variability=0.15, sigh_every=12)
        volume = tidal(breather, TIDAL_S, np.random.default_rng(config.seed + 17))
        truth = _read(np.arange(len(volume)) / RATE_HZ, volume)
        if truth is None:
            continue
        t, clean = maps_of(volume, RATE_HZ, 0.0)
        rng = np.random.default_rng(subject.seed)
        for noise in noise_l:
            for _ in range(draws if noise > 0 else 1):
                read = _read(t, clean + rng.normal(0.0, noise, len(clean)))
                if read is not None:
                    out.append(Reading(noise, truth[0], read[0], (truth[1], read[1])))
    return out


def _agreement(differences: np.ndarray, tolerance: float, unit: str, digits: int) -> list[str]:
    bias = float(np.mean(differences))
    spread = 1.96 * float(np.std(differences, ddof=1)) if len(differences) > 1 else 0.0
    return [f"{bias:+.{digits}f} {unit}", f"{bias - spread:+.{digits}f} to {bias + spread:+.{digits}f} {unit}",
            f"{100 * np.mean(np.abs(differences) <= tolerance):.0f} %"]


def table(rows: list[Reading]) -> str:
    lines = ["| noise a map | samplings | TV bias | TV 95 % limits | TV within 50 mL | RR bias | RR 95 % limits "
             "| RR within 0.5/min | RR between minima (before): bias, within 0.5/min | breaths as the truth's |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for noise in sorted({r.noise_l for r in rows}):
        band = [r for r in rows if r.noise_l == noise]
        tv = 1000.0 * np.array([r.optical[0] - r.truth[0] for r in band])
        rr = np.array([r.optical[1] - r.truth[1] for r in band])
        before = np.array([r.between_minima[1] - r.between_minima[0] for r in band])
        same = np.mean([r.optical[2] == r.truth[2] for r in band])
        cells = [f"{1000 * noise:g} mL", str(len(band)), *_agreement(tv, 50.0, "mL", 1),
                 *_agreement(rr, 0.5, "/min", 2),
                 f"{np.mean(before):+.2f} /min, {100 * np.mean(np.abs(before) <= 0.5):.0f} %", f"{100 * same:.0f} %"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_tidal_bench(subjects: int, seed: int, noise_ml: list[float], draws: int) -> str:
    rows = readings(subjects, seed, [n / 1000 for n in noise_ml], draws)
    if not rows:
        raise ValueError("no subject breathed two whole breaths to read")
    intro = (f"The quiet breathing ({TIDAL_S:g} s, irregular rate, sighs) of `bench population`'s {subjects} subjects "
             f"(seed {seed}) sampled one map a light cycle (1/22 s, each map the mean over its cycle), with white noise "
             f"of {', '.join(f'{n:g}' for n in noise_ml)} mL a map ({draws} draws each), read as the session analysis "
             "reads a curve, against the same reading of the noise-free curve.")
    return intro + "\n\n" + table(rows)


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench tidal`: its arguments and what it runs."""
    ti = what.add_parser("tidal", help="the population's quiet breathing read as optical maps with noise: TV and RR")
    ti.add_argument("--subjects", type=int, default=30)
    ti.add_argument("--seed", type=int, default=1, help="the population's seed (bench population's)")
    ti.add_argument("--noise-ml", default="0,5,10,15,20,25,35", help="noise of a map, mL (comma-separated)")
    ti.add_argument("--draws", type=int, default=4, help="noise draws per subject and noise")
    ti.add_argument("--no-write", action="store_true", help="print only")

    def run_tidal(args: argparse.Namespace) -> int:
        from app.errors import UserError

        noise = noises_ml(args.noise_ml)
        if args.subjects < 1 or args.draws < 1:
            raise UserError("--subjects and --draws take 1 or more")
        try:
            text = run_tidal_bench(args.subjects, args.seed, noise, args.draws)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
        return publish(args, "tidal", f"Quiet breathing read through the maps' noise (`photopft bench tidal "
                                       f"--subjects {args.subjects} --seed {args.seed} --noise-ml {args.noise_ml} "
                                       f"--draws {args.draws}`)", text)

    ti.set_defaults(run=run_tidal)
