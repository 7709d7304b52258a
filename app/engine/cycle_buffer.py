"""One head's newest frames as the capture thread hands them on, for its reconstruction thread and
the sphere wizard's preview: three light cycles (the newest complete one and the one before it, for
motion compensation) and the last second's dark frames (the room light's flicker)."""

from __future__ import annotations

import collections
import threading

import numpy as np

from core.reconstruction.ambient import FLICKER_WINDOW_S
from core.rig import DARK
from drivers.camera import Frame


class CycleBuffer:
    """A head's frames, each with the light that lit it; `condition` is notified on every frame."""

    def __init__(self, rig) -> None:
        self.rig = rig
        self.condition = threading.Condition()
        self._frames: collections.deque = collections.deque(maxlen=3 * rig.cycle_length)
        self._darks: collections.deque = collections.deque(
            maxlen=int(FLICKER_WINDOW_S * rig.frame_rate_hz / rig.cycle_length) + 5)

    def take(self, frame: Frame, light: int) -> None:
        with self.condition:
            self._frames.append((frame, light))
            if light == DARK:
                self._darks.append(frame)
            self.condition.notify()

    def wake(self) -> None:
        """Wakes a thread waiting for a frame (the engine is stopping)."""
        with self.condition:
            self.condition.notify_all()

    def clear(self) -> None:
        with self.condition:
            self._frames.clear()
            self._darks.clear()

    def wait_for_cycle(self, timeout_s: float, after_dark_id: int) -> tuple[list | None, dict | None, list[Frame]]:
        """After a frame or `timeout_s`: (the newest complete cycle, each light's frame one period
        before it, the dark frames newer than `after_dark_id`)."""
        with self.condition:
            self.condition.wait(timeout=timeout_s)
            window = self.newest_cycle()
            before = self.cycle_before(window) if window is not None else None
            darks = [d for d in self._darks if d.frame_id > after_dark_id]
        return window, before, darks

    def newest_cycle(self) -> list[tuple[Frame, int]] | None:
        """The newest complete light cycle in the buffer: consecutive frame ids, each light once,
        ending with the dark frame."""
        items = list(self._frames)
        n = self.rig.cycle_length
        for end in range(len(items) - 1, n - 2, -1):
            window = items[end - n + 1:end + 1]
            ids = [f.frame_id for f, _ in window]
            lights = sorted(light for _, light in window)
            if ids == list(range(ids[0], ids[0] + n)) and lights == sorted(self.rig.sequence):
                return window
        return None

    def cycle_before(self, window: list[tuple[Frame, int]]) -> dict[int, Frame] | None:
        """Each light's frame one period before the window's, if all are still in the buffer."""
        n = self.rig.cycle_length
        wanted = {frame.frame_id - n: light for frame, light in window if light != DARK}
        found = {light: frame for frame, light in list(self._frames) if wanted.get(frame.frame_id) == light}
        return found if len(found) == len(wanted) else None

    def preview(self, width_px: int = 400) -> np.ndarray | None:
        """The newest light cycle as one image (the brightest of its frames), at most about `width_px`
        wide: for placing the calibration sphere."""
        window = self.newest_cycle()
        if window is None:
            return None
        step = max(1, int(np.ceil(window[0][0].image.shape[1] / width_px)))
        return np.max([f.image[::step, ::step] for f, _ in window], axis=0)
