"""The live session engine behind the GUI (no Qt here): capture, recording, reconstruction.

One capture thread per camera and one for the flow sensor hand every frame and block to the
recorder, when one is recording (it never drops), and to the display buffers, which keep only the
newest light cycle (the display may skip). One reconstruction thread per head takes the newest
complete cycle, runs the same HeadReconstructor as `photopft process`, and publishes the map and
a volume sample. The GUI pulls `snapshot()` on its own timer; nothing here waits for it.
"""

from __future__ import annotations

import collections
import logging
import os
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from app.engine.cycle_buffer import CycleBuffer
from app.engine.feeds import WINDOW_S, EngineInfo, HeadView, Rate, Snapshot
from app.engine.flow_display import FlowDisplay
from app.engine.head_stream import HeadStream
from app.engine.recording import NO_LIMIT_NS, SubjectRecording
from app.engine.sources import Source
from core.analysis.optical_litres import ESTIMATE_UNCERTAINTY, POPULATION_GAIN, estimate_label
from core.io.session import SubjectRecord
from core.pipeline.head_maps import use_threads
from core.pipeline.live_checks import LiveOpticalChecks
from core.reconstruction.binning import binned_head, working_binning
from core.reconstruction.pipeline import HeadMap, HeadReconstructor, ReconstructionSettings
from core.volume.flow_sensor import btps_factor
from core.volume.metric import LiveMetricVolume
from core.volume.sides import side_profile_mm
from core.volume.subject_calibration import SubjectCalibration, regional_signals
from drivers.camera import CameraError, Frame, capture_frames
from drivers.light_phase import LightPhaseError
from drivers.recorder import Recorder, RecordSummary

log = logging.getLogger(__name__)

CALIBRATION_WINDOW_S = 180.0  # the longest calibration through the flow sensor the live view can fit
WORKER_NICENESS = 10
SIMULATED_CAMERA_NICENESS = 14



