"""A noisy, sparsely sampled volume curve fitted before its manoeuvres are read.

An optical volume has one sample a light cycle (45 ms) and each sample its own noise (10-25 mL on the
population's subjects). Read straight, a forced expiration's steepest 45 ms and its largest sample are
the noise's largest excursions: PEF, the back-extrapolated time zero (and so FEV1), the FVC and the
cough check follow them. A cubic smoothing spline whose roughness weight is chosen by generalised
cross-validation (Craven and Wahba 1979) weighs the curve's own noise against its bends, with nothing
set in litres or seconds (docs/history/volume-log.md, "Forced expirations read through the maps' noise").
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import make_smoothing_spline

MIN_SAMPLES = 5  # fewer samples than this are not fitted: the curve is taken straight


def smoothed_on_grid(t_s: np.ndarray, volume_l: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """The smoothing spline through (t_s, volume_l), evaluated on an even grid at rate_hz from the
    first sample to the last. Samples at the same time are merged (their mean). The samples must be
    finite (core.analysis.values leaves out a manoeuvre with a missing one, and says so)."""
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(volume_l, dtype=float)
    t, inverse = np.unique(t, return_inverse=True)
    v = np.bincount(inverse, weights=v) / np.bincount(inverse)
    grid = np.arange(t[0], t[-1], 1.0 / rate_hz)
    if len(t) < MIN_SAMPLES:
        return grid, np.interp(grid, t, v)
    return grid, make_smoothing_spline(t, v)(grid)
