"""A volume curve's noise from sample to sample: what the metric volume's refusals and the analysis's
least breath are measured against."""

from __future__ import annotations

import numpy as np


def curve_noise_l(volume_l: np.ndarray) -> float:
    """A volume curve's noise from sample to sample (L): the robust rms (1.4826 MAD) of its second
    differences over sqrt(6), which breathing's own curvature from one optical map to the next hardly
    reaches. NaN with fewer than four samples."""
    v = np.asarray(volume_l, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) < 4:
        return float("nan")
    second = np.diff(v, 2)
    return float(1.4826 * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0))
