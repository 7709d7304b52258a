"""One head's maps from a session's frames: its light cycles reconstructed in order, in this process
or in worker processes (HeadWorkers), with the displacement sums the volume is made from."""

from __future__ import annotations

import multiprocessing
import os
import queue
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import h5py
import numba
import numpy as np

from core.io.outputs import stop_if_requested
from core.io.session import SessionError, SessionFile
from core.pipeline.quality import sides_shown
from core.reconstruction.ambient import FlickerCorrection
from core.reconstruction.binning import binned_head
from core.reconstruction.cycle import CycleFrame, cycle_frame, cycle_signal_of
from core.reconstruction.photometric import CycleWindow, complete_cycles
from core.reconstruction.pipeline import HeadMap, HeadReconstructor, ReconstructionSettings
from core.reconstruction.reflectance import RedundancyFit
from core.rig import DARK
from core.volume.maps import DisplacementSums, DisplacementTracker
from core.volume.sides import side_profile_mm


def trunk_area_m2(valid_pixels: np.ndarray, distance_mm: np.ndarray, head) -> np.ndarray:
    """The area of the subject a head's maps hold (m^2): valid pixels times each pixel's footprint at
    the map's distance."""
    return (np.asarray(valid_pixels, float) * (np.asarray(distance_mm, float) / head.fx)
            * (np.asarray(distance_mm, float) / head.fy) * 1e-6)

class DarkFeed:
    """A head's dark frames, handed to its FlickerCorrection (core/reconstruction/ambient.py) as the cycles move on:
    `flicker_of(window)` gives each frame's flicker, fitted on the dark frames around that cycle."""

    def __init__(self, frames: h5py.Dataset, light_index: np.ndarray, timestamp_ns: np.ndarray, mains_hz: float,
                 binning: int = 1) -> None:
        self.correction = FlickerCorrection(2.0 * mains_hz, binning=binning)
        self._frames = frames
        self._t = np.asarray(timestamp_ns, dtype=np.int64) / 1e9
        self._darks = np.flatnonzero(np.asarray(light_index) == DARK)
        self._dark_t = self._t[self._darks]
        self._next = 0

    def flicker_of(self, window: CycleWindow) -> Callable[[CycleFrame], np.ndarray | None]:
        t_cycle = float(self._t[window.newest])
        start, stop = self.correction.span(t_cycle)
        self._next = max(self._next, int(np.searchsorted(self._dark_t, start)))
        while self._next < len(self._darks) and self._dark_t[self._next] <= stop:
            j = int(self._darks[self._next])
            self.correction.add_dark(float(self._t[j]), self._frames[j])
            self._next += 1
        return lambda frame: self.correction.excess(frame.time_s, t_cycle)

    @property
    def flicker_share(self) -> float:
        """The room light's flicker as found (amplitude over the mean dark level, median over the
        fits); 0 when none stood above the dark frames' noise."""
        return float(np.median(self.correction.amplitudes)) if self.correction.amplitudes else 0.0


# How each light's frame is brought to its cycle's newest instant (core/reconstruction/cycle.py): a
# recorded session has the cycle after each one, so `process` interpolates towards it; the live view,
# which has only the frames so far, extrapolates from the cycle before (`photopft bench motion`).
MOTION_MODES = ("none", "extrapolated", "interpolated")


def motion_mode(motion_compensation: bool | str) -> str:
    """The mode of MOTION_MODES that `process`'s motion_compensation names: True interpolates, False is none."""
    mode = {True: "interpolated", False: "none"}.get(motion_compensation, motion_compensation)
    if mode not in MOTION_MODES:
        raise ValueError(f"motion_compensation must be one of {', '.join(MOTION_MODES)}, got {motion_compensation!r}")
    return mode


def neighbour_cycles(windows_by_id: dict[int, CycleWindow], newest_id: int, cycle_length: int,
                     mode: str) -> tuple[CycleWindow | None, CycleWindow | None]:
    """(the cycle before, the cycle after) a window whose newest frame has id newest_id, as `mode` uses
    them; the last cycle of a recording, which has none after it, is extrapolated."""
    if mode == "none":
        return None, None
    previous = windows_by_id.get(newest_id - cycle_length)
    following = windows_by_id.get(newest_id + cycle_length) if mode == "interpolated" else None
    return previous, following


