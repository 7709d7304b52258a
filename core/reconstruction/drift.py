"""The LEDs' drift followed through a session from the subject's own cycles.

An LED's output changes as it warms (the clinic's: 2 % over minutes, up to 4 % over a 60 s session
between two LEDs), and the normals follow every change the intensities do not: on population subject 15
the metric volume wandered by 350 mL over 60 s. The four lights' redundant value per pixel
(core/reconstruction/reflectance.py) measures each light's output against the intensity a cycle was
solved with, the last light's taken as the reference; measured every so often (`process` takes the
survey's cycles, about 0.5 s apart, at the two heads' distance), rejected where it jumps (an arm, a
step, a blow's own motion), smoothed over LIGHT_GAIN_SMOOTHING_S, it gives each cycle its lights'
outputs. Only their change over the session is taken: what they are at its median stays as the sphere
calibration put it (the redundant value reads a light 1-2 mm off as a few per cent of output, which a
change over time is not).
"""

from __future__ import annotations

import numpy as np

# the drift's periods are minutes (3-10 in the simulated clinic) and quiet breathing's seconds: a Gaussian
# of this sigma keeps 98.5 % of a 3-minute change and 0.1 % of a 4-s breath's
LIGHT_GAIN_SMOOTHING_S = 5.0
# a cycle's reading this many robust deviations from its neighbours' median is not taken
LIGHT_GAIN_OUTLIER = 4.0
MIN_LIGHT_GAIN_READINGS = 5


def light_gains_over_time(t_s: np.ndarray, gains: np.ndarray, at_s: np.ndarray,
                          sigma_s: float = LIGHT_GAIN_SMOOTHING_S) -> np.ndarray:
    """(len(at_s), 4) each light's output at the times at_s as a factor of the intensities the readings
    were made with, from readings gains (n, 4) at t_s (NaN where none): their log smoothed in time, less
    its median, so that the factors are 1 at the session's median. Ones where fewer than
    MIN_LIGHT_GAIN_READINGS readings are finite."""
    t = np.asarray(t_s, float)
    log_gain = np.log(np.clip(np.asarray(gains, float), 1e-6, None))
    out = np.zeros((len(at_s), log_gain.shape[1]))
    for k in range(log_gain.shape[1]):
        good = np.isfinite(log_gain[:, k])
        if good.sum() < MIN_LIGHT_GAIN_READINGS:
            continue
        tk, gk = t[good], log_gain[good, k]
        near = np.abs(tk[:, None] - tk[None, :]) <= sigma_s
        local = np.array([np.median(gk[row]) for row in near])
        deviation = np.abs(gk - local)
        spread = 1.4826 * np.median(deviation)
        keep = deviation <= LIGHT_GAIN_OUTLIER * spread if spread > 0 else np.ones(len(gk), bool)
        tk, gk = tk[keep], gk[keep]
        out[:, k] = _smoothed(np.asarray(at_s, float), tk, gk, sigma_s) - np.median(_smoothed(tk, tk, gk, sigma_s))
    return np.exp(out)


def _smoothed(at_s: np.ndarray, t_s: np.ndarray, values: np.ndarray, sigma_s: float, block: int = 2000) -> np.ndarray:
    """A line fitted about each time of at_s to values (at t_s, in any spacing) with Gaussian weights,
    its value there: a drift's slope is kept to the session's ends, where a weighted mean would lag.
    `block` times of at_s at once (a long session's every map against every reading)."""
    if len(at_s) > block:
        return np.concatenate([_smoothed(at_s[i:i + block], t_s, values, sigma_s, block)
                               for i in range(0, len(at_s), block)])
    dt = t_s[None, :] - at_s[:, None]
    weights = np.exp(-0.5 * (dt / sigma_s) ** 2)
    s0, s1, s2 = weights.sum(axis=1), (weights * dt).sum(axis=1), (weights * dt * dt).sum(axis=1)
    t0, t1 = weights @ values, (weights * dt) @ values
    determinant = s0 * s2 - s1 * s1
    flat = determinant <= 1e-12 * np.maximum(s0 * s2, 1e-300)  # readings on one side only, or one
    with np.errstate(divide="ignore", invalid="ignore"):
        line = (s2 * t0 - s1 * t1) / determinant
    return np.where(flat, t0 / np.maximum(s0, 1e-300), line)
