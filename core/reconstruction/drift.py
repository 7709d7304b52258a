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
# The live view reads the lights every LOOK_INTERVAL_S (2 s, core/reconstruction/live_checks.py) and has only
# the readings so far: a line through them weighted over this sigma. On readings with 0.2 % of noise of
# lights drifting by 2 % on a 3-minute sine and 3.6 % a minute, 5 s followed them within 0.25 % rms, 10 s
# 0.22 %, 15 s 0.20 %, 20 s 0.23 %, 30 s 0.40 % (the curve's bend; scratch, 2026-12-02)
LIVE_LIGHT_GAIN_SMOOTHING_S = 15.0


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
        tk, gk = _without_outliers(t[good], log_gain[good, k], sigma_s)
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


class FollowedLightGains:
    """The lights' outputs followed as a stream comes in (the live view), where `process` fits them over
    the whole session (light_gains_over_time). `add` takes a cycle's redundancy reading of each light's
    output (reflectance.RedundancyFit.light_gain) with the factors the cycle was solved with; `factors`
    gives each light's output at an instant over what it was at the first readings, when the stream's
    first maps (the live volume's reference) were made: a line fitted about the instant with Gaussian
    weights of LIVE_LIGHT_GAIN_SMOOTHING_S over the readings so far, those LIGHT_GAIN_OUTLIER robust deviations
    from their neighbours' median left out. Ones until MIN_LIGHT_GAIN_READINGS readings have come."""

    def __init__(self, sigma_s: float = LIVE_LIGHT_GAIN_SMOOTHING_S) -> None:
        self.sigma_s = sigma_s
        self._t: list[float] = []
        self._log_gain: list[np.ndarray] = []
        self._level: np.ndarray | None = None  # each light's log output at the first readings

    def add(self, t_s: float, light_gain: np.ndarray, solved_with: np.ndarray | None) -> None:
        gain = np.asarray(light_gain, dtype=float) * (1.0 if solved_with is None else np.asarray(solved_with, float))
        if not np.all(np.isfinite(gain)) or np.any(gain <= 0):
            return
        if self._t and t_s < self._t[-1]:  # a replay moved back: its readings start afresh, the level stays
            self._t, self._log_gain = [], []
        self._t.append(float(t_s))
        self._log_gain.append(np.log(gain))
        if self._level is None and len(self._t) >= MIN_LIGHT_GAIN_READINGS:
            self._level = np.median(np.array(self._log_gain), axis=0)
        if self._level is not None:  # a reading 4 sigma back weighs 3e-4 of the newest: the rest are kept
            while len(self._t) > MIN_LIGHT_GAIN_READINGS and self._t[0] < t_s - 4.0 * self.sigma_s:
                del self._t[0], self._log_gain[0]

    def factors(self, t_s: float) -> np.ndarray:
        if self._level is None or not self._t:
            return np.ones(4)
        t, log_gain = np.array(self._t), np.array(self._log_gain)
        out = np.zeros(log_gain.shape[1])
        for k in range(log_gain.shape[1]):
            tk, gk = _without_outliers(t, log_gain[:, k], self.sigma_s)
            out[k] = _smoothed(np.array([float(t_s)]), tk, gk, self.sigma_s)[0] - self._level[k]
        return np.exp(out)


def _without_outliers(t_s: np.ndarray, values: np.ndarray, sigma_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The readings within LIGHT_GAIN_OUTLIER robust deviations of their neighbours' (within sigma_s) median."""
    near = np.abs(t_s[:, None] - t_s[None, :]) <= sigma_s
    local = np.array([np.median(values[row]) for row in near])
    deviation = np.abs(values - local)
    spread = 1.4826 * np.median(deviation)
    keep = deviation <= LIGHT_GAIN_OUTLIER * spread if spread > 0 else np.ones(len(values), bool)
    return t_s[keep], values[keep]
