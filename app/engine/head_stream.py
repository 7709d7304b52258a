"""One head's live maps: the newest complete light cycle made into a map by the same cycle signal and
HeadReconstructor as `photopft process` (binned, the room light's flicker out, motion-compensated)."""

from __future__ import annotations

from core.reconstruction.ambient import FlickerCorrection
from core.reconstruction.cycle import CycleFrame, cycle_frame, cycle_signal_of
from core.reconstruction.pipeline import HeadMap, HeadReconstructor, ReconstructionSettings
from core.rig import DARK
from drivers.camera import Frame


class HeadStream:
    """A head's reconstruction state from cycle to cycle: the reconstructor (its running distance and
    last surface), the flicker fitted on the dark frames so far, and each frame binned once."""

    def __init__(self, rig, head_name: str, live_head, binning: int, settings: ReconstructionSettings) -> None:
        self.reconstructor = HeadReconstructor(live_head, None, settings)
        self.cycle_length = rig.cycle_length
        self._max_value = rig.heads[head_name].max_value
        self._binning = binning
        self._flicker = FlickerCorrection(2.0 * rig.mains_hz, centred=False, binning=binning)
        self._binned: dict[int, CycleFrame] = {}
        self.done_id = -1  # the newest frame of the last cycle made
        self.fed_id = -1  # the last dark frame the flicker has seen

    def feed_darks(self, darks: list[Frame]) -> None:
        for d in darks:
            self._flicker.add_dark(d.timestamp_ns / 1e9, d.image)
            self.fed_id = d.frame_id

    def is_new(self, window: list[tuple[Frame, int]] | None) -> bool:
        return window is not None and window[-1][0].frame_id > self.done_id

    def reconstruct(self, window: list[tuple[Frame, int]], before: dict[int, Frame] | None,
                    distance_mm: float | None) -> tuple[HeadMap, tuple]:
        """The window's map (at `distance_mm` when the two heads' geometry gives one) and the
        (signal, saturated) it was made from."""
        self.done_id = window[-1][0].frame_id
        newest_s = window[-1][0].timestamp_ns / 1e9
        by_light = {light: frame for frame, light in window}
        signal, saturated, dark = cycle_signal_of(
            [self._framed(by_light[k]) for k in range(4)], self._framed(by_light[DARK]),
            [self._framed(before[k]) for k in range(4)] if before is not None else None,
            lambda f: self._flicker.excess(f.time_s, newest_s))
        for stale in [i for i in self._binned if i < self.done_id - 3 * self.cycle_length]:
            del self._binned[stale]
        return self.reconstructor.reconstruct(signal, saturated, dark, distance_mm), (signal, saturated)

    def _framed(self, frame: Frame) -> CycleFrame:
        if frame.frame_id not in self._binned:
            self._binned[frame.frame_id] = cycle_frame(frame.image, self._binning, self._max_value,
                                                       frame.timestamp_ns / 1e9, frame.frame_id)
        return self._binned[frame.frame_id]
