"""Recovering a session cut off mid-recording (crash, SIGKILL, power loss, a full disk, a file
truncated on disk).

What every dataset reached, and still reads back, is copied into a fresh file that takes the
original's name; the original is kept beside it (`NAME.crashed.h5`, or `NAME.crashed-2.h5` when
that exists already): nothing is ever removed or replaced. A complete session is refused.

A killed writer leaves HDF5's "open for writing" flags set, so the file is read in SWMR mode. On
a file truncated on disk HDF5's SWMR reader retries every unreadable piece of metadata 100 times
with back-off (measured: more than 20 minutes on one file); the writer is dead and retrying
cannot help, so the recovery reads with `READ_ATTEMPTS` and every unreadable piece fails at once.
"""

from __future__ import annotations

import ctypes
import os
import re
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import h5py
import numpy as np

from core.io.outputs import atomic_output, next_free_path
from core.io.results import READ_ERRORS
from core.io.session import SessionError, frame_filter, now_iso, validate_session

READ_ATTEMPTS = 2
HEAD_KEYS = ("frames", "light_index", "timestamp_ns", "frame_id")
BLOCK = 64
_READ_ERRORS = READ_ERRORS  # what h5py raises for a damaged part (core/io/results.py)


@dataclass
class Recovery:
    """What `recover_session` kept: frames per head (and flow samples), where the original went, and
    what could not be read back."""

    kept: dict[str, int]
    original: Path
    notes: list[str] = field(default_factory=list)


def _hdf5_library() -> ctypes.CDLL | None:
    """The HDF5 library h5py itself loaded (found in this process' memory map), for the one setting
    h5py does not expose."""
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if re.search(r"/libhdf5[-.][^/]*\.so", line)
                     and "_hl" not in line}
    except OSError:
        return None
    for path in sorted(paths):
        try:
            library = ctypes.CDLL(path)
            library.H5Pset_metadata_read_attempts  # noqa: B018 - the symbol must exist
            return library
        except (OSError, AttributeError):
            continue
    return None


def _open_dead_writers_file(path: Path) -> h5py.File:
    """Open a file whose writer is gone: SWMR read (its flags may still say "open for writing"),
    metadata read attempts bounded where the library lets us."""
    fapl = h5py.h5p.create(h5py.h5p.FILE_ACCESS)
    fapl.set_libver_bounds(h5py.h5f.LIBVER_LATEST, h5py.h5f.LIBVER_LATEST)
    library = _hdf5_library()
    if library is not None:
        library.H5Pset_metadata_read_attempts(ctypes.c_int64(fapl.id), ctypes.c_uint(READ_ATTEMPTS))
    try:
        fid = h5py.h5f.open(os.fsencode(path), h5py.h5f.ACC_RDONLY | h5py.h5f.ACC_SWMR_READ, fapl=fapl)
    except _READ_ERRORS as exc:
        raise SessionError(f"cannot open {path} to recover it: {exc}") from exc
    return h5py.File(fid)


def _diagnose(path: Path) -> str | None:
    """Why the file needs recovering (a note for the user), or SessionError when it does not or cannot be."""
    if not path.exists():
        raise SessionError(f"{path}: no such file")
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89HDF\r\n\x1a\n":
            raise SessionError(f"{path} is not an HDF5 file: there is nothing photopft can recover from it")
    try:
        h5py.File(path, "r").close()
    except OSError as exc:
        text = str(exc)
        truncated = re.search(r"eof = (\d+).*stored_eof = (\d+)", text)
        if truncated:
            size, stored = int(truncated.group(1)), int(truncated.group(2))
            return (f"{path} is truncated on disk: {size:,} of {stored:,} bytes ({100 * size / stored:.0f} %); "
                    "what lies past the cut is lost")
        if "already open for write" in text:
            return None
        raise SessionError(f"cannot open {path} to recover it: {exc}") from exc
    problems = validate_session(path)
    if not problems:
        raise SessionError(f"{path} is a complete, valid session: there is nothing to recover")
    return None


