"""Steps: the maps a subject's step spoils, found from the body's own motion in the image.

A step (20-100 mm within half a second) moves the whole body faster than postural sway does. Its
maps are spoilt twice: the four lights of one cycle see the body at four places, and the motion
compensation draws a straight line between cycles across the step (core/reconstruction/cycle.py).
Each map's body frame (core/volume/maps.py, BodySilhouette) carries the body's shift in the image
plane since the reference map; where its speed passes STEP_SPEED_MM_S the maps are left out, with
their neighbours within STEP_MARGIN_S, as maps an arm hides are: not bridged, not referred to.
The motion along the axis is followed by the two heads' distances (core/volume/metric.py).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage, signal

from core.runs import runs
from core.volume.maps import maps_within

# In-plane body speed (mm/s) above which a map is in a step: over sway's, under a step's (docs/constants.md)
STEP_SPEED_MM_S = 40.0
# The shifts' running median and the line their speed is read from span this (docs/constants.md)
SHIFT_MEDIAN_S = 0.2
# Maps this close to a map in a step are left out too: their cycles and the neighbour cycles their
# motion compensation reads overlap the step's slower start and end.
STEP_MARGIN_S = 0.1


def maps_in_steps(timestamp_ns: np.ndarray, shift_mm: np.ndarray) -> np.ndarray:
    """Per map, whether it lies in a step: the body's in-plane shift (maps, 2) in mm since the
    reference, its running median over SHIFT_MEDIAN_S moving faster than STEP_SPEED_MM_S, widened by
    STEP_MARGIN_S each way. Maps without a shift (NaN) are judged by their neighbours' times."""
    seconds = np.asarray(timestamp_ns, dtype=float) / 1e9
    shift = np.asarray(shift_mm, dtype=float).reshape(len(seconds), 2)
    moving = np.zeros(len(seconds), dtype=bool)
    good = np.isfinite(shift).all(axis=1)
    if good.sum() < 3:
        return moving
    times = seconds[good]
    size = maps_within(times, SHIFT_MEDIAN_S)
    smooth = np.stack([ndimage.median_filter(shift[good, k], size, mode="nearest") for k in range(2)], axis=1)
    period = float(np.median(np.diff(times)))
    if len(times) < size or period <= 0:
        return moving
    speed = np.hypot(*signal.savgol_filter(smooth, size, 1, deriv=1, delta=period, axis=0, mode="interp").T)
    fast = times[speed > STEP_SPEED_MM_S]
    if not len(fast):
        return moving
    nearest = np.abs(seconds[:, None] - fast[None, :]).min(axis=1)
    return nearest <= STEP_MARGIN_S


def step_spans_s(timestamp_ns: np.ndarray, in_step: np.ndarray) -> list[tuple[float, float]]:
    """The (start, end) times in s since the first map of each run of maps in a step."""
    seconds = (np.asarray(timestamp_ns, dtype=float) - float(timestamp_ns[0])) / 1e9 if len(timestamp_ns) else []
    return [(float(seconds[a]), float(seconds[b - 1])) for a, b in runs(in_step)]


class StepWatch:
    """maps_in_steps for the live view, causally: each map's in-plane shift (mm) and time in; whether the
    body moves faster than STEP_SPEED_MM_S (the slope of a line over the shifts of the last SHIFT_MEDIAN_S)
    or did within the last STEP_MARGIN_S."""

    def __init__(self) -> None:
        self._times: list[float] = []
        self._shifts: list[tuple[float, float]] = []
        self._until_s = float("-inf")

    def moving(self, t_s: float, shift_mm: tuple[float, float]) -> bool:
        if all(np.isfinite(shift_mm)):
            self._times.append(float(t_s))
            self._shifts.append((float(shift_mm[0]), float(shift_mm[1])))
            while self._times and self._times[0] < t_s - SHIFT_MEDIAN_S:
                del self._times[0], self._shifts[0]
            if len(self._times) >= 3 and self._times[-1] > self._times[0]:
                slope = np.polyfit(np.asarray(self._times) - self._times[0], np.asarray(self._shifts), 1)[0]
                if float(np.hypot(*slope)) > STEP_SPEED_MM_S:
                    self._until_s = t_s + STEP_MARGIN_S
        return t_s <= self._until_s
