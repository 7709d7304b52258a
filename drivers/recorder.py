"""The recorder: both heads and the flow sensor into one session file, never dropping a frame.

Capture threads (one per camera, one for the flow sensor) put what arrives on a bounded queue;
one writer thread owns the session file (h5py serialises every call). A capture thread never
waits on the disk: when the queue is nearly full the recorder reports back-pressure, and if it
fills it stops cleanly, keeping everything written so far, and says the disk does not keep up.
The file is written in HDF5 single-writer/multiple-reader mode and flushed about once a second, so
a crash (or SIGKILL) loses at most the last second; core.io.session.recover_session trims a file cut
off mid-frame to what all its datasets reached.
"""

from __future__ import annotations

import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from core.rig import Rig
from core.io.session import SessionWriter, SubjectRecord
from drivers.camera import Camera, CameraError, capture_frames
from drivers.light_phase import LightPhase, LightPhaseError, RecordedLights


BATCH_ITEMS = 500  # queue items written in one batch at most
BATCH_INTERVAL_S = 0.05  # the writer's pause when it has caught up


class RecordingError(Exception):
    """The recording stopped before its end; the message says why. The file keeps what was written."""


@dataclass
class RecordSummary:
    path: Path
    frames: dict[str, int]
    camera_failed: dict[str, int]
    camera_lost: dict[str, int]
    flow_samples: int
    flow_lost: int
    dropped_by_software: int
    max_queue_fill: float
    elapsed_s: float
    written_mb: float
    problems: list[str] = field(default_factory=list)  # what stopped the recording
    notices: list[str] = field(default_factory=list)  # what happened without stopping it (a camera gone and back)


