"""The daily calibration check with a 3 L syringe (ATS/ERS 2019): strokes pumped through the flow
sensor, each stroke's volume from the flow line in force, every one within 3 % of the syringe's
volume (2.91-3.09 L for 3 L: 2.5 % for the spirometer, 0.5 % for the syringe)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.runs import runs

SYRINGE_L = 3.0
TOLERANCE = 0.03
MIN_STROKES = 3  # the standard asks for at least three strokes at different flows
STROKE_FLOW_LPS = 0.1  # the flow is "moving" above this


@dataclass(frozen=True)
class Stroke:
    start_s: float
    duration_s: float
    volume_l: float  # positive: into the syringe side (inspiration), negative: out
    peak_flow_lps: float

    def error(self, syringe_l: float = SYRINGE_L) -> float:
        return abs(self.volume_l) / syringe_l - 1.0


@dataclass(frozen=True)
class SyringeCheck:
    strokes: list[Stroke]
    syringe_l: float = SYRINGE_L

    @property
    def passed(self) -> bool:
        return len(self.strokes) >= MIN_STROKES and all(abs(s.error(self.syringe_l)) <= TOLERANCE
                                                        for s in self.strokes)

    def verdict(self) -> str:
        if len(self.strokes) < MIN_STROKES:
            return f"{len(self.strokes)} strokes found, {MIN_STROKES} needed: pump the syringe fully, in and out"
        worst = max(self.strokes, key=lambda s: abs(s.error(self.syringe_l)))
        words = "passed" if self.passed else "FAILED: recalibrate the flow sensor"
        return (f"{words}: {len(self.strokes)} strokes, worst {abs(worst.volume_l):.3f} L "
                f"({100 * worst.error(self.syringe_l):+.1f} %, limit ±{100 * TOLERANCE:.0f} %)")


PAD_S = 0.3  # a stroke's slow start and end, under STROKE_FLOW_LPS, counted with it


def quiet_samples(t_s: np.ndarray, flow_lps: np.ndarray) -> np.ndarray:
    """The samples at least PAD_S away from any stroke: where the flow is the sensor's zero."""
    moving = np.abs(flow_lps) > STROKE_FLOW_LPS
    near = np.zeros(len(t_s), dtype=bool)
    for start, end in runs(moving):
        near |= (t_s >= t_s[start] - PAD_S) & (t_s <= t_s[end - 1] + PAD_S)
    return ~near


def syringe_strokes(t_s: np.ndarray, flow_lps: np.ndarray, min_volume_l: float = 0.5) -> list[Stroke]:
    """Each stroke of a syringe: a run of flow of one sign over STROKE_FLOW_LPS, with PAD_S either
    side (not into the next stroke), and its volume: the flow integrated over it."""
    t = np.asarray(t_s, dtype=float)
    f = np.asarray(flow_lps, dtype=float)
    if len(t) < 3:
        return []
    dt = np.diff(t, prepend=t[0])
    signed = []
    for sign in (1, -1):
        signed += [(a, b, sign) for a, b in runs(f * sign > STROKE_FLOW_LPS)]
    signed.sort()
    merged: list[tuple[int, int, int]] = []
    for a, b, sign in signed:  # noise about the threshold splits a slow stroke's ends off it
        if merged and merged[-1][2] == sign and t[a] - t[merged[-1][1] - 1] < 2 * PAD_S:
            merged[-1] = (merged[-1][0], b, sign)
        else:
            merged.append((a, b, sign))
    strokes = []
    for k, (a, b, sign) in enumerate(merged):
        low = t[a] - PAD_S if k == 0 else max(t[a] - PAD_S, t[merged[k - 1][1] - 1])
        high = t[b - 1] + PAD_S if k == len(merged) - 1 else min(t[b - 1] + PAD_S, t[merged[k + 1][0]])
        inside = (t >= low) & (t <= high)
        volume = float(np.sum(f[inside] * dt[inside]))
        if abs(volume) >= min_volume_l:
            strokes.append(Stroke(float(t[a]), float(t[b - 1] - t[a]), volume, float(np.max(np.abs(f[a:b])))))
    return strokes