def cycle_signal(frames: h5py.Dataset, window: CycleWindow, previous: CycleWindow | None, max_value: int,
                 cache: dict[int, CycleFrame], frame_id: np.ndarray, timestamp_ns: np.ndarray,
                 flicker: Callable[[CycleFrame], np.ndarray | None] | None = None, binning: int = 1,
                 following: CycleWindow | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A window's signal from a session's frames (core/reconstruction/cycle.py, as the live view makes it): with
    `previous` (the cycle one period earlier) motion-compensated, or with `following` too (the cycle one
    period later) interpolated towards it; `flicker` (DarkFeed.flicker_of,
    binned alike) the room light's flicker in a frame; `cache` keeps each frame read."""
    def frame(i: int) -> CycleFrame:
        if i not in cache:
            cache[i] = cycle_frame(frames[i], binning, max_value, timestamp_ns[i] / 1e9, int(frame_id[i]))
        return cache[i]

    return cycle_signal_of([frame(i) for i in window.lit], frame(window.dark),
                           [frame(i) for i in previous.lit] if previous is not None else None, flicker,
                           [frame(i) for i in following.lit] if following is not None else None)

@dataclass(frozen=True)
class HeadJob:
    """One head's share of `process_session`, picklable for a worker process."""
    session_path: Path
    rig: object  # core.rig.Rig
    name: str
    windows: list[CycleWindow]
    settings: ReconstructionSettings
    pseudo_light_vectors: np.ndarray | None
    motion_compensation: str  # one of MOTION_MODES
    maps_at: tuple[int, ...]
    distances_mm: np.ndarray | None = None  # each window's subject distance, when known from elsewhere
    binning: int = 1  # the stream reconstructed on binning x binning bins (maps_at frames at full resolution)
    profile_every: int = 0  # every so many maps, the trunk's sides along its height (side_profile_mm); 0 none
    # (len(windows), 4) the lights' outputs at each window as factors of the rig's intensities
    # (light_gains_over_time); None: the intensities as calibrated
    light_gains: np.ndarray | None = None


@dataclass
class HeadResult:
    name: str
    timestamp_ns: np.ndarray
    frame_index: np.ndarray
    distance_mm: np.ndarray
    gradient_volume: np.ndarray
    valid_pixels: np.ndarray
    occluded_side_share: np.ndarray
    side_out_of_view_share: np.ndarray
    sheen: np.ndarray
    saved_index: list[int]
    saved_normals: list[np.ndarray]
    saved_depth: list[np.ndarray]
    sums: list
    ambient_flicker: float = 0.0  # DarkFeed.flicker_share
    # (n, 4) every job.profile_every maps the lights' outputs against the intensities solved with (NaN between)
    light_gain: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    # (timestamp_ns, side_profile_mm) every job.profile_every maps
    side_profiles: tuple[np.ndarray, list] = field(default_factory=lambda: (np.zeros(0, np.int64), []))


def process_head(job: HeadJob, tick: Callable[[], None]) -> HeadResult:
    """Reconstructs one head's windows in order (the running distance and the displacement tracker
    follow the stream); `tick` after each."""
    rig, name = job.rig, job.name
    full_head = rig.heads[name]
    head = binned_head(full_head, job.binning)
    reconstructor = HeadReconstructor(head, job.pseudo_light_vectors, job.settings)
    full_reconstructor = None  # the maps asked for at full resolution, when the stream is binned
    tracker = DisplacementTracker(head)
    rows: dict[str, list] = {"timestamp_ns": [], "frame_index": [], "distance_mm": [], "gradient_volume": [],
                             "valid_pixels": [], "occluded_side_share": [], "side_out_of_view_share": [], "sheen": []}
    saved_index, saved_normals, saved_depth, sums, gains = [], [], [], [], []
    profile_times, profiles = [], []
    near = job.settings.method == "near"  # the sheen's fit needs the near lights' per-pixel irradiance
    # the command that planned the job validated the file; HDF5 checks each chunk's checksum as it is read
    with SessionFile(job.session_path, check=False) as session:
        frames = session.frames(name)
        stamps = session.timestamp_ns(name)
        ids = session.frame_id(name)
        all_windows = {int(ids[w.newest]): w for w in complete_cycles(session.light_index(name), ids,
                                                                       rig.cycle_length)}
        cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        darks = DarkFeed(frames, session.light_index(name), stamps, rig.mains_hz, job.binning)
        for number, window in enumerate(job.windows):
            stop_if_requested()
            for stale in [k for k in cache if k < window.newest - 2 * rig.cycle_length]:
                del cache[stale]
            previous, following = neighbour_cycles(all_windows, int(ids[window.newest]), rig.cycle_length,
                                                   job.motion_compensation)
            signal, saturated, dark = cycle_signal(frames, window, previous, head.max_value, cache, ids, stamps,
                                                   darks.flicker_of(window), job.binning, following)
            known = job.distances_mm[number] if job.distances_mm is not None else np.nan
            if job.light_gains is not None:
                reconstructor.intensity_factors = job.light_gains[number]
            result = reconstructor.reconstruct(signal, saturated, dark, float(known) if np.isfinite(known) else None)
            rows["timestamp_ns"].append(stamps[window.newest])
            rows["frame_index"].append(window.newest)
            rows["distance_mm"].append(result.distance_mm)
            rows["gradient_volume"].append(result.gradient_volume)
            rows["valid_pixels"].append(int(result.mask.sum()))
            for key in ("occluded_side_share", "side_out_of_view_share"):
                rows[key].append(result.extra.get(key, np.nan))
            looked_at = job.profile_every and number % job.profile_every == 0
            redundancy = (reconstructor.redundancy(signal, saturated, result) if looked_at and near
                          else RedundancyFit.none())
            rows["sheen"].append(redundancy.sheen)
            gains.append(redundancy.light_gain)
            if sides_shown(rows["occluded_side_share"][-1]):
                sums.append(tracker.add(result.depth_mm, result.mask, result.silhouette, known))
            else:  # an arm hides the sides the map is referred to: left out (MAX_HIDDEN_MAPS), nor the reference
                sums.append(DisplacementSums(float("nan"), float("nan"), {}, {}))
            if looked_at:
                profile_times.append(stamps[window.newest])
                profiles.append(side_profile_mm(result.depth_mm, result.mask, result.silhouette, head))
            if window.newest in job.maps_at:
                full = result
                if job.binning > 1:
                    full_reconstructor = full_reconstructor or HeadReconstructor(full_head, job.pseudo_light_vectors,
                                                                                 job.settings)
                    full_reconstructor.intensity_factors = reconstructor.intensity_factors
                    full_darks = DarkFeed(frames, session.light_index(name), stamps, rig.mains_hz)
                    full = full_reconstructor.reconstruct(
                        *cycle_signal(frames, window, previous, head.max_value, {}, ids, stamps,
                                      full_darks.flicker_of(window), following=following),
                        float(result.distance_mm))
                saved_index.append(window.newest)
                saved_normals.append(full.normals.astype(np.float32))
                saved_depth.append(full.depth_mm.astype(np.float32))
            tick()
    return HeadResult(name, np.asarray(rows["timestamp_ns"], dtype=np.int64),
                       np.asarray(rows["frame_index"], dtype=np.int64),
                       np.asarray(rows["distance_mm"], dtype=np.float64),
                       np.asarray(rows["gradient_volume"], dtype=np.float64),
                       np.asarray(rows["valid_pixels"], dtype=np.int64),
                       np.asarray(rows["occluded_side_share"], dtype=np.float64),
                       np.asarray(rows["side_out_of_view_share"], dtype=np.float64),
                       np.asarray(rows["sheen"], dtype=np.float64), saved_index, saved_normals,
                       saved_depth, sums, darks.flicker_share,
                       light_gain=np.asarray(gains, dtype=np.float64).reshape(-1, 4),
                       side_profiles=(np.asarray(profile_times, dtype=np.int64), profiles))


_worker_ticks = None  # in a worker process: the queue its progress goes to


def use_threads(threads: int) -> None:
    """The calling thread's numba kernels, and the DCTs that follow them (core/reconstruction/integrate.py),
    on `threads` cores: at least one, at most numba's pool. Per thread: a live head's reconstruction
    thread, a worker process, a Dask task each take their share of the cores."""
    numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))


