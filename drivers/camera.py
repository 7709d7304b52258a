"""Cameras: a small protocol, GigE Vision cameras through Aravis 0.8, and the simulated twin.

Aravis lessons (shared/design/STYLE.md): buffers are popped from our own thread (no Python
stream callback), every popped buffer is pushed back, incomplete or failed buffers are counted
and never passed on as images; frame ids and timestamps are kept, so a lost frame is a gap.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

GIGABIT_MB_S = 115.0  # what one gigabit link carries in practice
OPEN_ATTEMPTS = 3  # opening a camera: tries before giving up
OPEN_RETRY_S = 0.5


class CameraError(Exception):
    """A camera that cannot be found, configured, or that stopped answering; the message names it."""


class CameraDisconnected(CameraError):
    """The camera stopped answering. Its stream is stopped cleanly; later grabs look for it again and
    deliver frames once it is back, the gap visible in frame_id."""


@dataclass(frozen=True)
class Frame:
    image: np.ndarray  # (H, W) uint8 or uint16
    frame_id: int
    timestamp_ns: int


@dataclass(frozen=True)
class CameraSettings:
    width: int | None = None  # None: the whole sensor (after binning)
    height: int | None = None
    offset_x: int = 0
    offset_y: int = 0
    binning: int = 1
    pixel_format: str = "Mono8"  # Mono8 or Mono12 (delivered as uint16)
    exposure_us: float = 1000.0
    gain_db: float = 0.0
    frame_rate_hz: float = 110.0
    trigger: str = "free"  # free (internal rate), software, or line (hardware trigger from the sequencer)


@dataclass
class CameraStats:
    delivered: int = 0
    failed: int = 0  # incomplete, timed-out or otherwise bad buffers: counted, never delivered
    lost: int = 0  # gaps in the frame ids of delivered frames
    resent_packets: int = 0  # GigE Vision: packets lost on the wire and recovered by resend requests
    missing_packets: int = 0  # GigE Vision: packets lost for good (their frames fail)
    reconnects: int = 0  # times the camera came back after a disconnect
    last_frame_id: int | None = None
    last_timestamp_ns: int | None = None

    def count(self, frame: Frame) -> None:
        if self.last_frame_id is not None and frame.frame_id > self.last_frame_id + 1:
            self.lost += frame.frame_id - self.last_frame_id - 1
        self.last_frame_id = frame.frame_id
        self.last_timestamp_ns = frame.timestamp_ns
        self.delivered += 1


class Camera(Protocol):
    name: str
    stats: CameraStats

    def configure(self, settings: CameraSettings) -> None: ...
    def start(self) -> None: ...
    def grab(self, timeout_s: float = 0.5) -> Frame | None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...


def frame_due_within(wait_s: float, timeout_s: float) -> bool:
    """A paced camera's grab: sleeps until a frame due in `wait_s` is, and True; or, when it is due
    after `timeout_s`, sleeps the timeout out and False (the grab returns no frame, as a camera would)."""
    if wait_s > timeout_s:
        time.sleep(timeout_s)
        return False
    if wait_s > 0:
        time.sleep(wait_s)
    return True


def capture_frames(camera: Camera, stop: threading.Event, deliver: Callable[[Frame], None],
                   say: Callable[[str], None], timeout_s: float = 0.2) -> None:
    """Grab from `camera` until `stop` is set, handing each frame to `deliver`.

    A camera that disconnects is said (`say`) and waited for; when it is back, how long it was
    gone and which frame ids are missing is said too. Any other CameraError propagates.
    """
    gone = False
    while not stop.is_set():
        try:
            frame = camera.grab(timeout_s)
        except CameraDisconnected as exc:
            gone, last_id, last_ns = True, camera.stats.last_frame_id, camera.stats.last_timestamp_ns
            say(f"{exc}; waiting for it to come back")
            continue
        if frame is None:
            continue
        if gone:
            gap = "" if last_id is None else \
                (f" after {(frame.timestamp_ns - last_ns) / 1e9:.1f} s without frames; frame ids {last_id + 1} "
                 f"to {frame.frame_id - 1} ({frame.frame_id - last_id - 1} frames) are missing")
            say(f"camera {camera.name} is back{gap}")
            gone = False
        deliver(frame)


def bandwidth_mb_s(width: int, height: int, bits: int, frame_rate_hz: float) -> float:
    """Payload bandwidth in MB/s (1e6 bytes): Mono8 takes one byte a pixel, Mono12 and Mono16 two."""
    return width * height * (1 if bits <= 8 else 2) * frame_rate_hz / 1e6


def bandwidth_advice(width: int, height: int, bits: int, frame_rate_hz: float,
                     link_mb_s: float = GIGABIT_MB_S) -> str | None:
    """None when the settings fit the link; otherwise what does not fit and which settings would."""
    need = bandwidth_mb_s(width, height, bits, frame_rate_hz)
    if need <= link_mb_s:
        return None
    options = []
    for binning in (2, 4):
        if bandwidth_mb_s(width // binning, height // binning, bits, frame_rate_hz) <= link_mb_s:
            options.append(f"binning {binning} x {binning} ({width // binning} x {height // binning}, "
                           f"{bandwidth_mb_s(width // binning, height // binning, bits, frame_rate_hz):.0f} MB/s)")
            break
    rows = int(link_mb_s * 1e6 / (width * (1 if bits <= 8 else 2) * frame_rate_hz))
    if rows >= 64:
        options.append(f"a region of {width} x {rows // 8 * 8} pixels")
    rate = link_mb_s * 1e6 / (width * height * (1 if bits <= 8 else 2))
    options.append(f"{rate:.0f} frames/s at full size")
    if bits > 8:
        options.append(f"Mono8 ({bandwidth_mb_s(width, height, 8, frame_rate_hz):.0f} MB/s)")
    return (f"{width} x {height} {'Mono8' if bits <= 8 else f'Mono{bits}'} at {frame_rate_hz:g} frames/s needs "
            f"{need:.0f} MB/s, more than a gigabit link's {link_mb_s:.0f} MB/s; these would fit: "
            + "; ".join(options))


def _aravis():
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise CameraError("Aravis 0.8 is not available (Debian: gir1.2-aravis-0.8, and PyGObject < 3.51): "
                          f"{exc}") from exc
    return Aravis


def find_aravis_device(identifier: str, interfaces: tuple[str, ...] = ()) -> str:
    """The Aravis device id of a camera named by device id, serial number or IP address."""
    aravis = _aravis()
    for interface in interfaces:
        aravis.enable_interface(interface)
    aravis.update_device_list()
    devices = [(aravis.get_device_id(i), aravis.get_device_serial_nbr(i), aravis.get_device_address(i))
               for i in range(aravis.get_n_devices())]
    for device_id, serial, address in devices:
        if identifier in (device_id, serial, address):
            return device_id
    found = ", ".join(f"{d} (serial {s}, {a})" for d, s, a in devices) or "none"
    raise CameraError(f"no camera {identifier!r} found; cameras seen: {found}")


@dataclass
class AravisCamera:
    """A GigE Vision (or Aravis Fake) camera; frames popped from the caller's thread.

    When the camera stops answering, grab() raises CameraDisconnected once, after stopping the
    stream; later grabs look for the camera again (at most once every `reconnect_interval_s`) and,
    once it answers, reopen it with the same settings and go on. The camera counts its frames from
    scratch when it comes back, so ids after the gap continue from the last id before it plus the
    frame periods elapsed: the gap shows in frame_id, and since every id is one trigger of the
    sequencer, the light of each frame stays right.
    """

    identifier: str
    buffers: int = 16
    interfaces: tuple[str, ...] = ()
    packet_resend: bool = True  # GigE Vision: ask the camera again for lost packets
    reconnect_interval_s: float = 1.0
    name: str = ""
    stats: CameraStats = field(default_factory=CameraStats)

    def __post_init__(self) -> None:
        self._aravis = _aravis()
        self._last_raw_id: int | None = None
        self._wraps = 0
        self._id_offset = 0
        self._settings: CameraSettings | None = None
        self._gone = False  # disconnected and said so; grab() looks for the camera again
        self._next_look = 0.0
        self._resume = False  # back after a gap: the next frame re-bases the frame ids
        self.device_id = find_aravis_device(self.identifier, self.interfaces)
        self.name = self.name or self.device_id
        for attempt in range(OPEN_ATTEMPTS):
            try:
                self._open()
                break
            except CameraError:
                # a GigE Vision camera's first control reads can time out on a busy link or host
                if attempt == OPEN_ATTEMPTS - 1:
                    raise
                time.sleep(OPEN_RETRY_S)

    def _open(self) -> None:
        self._lost_control = threading.Event()
        try:
            self._camera = self._aravis.Camera.new(self.device_id)
        except Exception as exc:  # GLib.Error and friends
            raise CameraError(f"cannot open camera {self.device_id}: {exc}") from exc
        device = self._camera.get_device()
        if hasattr(device, "connect"):
            try:
                device.connect("control-lost", lambda *_: self._lost_control.set())
            except TypeError:
                pass
        self._stream = None
        self.bits = 8

    @property
    def sensor_size(self) -> tuple[int, int]:
        return tuple(self._camera.get_sensor_size())

    def configure(self, settings: CameraSettings) -> None:
        camera = self._camera
        try:
            formats = camera.dup_available_pixel_formats_as_strings()
            wanted = settings.pixel_format
            if wanted == "Mono12" and "Mono12" not in formats:
                if "Mono16" not in formats:
                    raise CameraError(f"{self.name} offers neither Mono12 nor Mono16 ({', '.join(formats)})")
                wanted = "Mono16"  # the same 16-bit container
            if wanted not in formats:
                raise CameraError(f"{self.name} does not offer {wanted} ({', '.join(formats)})")
            camera.set_pixel_format_from_string(wanted)
            self.bits = 8 if wanted == "Mono8" else (12 if settings.pixel_format == "Mono12" else 16)
            if settings.binning > 1:
                if not camera.is_binning_available():
                    raise CameraError(f"{self.name} has no binning")
                camera.set_binning(settings.binning, settings.binning)
            full_w, full_h = self.sensor_size
            width = settings.width or full_w // settings.binning
            height = settings.height or full_h // settings.binning
            camera.set_region(settings.offset_x, settings.offset_y, width, height)
            camera.set_exposure_time(settings.exposure_us)
            if camera.is_gain_available():
                camera.set_gain(settings.gain_db)
            if settings.trigger == "line":
                camera.set_trigger("Line1")
            elif settings.trigger == "software":
                camera.set_trigger("Software")
            else:
                camera.set_frame_rate(settings.frame_rate_hz)
        except CameraError:
            raise
        except Exception as exc:
            raise CameraError(f"cannot configure {self.name}: {exc}") from exc
        self._settings = settings

    def region(self) -> tuple[int, int, int, int]:
        return tuple(self._camera.get_region())

    def start(self) -> None:
        try:
            self._stream = self._camera.create_stream(None, None)
            if isinstance(self._stream, self._aravis.GvStream):
                resend = self._aravis.GvStreamPacketResend
                self._stream.set_property("packet-resend", resend.ALWAYS if self.packet_resend else resend.NEVER)
            size = self._camera.get_payload()
            for _ in range(self.buffers):
                self._stream.push_buffer(self._aravis.Buffer.new_allocate(size))
            self._camera.start_acquisition()
        except Exception as exc:
            raise CameraError(f"cannot start {self.name}: {exc}") from exc

    def software_trigger(self) -> None:
        self._camera.software_trigger()

    def grab(self, timeout_s: float = 0.5) -> Frame | None:
        """The next complete frame, or None on timeout; bad buffers are counted and skipped."""
        if self._gone:
            self._look_for_camera(timeout_s)
            return None
        if self._stream is None:
            raise CameraError(f"{self.name} is not started")
        if self._lost_control.is_set():
            self.stop()
            self._camera = None
            self._gone = True
            raise CameraDisconnected(f"camera {self.name} disconnected (lost control): stopped cleanly; "
                                     "check its cable and power")
        buffer = self._stream.timeout_pop_buffer(int(timeout_s * 1e6))
        if buffer is None:
            return None
        try:
            if buffer.get_status() != self._aravis.BufferStatus.SUCCESS:
                self.stats.failed += 1
                return None
            dtype = np.uint8 if self.bits == 8 else np.uint16
            image = np.frombuffer(buffer.get_data(), dtype=dtype).reshape(
                buffer.get_image_height(), buffer.get_image_width()).copy()
            # Aravis stamps a buffer with the wall clock (g_get_real_time); the session clock, which
            # the flow sensor and the protocol events use too, is the monotonic clock.
            stamp = int(buffer.get_system_timestamp()) + (time.monotonic_ns() - time.time_ns())
            frame = Frame(image, self._frame_id(int(buffer.get_frame_id()), stamp), stamp)
            self.stats.count(frame)
            return frame
        finally:
            self._stream.push_buffer(buffer)

    def _look_for_camera(self, timeout_s: float) -> None:
        """One attempt to find, reopen, configure and start the camera that went away."""
        wait = self._next_look - time.monotonic()
        if wait > 0:
            time.sleep(min(wait, timeout_s))
            return
        self._next_look = time.monotonic() + self.reconnect_interval_s
        try:
            find_aravis_device(self.device_id, self.interfaces)
            self._open()
            if self._settings is not None:
                self.configure(self._settings)
            self.start()
        except CameraError:
            self._camera = self._stream = None
            return
        self._gone, self._resume = False, True
        self._last_raw_id, self._wraps = None, 0
        self.stats.reconnects += 1

    def _frame_id(self, raw: int, stamp_ns: int) -> int:
        """The unwrapped block id, re-based after a reconnect on the frame periods the gap lasted."""
        unwrapped = self._unwrap(raw)
        if self._resume:
            self._resume = False
            last_id, last_ns = self.stats.last_frame_id, self.stats.last_timestamp_ns
            if last_id is not None and last_ns is not None:
                rate = self._settings.frame_rate_hz if self._settings is not None else 110.0
                periods = max(1, round((stamp_ns - last_ns) * rate / 1e9))
                self._id_offset = last_id + periods - unwrapped
        return unwrapped + self._id_offset

    def _unwrap(self, raw: int) -> int:
        """GigE Vision 1.x block ids are 16-bit and wrap from 65535 to 1 (0 is reserved): count the wraps."""
        if self._last_raw_id is not None and raw < self._last_raw_id - 32768:
            self._wraps += 1
        self._last_raw_id = raw
        return raw + self._wraps * 65535

    def _packet_statistics(self) -> None:
        if self._stream is not None and isinstance(self._stream, self._aravis.GvStream):
            resent, missing = self._stream.get_statistics()
            self.stats.resent_packets, self.stats.missing_packets = int(resent), int(missing)

    def stop(self) -> None:
        if self._stream is not None:
            self._packet_statistics()
            try:
                self._camera.stop_acquisition()
            except Exception:  # a camera that is gone cannot be stopped; the stream is dropped anyway
                pass
            self._stream = None

    def close(self) -> None:
        self.stop()
        self._camera = None
        self._gone = False

    @property
    def disconnected(self) -> bool:
        return self._gone or self._lost_control.is_set()
