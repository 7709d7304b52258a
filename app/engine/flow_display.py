"""The flow sensor's volume as the live view draws it: BTPS, the mean flow of the last 30 s taken out
(a zero offset drifts the volume; the report's volume removes drift properly), a point every 10 ms."""

from __future__ import annotations

import collections

import numpy as np

from app.engine.feeds import WINDOW_S
from drivers.flowsensor import FlowBlock

CHUNK_SAMPLES = 10  # the flow is integrated in chunks of this many samples (10 ms at 1 kHz)
MEAN_CHUNKS = 3000  # the drift taken out: the mean flow over this many chunks (30 s)
SHOWN_EVERY_NS = 10_000_000


class FlowDisplay:
    def __init__(self, btps: float) -> None:
        self.btps = btps
        self.points: collections.deque = collections.deque(maxlen=int(WINDOW_S * 100) + 10)  # (s, L)
        self.clear()

    def clear(self) -> None:
        self.points.clear()
        self._volume_l = 0.0
        self._last_ns: int | None = None
        self._means: collections.deque = collections.deque(maxlen=MEAN_CHUNKS)
        self._sum = 0.0
        self._shown_ns = 0

    def add(self, block: FlowBlock, gain: float, offset: float, t0_ns: int | None) -> None:
        """A block's flow integrated; `t0_ns` the live view's time zero (None: nothing drawn yet)."""
        flow = (gain * block.adc.astype(float) + offset) * self.btps
        for k in range(0, len(flow), CHUNK_SAMPLES):
            chunk = flow[k:k + CHUNK_SAMPLES]
            stamps = block.timestamp_ns[k:k + CHUNK_SAMPLES]
            mean = float(chunk.mean())
            if len(self._means) == self._means.maxlen:  # a running sum: the mean of the last chunks in O(1)
                self._sum -= self._means[0]
            self._means.append(mean)
            self._sum += mean
            if self._last_ns is not None:
                dt = (int(stamps[-1]) - self._last_ns) / 1e9
                self._volume_l += (mean - self._sum / len(self._means)) * dt
            self._last_ns = int(stamps[-1])
            # at most a point every 10 ms, whatever the blocks' sizes: the buffer holds the whole window
            if t0_ns is not None and int(stamps[-1]) - self._shown_ns >= SHOWN_EVERY_NS:
                self._shown_ns = int(stamps[-1])
                self.points.append(((int(stamps[-1]) - t0_ns) / 1e9, self._volume_l))

    def curve(self) -> np.ndarray:
        """(n, 2): seconds from the live view's time zero, litres."""
        return np.array(self.points, dtype=float).reshape(-1, 2)
