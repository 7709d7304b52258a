"""The live engine (app.engine.live_rig.LiveRig) in a process of its own, behind the same calls.

In one process the capture, reconstruction and recording threads share Python's GIL with the GUI
thread, and a worker inside a long C call that holds it (an HDF5 write, a numpy reduction) stops
the drawing: 133 ms at scale 0.5 while recording (`photopft bench gui`). Here the GUI process has
its GIL to itself; it sends commands and receives snapshots.

- The engine process is started with "spawn" (a process running Qt's threads is never forked) and
  opens the source itself: cameras, serial ports and files belong to the process that uses them.
  `opener` is a picklable callable that returns an app.engine.sources.Source, e.g.
  functools.partial(app.engine.sources.simulated_source, scale=0.5).
- Snapshots: a thread there publishes one every PUBLISH_INTERVAL_S, a height map only when it is
  new; a thread here receives them, and `snapshot()` returns the newest without waiting.
- Commands (recording, the recording's values, a simulated manoeuvre) wait for their answer. An
  event mark is stamped here, on the monotonic clock both processes share, and is not waited for.
- If the engine process dies, the snapshots say so, commands raise EngineError, and what the
  recorder wrote stays on disk (the session file is crash-safe: tests/drivers/test_crash_safety.py).
"""

from __future__ import annotations

import gc
import logging
import multiprocessing
import os
import pickle
import threading
import time
from contextlib import contextmanager
from dataclasses import replace
from pathlib import Path
from typing import Callable

from app.engine.feeds import EngineInfo, HeadView, Snapshot
from app.engine.live_rig import LiveRig, WORKER_NICENESS
from app.engine.sources import Source
from app.memory import start_memory_trimmer

log = logging.getLogger(__name__)

PUBLISH_INTERVAL_S = 0.030  # a little faster than the display's 33 ms, so each update has a fresh snapshot
START_TIMEOUT_S = 300.0  # a cold start imports numba and renders the simulated subject
COMMAND_TIMEOUT_S = 120.0  # stopping a recording flushes its queues to disk
# Two glibc arenas: one per thread fragmented the heaps the engine keeps (docs/benchmarks.md, constants).
ENGINE_MALLOC_ARENAS = "2"


@contextmanager
def _environment(**variables: str):
    """Environment variables for a process started inside the block (this one's C library has read
    its own already)."""
    before = {k: os.environ.get(k) for k in variables}
    os.environ.update({k: v for k, v in variables.items() if before[k] is None})
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)


class EngineError(RuntimeError):
    """The engine process failed to start, stopped, or did not answer."""


