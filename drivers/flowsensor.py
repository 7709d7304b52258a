"""The pneumotachometer's ADC on a serial line (protocol: docs/protocols.md), and its emulator.

The device streams one frame per sample at 1000 samples/s: a 32-bit counter and the 12-bit ADC
reading, framed with a CRC. The driver resynchronises after corrupted or dropped bytes, counts the
samples lost (gaps in the counter) and timestamps every sample on the session clock from the
device's own sample clock, anchored at the first sample received.
"""

from __future__ import annotations

import os
import struct
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import serial

from drivers.framing import FrameReader, encode
from drivers.pty_device import PtyDevice

IDENTIFY, GO, HALT, SAMPLE = b"I", b"G", b"H", b"S"


class FlowSensorError(Exception):
    """The flow sensor cannot be opened or stopped answering; the message says which."""


@dataclass
class FlowBlock:
    adc: np.ndarray  # int32
    counter: np.ndarray  # int64
    timestamp_ns: np.ndarray  # int64, session clock
    lost: int  # samples missing since the previous block (gaps in the counter)


class FlowSensor:
    def __init__(self, port: str, sample_rate_hz: float = 1000.0, baudrate: int = 921600,
                 clock_ns: Callable[[], int] = time.monotonic_ns, timeout_s: float = 0.5) -> None:
        self.port_name = port
        self.sample_rate_hz = sample_rate_hz
        self.timeout_s = timeout_s
        self._clock = clock_ns
        try:
            self._port = serial.Serial(port, baudrate=baudrate, timeout=0.01)
        except serial.SerialException as exc:
            raise FlowSensorError(f"cannot open the flow sensor on {port}: {exc}") from exc
        self._reader = FrameReader()
        self._anchor: tuple[int, int] | None = None  # (counter, session time) of the first sample
        self._last_counter: int | None = None
        self.lost_samples = 0
        self._last_data = time.monotonic()

    @property
    def corrupted_frames(self) -> int:
        return self._reader.bad_frames

    def _command(self, command: bytes) -> None:
        self._port.write(encode(command))

    def identify(self) -> str:
        self._command(IDENTIFY)
        deadline = time.monotonic() + self.timeout_s
        while time.monotonic() < deadline:
            for body in self._reader.feed(self._port.read(256)):
                if body[:1] == IDENTIFY:
                    return body[1:].decode(errors="replace")
        raise FlowSensorError(f"the flow sensor on {self.port_name} did not identify itself")

    def start(self) -> None:
        self._anchor = None
        self._last_counter = None
        self._last_data = time.monotonic()
        self._command(GO)

    def stop(self) -> None:
        self._command(HALT)

    def read(self) -> FlowBlock:
        """The samples that have arrived; raises FlowSensorError when the stream has been silent too long."""
        data = self._port.read(max(1, self._port.in_waiting))
        now = self._clock()
        counters, values = [], []
        for body in self._reader.feed(data):
            if body[:1] == SAMPLE and len(body) == 7:
                counter, adc = struct.unpack("<IH", body[1:])
                counters.append(counter)
                values.append(adc)
        if data:
            self._last_data = time.monotonic()
        elif time.monotonic() - self._last_data > self.timeout_s:
            raise FlowSensorError(f"the flow sensor on {self.port_name} sent nothing for {self.timeout_s:g} s")
        counter = np.asarray(counters, dtype=np.int64)
        lost = 0
        if len(counter):
            if self._anchor is None:
                self._anchor = (int(counter[0]), now - int(round(1e9 / self.sample_rate_hz)))
            previous = self._last_counter if self._last_counter is not None else int(counter[0]) - 1
            steps = np.diff(np.concatenate([[previous], counter]))
            lost = int(np.sum(np.clip(steps - 1, 0, None)))
            self._last_counter = int(counter[-1])
            self.lost_samples += lost
        first, at = self._anchor if self._anchor is not None else (0, now)
        stamps = at + np.round((counter - first) * 1e9 / self.sample_rate_hz).astype(np.int64)
        return FlowBlock(np.asarray(values, dtype=np.int32), counter, stamps, lost)

    def close(self) -> None:
        self._port.close()


class FlowSensorEmulator(PtyDevice):
    """The sensor's firmware on a pseudo-terminal, streaming a flow signal through its ADC transfer.

    `corrupt_rate` flips a random byte of that share of the frames, `drop_rate` loses that share
    of them whole: the faults a real serial link has.
    """

    def __init__(self, flow_lps: Callable[[float], float] | None = None, gain_lps: float = 0.0075,
                 offset_lps: float = -15.36, sample_rate_hz: float = 1000.0, corrupt_rate: float = 0.0,
                 drop_rate: float = 0.0, seed: int = 0) -> None:
        super().__init__()
        self.flow_lps = flow_lps or (lambda t: 0.5 * np.sin(2 * np.pi * t / 4.0))
        self.gain_lps, self.offset_lps = gain_lps, offset_lps
        self.sample_rate_hz = sample_rate_hz
        self.corrupt_rate, self.drop_rate = corrupt_rate, drop_rate
        self._rng = np.random.default_rng(seed)
        self.counter = 0
        self.sent = 0
        self.streaming = False

    def adc_for(self, flow_lps: float) -> int:
        return int(np.clip(round((flow_lps - self.offset_lps) / self.gain_lps), 0, 4095))

    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self.master, view)
                view = view[n:]
            except BlockingIOError:
                time.sleep(0.0005)

    def _serve(self) -> None:
        reader = FrameReader()
        os.set_blocking(self.master, False)
        started = None
        while not self._stop.is_set():
            try:
                for body in reader.feed(os.read(self.master, 256)):
                    if body[:1] == IDENTIFY:
                        self._write(encode(IDENTIFY + b"photopft-flowsensor,1.0,12-bit,1000Hz"))
                    elif body[:1] == GO:
                        self.streaming, started = True, time.monotonic() - self.counter / self.sample_rate_hz
                    elif body[:1] == HALT:
                        self.streaming = False
            except BlockingIOError:
                pass
            except OSError:
                return
            if self.streaming and started is not None:
                due = int((time.monotonic() - started) * self.sample_rate_hz)
                chunk = bytearray()
                while self.counter < due:
                    t = self.counter / self.sample_rate_hz
                    frame = bytearray(encode(SAMPLE + struct.pack("<IH", self.counter, self.adc_for(self.flow_lps(t)))))
                    self.counter += 1
                    if self._rng.random() < self.drop_rate:
                        continue
                    if self._rng.random() < self.corrupt_rate:
                        frame[int(self._rng.integers(0, len(frame)))] ^= 0xFF
                    chunk += frame
                    self.sent += 1
                if chunk:
                    self._write(bytes(chunk))
            time.sleep(0.002)
