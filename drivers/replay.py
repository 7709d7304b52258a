"""A recorded session's devices: its cameras and flow sensor played back on one clock, at real speed
(or `speed` times it), with pause and seek (the live view's replay of a session file)."""

from __future__ import annotations

import threading
import time

import numpy as np

from core.io.session import SessionFile
from drivers.camera import CameraStats, Frame, frame_due_within
from drivers.flowsensor import FlowBlock


class FileCamera:
    """A recorded head played back at its own pace (times `speed`)."""

    def __init__(self, session: SessionFile, head: str, clock: "ReplayClock") -> None:
        self.head = head
        self._frames = session.frames(head)
        self._ids = session.frame_id(head)
        self._stamps = session.timestamp_ns(head)
        self._clock = clock
        self._next = 0
        self._generation = 0
        self._drained = False  # asked for a frame after the last one: every frame was handed on
        self.stats = CameraStats()
        self.name = f"replay-{head}"

    def start(self) -> None:
        self._clock.start()

    def grab(self, timeout_s: float = 0.5) -> Frame | None:
        if self._generation != self._clock.generation:  # the operator moved the position
            self._generation = self._clock.generation
            self._next = int(np.searchsorted(self._stamps, self._clock.now_ns()))
            self._drained = False
        if self._next >= len(self._ids):
            self._drained = True
            time.sleep(timeout_s)
            return None
        if not frame_due_within(self._clock.wait_s(int(self._stamps[self._next])), timeout_s):
            return None
        k = self._next
        self._next += 1
        frame = Frame(np.asarray(self._frames[k]), int(self._ids[k]), int(self._stamps[k]))
        self.stats.count(frame)
        return frame

    @property
    def finished(self) -> bool:
        """Every frame handed on: the capture loop came back for one after the last (a frame is
        counted by the engine between one grab and the next, and a replay that said it was over on
        taking its last frame left the count one short for a moment)."""
        return self._drained

    def stop(self) -> None:
        pass

    def close(self) -> None:
        pass


class ReplayClock:
    """The recording's time during a replay: running at `speed` times real time, paused, or moved
    to another position (each move counted in `generation`, so the readers find their place)."""

    def __init__(self, first_ns: int, speed: float, last_ns: int | None = None) -> None:
        self.first_ns = first_ns
        self.last_ns = last_ns if last_ns is not None else first_ns
        self.speed = speed
        self._started: int | None = None
        self._anchor_ns = first_ns  # the recording's time at the wall clock's _started
        self._paused_at: int | None = None
        self.generation = 0
        self._lock = threading.Lock()

    def start(self) -> None:
        with self._lock:
            if self._started is None:
                self._started = time.monotonic_ns()

    def now_ns(self) -> int:
        """The recording's time now."""
        self.start()
        with self._lock:
            if self._paused_at is not None:
                return self._paused_at
            return self._anchor_ns + int((time.monotonic_ns() - self._started) * self.speed)

    def wait_s(self, stamp_ns: int) -> float:
        if self.paused:
            return float("inf")
        return (stamp_ns - self.now_ns()) / self.speed / 1e9

    @property
    def paused(self) -> bool:
        return self._paused_at is not None

    def pause(self) -> None:
        now = self.now_ns()
        with self._lock:
            self._paused_at = now

    def resume(self) -> None:
        self.seek(self.now_ns(), paused=False)

    def seek(self, stamp_ns: int, paused: bool | None = None) -> None:
        stamp = int(min(max(stamp_ns, self.first_ns), self.last_ns))
        with self._lock:
            keep_paused = self._paused_at is not None if paused is None else paused
            self._started = time.monotonic_ns()
            self._anchor_ns = stamp
            self._paused_at = stamp if keep_paused else None
            self.generation += 1


class FileFlow:
    def __init__(self, session: SessionFile, clock: ReplayClock) -> None:
        self._adc, self._stamps = session.flow_samples()
        self._clock = clock
        self._next = 0
        self._generation = 0
        self.sample_rate_hz = session.flow.sample_rate_hz
        self.lost_samples = 0

    def start(self) -> None:
        self._clock.start()

    def read(self) -> FlowBlock:
        now = self._clock.now_ns()
        if self._generation != self._clock.generation:
            self._generation = self._clock.generation
            self._next = int(np.searchsorted(self._stamps, now))
        end = int(np.searchsorted(self._stamps, now, side="right"))
        k = np.arange(self._next, end)
        self._next = max(self._next, end)
        return FlowBlock(self._adc[k].astype(np.int32), k.astype(np.int64), self._stamps[k], 0)

    def stop(self) -> None:
        pass

    def close(self) -> None:
        pass