def _first_unreadable(dataset: h5py.Dataset, start: int, stop: int) -> int:
    """The first entry from `start` that does not read back (`stop` if all do)."""
    for i in range(start, stop):
        try:
            dataset[i]
        except _READ_ERRORS:
            return i
    return stop


def _written_prefix(timestamp_ns: np.ndarray) -> int:
    """How many leading entries were really written: a dataset's extent can reach the file before
    its data does (a full disk), and unwritten entries read back as zeros, so the times stop rising."""
    n = len(timestamp_ns)
    if n == 0:
        return 0
    if timestamp_ns[0] == 0:
        return 0
    bad = np.nonzero((np.diff(timestamp_ns) <= 0) | (timestamp_ns[1:] == 0))[0]
    return int(bad[0]) + 1 if len(bad) else n


def _same_filter(dataset: h5py.Dataset) -> dict:
    """The copy compressed as the original was: Blosc (the recorder's frames) or HDF5's own."""
    checksum = {"fletcher32": True} if dataset.fletcher32 else {}
    if "32001" in dataset._filters:  # h5py names a plugin filter by its id
        return frame_filter("blosc-lz4") | checksum
    if dataset.compression:
        return {"compression": dataset.compression, "compression_opts": dataset.compression_opts} | checksum
    return checksum


def _copy_readable(source: h5py.Group, target: h5py.Group, keys: tuple[str, ...], limit: int,
                   entry_written: Callable[[dict, int], bool] | None = None) -> int:
    """Copies the keys' leading entries in one pass, block by block and all keys alike: up to
    `limit`, up to the first entry any key cannot read back (a truncated file loses its tail, and so
    may any chunk), and then only the entries really written (_written_prefix of the times, and
    `entry_written` tested from the end). Returns how many were kept."""
    sources = {k: source[k] for k in keys}
    copies = {k: target.create_dataset(k, shape=(0,) + d.shape[1:], dtype=d.dtype, maxshape=(None,) + d.shape[1:],
                                       chunks=d.chunks, **_same_filter(d)) for k, d in sources.items()}
    n = 0
    while n < limit:
        stop = min(n + BLOCK, limit)
        try:
            blocks = {k: d[n:stop] for k, d in sources.items()}
        except _READ_ERRORS:
            stop = limit = min(_first_unreadable(d, n, stop) for d in sources.values())
            blocks = {k: d[n:stop] for k, d in sources.items()}
        for k, block in blocks.items():
            copies[k].resize(stop, axis=0)
            copies[k][n:stop] = block
        n = stop
    if "timestamp_ns" in copies:
        n = _written_prefix(copies["timestamp_ns"][:n])
    while entry_written is not None and n > 0 and not entry_written(copies, n - 1):
        n -= 1
    for copy in copies.values():
        copy.resize(n, axis=0)
    return n


def _readable(group: h5py.Group, key: str) -> bool:
    """Whether the dataset is there and its header reads back (a writer killed while writing it can
    leave its object header with a wrong checksum)."""
    try:
        return key in group and group[key].shape is not None
    except _READ_ERRORS:
        return False


def _copy_head(src: h5py.Group, dst: h5py.File, name: str, notes: list[str]) -> int:
    missing = [k for k in HEAD_KEYS if not _readable(src, k)]
    out = dst.require_group(src.name)
    if missing:
        notes.append(f"head {name}: {', '.join(missing)} lost or unreadable; none of its frames can be kept")
        _copy_readable(src, out, tuple(k for k in HEAD_KEYS if k not in missing), 0)
        rig = dst[f"rig/{name}"].attrs
        shapes = {"frames": ((0, int(rig["height"]), int(rig["width"])),
                             np.uint8 if int(rig["bit_depth"]) <= 8 else np.uint16),
                  "light_index": ((0,), np.int8), "timestamp_ns": ((0,), np.int64), "frame_id": ((0,), np.uint64)}
        for key in missing:
            shape, dtype = shapes[key]
            out.create_dataset(key, shape=shape, dtype=dtype, maxshape=(None,) + shape[1:])
        return 0
    total = min(src[k].shape[0] for k in HEAD_KEYS)
    # the last frames may have been half written: keep the frames that read back and are not blank
    n = _copy_readable(src, out, HEAD_KEYS, total, lambda copies, i: bool(copies["frames"][i].any()))
    if n < src["frames"].shape[0]:
        notes.append(f"head {name}: {n} of {src['frames'].shape[0]} frames kept" + ("" if n else " (none read back)"))
    return n