class Recorder:
    def __init__(self, path: str | Path, rig: Rig, cameras: dict[str, Camera],
                 lights: LightPhase | RecordedLights, flow=None, flow_calibration: tuple[float, float] | None = None,
                 subject: SubjectRecord | None = None, kind: str = "patient", queue_items: int = 2000,
                 flow_sensor_name: str = "pneumotachometer (12-bit ADC)", compression: str = "none") -> None:
        """`compression`: the frames' lossless filter (core/io/session.py FRAME_COMPRESSION)."""
        self.path = Path(path)
        self.rig = rig
        self.cameras = cameras
        self.lights = lights
        self._pending: dict[str, list] = {h: [] for h in cameras}  # frames held until the head's light phase is checked
        self.flow = flow
        self._queue: queue.Queue = queue.Queue(maxsize=queue_items)
        self._stop = threading.Event()
        self._errors: list[str] = []
        self._notices: list[str] = []
        self._lock = threading.Lock()
        self._max_fill = 0.0
        self._dropped = 0
        self._counts = {h: 0 for h in cameras}
        self._flow_samples = 0
        self._written_bytes = 0
        self.writer = SessionWriter(self.path, kind=kind, rig=rig, subject=subject, compression=compression)
        if flow is not None:
            gain, offset = flow_calibration if flow_calibration else (None, None)
            self.writer.configure_flow(sample_rate_hz=flow.sample_rate_hz, adc_bits=12, sensor=flow_sensor_name,
                                       conditions="ATPS", gain_lps=gain, offset_lps=offset)

    def _put(self, item) -> None:
        """Never blocks the capture thread; a full queue stops the recording (the disk cannot keep up)."""
        fill = self._queue.qsize() / self._queue.maxsize
        self._max_fill = max(self._max_fill, fill)
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            with self._lock:
                self._dropped += 1
                if not self._errors:
                    self._errors.append("the disk does not keep up with the cameras: the recording stopped, "
                                        "everything before is in the file")
            self._stop.set()

    def submit_frame(self, head: str, frame) -> None:
        """From a capture thread: never blocks."""
        self._put(("frame", head, frame))

    def submit_flow(self, block) -> None:
        self._put(("flow", block))

    def submit_event(self, timestamp_ns: int, label: str) -> None:
        """A protocol event, written by the writer thread in its turn."""
        self._put(("event", int(timestamp_ns), label))

    @property
    def stopped(self) -> bool:
        """True once the recording has stopped itself (a full disk, a device gone): see problems."""
        return self._stop.is_set()

    @property
    def problems(self) -> list[str]:
        with self._lock:
            return list(self._errors)

    @property
    def notices(self) -> list[str]:
        with self._lock:
            return list(self._notices)

    def _notice(self, message: str) -> None:
        with self._lock:
            self._notices.append(message)

    @property
    def dropped(self) -> int:
        """Items the queue had no room for (the recording stops at the first)."""
        return self._dropped

    def frames_written(self) -> dict[str, int]:
        return dict(self._counts)

    def _capture(self, head: str, camera: Camera) -> None:
        """A camera that disconnects is waited for while the other devices record on."""
        try:
            capture_frames(camera, self._stop, lambda frame: self.submit_frame(head, frame), self._notice)
        except CameraError as exc:
            with self._lock:
                self._errors.append(str(exc))
            self._stop.set()

    def _capture_flow(self) -> None:
        try:
            while not self._stop.is_set():
                block = self.flow.read()
                if len(block.adc):
                    self.submit_flow(block)
                time.sleep(0.01)
        except Exception as exc:  # a flow sensor that fails stops the recording with its message
            with self._lock:
                self._errors.append(str(exc))
            self._stop.set()

    def _write(self) -> None:
        """Write what the queue holds in batches, about 20 a second: one resize per dataset and
        batch instead of eight h5py calls a frame (h5py holds the GIL throughout each call, so fewer
        calls leave the GUI thread and the capture threads more of it)."""
        last_flush = time.monotonic()
        final = False
        while not final:
            final = self._stop.is_set()  # one more pass after the stop: what is queued and held
            items = []
            try:
                while len(items) < BATCH_ITEMS:
                    items.append(self._queue.get_nowait())
            except queue.Empty:
                pass
            final = final and self._queue.empty()
            try:
                self._write_batch(items, final)
                if time.monotonic() - last_flush > 1.0:
                    self.writer.flush()
                    last_flush = time.monotonic()
            except (OSError, RuntimeError) as exc:  # a full disk or a permission error (h5py raises either)
                with self._lock:
                    self._errors.append(f"cannot write {self.path} ({write_failure_reason(exc)}): the recording "
                                        f"stopped; what was written before is kept: free space, then run "
                                        f"`photopft recover {self.path}`")
                self._stop.set()
                return
            if len(items) < BATCH_ITEMS and not final:
                self._stop.wait(BATCH_INTERVAL_S)

    def _write_batch(self, items: list, final: bool = False) -> None:
        """Frames per head in arrival order, flow blocks joined, events one by one. A head's frames
        are held until the images have checked its light phase (two cycles, drivers/light_phase.py),
        so that none is written with a light the check would correct."""
        flow = []
        for item in items:
            if item[0] == "frame":
                head, frame = item[1], item[2]
                try:
                    self.lights.observe(head, frame.frame_id, frame.image)
                except LightPhaseError as exc:
                    with self._lock:
                        self._errors.append(f"{exc}; the recording stopped")
                    self._stop.set()
                self._pending.setdefault(head, []).append(frame)
            elif item[0] == "flow":
                flow.append(item[1])
            else:
                self.writer.add_event(item[1], item[2])
        for head, batch in self._pending.items():
            if not batch or not (final or self.lights.ready(head)):
                continue
            self._pending[head] = []
            self.writer.append_frames(head, np.stack([f.image for f in batch]),
                                      [self.lights.light_of(head, f.frame_id) for f in batch],
                                      [f.timestamp_ns for f in batch], [f.frame_id for f in batch])
            self._counts[head] += len(batch)
            self._written_bytes += sum(f.image.nbytes for f in batch)
        if flow:
            self.writer.append_flow(np.concatenate([b.adc for b in flow]), np.concatenate([b.timestamp_ns for b in flow]))
            self._flow_samples += sum(len(b.adc) for b in flow)

    def begin(self, events: list[tuple[int, str]] | None = None) -> None:
        """Start the writer; from here frames, flow and events may be submitted from any thread."""
        self._started = time.monotonic()
        for t, label in events or []:
            self.writer.add_event(t, label)
        self.writer.start_swmr()  # from here a crash keeps everything up to the last flush (about 1 s)
        self._writer_thread = threading.Thread(target=self._write, name="writer", daemon=True)
        self._writer_thread.start()

    def end(self, stats: dict | None = None, flow_lost: int = 0) -> RecordSummary:
        """Write what is queued, close the file and sum up. `stats`: each camera's CameraStats."""
        self._stop.set()
        self._writer_thread.join(timeout=30)
        try:
            self.writer.close()
        except (OSError, RuntimeError) as exc:
            with self._lock:
                if not any("cannot write" in e for e in self._errors):
                    self._errors.append(f"cannot close {self.path} ({write_failure_reason(exc)}); what was "
                                        f"written before is kept: run `photopft recover {self.path}`")
        for notice in self.lights.summary():
            self._notice(notice)
        stats = stats or {}
        elapsed = time.monotonic() - self._started
        return RecordSummary(self.path, dict(self._counts), {h: s.failed for h, s in stats.items()},
                             {h: s.lost for h, s in stats.items()}, self._flow_samples, flow_lost,
                             self._dropped, self._max_fill, elapsed, self._written_bytes / 1e6, self.problems,
                             self.notices)

    def run(self, seconds: float, progress: Callable[[float, dict], None] | None = None,
            events: list[tuple[int, str]] | None = None) -> RecordSummary:
        """Record from the recorder's own cameras and flow sensor for `seconds`."""
        for head, camera in self.cameras.items():
            camera.start()
        self.lights.begin()
        if self.flow is not None:
            self.flow.start()
        self.begin(events)
        threads = [threading.Thread(target=self._capture, args=(h, c), name=f"capture-{h}", daemon=True)
                   for h, c in self.cameras.items()]
        if self.flow is not None:
            threads.append(threading.Thread(target=self._capture_flow, name="capture-flow", daemon=True))
        for t in threads:
            t.start()
        try:
            while time.monotonic() - self._started < seconds and not self._stop.is_set():
                time.sleep(0.1)
                if progress is not None:
                    progress(time.monotonic() - self._started, dict(self._counts))
        finally:
            self._stop.set()
            for t in threads:
                t.join(timeout=5)
            for camera in self.cameras.values():
                camera.stop()
            if self.flow is not None:
                self.flow.stop()
        return self.end({h: c.stats for h, c in self.cameras.items()},
                        int(getattr(self.flow, "lost_samples", 0)) if self.flow is not None else 0)


def write_failure_reason(exc: Exception) -> str:
    """The operating system's words for a failed write (h5py wraps them in a long message)."""
    text = str(exc)
    for known in ("No space left on device", "File too large", "Permission denied", "Read-only file system",
                  "Disk quota exceeded", "Not a directory", "No such file or directory"):
        if known in text:
            return "the disk is full" if known in ("No space left on device", "Disk quota exceeded") else known.lower()
    return text.splitlines()[0][:200]

