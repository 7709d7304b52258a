"""Reading a results file (written by core.process) safely: `check_results` reads every part once
and refuses, in one line naming the file and the part, anything the readers could not use: an
unreadable or missing dataset, a series of the wrong type or length, an infinite value, a
parameter that should be a number and is not. A results file that passes can be read by raw paths
without further checks (docs/data-format.md gives the layout).
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from core.session import SessionError

RESULTS_FORMAT = "photopft-results"
HEAD_SERIES = {"timestamp_ns": "i", "frame_index": "i", "distance_mm": "f", "gradient_volume": "f",
               "valid_pixels": "i"}
READ_ERRORS = (OSError, RuntimeError, KeyError, TypeError, ValueError)


def _series(path: Path, group: h5py.Group, name: str, kind: str, length: int | None) -> int:
    """Reads one 1-D series; its length."""
    where = f"{group.name.rstrip('/')}/{name}"
    if name not in group or not isinstance(group[name], h5py.Dataset):
        raise SessionError(f"{path}: {where} is missing")
    values = np.asarray(group[name][()])
    if values.ndim != 1 or values.dtype.kind not in ("iu" if kind == "i" else "fiu"):
        raise SessionError(f"{path}: {where} must be a series of {'whole numbers' if kind == 'i' else 'numbers'}, "
                           f"found {values.dtype} {values.shape}")
    if values.dtype.kind == "f" and np.isinf(values).any():
        raise SessionError(f"{path}: {where} holds an infinite value")
    if length is not None and len(values) != length:
        raise SessionError(f"{path}: {where} has {len(values)} values where its group has {length}")
    return len(values)


def _group_of_series(path: Path, group: h5py.Group, kinds: dict[str, str]) -> int:
    length = None
    for name, kind in kinds.items():
        length = _series(path, group, name, kind, length)
    return length or 0


def _check_head(path: Path, head: h5py.Group) -> None:
    _group_of_series(path, head, HEAD_SERIES)
    if "maps" in head:
        maps = head["maps"]
        count = _series(path, maps, "frame_index", "i", None)
        for name, rank in (("depth_mm", 3), ("normals", 4)):
            if name not in maps:
                raise SessionError(f"{path}: {maps.name}/{name} is missing")
            data = maps[name]
            if data.ndim != rank or data.shape[0] != count or data.dtype.kind != "f":
                raise SessionError(f"{path}: {data.name} must hold {count} maps of numbers, found {data.dtype} "
                                   f"{data.shape}")
            data[()]


def _check_volume(path: Path, f: h5py.File) -> None:
    if "volume" in f:
        _group_of_series(path, f["volume"], {"timestamp_ns": "i", "volume_l": "f"})
    if "flow_sensor" in f:
        _group_of_series(path, f["flow_sensor"], {"time_s": "f", "volume_l": "f"})
    if "metric_volume" in f:
        metric = f["metric_volume"]
        length = _group_of_series(path, metric, {"timestamp_ns": "i", "volume_l": "f"})
        for part in ("heads", "regions"):
            for name in metric.get(part, {}):
                _series(path, metric[f"{part}/{name}"], "volume_l", "f", length)
        for name in metric.get("heads", {}):  # one per map of the head, not on the volume's times
            _series(path, metric[f"heads/{name}"], "side_distance_mm", "f", None)


def _check_parameters(path: Path, f: h5py.File) -> None:
    for key, value in f["parameters"].attrs.items() if "parameters" in f else ():
        if isinstance(value, (bytes, str)):
            if key == "FEV1_FVC" or key.endswith(("_l", "_lps", "_bpm", "_s", "_pct")):
                raise SessionError(f"{path}: /parameters {key} must be a number, found {value!r}")
            continue
        number = np.asarray(value)
        if number.dtype.kind not in "fiub" or (number.dtype.kind == "f" and np.isinf(number).any()):
            raise SessionError(f"{path}: /parameters {key} must be a finite number, found {value!r}")


def check_results(path: str | os.PathLike) -> None:
    """Refuses a results file that any reader would stumble on (see the module doc)."""
    from core.hdf5_probe import probe

    path = Path(path)
    probe(path)
    try:
        with h5py.File(path, "r") as f:
            if str(f.attrs.get("format", "")) != RESULTS_FORMAT:
                raise SessionError(f"{path} is not a photopft results file (no format = {RESULTS_FORMAT!r})")
            heads = f.get("heads")
            if not isinstance(heads, h5py.Group) or not any(h in heads for h in ("front", "back")):
                raise SessionError(f"{path} is a results file without heads (cut off?): process the session again")
            for name in heads:
                if name not in ("front", "back") or not isinstance(heads[name], h5py.Group):
                    raise SessionError(f"{path}: /heads/{name} is not a head")
                _check_head(path, heads[name])
            _check_volume(path, f)
            _check_parameters(path, f)
            if not isinstance(f.attrs.get("session", ""), str):
                raise SessionError(f"{path}: its session attribute is not a file name")
    except SessionError:
        raise
    except READ_ERRORS as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise SessionError(f"{path} is damaged and cannot be read ({reason}): process the session again") from exc


def is_results_file(path: str | os.PathLike) -> bool:
    """True for an HDF5 file that says it is a results file (whether or not it is whole)."""
    from core.hdf5_probe import probe

    probe(path)
    try:
        with h5py.File(path, "r") as f:
            return str(f.attrs.get("format", "")) == RESULTS_FORMAT
    except READ_ERRORS:
        return False