def _start_worker(ticks, threads: int) -> None:
    global _worker_ticks
    _worker_ticks = ticks
    use_threads(threads)


def _head_in_worker(job: HeadJob) -> HeadResult:
    return process_head(job, lambda: _worker_ticks.put(1))


class HeadWorkers:
    """Where `process_session` reconstructs its heads: here (workers <= 1), or in spawned worker
    processes (fork is unsafe once OpenMP threads run), each with its share of the cores, started
    once for both of its passes: a worker takes about 2 s to start (imports, numba's cached kernels),
    and a pool per pass spent that twice."""

    def __init__(self, workers: int, heads: int) -> None:
        self._count = min(workers, heads)
        self._pool = None
        self._ticks = None

    def __enter__(self) -> "HeadWorkers":
        if self._count > 1:
            context = multiprocessing.get_context("spawn")
            self._ticks = context.Queue()
            self._pool = context.Pool(self._count, initializer=_start_worker,
                                      initargs=(self._ticks, max(1, (os.cpu_count() or 1) // self._count)))
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()

    def run(self, jobs: list[HeadJob], progress: Callable[[float], None]) -> list[HeadResult]:
        """Each job's head reconstructed; `progress` gets the share of their windows done."""
        done = 0
        total = sum(len(job.windows) for job in jobs)

        def tick(count: int = 1) -> None:
            nonlocal done
            done += count
            if total:
                progress(done / total)

        if self._pool is None or len(jobs) <= 1:
            return [process_head(job, tick) for job in jobs]
        pending = self._pool.map_async(_head_in_worker, jobs, chunksize=1)
        while not pending.ready():
            stop_if_requested()
            try:
                tick(self._ticks.get(timeout=0.2))
            except queue.Empty:
                pass
        return pending.get()


def maps_at(session_path: str | os.PathLike, head_name: str, frame_indices: list[int], *,
            settings: ReconstructionSettings | None = None, motion_compensation: bool | str = True,
            distances_mm: list[float] | None = None, light_gains: np.ndarray | None = None) -> list[HeadMap]:
    """Maps of one head at the given frames (each the newest complete cycle ending at or before
    it), by the same reconstruction `process_session` runs, for reports and reviews.
    distances_mm: the subject's distance at each frame as `process` measured it (processed_distance_mm);
    without it, or where it is NaN, each map's distance is the photometric fit's, which the
    lights' and the skin's errors move by tens to hundreds of millimetres (docs/reconstruction.md).
    light_gains: (len(frame_indices), 4) the lights' outputs `process` followed at those frames
    (processed_light_gains); None: the intensities as calibrated."""
    settings = settings or ReconstructionSettings()
    mode = motion_mode(motion_compensation)
    with SessionFile(session_path) as session:
        rig = session.rig
        if head_name not in rig.heads:
            raise SessionError(f"{session_path} has no head {head_name!r}")
        head = rig.heads[head_name]
        ids = session.frame_id(head_name)
        windows = complete_cycles(session.light_index(head_name), ids, rig.cycle_length)
        if not windows:
            raise SessionError(f"head {head_name}: no complete light cycle in {session_path}")
        ends = np.array([w.newest for w in windows])
        by_id = {int(ids[w.newest]): w for w in windows}
        frames = session.frames(head_name)
        reconstructor = HeadReconstructor(head, None, settings)
        lights, stamps = session.light_index(head_name), session.timestamp_ns(head_name)
        out = []
        known = list(distances_mm) if distances_mm is not None else [float("nan")] * len(frame_indices)
        for number, (index, distance) in enumerate(zip(frame_indices, known)):
            if light_gains is not None:
                reconstructor.intensity_factors = np.asarray(light_gains[number], dtype=float)
            window = windows[max(0, int(np.searchsorted(ends, index, side="right")) - 1)]
            previous, following = neighbour_cycles(by_id, int(ids[window.newest]), rig.cycle_length, mode)
            darks = DarkFeed(frames, lights, stamps, rig.mains_hz)  # a feed per frame asked: they come in any order
            signal, saturated, dark = cycle_signal(frames, window, previous, head.max_value, {}, ids, stamps,
                                                   darks.flicker_of(window), following=following)
            out.append(reconstructor.reconstruct(signal, saturated, dark,
                                                 float(distance) if np.isfinite(distance) else None))
    return out
