"""The room light's mains flicker, measured on the dark frames and taken out of every frame.

The dark frame of a light cycle measures the ambient light (ARCHITECTURE.md: I_k = ... + ambient),
but only at its own instant. Lamps on the mains flicker at twice its frequency (100 Hz on a 50 Hz
supply); the camera's frames sample that flicker at another phase each, so "lit minus dark" leaves
every light with its own share of it: a different error in each light's image, a different normal
error in every cycle, a volume curve that jumps from map to map (docs/history/reconstruction-log.md, "Room
light": 0.47 L of map-to-map noise from a 30 % flicker on a population subject, 0.016 L without).

Over a short window of dark frames j (FLICKER_WINDOW_S) the ambient image is modelled as

    D_j(x) = C(x) + s(x) (t_j - t_0) + m(x) u(t_j),    u(t) = cos(2 pi f t - phi),

with f the flicker frequency (twice the rig's mains frequency), one phase phi for the whole image
(one mains) fitted on the dark frames' mean level, and per pixel a steady part C, a slow trend s
(the subject moves) and the flicker's amplitude m (daylight does not flicker, lamps do, and their
shares differ over the image). Every frame i, lit or dark, then has m(x) u(t_i) taken out: all
of a cycle's frames see the ambient at its steady level and the dark frame's subtraction is exact.
A flicker the dark frames do not show above their noise (MIN_FLICKER_SNR) is left alone, so a room
without flicker gets no noise added, and so is each pixel whose own m(x) does not stand above its
noise (PIXEL_FLICKER_FALSE_ALARM: a backdrop the lamps do not light); nor is a window whose dark
frames all fall on one phase of the flicker (a frame rate locked to the mains) corrected, since it
cannot be measured there.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from scipy.stats import t as student_t

from core.reconstruction.binning import bin_mean, frame_mean

FLICKER_WINDOW_S = 1.0  # ten beats of a 100 Hz flicker against 110 frames/s; the subject moves little in it
MIN_DARK_FRAMES = 10
# The mean dark level's flicker amplitude over its standard error below which nothing is corrected.
MIN_FLICKER_SNR = 6.0
# The share of pixels whose flicker amplitude, where nothing flickers, noise alone may put past the
# test of significant_amplitude (Student's t: 5.1 standard errors with a second's 22 dark frames, 7.7
# with the half second a recording's first cycles have)
PIXEL_FLICKER_FALSE_ALARM = 6e-5
# The dark frames' phases must spread over the flicker's period: the smallest singular value of the
# (sin, cos) columns, normalised, below which the window cannot tell a flicker from a steady light.
MIN_PHASE_SPREAD = 0.3


def _steady_and_trend(t: np.ndarray) -> np.ndarray:
    """The design's columns for a steady level and a linear trend over the window (n, 2)."""
    return np.column_stack([np.ones(len(t)), (t - t.mean()) / max(float(np.ptp(t)), 1e-9)])


def flicker_phase(t_s: np.ndarray, level: np.ndarray, flicker_hz: float) -> tuple[float, float] | None:
    """(amplitude, phase) of the flicker in a series of mean dark levels (DN), fitted with a steady
    level and a linear trend; None when it is not measurable or not above the noise."""
    t = np.asarray(t_s, dtype=float)
    y = np.asarray(level, dtype=float)
    n = len(t)
    if n < MIN_DARK_FRAMES:
        return None
    w = 2.0 * np.pi * flicker_hz * t
    design = np.column_stack([_steady_and_trend(t), np.cos(w), np.sin(w)])
    trig = design[:, 2:] - design[:, 2:].mean(axis=0)
    if np.linalg.svd(trig / np.sqrt(n / 2.0), compute_uv=False)[-1] < MIN_PHASE_SPREAD:
        return None
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = y - design @ coef
    sigma = float(np.sqrt(np.sum(residual ** 2) / max(n - 4, 1)))
    amplitude = float(np.hypot(coef[2], coef[3]))
    standard_error = sigma * np.sqrt(2.0 / n)
    if amplitude <= MIN_FLICKER_SNR * max(standard_error, 1e-12):
        return None
    return amplitude, float(np.arctan2(coef[3], coef[2]))


