"""A damaged HDF5 file can make the HDF5 library loop for ever inside one call (seen: reading a root
attribute of a results file with flipped bits, in the fuzz test), where no Python timeout can stop
it. Before a command reads a file, `probe` walks its structure (every object, every attribute,
every dataset's shape and type; no data) in a forked child and refuses the file if the child does
not finish within PROBE_TIMEOUT_S. Each file is probed once per process while it is unchanged.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path

import h5py

from core.io.errors import SessionError

PROBE_TIMEOUT_S = 20.0
_probed: set[tuple[str, int, int]] = set()


def _read_attributes(item) -> None:
    """Every attribute by name, as the readers ask for them (a damaged one may fail: go on)."""
    try:
        names = list(item.attrs.keys())
    except Exception:
        return
    for name in names + ["format", "kind", "session", "source"]:
        try:
            item.attrs.get(name)
        except Exception:
            pass


def _walk(path: str) -> None:
    with h5py.File(path, "r") as f:
        _read_attributes(f)

        def visit(name: str, item) -> None:
            _read_attributes(item)
            if isinstance(item, h5py.Dataset):
                item.shape, item.dtype

        try:
            f.visititems(visit)
        except Exception:
            pass


def _qt_application_running() -> bool:
    qt = sys.modules.get("PySide6.QtCore")
    return qt is not None and qt.QCoreApplication.instance() is not None


def probe(path: str | os.PathLike) -> None:
    """Raises SessionError naming the file when reading its structure does not end; any other
    failure is left to the reader, which names it. Skipped where forking is not safe: in the
    application's window (Qt and its threads, some of which may hold HDF5's lock)."""
    path = Path(path)
    try:
        stat = path.stat()
    except OSError:
        return  # the reader says it is missing
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    if key in _probed or _qt_application_running() or not hasattr(os, "fork"):
        return
    child = os.fork()
    if child == 0:  # the child: walk, and leave without running the parent's clean-up
        code = 0
        try:
            _walk(str(path))
        except BaseException:
            code = 1
        os._exit(code)
    deadline = time.monotonic() + PROBE_TIMEOUT_S
    while True:
        done, _ = os.waitpid(child, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(child, signal.SIGKILL)
            os.waitpid(child, 0)
            raise SessionError(f"{path}: reading its structure did not end within {PROBE_TIMEOUT_S:g} s; the file "
                               f"is damaged (a recording cut off: try `photopft recover`)")
        time.sleep(0.005)
    _probed.add(key)
