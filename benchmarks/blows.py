"""`photopft bench blows`: the standard test waveforms read as an optical volume reads them.

Each waveform (ISO 26782 and ATS 24, ../shared/data/spirometry-waveforms) is sampled one map a light
cycle (1/22 s) or, with `every_frame`, one map a frame (1/110 s: the maps process makes through the
top of each forced blow), each map the mean volume over its cycle, at several phases, with white
noise of a given size a map, and read two ways: straight (the samples joined by straight lines, as a flow
sensor's curve is read) and fitted (core.analysis.fitted_curve, as the optical curve is read). The
table gives, per band of the curve's own flow noise over its peak flow (the ratio PEF is refused
on, core.analysis.values.MAX_PEF_NOISE_RATIO), the share of FEV1 and FVC within 3 % or 50 mL of the
waveform's own, of blows whose acceptability is the waveform's, and of PEF within 10 % or 0.30 L/s.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.common import SHARED, noises_ml, publish
from core.analysis.fitted_curve import smoothed_on_grid
from core.analysis.spirometry import ForcedValues, forced_values, read_waveform
from benchmarks.population import within
from core.analysis.values import (ANALYSIS_RATE_HZ, MAX_PEF_NOISE_RATIO, MAX_PEF_NOISE_RATIO_FRAMES,
                                  peak_flow_of_frames, pef_noise_ratio, resample)


CYCLE_S = 1.0 / 22.0  # one light cycle: four lit frames and a dark one at 110 frames/s
FRAME_S = CYCLE_S / 5.0
LEAD_S = 0.6  # the flat curve before the blow and after its end
BANDS = (0.0, 0.03, 0.05, 0.08, 0.10, 0.15, 0.20, 0.30, np.inf)


@dataclass


class Reading:
    """One sampling of one waveform, read straight and fitted, against the waveform's own values."""

    noise_ratio: float  # the curve's flow noise over one step over its fitted PEF
    truth: ForcedValues
    straight: ForcedValues
    fitted: ForcedValues
    given: bool = True  # whether the analysis would give its PEF for the noise (MAX_PEF_NOISE_RATIO...)


def maps_of(volume_l: np.ndarray, rate_hz: float, phase_s: float, step_s: float = CYCLE_S,
            ) -> tuple[np.ndarray, np.ndarray]:
    """(times, volumes) of one map every step_s (default a light cycle) from phase_s on, each the mean
    over the light cycle it ends."""
    integral = np.concatenate([[0.0], np.cumsum(volume_l) / rate_hz])
    samples = np.arange(len(integral))
    times = np.arange(CYCLE_S + phase_s, (len(volume_l) - 1) / rate_hz, step_s)

    def area(when: np.ndarray) -> np.ndarray:
        return np.interp(when * rate_hz, samples, integral)

    return times, (area(times) - area(times - CYCLE_S)) / CYCLE_S


def standard_waveforms(folder: Path) -> list[tuple[np.ndarray, float, ForcedValues]]:
    """Each standard waveform (ISO 26782, ATS 24) with LEAD_S of flat curve before and after it: (its
    volume, its sample rate, its own values)."""
    files = sorted(p for name in ("ISO26782", "ATS24") for p in (folder / name).glob("*.wf"))
    if not files:
        raise FileNotFoundError(f"no standard waveforms (*.wf) under {folder}/ISO26782 or {folder}/ATS24")
    out = []
    for path in files:
        waveform = read_waveform(path)
        lead = np.zeros(int(LEAD_S * waveform.rate_hz))
        volume = np.concatenate([lead, waveform.volume_l, lead + waveform.volume_l[-1]])
        out.append((volume, waveform.rate_hz, forced_values(volume, waveform.rate_hz)))
    return out


def read_sampling(truth: ForcedValues, t_s: np.ndarray, volume_l: np.ndarray, every_frame: bool = False) -> Reading:
    """Read straight and fitted; at a map every frame the straight PEF is the analysis' reading of maps at
    every frame (core.analysis.values.peak_flow_of_frames: smoothed as little as its noise allows), and
    `given` whether its noise ratio after that smoothing allows it."""
    straight = forced_values(resample(t_s, volume_l)[1], ANALYSIS_RATE_HZ)
    fitted = forced_values(smoothed_on_grid(t_s, volume_l, ANALYSIS_RATE_HZ)[1], ANALYSIS_RATE_HZ)
    ratio = pef_noise_ratio(t_s, volume_l, fitted.pef_lps)
    if not every_frame:
        return Reading(ratio, truth, straight, fitted, ratio <= MAX_PEF_NOISE_RATIO)
    # the analysis reads a lung volume, which falls as the blow exhales
    peak_flow_of_frames(straight, t_s, -np.asarray(volume_l), float(t_s[0]), float(t_s[-1]), fitted.pef_lps)
    return Reading(ratio, truth, straight, fitted, straight.pef_noise_ratio <= MAX_PEF_NOISE_RATIO_FRAMES)