class LiveRig:
    def __init__(self, source: Source, settings: ReconstructionSettings | None = None) -> None:
        self.source = source
        self.rig = source.rig
        self.settings = settings or ReconstructionSettings(track=True)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._recording: SubjectRecording | None = None
        self._buffers = {h: CycleBuffer(self.rig) for h in source.cameras}
        self._views = {h: HeadView() for h in source.cameras}
        self._rates = {h: Rate() for h in source.cameras}
        n = int(WINDOW_S * self.rig.frame_rate_hz / self.rig.cycle_length * 2) + 10
        self._optical = collections.deque(maxlen=n)
        self._gradient = {h: 0.0 for h in source.cameras}
        # each head reconstructed binned to about WORKING_WIDTH_PX wide (core/reconstruction/binning.py);
        # recordings keep every pixel
        self._binning = {h: working_binning(self.rig.heads[h]) for h in source.cameras}
        self._live_heads = {h: binned_head(self.rig.heads[h], self._binning[h]) for h in source.cameras}
        self._metric = LiveMetricVolume(self._live_heads, self.rig.baseline_mm)
        self._checks = LiveOpticalChecks(list(source.cameras))
        self._metric_curve = collections.deque(maxlen=n)
        # each map's regional signals (core/volume/subject_calibration.py) over the last CALIBRATION_WINDOW_S,
        # for the subject's calibration through the flow sensor; the calibration once it is made
        self._regional_curve: collections.deque = collections.deque(
            maxlen=int(CALIBRATION_WINDOW_S * self.rig.frame_rate_hz / self.rig.cycle_length) + 10)
        self._recent_flow: collections.deque = collections.deque(maxlen=9000)  # (arrival ns, block), ~90 s
        self._problems: list[str] = []
        self._t0: int | None = None
        self._latest_ns = 0
        self._threads: list[threading.Thread] = []
        self._started = time.monotonic()
        self._btps = btps_factor(*source.room) if source.conditions == "ATPS" else 1.0
        self._flow_display = FlowDisplay(self._btps)

    # life cycle
    def start(self) -> None:
        for camera in self.source.cameras.values():
            camera.start()
        try:
            self.source.lights.begin()  # the sequencer starts once the cameras wait for its triggers
        except LightPhaseError as exc:
            self._problem(str(exc))
        if self.source.flow is not None:
            self.source.flow.start()
        # Simulated cameras render their frames on this computer's cores, which a real camera's
        # capture does not: at a lower priority than the reconstruction, or they starve it.
        capture_niceness = SIMULATED_CAMERA_NICENESS if self.source.simulated is not None else WORKER_NICENESS
        for head, camera in self.source.cameras.items():
            self._spawn(self._capture, f"capture-{head}", head, camera, niceness=capture_niceness)
            self._spawn(self._reconstruct, f"reconstruct-{head}", head)
        if self.source.flow is not None:
            self._spawn(self._capture_flow, "capture-flow")

    def _spawn(self, target, name: str, *args, niceness: int = WORKER_NICENESS) -> None:
        def run() -> None:
            # Workers yield the CPU to the GUI thread: it only draws, but must never wait long.
            try:
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
            except (OSError, AttributeError):
                pass
            target(*args)

        thread = threading.Thread(target=run, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    def stop(self) -> RecordSummary | None:
        summary = self.stop_recording() if self._recording is not None else None
        self._stop.set()
        for buffer in self._buffers.values():
            buffer.wake()
        for thread in self._threads:
            thread.join(timeout=5)
        for camera in self.source.cameras.values():
            camera.stop()
            camera.close()
        if self.source.flow is not None:
            self.source.flow.stop()
            self.source.flow.close()
        for close in self.source.closers:
            close()
        return summary

    @property
    def info(self) -> EngineInfo:
        s = self.source
        return EngineInfo(self.rig, tuple(s.cameras), s.name, s.replay, s.simulated is not None, s.calibration,
                          s.flow_calibration, s.flow_from)

    def flow_adc_mean(self, seconds: float = 2.0) -> float:
        """The flow sensor's mean raw reading (ADC counts) over the next `seconds`: a steady flow
        read for the spirometer calibration (thesis eq. 5.4)."""
        started = time.monotonic_ns()
        self._stop.wait(seconds + 0.1)
        counts, _ = self.flow_since(started)
        if len(counts) < 0.5 * seconds * 1000:
            raise TimeoutError(f"the flow sensor gave {len(counts)} samples in {seconds:g} s: is it connected?")
        return float(counts.mean())

    def flow_since(self, monotonic_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The flow sensor's raw samples (ADC counts, session-clock stamps) that arrived since
        `monotonic_ns` (the last 90 s at most): a 3 L syringe check's strokes."""
        if self.source.flow is None:
            raise RuntimeError("this rig has no flow sensor")
        blocks = [b for arrived, b in list(self._recent_flow) if arrived >= monotonic_ns]
        if not blocks:
            return np.zeros(0, np.int32), np.zeros(0, np.int64)
        return np.concatenate([b.adc for b in blocks]), np.concatenate([b.timestamp_ns for b in blocks])

    def perform(self, manoeuvre: str) -> float:
        """The simulated subject does the manoeuvre ("vc" or "forced"); the seconds it takes (0 on a real rig)."""
        return self.source.simulated.perform(manoeuvre) if self.source.simulated is not None else 0.0

    # recording
    def start_recording(self, path: str | Path, subject: SubjectRecord | None, kind: str = "patient",
                        root_attrs: dict | None = None, heads: list[str] | None = None) -> None:
        """Record every head (or only `heads`: a front-only session) and the flow sensor."""
        if self.source.replay:
            raise ValueError("a replayed session cannot be recorded again")
        heads = heads or list(self.source.cameras)
        rig = self.rig if len(heads) == len(self.rig.heads) else replace(
            self.rig, heads={h: self.rig.heads[h] for h in heads}, baseline_mm=None)
        recorder = Recorder(path, rig, {h: self.source.cameras[h] for h in heads}, self.source.lights,
                            self.source.flow, self.source.flow_calibration, subject, kind=kind,
                            compression=self.source.compression)
        for key, value in (root_attrs or {}).items():
            recorder.writer.set_root_attr(key, value)
        if self.source.simulated is not None and subject is not None:  # the simulated subject is the patient
            self.source.simulated.follow(subject.sex, subject.age_years, subject.height_cm, subject.weight_kg,
                                         subject.id)
        recorder.begin()
        recording = SubjectRecording(recorder, self.source.flow_calibration, self._btps, self.source.flow is not None)
        with self._lock:
            self._recording = recording  # a new recording is a new subject's: not calibrated

    def mark(self, label: str, stamp_ns: int | None = None) -> int:
        """A protocol event now (or at `stamp_ns`), on the session clock: the system's monotonic clock,
        which stamps frames and flow samples in every process (not the newest frame's time, which
        lags when capture falls behind)."""
        stamp = time.monotonic_ns() if stamp_ns is None else stamp_ns
        recording = self._recording
        if recording is not None:
            recording.mark(stamp, label)
        return stamp

    def calibrate_on_subject(self, start_ns: int) -> SubjectCalibration:
        """The subject's calibration on the recording's flow sensor volume and the live regional signals
        from `start_ns` (a mark) to now (SubjectRecording.calibrate); the live volume takes it when it
        is not refused. Returns the SubjectCalibration, refused or not."""
        with self._lock:
            curve = list(self._regional_curve)
            t0 = self._t0
            recording = self._recording
        if recording is None:
            return SubjectCalibration.refused_for("calibration-no-signal", "nothing is being recorded to calibrate on")
        return recording.calibrate(start_ns, curve, t0)

    def flow_reaches(self, timestamp_ns: int) -> bool:
        """Whether the volume the recording's values come from reaches `timestamp_ns`
        (SubjectRecording.flow_until_ns)."""
        return self._flow_until_ns() >= timestamp_ns

    def _flow_until_ns(self) -> int:
        recording = self._recording
        return recording.flow_until_ns() if recording is not None else NO_LIMIT_NS

    def recorded_values(self, age_years: float | None = None):
        """The pulmonary function values of the recording so far (SubjectRecording.values): for
        feedback after each manoeuvre. None without a volume to read them from."""
        recording = self._recording
        return recording.values(age_years) if recording is not None else None

    def blow_trace(self, mark_ns: int, before_s: float = 2.5) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The volume curves (s from the mark, L positive inhaled, BTPS) since `before_s` before a
        manoeuvre's mark, for the forced-blow screen: the flow sensor's from the recording
        (SubjectRecording.flow_trace) and the optical metric volume."""
        out: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        recording = self._recording
        if recording is not None and (flow := recording.flow_trace(mark_ns, before_s)) is not None:
            out["flow sensor"] = flow
        with self._lock:
            metric = np.array(self._metric_curve, dtype=float).reshape(-1, 2)
        if self._t0 is not None and len(metric):
            t = metric[:, 0] - (mark_ns - self._t0) / 1e9
            keep = t >= -before_s
            out["optical"] = (t[keep], metric[keep, 1])
        return out

    def stop_recording(self) -> RecordSummary:
        with self._lock:  # the calibration was the subject's: whoever stands in the rig next is not calibrated
            recording, self._recording = self._recording, None
        if recording is None:
            raise ValueError("not recording")
        recorder = recording.recorder
        return recorder.end({h: c.stats for h, c in recorder.cameras.items()},
                            int(getattr(self.source.flow, "lost_samples", 0)) if self.source.flow else 0)

    @property
    def recording(self) -> bool:
        return self._recording is not None

    @property
    def checks(self) -> LiveOpticalChecks:
        """The checks `process` makes on the optical volume, as the live maps come in."""
        return self._checks

    # threads
    def _capture(self, head: str, camera) -> None:
        try:
            capture_frames(camera, self._stop, lambda frame: self._take_frame(head, frame), self._problem)
        except CameraError as exc:
            self._problem(str(exc))

    def _take_frame(self, head: str, frame: Frame) -> None:
        self._latest_ns = max(self._latest_ns, frame.timestamp_ns)
        if self._t0 is None:
            self._t0 = frame.timestamp_ns
        recording = self._recording
        if recording is not None and head in recording.recorder.cameras:
            recording.recorder.submit_frame(head, frame)
        self._rates[head].tick()
        try:
            self.source.lights.observe(head, frame.frame_id, frame.image)
        except LightPhaseError as exc:
            self._problem(str(exc))
        self._buffers[head].take(frame, self.source.lights.light_of(head, frame.frame_id))

    def _capture_flow(self) -> None:
        gain, offset = self.source.flow_calibration or (None, None)
        try:
            while not self._stop.is_set():
                block = self.source.flow.read()
                if len(block.adc):
                    self._recent_flow.append((time.monotonic_ns(), block))
                    recording = self._recording
                    if recording is not None:
                        recording.take_flow(block)
                    if gain is not None:
                        self._flow_display.add(block, gain, offset, self._t0)
                time.sleep(0.01)
        except Exception as exc:  # a flow sensor that stops answering: said, and the cameras go on
            self._problem(f"flow sensor: {exc}")

    def preview(self, head: str, width_px: int = 400) -> np.ndarray | None:
        """The head's newest light cycle as one image, at most about `width_px` wide (CycleBuffer.preview)."""
        return self._buffers[head].preview(width_px)

    def _reconstruct(self, head: str) -> None:
        # each head's thread keeps to its share of the cores: numba's parallel kernels (OpenMP) and
        # the DCTs of two heads running at once on all of them oversubscribed the cores
        use_threads((os.cpu_count() or 1) // len(self._live_heads))
        stream = HeadStream(self.rig, head, self._live_heads[head], self._binning[head], self.settings)
        buffer = self._buffers[head]
        while not self._stop.is_set():
            window, before, darks = buffer.wait_for_cycle(0.2, stream.fed_id)
            stream.feed_darks(darks)
            if not stream.is_new(window):
                continue
            # the distance the two heads' geometry gave the last maps (as `process` does), once it has one
            geometric = self._metric.geometric_distance_mm(head)
            try:
                result, cycle = stream.reconstruct(window, before, geometric)
            except Exception as exc:  # a map that cannot be made is skipped, and said once
                self._problem(f"{head}: reconstruction failed: {exc}")
                continue
            self._publish(head, window[-1][0].timestamp_ns, stream, result, cycle, geometric)

    def _publish(self, head: str, stamp: int, stream: HeadStream, result: HeadMap, cycle: tuple,
                 geometric: float | None) -> None:
        """A head's new map to the live view: its height map, its share of the volume curves, the
        checks `process` makes, and the subject's calibrated litres once there is a calibration."""
        depth = np.where(result.mask, result.depth_mm, np.nan)
        height = (np.nanmean(depth) - depth).astype(np.float32) if result.mask.any() else None
        t_s = (stamp - self._t0) / 1e9 if self._t0 is not None else None
        litres = (self._metric.add(head, t_s, result.depth_mm, result.mask, result.distance_mm,
                                     result.silhouette) if t_s is not None
                  else float("nan"))
        if geometric is not None and t_s is not None and result.mask.any() and self._checks.due(head, t_s):
            self._look(head, t_s, result, stream.reconstructor, cycle)
        view = self._views[head]
        with self._lock:
            view.height_mm = height
            view.distance_mm = float(result.distance_mm)
            view.occluded_side_share = float(result.extra.get("occluded_side_share", np.nan))
            view.frame_id = stream.done_id
            view.reconstructed += 1
            self._gradient[head] = float(result.gradient_volume)
            if head == next(iter(self.source.cameras)) and t_s is not None:  # one clock for the curves
                self._optical.append((t_s, sum(self._gradient.values())))
                recording = self._recording
                calibration = recording.calibration if recording is not None else None
                regions = self._metric.head_regions()
                if regions:
                    signals = regional_signals(regions)
                    self._regional_curve.append((t_s, signals))
                    if calibration is not None:
                        litres = float(calibration.volume_l(signals))
                if calibration is None:
                    litres *= POPULATION_GAIN
                if np.isfinite(litres):
                    self._metric_curve.append((t_s, litres))
                    if calibration is not None:
                        recording.take_optical(stamp, litres)

    def _look(self, head: str, t_s: float, result: HeadMap, reconstructor: HeadReconstructor, cycle: tuple) -> None:
        """What `process` checks on a map made at the geometric distance: its sides along the height
        and its sheen."""
        try:
            profile = side_profile_mm(result.depth_mm, result.mask, result.silhouette, self._live_heads[head])
            sheen = reconstructor.sheen(*cycle, result)
        except Exception as exc:  # said once; the checks go without this look, the live view goes on
            self._problem(f"{head}: the optical volume's checks failed: {exc}")
            return
        self._checks.add_profile(head, t_s, profile)
        if np.isfinite(sheen):
            self._checks.add_sheen(head, t_s, sheen)

    def _problem(self, message: str) -> None:
        log.warning(message)
        with self._lock:
            if message not in self._problems:
                self._problems.append(message)

    # what the GUI pulls
    def snapshot(self) -> Snapshot:
        with self._lock:
            heads = {}
            for h, v in self._views.items():
                stats = self.source.cameras[h].stats
                heads[h] = HeadView(v.height_mm, v.distance_mm, v.frame_id, v.occluded_side_share, v.reconstructed,
                                    stats.delivered, stats.lost + stats.failed, self._rates[h].per_s())
            optical = np.array(self._optical, dtype=float).reshape(-1, 2)
            flow = self._flow_display.curve()
            metric = np.array(self._metric_curve, dtype=float).reshape(-1, 2)
            recording = self._recording
            recorder = recording.recorder if recording is not None else None
            problems = list(self._problems) + (recorder.problems if recorder is not None else [])
            flow_until = self._flow_until_ns()
            calibration = recording.calibration if recording is not None else None
        snapshot = Snapshot(heads, optical[:, 0], optical[:, 1], flow[:, 0], flow[:, 1],
                            recorder.path if recorder is not None else None,
                            recorder.frames_written() if recorder is not None else {},
                            recorder.dropped if recorder is not None else 0, problems,
                            time.monotonic() - self._started, metric[:, 0], metric[:, 1], flow_until,
                            # a bend changes the volume's scale, which the subject's calibration takes
                            self.replay_finished, self._checks.refusal() if calibration is None else None,
                            self._checks.checked,
                            calibration.label() if calibration is not None else estimate_label(ESTIMATE_UNCERTAINTY))
        clock = self.source.replay_clock
        if clock is not None:
            snapshot.replay_position_s = (min(clock.now_ns(), clock.last_ns) - clock.first_ns) / 1e9
            snapshot.replay_length_s = (clock.last_ns - clock.first_ns) / 1e9
            snapshot.replay_paused = clock.paused
        return snapshot

    def replay_control(self, action: str, position_s: float | None = None) -> None:
        """Pause, resume, or move a replay to `position_s` into its recording; after a move the
        curves start afresh (their time would run backwards)."""
        clock = self.source.replay_clock
        if clock is None:
            raise RuntimeError("not a replay")
        if action == "pause":
            clock.pause()
        elif action == "resume":
            clock.resume()
        elif action == "seek":
            clock.seek(clock.first_ns + int(float(position_s) * 1e9))
            with self._lock:
                for curve in (self._optical, self._metric_curve):
                    curve.clear()
                self._flow_display.clear()
            for buffer in self._buffers.values():
                buffer.clear()
            self._checks.clear()
        else:
            raise ValueError(f"unknown replay action {action!r}: pause, resume or seek")

    @property
    def replay_finished(self) -> bool:
        return self.source.replay and all(getattr(c, "finished", False) for c in self.source.cameras.values())
