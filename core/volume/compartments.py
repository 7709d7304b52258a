"""Compartments of quiet breathing from regional volumes: each region's share of the breaths and
the thoraco-abdominal phase angle (what optoelectronic plethysmography reports by compartment).

Both are taken over the stretches of quiet breathing only (core/analysis/values.py, tidal_windows), each
stretch detrended, so the slow drift of a long recording does not count as breathing.
"""

from __future__ import annotations

import numpy as np
from scipy import signal

GRID_HZ = 100.0


def _stretches(t_s: np.ndarray, curves: dict[str, np.ndarray],
               windows: list[tuple[float, float]]) -> list[dict[str, np.ndarray]]:
    """Each window's curves on an even grid, linearly detrended."""
    out = []
    for a, b in windows:
        grid = np.arange(max(a, t_s[0]), min(b, t_s[-1]), 1.0 / GRID_HZ)
        if len(grid) < 2 * GRID_HZ:
            continue
        out.append({k: signal.detrend(np.interp(grid, t_s, v)) for k, v in curves.items()})
    return out


def compartment_shares(t_s: np.ndarray, regions: dict[str, np.ndarray],
                       windows: list[tuple[float, float]]) -> dict[str, float]:
    """Each region's share of the breaths: the slope of its volume against the regions' sum."""
    stretches = _stretches(np.asarray(t_s, float), regions, windows)
    if not stretches:
        return {}
    joined = {k: np.concatenate([s[k] for s in stretches]) for k in regions}
    total = sum(joined.values())
    power = float(total @ total)
    return {k: float(v @ total) / power for k, v in joined.items()} if power > 0 else {}


def phase_angle_deg(t_s: np.ndarray, chest_l: np.ndarray, abdomen_l: np.ndarray,
                    windows: list[tuple[float, float]], breath_period_s: float) -> float:
    """Thoraco-abdominal phase angle: 360 degrees times the abdomen's delay behind the rib cage over
    the breath period (positive: the abdomen lags; 180: paradoxical breathing). The delay is where
    the two curves' cross-correlation, summed over the stretches, peaks within half a breath."""
    stretches = _stretches(np.asarray(t_s, float), {"chest": chest_l, "abdomen": abdomen_l}, windows)
    if not stretches or not np.isfinite(breath_period_s) or breath_period_s <= 0:
        return float("nan")
    max_lag = int(0.5 * breath_period_s * GRID_HZ)
    lags = np.arange(-max_lag, max_lag + 1)
    total = np.zeros(len(lags))
    for s in stretches:
        c, a = s["chest"], s["abdomen"]
        full = signal.correlate(a, c, mode="full")  # index len(c) - 1 is lag 0; a delayed shows at +lag
        centre = len(c) - 1
        lo, hi = max(0, centre - max_lag), min(len(full), centre + max_lag + 1)
        total[lo - centre + max_lag:hi - centre + max_lag] += full[lo:hi]
    k = int(np.argmax(total))
    shift = 0.0
    if 0 < k < len(total) - 1:  # parabola through the peak and its neighbours
        y0, y1, y2 = total[k - 1:k + 2]
        denominator = y0 - 2 * y1 + y2
        shift = 0.5 * (y0 - y2) / denominator if denominator != 0 else 0.0
    return float(360.0 * (lags[k] + shift) / GRID_HZ / breath_period_s)
