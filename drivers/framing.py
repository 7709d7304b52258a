"""Binary framing for photopft's serial devices (docs/protocols.md).

Frame: SYNC (0xA5 0x5A) | length (1 byte: of the body) | body | CRC-16/CCITT-FALSE of the body
(big-endian). The reader resynchronises after corrupted or dropped bytes: it searches for SYNC,
checks the length and the CRC, and on failure moves one byte on. It never trusts a frame whose
CRC does not match.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

SYNC = b"\xa5\x5a"
MAX_BODY = 250


def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection)."""
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def encode(body: bytes) -> bytes:
    if len(body) > MAX_BODY:
        raise ValueError(f"frame body of {len(body)} bytes exceeds {MAX_BODY}")
    return SYNC + bytes([len(body)]) + body + struct.pack(">H", crc16_ccitt(body))


@dataclass
class FrameReader:
    """Incremental decoder: feed bytes, take whole frames; counts what it had to skip."""

    buffer: bytearray = field(default_factory=bytearray)
    skipped_bytes: int = 0
    bad_frames: int = 0

    def feed(self, data: bytes) -> list[bytes]:
        self.buffer.extend(data)
        frames = []
        while True:
            start = self.buffer.find(SYNC)
            if start < 0:
                keep = 1 if self.buffer[-1:] == SYNC[:1] else 0
                self.skipped_bytes += len(self.buffer) - keep
                del self.buffer[: len(self.buffer) - keep]
                return frames
            if start:
                self.skipped_bytes += start
                del self.buffer[:start]
            if len(self.buffer) < 3:
                return frames
            length = self.buffer[2]
            total = 3 + length + 2
            if length > MAX_BODY:
                self._skip_one()
                continue
            if len(self.buffer) < total:
                return frames
            body = bytes(self.buffer[3:3 + length])
            (crc,) = struct.unpack(">H", self.buffer[3 + length:total])
            if crc != crc16_ccitt(body):
                self.bad_frames += 1
                self._skip_one()
                continue
            del self.buffer[:total]
            frames.append(body)

    def _skip_one(self) -> None:
        self.skipped_bytes += 1
        del self.buffer[:1]