@contextmanager
def _needed(path: Path, what: str, notes: list[str]) -> Iterator[None]:
    """A part without which no valid session can be made: unreadable, the recovery stops, naming it."""
    try:
        yield
    except _READ_ERRORS as exc:
        lost = "; ".join(notes) + "; " if notes else ""
        raise SessionError(f"{path}: {what} cannot be read back ({exc}), so no session can be made from what is "
                           f"left; {lost}nothing was changed") from exc


def recover_session(path: str | os.PathLike) -> Recovery:
    """Recover a cut-off session under its own name, keeping the original beside it.

    Raises SessionError naming the file when it needs no recovery (a complete session), is not
    HDF5, or holds nothing a session can be made of (its /rig is lost).
    """
    path = Path(path)
    notes = [note] if (note := _diagnose(path)) else []
    kept: dict[str, int] = {}
    src = _open_dead_writers_file(path)
    with src, atomic_output(path, replace_session=True) as partial:
        try:
            if "rig" not in src or "front" not in src["rig"]:
                raise SessionError(f"{path}: the rig description (/rig) is lost, so no session can be made from "
                                   f"what is left; nothing was changed")
            with h5py.File(partial, "w", libver="latest") as dst:
                with _needed(path, "the file's own attributes (format, kind, created)", notes):
                    for key, value in src.attrs.items():
                        dst.attrs[key] = value
                dst.attrs["recovered"] = now_iso()
                for name in ("rig", "subject"):
                    if name in src:
                        with _needed(path, f"/{name}", notes):
                            src.copy(src[name], dst, name)
                heads = src["heads"] if "heads" in src else {}
                for name in src["rig"]:
                    if name in heads:
                        kept[name] = _copy_head(heads[name], dst, name, notes)
                    else:
                        notes.append(f"head {name}: its frames (/heads/{name}) are lost")
                for group, keys in (("flow", ("adc", "timestamp_ns")), ("events", ("timestamp_ns", "label"))):
                    if group not in src:
                        if group == "events":
                            events = dst.create_group("events")
                            events.create_dataset("timestamp_ns", shape=(0,), dtype=np.int64, maxshape=(None,))
                            events.create_dataset("label", shape=(0,), dtype=h5py.string_dtype(), maxshape=(None,))
                        continue
                    g = src[group]
                    present = tuple(k for k in keys if k in g)
                    n = _copy_readable(g, dst.require_group(group), present,
                                       min(g[k].shape[0] for k in keys) if present == keys else 0)
                    for key, value in g.attrs.items():
                        dst[group].attrs[key] = value
                    if group == "flow":
                        kept["flow"] = n
                if "truth" in src:
                    try:
                        src.copy(src["truth"], dst, "truth")
                    except _READ_ERRORS:
                        notes.append("the simulation's truth (/truth) could not be read back; left out")
        except _READ_ERRORS as exc:
            raise SessionError(f"{path} could not be recovered: {exc}; nothing was changed") from exc
        if not any(kept.get(h, 0) for h in src["rig"] if h != "flow"):
            raise SessionError(f"{path}: no frame of any head reads back, so there is nothing to recover; "
                               + "; ".join(notes) + ("; " if notes else "") + "nothing was changed")
        original = next_free_path(path.with_name(path.stem + ".crashed.h5"))
        try:
            os.link(path, original)  # the original under its new name before the recovered file takes the old
        except OSError:
            os.rename(path, original)
    return Recovery(kept, original, notes)