def readings(folder: Path, noise_l: list[float], phases: int, draws: int, seed: int,
             every_frame: bool = False) -> list[Reading]:
    rng = np.random.default_rng(seed)
    out = []
    for volume, rate_hz, truth in standard_waveforms(folder):
        for phase in np.arange(phases) * CYCLE_S / phases:
            t, clean = maps_of(volume, rate_hz, phase, FRAME_S if every_frame else CYCLE_S)
            for noise in noise_l:
                for _ in range(draws if noise > 0 else 1):
                    sampled = clean + rng.normal(0.0, noise, len(clean))
                    out.append(read_sampling(truth, t, sampled - sampled[0], every_frame))
    return out


def table(rows: list[Reading], every_frame: bool = False) -> str:
    pef = "smoothed as little as its noise allows, given" if every_frame else "straight"
    lines = ["| flow noise over PEF | samplings | FEV1 straight / fitted | FVC straight / fitted "
             f"| acceptability as the waveform's, straight / fitted | PEF within 10 % or 0.30 L/s, {pef} |",
             "|---|---|---|---|---|---|"]
    ratios = np.array([r.noise_ratio for r in rows])

    def share(selected: list[Reading], test) -> str:
        return f"{100 * np.mean([test(r) for r in selected]):.0f} %" if selected else "-"

    for lo, hi in zip(BANDS[:-1], BANDS[1:]):
        band = [r for r, x in zip(rows, ratios) if lo <= x < hi]
        fev1 = [share(band, lambda r, k=k: within(getattr(r, k).fev1_l, r.truth.fev1_l, 0.05, 0.03))
                for k in ("straight", "fitted")]
        fvc = [share(band, lambda r, k=k: within(getattr(r, k).fvc_l, r.truth.fvc_l, 0.05, 0.03))
               for k in ("straight", "fitted")]
        accept = [share(band, lambda r, k=k: getattr(r, k).fvc_acceptable == r.truth.fvc_acceptable
                        and getattr(r, k).fev1_acceptable == r.truth.fev1_acceptable) for k in ("straight", "fitted")]
        read = [r for r in band if r.given] if every_frame else band
        pef = share(read, lambda r: within(r.straight.pef_lps, r.truth.pef_lps, 0.30, 0.10))
        if every_frame:
            pef += f" ({len(read)} given)"
        label = f"{100 * lo:.0f}-{100 * hi:.0f} %" if np.isfinite(hi) else f"{100 * lo:.0f} % and more"
        cells = [label, str(len(band)), " / ".join(fev1), " / ".join(fvc), " / ".join(accept), pef]
        lines.append("| " + " | ".join(cells) + " |")
    given = [r for r in rows if r.given]
    if every_frame:
        rule = (f"the ratio of the maps smoothed as little as brings it to at most "
                f"{100 * MAX_PEF_NOISE_RATIO_FRAMES:.0f} % (MAX_PEF_NOISE_RATIO_FRAMES, PEAK_FLOW_SIGMAS_S) is so")
    else:
        rule = f"the ratio is at most {100 * MAX_PEF_NOISE_RATIO:.0f} % (MAX_PEF_NOISE_RATIO)"
    lines += ["", f"PEF is given where {rule}: {len(given)} of {len(rows)} samplings, "
                  f"{share(given, lambda r: within(r.straight.pef_lps, r.truth.pef_lps, 0.30, 0.10))} of them "
                  "within 10 % or 0.30 L/s."]
    return "\n".join(lines)


def bev_by_step(folder: Path, steps_s: list[float], phases: int) -> str:
    """The back-extrapolated volume of the standard waveforms on error-free maps `steps_s` apart, read
    straight and fitted, against each waveform's own: how far apart the maps may be for a blow's start
    to be judged (core.analysis.spirometry.start_not_judged)."""
    waveforms = standard_waveforms(folder)
    lines = ["| map step (ms) | samplings | BEV error median / 95th percentile / largest (mL), straight "
             "| the same, fitted | start judged as the waveform's, straight / fitted "
             "| a good start called hesitant, straight / fitted |", "|---|---|---|---|---|---|"]
    for step in steps_s:
        errors: dict[str, list[float]] = {"straight": [], "fitted": []}
        same: dict[str, list[bool]] = {"straight": [], "fitted": []}
        false: dict[str, list[bool]] = {"straight": [], "fitted": []}
        for volume, rate_hz, truth in waveforms:
            for phase in np.arange(phases) * step / phases:
                t, v = maps_of(volume, rate_hz, phase, step)
                for kind, curve in (("straight", resample(t, v)[1]),
                                    ("fitted", smoothed_on_grid(t, v, ANALYSIS_RATE_HZ)[1])):
                    read = forced_values(curve, ANALYSIS_RATE_HZ)
                    errors[kind].append(1000 * (read.bev_l - truth.bev_l))
                    same[kind].append(read.bev_ok == truth.bev_ok)
                    false[kind].append(truth.bev_ok and not read.bev_ok)

        def spread(kind: str) -> str:
            e = np.asarray(errors[kind])
            return f"{np.median(e):+.0f} / {np.percentile(np.abs(e), 95):.0f} / {np.abs(e).max():.0f}"

        def pair(shares: dict[str, list[bool]]) -> str:
            return " / ".join(f"{100 * np.mean(shares[k]):.0f} %" for k in ("straight", "fitted"))

        lines.append(f"| {1000 * step:.1f} | {len(errors['straight'])} | {spread('straight')} | {spread('fitted')} "
                     f"| {pair(same)} | {pair(false)} |")
    intro = (f"The {len(waveforms)} standard waveforms (ISO 26782, ATS 24) as error-free maps of a light cycle's mean "
             f"volume, one every map step at {phases} phases, read straight (as the live view reads a blow) and "
             "fitted (as the analysis reads an optical blow); their back-extrapolated volume (BEV) and start "
             "verdict (ATS/ERS 2019: BEV at most 5 % of FVC or 0.100 L) against the waveform's own.")
    return intro + "\n\n" + "\n".join(lines)


