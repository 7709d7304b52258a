"""The recording's flow samples as the live engine keeps them for the feedback after each manoeuvre."""

from __future__ import annotations


import numpy as np

from drivers.flowsensor import FlowBlock


class FlowRecord:
    """The flow samples of the recording so far (ADC counts and session-clock stamps), for the
    feedback after each manoeuvre: the sensor's hundred blocks a second joined into one pair of
    arrays every JOIN_BLOCKS (kept as blocks, 60 000 of them in a 10-minute recording, their Python
    objects come to an estimated 40 MB)."""

    JOIN_BLOCKS = 500

    def __init__(self) -> None:
        self._adc: list[np.ndarray] = []
        self._stamps: list[np.ndarray] = []
        self._joined = 0  # leading parts that are joined already
        self.last_ns = 0

    def append(self, block: FlowBlock) -> None:
        self._adc.append(block.adc)
        self._stamps.append(block.timestamp_ns)
        self.last_ns = int(block.timestamp_ns[-1])
        if len(self._adc) - self._joined >= self.JOIN_BLOCKS:
            for parts in (self._adc, self._stamps):
                parts[self._joined:] = [np.concatenate(parts[self._joined:])]
            self._joined += 1

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        if not self._adc:
            return np.zeros(0, np.int32), np.zeros(0, np.int64)
        return np.concatenate(self._adc), np.concatenate(self._stamps)
