"""A forced expiration as it happens: start detection, back-extrapolated volume, time since time
zero, the end-of-test plateau, on the volume so far; and the best blow of a session.

The same rules as the report's (core.analysis.spirometry.forced_values, ATS/ERS 2019), run on the blow so
far, so that what the operator sees during the blow is what the report will say of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.analysis.spirometry import PLATEAU_L, ForcedValues, cough_not_judged, forced_values, start_not_judged
from core.analysis.values import (ANALYSIS_RATE_HZ, MAX_PEF_NOISE_RATIO, MAX_PEF_SAMPLE_INTERVAL_S, pef_noise_ratio,
                                  resample)

START_FLOW_LPS = 0.5  # the blow has started once the exhaled flow exceeds this after the full inspiration


@dataclass
class LiveBlow:
    """The blow so far. Curves from the full inspiration on, time from the back-extrapolated time
    zero once the blow has started."""

    t_s: np.ndarray
    exhaled_l: np.ndarray
    flow_lps: np.ndarray  # exhaled flow, positive out
    values: ForcedValues | None  # None until the blow has started
    seconds_since_mark: float

    @property
    def started(self) -> bool:
        return self.values is not None

    @property
    def end_of_test(self) -> bool:
        """Plateau: under 25 mL in the last second (or 15 s of expiration)."""
        return self.values is not None and self.values.eofe

    def status(self) -> str:
        if self.values is None:
            return "waiting for the blow: full inspiration, then blast out"
        v = self.values
        bev = (f"BEV not judged (a map every {1000 * v.samples_step_s:.0f} ms)" if not v.bev_judged else
               f"BEV {1000 * v.bev_l:.0f} mL (limit {1000 * v.bev_limit_l:.0f})"
               + ("" if v.bev_ok else ": hesitant start"))
        end = ("end of test reached: plateau" if v.eofe else
               f"keep blowing: {1000 * v.plateau_l:.0f} mL in the last second (plateau under {1000 * PLATEAU_L:.0f})")
        return f"FET {v.fet_s:.1f} s; {bev}; volume {v.fvc_l:.2f} L; {end}"


def live_blow(t_s: np.ndarray, volume_l: np.ndarray, mark_s: float) -> LiveBlow:
    """The blow on a volume curve (L, positive inhaled; t in s) that the operator marked at
    `mark_s`: from the highest volume since 2 s before the mark (the full inspiration) to now."""
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(volume_l, dtype=float)
    keep = np.isfinite(t) & np.isfinite(v) & (t >= mark_s - 2.0)
    t, v = t[keep], v[keep]
    now = float(t[-1] - mark_s) if len(t) else 0.0
    empty = np.zeros(0)
    if len(t) < 3 or t[-1] - t[0] < 0.1:
        return LiveBlow(empty, empty, empty, None, now)
    grid, vg = resample(t, v)
    top = int(np.argmax(vg))
    exhaled = vg[top] - vg[top:]
    exhaled = exhaled[: int(np.argmax(exhaled)) + 1]  # to the end of expiration: what follows is the next breath in
    flow = np.gradient(exhaled, 1.0 / ANALYSIS_RATE_HZ) if len(exhaled) > 1 else np.zeros(len(exhaled))
    times = grid[top:top + len(exhaled)] - grid[top]
    values = None
    if len(exhaled) >= ANALYSIS_RATE_HZ and np.any(flow > START_FLOW_LPS):
        try:
            values = forced_values(exhaled, ANALYSIS_RATE_HZ)
        except ValueError:
            values = None
        blow = t >= grid[top]
        if values is not None and blow.sum() >= 3:  # the report's rules: its PEF and its cough weighed by its noise
            values.pef_noise_ratio = pef_noise_ratio(t[blow], v[blow], values.pef_lps)
            values.samples_step_s = float(np.median(np.diff(t[blow])))
            cough_not_judged(values, values.pef_noise_ratio, MAX_PEF_NOISE_RATIO)
            start_not_judged(values, values.samples_step_s, MAX_PEF_SAMPLE_INTERVAL_S)
    if values is not None:
        times = times - values.time_zero_s
    return LiveBlow(times, exhaled, flow, values, now)


def best_blow(blows: list[ForcedValues]) -> int | None:
    """ATS/ERS 2019: the best test curve is the acceptable blow with the largest FEV1 + FVC (else
    the usable one)."""
    for pool in ([i for i, b in enumerate(blows) if b.fvc_acceptable],
                 [i for i, b in enumerate(blows) if b.fvc_usable]):
        if pool:
            return max(pool, key=lambda i: blows[i].fvc_l + blows[i].fev1_l)
    return None