def run_blows_bench(folder: Path, noise_ml: list[float], phases: int, draws: int, seed: int,
                    every_frame: bool = False) -> str:
    rows = readings(folder, [n / 1000 for n in noise_ml], phases, draws, seed, every_frame)
    waveforms = len({id(r.truth) for r in rows})
    sampling = "one map a frame (1/110 s" if every_frame else "one map a light cycle (1/22 s"
    step = "9.1 ms" if every_frame else "45 ms"
    intro = (f"The {waveforms} standard waveforms (ISO 26782, ATS 24) sampled {sampling}, each map the mean "
             f"over its light cycle) at {phases} phases, with white noise of "
             f"{', '.join(f'{n:g}' for n in noise_ml)} mL a map ({draws} draws each, seed {seed}), read straight and "
             "fitted (a smoothing spline, its weight by generalised cross-validation). Bands of the curve's own "
             f"flow noise over one map step (sqrt(2) times its noise over {step}) over its fitted PEF; within: "
             "3 % or 50 mL of the waveform's own value read from the waveform itself.")
    if every_frame:
        intro += (" PEF is read as the analysis reads a blow's maps at every frame (core.analysis.values, "
                  "peak_flow_of_frames): smoothed with the least of PEAK_FLOW_SIGMAS_S whose flow noise is at most "
                  f"{100 * MAX_PEF_NOISE_RATIO_FRAMES:.0f} % of the fitted PEF, then straight; the bands are of the "
                  "maps' own ratio, unsmoothed.")
    return intro + "\n\n" + table(rows, every_frame)


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench blows`: its arguments and what it runs."""
    bl = what.add_parser("blows", help="the standard waveforms read as optical maps with noise: FEV1, FVC, "
                                       "acceptability and PEF, read straight and fitted")
    bl.add_argument("--noise-ml", default="0,5,10,15,20,25,35", help="noise of a map, mL (comma-separated)")
    bl.add_argument("--phases", type=int, default=4, help="phases of the light cycle each waveform is sampled at")
    bl.add_argument("--draws", type=int, default=2, help="noise draws per phase and noise")
    bl.add_argument("--seed", type=int, default=0)
    bl.add_argument("--waveforms", type=Path, default=SHARED / "data" / "spirometry-waveforms",
                    help="the standard test waveforms (default ../shared/data/spirometry-waveforms)")
    bl.add_argument("--every-frame", action="store_true",
                    help="one map a frame (1/110 s), as process makes through the top of each forced blow")
    bl.add_argument("--bev-steps-ms", default=None,
                    help="instead: the blows' back-extrapolated volume on error-free maps this far apart "
                         "(ms, comma-separated), against the waveforms' own")
    bl.add_argument("--no-write", action="store_true", help="print only")

    def run_blows(args: argparse.Namespace) -> int:
        from app.errors import UserError

        noise = noises_ml(args.noise_ml)
        if args.phases < 1 or args.draws < 1:
            raise UserError("--phases and --draws take 1 or more")
        if args.bev_steps_ms is not None:
            try:
                steps = [float(x) / 1000 for x in args.bev_steps_ms.split(",")]
            except ValueError:
                raise UserError(f"--bev-steps-ms takes numbers separated by commas, got {args.bev_steps_ms!r}") from None
            if not steps or not all(np.isfinite(s) and s > 0 for s in steps):
                raise UserError(f"--bev-steps-ms takes positive steps, got {args.bev_steps_ms!r}")
            try:
                text = bev_by_step(args.waveforms, steps, args.phases)
            except (FileNotFoundError, ValueError) as exc:
                raise UserError(str(exc)) from exc
            return publish(args, "blows-bev", f"A blow's start on maps far apart (`photopft bench blows "
                                              f"--bev-steps-ms {args.bev_steps_ms} --phases {args.phases}`)", text)
        try:
            text = run_blows_bench(args.waveforms, noise, args.phases, args.draws, args.seed, args.every_frame)
        except (FileNotFoundError, ValueError) as exc:
            raise UserError(str(exc)) from exc
        frames = " --every-frame" if args.every_frame else ""
        return publish(args, "blows-frames" if args.every_frame else "blows",
                        f"Forced expirations read through the maps' noise (`photopft bench blows "
                        f"--noise-ml {args.noise_ml} --phases {args.phases} --draws {args.draws} "
                        f"--seed {args.seed}{frames}`)", text)

    bl.set_defaults(run=run_blows)
