"""The LED and trigger sequencer on a serial line (protocol: docs/protocols.md), and its emulator.

The sequencer fires each LED in turn and triggers both cameras; its trigger counter and the
cameras' frame ids give every frame's light (drivers/light_phase.py).
"""

from __future__ import annotations

import os
import struct
import threading
import time
from dataclasses import dataclass

import serial

from drivers.framing import FrameReader, encode
from drivers.pty_device import PtyDevice

IDENTIFY, CONFIGURE, ARM, START, STOP, STATUS = b"I", b"C", b"A", b"S", b"P", b"T"
ACK, ERROR = b"K", b"E"
STATES = ("idle", "configured", "armed", "running")
MAX_RATE_HZ = 500.0


class SequencerError(Exception):
    """The sequencer refused a command, or stopped answering; the message says which."""


@dataclass(frozen=True)
class SequencerStatus:
    state: str
    trigger_count: int
    errors: int


class Sequencer:
    """Driver: one request at a time, each reply matched to its request by a sequence number."""

    def __init__(self, port: str, baudrate: int = 115200, timeout_s: float = 0.5) -> None:
        self.port_name = port
        self.timeout_s = timeout_s
        try:
            self._port = serial.Serial(port, baudrate=baudrate, timeout=0.02)
        except serial.SerialException as exc:
            raise SequencerError(f"cannot open the sequencer on {port}: {exc}") from exc
        self._reader = FrameReader()
        self._seq = 0
        self._lock = threading.Lock()

    def _request(self, command: bytes, payload: bytes = b"") -> bytes:
        with self._lock:
            self._seq = (self._seq + 1) % 256
            seq = self._seq
            self._port.write(encode(command + bytes([seq]) + payload))
            deadline = time.monotonic() + self.timeout_s
            while time.monotonic() < deadline:
                for body in self._reader.feed(self._port.read(256)):
                    if len(body) >= 2 and body[1] == seq:
                        if body[:1] == ERROR:
                            raise SequencerError(f"sequencer on {self.port_name} refused {command.decode()}: "
                                                 f"{body[3:].decode(errors='replace')} (code {body[2]})")
                        return body
            raise SequencerError(f"the sequencer on {self.port_name} did not answer {command.decode()} within "
                                 f"{self.timeout_s:g} s: check the cable and the power")

    def identify(self) -> str:
        return self._request(IDENTIFY)[2:].decode(errors="replace")

    def configure(self, sequence: tuple[int, ...], exposure_us: int, frame_rate_hz: float) -> None:
        payload = bytes([len(sequence)]) + struct.pack(f"<{len(sequence)}b", *sequence)
        payload += struct.pack("<II", int(exposure_us), int(round(frame_rate_hz * 1000)))
        self._request(CONFIGURE, payload)

    def arm(self) -> None:
        self._request(ARM)

    def start(self) -> None:
        self._request(START)

    def stop(self) -> None:
        self._request(STOP)

    def status(self) -> SequencerStatus:
        body = self._request(STATUS)
        state, count, errors = struct.unpack("<BQH", body[2:13])
        return SequencerStatus(STATES[state] if state < len(STATES) else f"unknown {state}", count, errors)

    def close(self) -> None:
        self._port.close()


class SequencerEmulator(PtyDevice):
    """The sequencer's firmware, serving its protocol on a pseudo-terminal (or any file descriptor)."""

    def __init__(self, serial_number: str = "EMU-0001") -> None:
        super().__init__()
        self.serial_number = serial_number
        self.state = 0
        self.sequence: tuple[int, ...] = (0, 1, 2, 3, -1)
        self.exposure_us = 0
        self.rate_hz = 0.0
        self.errors = 0
        self._started_at: float | None = None
        self.silent = False  # True: stops answering, as a device that hangs

    def trigger_count(self) -> int:
        if self._started_at is None:
            return 0
        return int((time.monotonic() - self._started_at) * self.rate_hz)

    def _reply(self, body: bytes) -> None:
        if not self.silent:
            os.write(self.master, encode(body))

    def _error(self, seq: int, code: int, message: str) -> None:
        self._reply(ERROR + bytes([seq, code]) + message.encode())

    def _handle(self, body: bytes) -> None:
        command, seq, payload = body[:1], body[1], body[2:]
        if command == IDENTIFY:
            self._reply(IDENTIFY + bytes([seq]) + f"photopft-sequencer,1.0,{self.serial_number}".encode())
        elif command == CONFIGURE:
            if self.state == 3:
                return self._error(seq, 3, "stop before configuring")
            n = payload[0] if payload else 0
            if len(payload) != 1 + n + 8:
                return self._error(seq, 1, "malformed configuration")
            sequence = struct.unpack(f"<{n}b", payload[1:1 + n])
            exposure, rate_mhz = struct.unpack("<II", payload[1 + n:])
            rate = rate_mhz / 1000.0
            if sorted(i for i in sequence if i != -1) != [0, 1, 2, 3] or -1 not in sequence:
                return self._error(seq, 2, "the cycle must fire LEDs 0-3 once each and hold a dark slot")
            if not 0 < rate <= MAX_RATE_HZ or exposure * rate > 1e6:
                return self._error(seq, 2, f"rate {rate:g} Hz with exposure {exposure} us is impossible")
            self.sequence, self.exposure_us, self.rate_hz, self.state = sequence, exposure, rate, 1
            self._reply(ACK + bytes([seq]))
        elif command == ARM:
            if self.state != 1:
                return self._error(seq, 3, "configure before arming")
            self.state = 2
            self._reply(ACK + bytes([seq]))
        elif command == START:
            if self.state != 2:
                return self._error(seq, 3, "arm before starting")
            self.state, self._started_at = 3, time.monotonic()
            self._reply(ACK + bytes([seq]))
        elif command == STOP:
            self.state, self._started_at = (1 if self.state else 0), None
            self._reply(ACK + bytes([seq]))
        elif command == STATUS:
            self._reply(STATUS + bytes([seq]) + struct.pack("<BQH", self.state, self.trigger_count(), self.errors))
        else:
            self._error(seq, 4, f"unknown command {command!r}")

    def _serve(self) -> None:
        reader = FrameReader()
        os.set_blocking(self.master, False)
        while not self._stop.is_set():
            try:
                data = os.read(self.master, 512)
            except BlockingIOError:
                time.sleep(0.002)
                continue
            except OSError:
                return
            for body in reader.feed(data):
                if len(body) >= 2:
                    self._handle(body)