def _portable(exc: BaseException) -> BaseException:
    """The exception itself when it survives pickling (so callers can catch SessionError and the
    like), else an EngineError with its message."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:
        return EngineError(f"{type(exc).__name__}: {exc}")


def _serve(opener: Callable[[], Source], commands, snapshots, log_path: str | None) -> None:
    """The engine process: open the source, run a LiveRig, publish snapshots, answer commands."""
    try:  # first, so that every thread made here inherits it (numba's, Aravis', the workers)
        os.setpriority(os.PRIO_PROCESS, 0, WORKER_NICENESS)
    except (OSError, AttributeError):
        pass
    if log_path:
        from app.logs import log_to_file

        log_to_file(Path(log_path))
    try:
        engine = LiveRig(opener())
        engine.start()
    except Exception as exc:
        log.exception("the engine could not start")
        commands.send(("error", _portable(exc)))
        return
    gc.freeze()  # modules and the scene are here to stay: full collections need not walk them
    start_memory_trimmer()
    commands.send(("ok", engine.info))
    stop = threading.Event()
    publisher = threading.Thread(target=_publish, args=(engine, snapshots, stop), name="publish", daemon=True)
    publisher.start()
    try:
        while True:
            try:
                name, args, kwargs = commands.recv()
            except (EOFError, OSError):  # the GUI has gone: stop, which closes a recording properly
                name, args, kwargs = "stop", (), {}
            try:
                result = getattr(engine, name)(*args, **kwargs)
                reply = ("ok", result)
            except Exception as exc:
                log.exception("engine command %s failed", name)
                reply = ("error", _portable(exc))
            if name != "mark":
                try:
                    commands.send(reply)
                except OSError:
                    pass
            if name == "stop":
                break
    finally:
        stop.set()
        publisher.join(timeout=2)


def _publish(engine: LiveRig, snapshots, stop: threading.Event) -> None:
    """Snapshots to the GUI process, each height map once."""
    sent_ids: dict[str, int] = {}
    while not stop.wait(PUBLISH_INTERVAL_S):
        snapshot = engine.snapshot()
        heads = {}
        for head, view in snapshot.heads.items():
            if sent_ids.get(head) == view.frame_id:
                view = replace(view, height_mm=None)
            else:
                sent_ids[head] = view.frame_id
            heads[head] = view
        try:
            snapshots.send(replace(snapshot, heads=heads))
        except OSError:  # the GUI process has gone
            return


class EngineProcess:
    """A LiveRig in its own process, with the calls the GUI makes of it (see the module's notes)."""

    def __init__(self, opener: Callable[[], Source], log_path: Path | None = None) -> None:
        context = multiprocessing.get_context("spawn")
        self._commands, their_commands = context.Pipe()
        snapshots_in, snapshots_out = context.Pipe(duplex=False)
        self._process = context.Process(target=_serve, name="photopft-engine", daemon=True,
                                        args=(opener, their_commands, snapshots_out,
                                              str(log_path) if log_path else None))
        with _environment(MALLOC_ARENA_MAX=ENGINE_MALLOC_ARENAS):
            self._process.start()
        their_commands.close()
        snapshots_out.close()
        self._lock = threading.Lock()
        self._closed = False
        self.recording = False
        if not self._commands.poll(START_TIMEOUT_S):
            self._process.kill()
            raise EngineError(f"the engine did not start within {START_TIMEOUT_S:.0f} s")
        try:
            status, value = self._commands.recv()
        except EOFError:
            self._process.join(timeout=5)
            raise EngineError(f"the engine stopped while starting (exit code {self._process.exitcode})") from None
        if status != "ok":
            self._process.join(timeout=5)
            raise value
        self.info: EngineInfo = value
        self._latest: Snapshot | None = None
        self._maps: dict[str, HeadView] = {}
        self._snapshots = snapshots_in
        self._receiver = threading.Thread(target=self._receive, name="engine-snapshots", daemon=True)
        self._receiver.start()

    @property
    def rig(self):
        return self.info.rig

    @property
    def pid(self) -> int:
        return self._process.pid

    def _receive(self) -> None:
        while True:
            try:
                snapshot = self._snapshots.recv()
            except (EOFError, OSError):
                break
            for head, view in snapshot.heads.items():
                if view.height_mm is not None:
                    self._maps[head] = view
                elif head in self._maps and self._maps[head].frame_id == view.frame_id:
                    snapshot.heads[head] = replace(view, height_mm=self._maps[head].height_mm)
            self._latest = snapshot
        if not self._closed:
            self._process.join(timeout=5)
            log.error("the engine process stopped (exit code %s)", self._process.exitcode)

    @property
    def stopped(self) -> bool:
        """The engine process ended without being asked to (it crashed or was killed): nothing more
        comes from it."""
        return not self._closed and not self._process.is_alive()

    def snapshot(self) -> Snapshot:
        """The newest state of the engine, without waiting (an empty one before the first arrives)."""
        latest = self._latest
        if latest is None:
            latest = Snapshot.empty(self.info.heads)
        if self.stopped:
            message = (f"the capture engine stopped (exit code {self._process.exitcode}); the recording so far "
                       "is on disk. Restart photopft.")
            latest = replace(latest, problems=latest.problems + [message])
        return latest

    def _call(self, name: str, *args, wait: bool = True, **kwargs):
        with self._lock:
            if self._closed or not self._process.is_alive():
                raise EngineError(f"the capture engine has stopped (exit code {self._process.exitcode})")
            try:
                self._commands.send((name, args, kwargs))
                if not wait:
                    return None
                if not self._commands.poll(COMMAND_TIMEOUT_S):
                    raise EngineError(f"the capture engine did not answer {name} within {COMMAND_TIMEOUT_S:.0f} s")
                status, value = self._commands.recv()
            except (EOFError, OSError) as exc:
                raise EngineError(f"the capture engine has stopped ({exc or 'no answer'})") from None
        if status != "ok":
            raise value
        return value

    def stop(self):
        """Stop the engine (and a recording, whose summary is returned) and end its process."""
        if self._closed:
            return None
        summary = None
        try:
            summary = self._call("stop")
        except EngineError as exc:
            log.warning("stopping the engine: %s", exc)
        self._closed = True
        self.recording = False
        self._process.join(timeout=10)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(timeout=5)
        self._commands.close()
        self._snapshots.close()
        return summary

    def start_recording(self, path, subject, kind: str = "patient", root_attrs: dict | None = None,
                        heads: list[str] | None = None) -> None:
        self._call("start_recording", path, subject, kind=kind, root_attrs=root_attrs, heads=heads)
        self.recording = True

    def stop_recording(self):
        self.recording = False
        return self._call("stop_recording")

    def mark(self, label: str) -> int:
        stamp = time.monotonic_ns()
        self._call("mark", label, stamp, wait=False)
        return stamp

    def flow_reaches(self, timestamp_ns: int) -> bool:
        return self.snapshot().flow_until_ns >= timestamp_ns

    def recorded_values(self, age_years: float | None = None):
        return self._call("recorded_values", age_years)

    def perform(self, manoeuvre: str) -> float:
        return self._call("perform", manoeuvre)

    def flow_since(self, monotonic_ns: int):
        return self._call("flow_since", monotonic_ns)

    def preview(self, head: str):
        return self._call("preview", head)

    def replay_control(self, action: str, position_s: float | None = None) -> None:
        self._call("replay_control", action, position_s)

    def blow_trace(self, mark_ns: int, before_s: float = 2.5):
        return self._call("blow_trace", mark_ns, before_s)

    def flow_adc_mean(self, seconds: float = 2.0) -> float:
        return self._call("flow_adc_mean", seconds)

    def calibrate_on_subject(self, start_ns: int):
        return self._call("calibrate_on_subject", start_ns)

    @property
    def replay_finished(self) -> bool:
        return self.snapshot().replay_finished