def significant_amplitude(design: np.ndarray, darks: np.ndarray) -> np.ndarray:
    """m(x), the last column's coefficient of the least-squares fit of `design` (n, 3) to each pixel of
    the dark frames (n, h, w), where it is significant against each pixel's own residual noise (at
    PIXEL_FLICKER_FALSE_ALARM), and 0 elsewhere.

    Each pixel's m(x) from the dark frames of one second carries about 0.3 of a frame's noise, and
    taking it out adds that noise to every frame of the cycle, at another phase in each: on pixels
    where nothing flickers (a backdrop the room's lamps do not light) it is noise alone. Behind
    polarisers, with the subject's edge at a few DN of signal, that noise let background pixels into
    the subject's silhouette and made one head's trunk 10 px wider in 350 (docs/reconstruction.md)."""
    pinv = np.linalg.pinv(design).astype(np.float32)
    n = len(design)
    flat = darks.reshape(n, -1)
    coefficients = pinv @ flat
    residual = flat - design.astype(np.float32) @ coefficients
    dof = max(n - design.shape[1], 1)
    variance = np.einsum("ij,ij->j", residual, residual) / dof
    amplitude = coefficients[-1]
    standard_error = np.sqrt(variance * float(np.linalg.inv(design.T @ design)[-1, -1]))
    amplitude[np.abs(amplitude) < student_t.isf(PIXEL_FLICKER_FALSE_ALARM / 2, dof) * standard_error] = 0.0
    return amplitude.reshape(darks.shape[1:])


class FlickerCorrection:
    """One head's dark frames over a sliding window and the flicker they show.

    Feed every dark frame in time order (`add_dark`); `excess(t_s)` is the flicker's part of a
    frame at t_s (an image to subtract), or None when there is nothing to correct. `centred`:
    the window is centred on the asked time (offline processing, which has the dark frames after
    it too); otherwise it ends there (the live view)."""

    def __init__(self, flicker_hz: float, window_s: float = FLICKER_WINDOW_S, centred: bool = True,
                 binning: int = 1) -> None:
        self.flicker_hz = float(flicker_hz)
        self.window_s = float(window_s)
        self.centred = centred
        self.binning = int(binning)  # the frames' binning (core/reconstruction/binning.py): m(x) is on its bins
        # [time s, the frame as it came, its mean level, the frame binned once a fit needed it]
        self._darks: deque[list] = deque()
        self._fitted_for: tuple[float, float] | None = None
        self._fit: tuple[float, np.ndarray] | None = None  # (phase, m(x))
        self.amplitudes: list[float] = []  # each fit's flicker amplitude over the mean dark level

    def add_dark(self, t_s: float, frame: np.ndarray) -> None:
        """A dark frame as the camera gave it (unbinned; kept by reference). Only its mean level
        is taken now: it is binned when a flicker is found and m(x) fitted, so a room without one
        costs no binning (a full-resolution frame takes about 1.5 ms)."""
        image = np.asarray(frame)
        self._darks.append([float(t_s), image, frame_mean(image, self.binning), None])

    def _binned(self, dark: list) -> np.ndarray:
        if dark[3] is None:
            dark[3] = bin_mean(dark[1], self.binning)
        return dark[3]

    def span(self, t_s: float) -> tuple[float, float]:
        """The window of dark frames used for a frame at t_s. Centred, it is cut short at a recording's
        ends rather than moved: the flicker of an edge that moves (an arm's) is best fitted around the
        frame's own instant (moved to lie whole within the recording, the front's trunk of population
        subject 4 behind polarisers read 137-144 px wide in the first second for 130-132)."""
        if self.centred:
            return t_s - self.window_s / 2.0, t_s + self.window_s / 2.0
        return t_s - self.window_s, t_s

    def _fit_window(self, start: float, stop: float) -> tuple[float, np.ndarray] | None:
        while self._darks and self._darks[0][0] < start:  # windows only move on
            self._darks.popleft()
        inside = [d for d in self._darks if start <= d[0] <= stop]
        if len(inside) < MIN_DARK_FRAMES:
            return None
        t = np.array([d[0] for d in inside])
        found = flicker_phase(t, np.array([d[2] for d in inside]), self.flicker_hz)
        if found is None:
            return None
        amplitude, phase = found
        self.amplitudes.append(amplitude / max(float(np.mean([d[2] for d in inside])), 1e-9))
        u = np.cos(2.0 * np.pi * self.flicker_hz * t - phase)
        design = np.column_stack([_steady_and_trend(t), u])
        return phase, significant_amplitude(design, np.stack([self._binned(d) for d in inside]).astype(np.float32))

    def excess(self, t_s: float, around_s: float | None = None) -> np.ndarray | None:
        """The flicker's part of a frame taken at t_s: m(x) cos(2 pi f t_s - phi), or None; fitted on
        the window around `around_s` (default t_s: give all frames of one cycle the same time)."""
        start, stop = self.span(t_s if around_s is None else around_s)
        step = self.window_s / 10.0  # refitted as the window moves on by a tenth of itself
        key = (round(start / step), round(stop / step))
        if key != self._fitted_for:
            self._fitted_for = key
            self._fit = self._fit_window(start, stop)
        if self._fit is None:
            return None
        phase, amplitude_image = self._fit
        return amplitude_image * np.float32(np.cos(2.0 * np.pi * self.flicker_hz * t_s - phase))
