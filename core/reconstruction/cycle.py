"""One light cycle's signal, the same for `photopft process` and the live view: each frame binned
(core/reconstruction/binning.py), the room light's flicker taken out (core/reconstruction/ambient.py), each light's frame brought
to the cycle's newest instant (motion compensation), the dark frame subtracted.

Frames come in as CycleFrame, from a session file (core.pipeline.head_maps) or from the cameras (app.engine).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy import ndimage

from core.reconstruction.binning import frame_bins

# The change of a light's frame over one period is smoothed with this sigma (pixels of the binned
# frame, about 350 px wide) before it is extrapolated: motion changes shading smoothly, the noise
# is per pixel and would be amplified.
MOTION_SMOOTHING_PX = 2.0


@dataclass(frozen=True)
class CycleFrame:
    level: np.ndarray  # the frame binned (float64), room light included
    saturated: np.ndarray  # bins with a saturated pixel
    time_s: float
    frame_id: int


def cycle_frame(raw: np.ndarray, binning: int, max_value: int, time_s: float, frame_id: int) -> CycleFrame:
    mean, peak = frame_bins(raw, binning)
    return CycleFrame(mean, peak >= max_value, float(time_s), int(frame_id))


def cycle_signal_of(lit: list[CycleFrame], dark: CycleFrame, previous: list[CycleFrame] | None = None,
                    excess: Callable[[CycleFrame], np.ndarray | None] | None = None,
                    following: list[CycleFrame] | None = None,
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(signal (4, h, w): each light minus the dark frame, saturated (4, h, w), the dark level).

    `lit`: the frames of lights 0-3 in that order; `previous`: the same lights one cycle earlier, for
    motion compensation (the subject moves within a cycle: a forced expiration moves the chest
    millimetres in 45 ms, and the thesis' static assumption would mix five instants into one
    normal), each light extrapolated linearly along the frame ids to the cycle's newest frame;
    `following`: the same lights one cycle later (a recorded session has them), each light then
    interpolated to the newest frame between its frame in the cycle and the next one instead: the
    error of a straight line between two captures, not beyond them (up to 0.72 of the change's
    curvature over a period for the oldest light extrapolated, at most 0.125 interpolated);
    `excess`: the room light's flicker in a frame (FlickerCorrection), taken out first."""
    def level(frame: CycleFrame) -> np.ndarray:
        extra = excess(frame) if excess is not None else None
        return frame.level if extra is None else frame.level - extra

    dark_level = level(dark)
    saturated = np.stack([f.saturated for f in lit])
    signal = np.stack([level(f) for f in lit])
    newest = max([f.frame_id for f in lit] + [dark.frame_id])
    if following is not None:
        for k, (now, after) in enumerate(zip(lit, following)):
            ahead = (newest - now.frame_id) / (after.frame_id - now.frame_id)
            saturated[k] |= after.saturated
            signal[k] += ahead * ndimage.gaussian_filter(level(after) - signal[k], MOTION_SMOOTHING_PX)
    elif previous is not None:
        for k, (now, before) in enumerate(zip(lit, previous)):
            ahead = (newest - now.frame_id) / (now.frame_id - before.frame_id)
            saturated[k] |= before.saturated
            signal[k] += ahead * ndimage.gaussian_filter(signal[k] - level(before), MOTION_SMOOTHING_PX)
    return signal - dark_level[None], saturated, dark_level
