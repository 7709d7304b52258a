"""Session files: shared/spec/session-format.md, format version 1.

`SessionWriter` streams frames, flow samples and events into a new file (one writer thread);
`SessionFile` reads any file that follows the spec; `validate_session` lists what is wrong
with a file, naming the item.

Additions to the spec (allowed: "the project may add groups and attributes"), compressed frames
among them, are listed in docs/format-extensions.md.
"""

from __future__ import annotations

import datetime as dt
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import h5py
import hdf5plugin  # noqa: F401  (registers the Blosc filters: frames recorded compressed read like any other)
import numpy as np

from core import __version__
from core.io.errors import SessionError
from core.io.hdf5_probe import probe
from core.io.plausibility import (flow_gaps, flow_refusal, frame_gaps_in_manoeuvres, gaps_in_manoeuvres,
                                  head_intrinsics_problems)
from core.rig import DARK, Head, Rig, light_position_problems

FORMAT = "photopft-session"
FORMAT_VERSION = 1
KINDS = ("patient", "sphere-calibration", "flow-calibration", "simulation")
SOFTWARE = f"photopft {__version__}"
HEAD_NAMES = ("front", "back")
SEXES = ("male", "female")


def now_iso() -> str:
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")


def parse_iso(value: str) -> dt.datetime:
    """An ISO 8601 time with a UTC offset; raises ValueError otherwise."""
    parsed = dt.datetime.fromisoformat(value)
    if parsed.tzinfo is None:
        raise ValueError(f"{value!r} has no UTC offset")
    return parsed


@dataclass(frozen=True)
class SubjectRecord:
    """/subject: pseudonymous; names live in the application's patient records."""

    id: str
    sex: str
    age_years: float
    height_cm: float
    weight_kg: float

    def __post_init__(self) -> None:
        if self.sex not in SEXES:
            raise ValueError(f"subject sex must be one of {SEXES}, got {self.sex!r}")


@dataclass(frozen=True)
class FlowInfo:
    sample_rate_hz: float
    adc_bits: int
    sensor: str
    conditions: str
    gain_lps: float | None
    offset_lps: float | None
    n_samples: int
    attrs: dict[str, Any] = field(default_factory=dict)


def _str(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


# --------------------------------------------------------------------------- writing


def _write_head_attrs(group: h5py.Group, head: Head) -> None:
    group.attrs["width"] = int(head.width)
    group.attrs["height"] = int(head.height)
    for name in ("fx", "fy", "cx", "cy", "pixel_size_mm"):
        group.attrs[name] = float(getattr(head, name))
    group.attrs["dist_coeffs"] = np.asarray(head.dist_coeffs, dtype=np.float64)
    if head.vignetting:
        group.attrs["vignetting"] = float(head.vignetting)
    group.attrs["bit_depth"] = int(head.bit_depth)
    group.attrs["light_positions_mm"] = np.asarray(head.light_positions_mm, dtype=np.float64)
    group.attrs["light_intensity"] = np.asarray(head.light_intensity, dtype=np.float64)
    if head.light_axis is not None:
        group.attrs["light_axis"] = np.asarray(head.light_axis, dtype=np.float64)
    if head.light_mu is not None:
        group.attrs["light_mu"] = np.asarray(head.light_mu, dtype=np.float64)
    # the spec asks a time; lights never calibrated (as built, as drawn) say so in lights_calibrated = 0
    group.attrs["calibrated"] = head.calibrated or now_iso()
    if not head.calibrated:
        group.attrs["lights_calibrated"] = np.int8(0)


def write_rig(parent: h5py.Group, rig: Rig) -> None:
    group = parent.require_group("rig")
    group.attrs["name"] = rig.name
    group.attrs["sequence"] = np.asarray(rig.sequence, dtype=np.int64)
    group.attrs["frame_rate_hz"] = float(rig.frame_rate_hz)
    if rig.baseline_mm is not None:
        group.attrs["head_baseline_mm"] = float(rig.baseline_mm)
    group.attrs["mains_hz"] = float(rig.mains_hz)
    for name, head in rig.heads.items():
        _write_head_attrs(group.require_group(name), head)


# Files whose close failed (a full disk). HDF5 crashes when such a file object is freed, so these
# are kept for the life of the process; `file_write_failed()` tells a command line to leave with
# os._exit, past HDF5's own teardown. The data on disk is what a recovery reads.
_UNCLOSABLE: list[h5py.File] = []


def file_write_failed() -> bool:
    return bool(_UNCLOSABLE)


class _OwnsFile:
    """Closes its HDF5 file once; a context manager."""

    _file: h5py.File

    def close(self) -> None:
        if self._file in _UNCLOSABLE or not self._file.id.valid:
            return
        try:
            self._file.close()
        except (OSError, RuntimeError):
            _UNCLOSABLE.append(self._file)
            raise

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# Lossless filters for the frames, by the name a rig file gives (`[recording] compression`), chosen by
# `photopft bench compression` and `bench record`: Blosc with LZ4 and bit-shuffle halves a recording
# and writes faster than two heads deliver. A program that reads such a file needs the Blosc filter
# (Python: `import hdf5plugin`; other HDF5 programs: HDF5_PLUGIN_PATH set to hdf5plugin's PLUGIN_PATH).
FRAME_COMPRESSION = ("none", "blosc-lz4")


def frame_filter(name: str) -> dict[str, Any]:
    """h5py create_dataset keyword arguments of a FRAME_COMPRESSION name."""
    if name == "none":
        return {}
    if name == "blosc-lz4":
        return dict(hdf5plugin.Blosc(cname="lz4", clevel=5, shuffle=hdf5plugin.Blosc.BITSHUFFLE))
    raise SessionError(f"frame compression must be one of {', '.join(FRAME_COMPRESSION)}, got {name!r}")


class SessionWriter(_OwnsFile):
    """Writes one session file, frame by frame. Use from one thread (h5py serialises every call)."""

    def __init__(self, path: str | os.PathLike, *, kind: str, rig: Rig, subject: SubjectRecord | None = None,
                 created: str | None = None, software: str = SOFTWARE, root_attrs: dict[str, Any] | None = None,
                 compression: str | None = None) -> None:
        """`compression`: a FRAME_COMPRESSION name, or one of HDF5's own filters by h5py's name (gzip, lzf)."""
        if kind not in KINDS:
            raise SessionError(f"kind must be one of {KINDS}, got {kind!r}")
        self.path = Path(path)
        self.rig = rig
        if self.path.exists():
            raise SessionError(f"{self.path} exists: a session file is never replaced (choose another name)")
        try:
            self._file = h5py.File(self.path, "w-", libver="latest")
        except OSError as exc:
            raise SessionError(f"cannot create session file {self.path}: {exc}") from exc
        f = self._file
        f.attrs["format"] = FORMAT
        f.attrs["format_version"] = np.int64(FORMAT_VERSION)
        f.attrs["kind"] = kind
        f.attrs["created"] = created or now_iso()
        f.attrs["software"] = software
        for key, value in (root_attrs or {}).items():
            f.attrs[key] = value
        write_rig(f, rig)
        if subject is not None:
            s = f.create_group("subject")
            s.attrs["id"] = subject.id
            s.attrs["sex"] = subject.sex
            for name in ("age_years", "height_cm", "weight_kg"):
                s.attrs[name] = float(getattr(subject, name))
        self._heads: dict[str, dict[str, h5py.Dataset]] = {}
        filters = frame_filter(compression) if compression in FRAME_COMPRESSION else \
            ({"compression": compression} if compression else {})
        for name, head in rig.heads.items():
            g = f.create_group(f"heads/{name}")
            self._heads[name] = {
                # a Fletcher-32 checksum per frame (one chunk): a byte changed on disk fails the read
                "frames": g.create_dataset("frames", shape=(0, head.height, head.width), dtype=head.frame_dtype,
                                           maxshape=(None, head.height, head.width),
                                           chunks=(1, head.height, head.width), fletcher32=True, **filters),
                "light_index": g.create_dataset("light_index", shape=(0,), dtype=np.int8, maxshape=(None,),
                                                chunks=(4096,)),
                "timestamp_ns": g.create_dataset("timestamp_ns", shape=(0,), dtype=np.int64, maxshape=(None,),
                                                 chunks=(4096,)),
                "frame_id": g.create_dataset("frame_id", shape=(0,), dtype=np.uint64, maxshape=(None,),
                                             chunks=(4096,)),
            }
        events = f.create_group("events")
        self._event_time = events.create_dataset("timestamp_ns", shape=(0,), dtype=np.int64, maxshape=(None,),
                                                 chunks=(256,))
        self._event_label = events.create_dataset("label", shape=(0,), dtype=h5py.string_dtype(),
                                                  maxshape=(None,), chunks=(256,))
        self._flow: dict[str, h5py.Dataset] | None = None

    @staticmethod
    def _append(dataset: h5py.Dataset, values: np.ndarray) -> None:
        n = dataset.shape[0]
        dataset.resize(n + len(values), axis=0)
        dataset[n:] = values

    @staticmethod
    def _append_frames(dataset: h5py.Dataset, frames: np.ndarray) -> None:
        """One frame per chunk and no filter: each frame goes to the file as its chunk, past the chunk
        cache (half the time of a sliced write, and nothing left for the next flush to write)."""
        if dataset.chunks != (1,) + frames.shape[1:] or dataset.id.get_create_plist().get_nfilters():
            SessionWriter._append(dataset, frames)
            return
        n = dataset.shape[0]
        dataset.resize(n + len(frames), axis=0)
        for k, frame in enumerate(frames):
            dataset.id.write_direct_chunk((n + k,) + (0,) * (frames.ndim - 1), np.ascontiguousarray(frame))

    def append_frames(self, head: str, frames: np.ndarray, light_index: Iterable[int],
                      timestamp_ns: Iterable[int], frame_id: Iterable[int]) -> None:
        """Append frames (N, H, W) of one head with their light index, timestamps and frame ids."""
        if head not in self._heads:
            raise SessionError(f"head {head!r} is not in the rig of {self.path}")
        ds = self._heads[head]
        frames = np.asarray(frames)
        if frames.ndim == 2:
            frames = frames[None]
        expected = ds["frames"].shape[1:]
        if frames.shape[1:] != expected:
            raise SessionError(f"head {head!r}: frame shape {frames.shape[1:]} differs from the rig's {expected}")
        light_index = np.atleast_1d(np.asarray(light_index, dtype=np.int8))
        timestamp_ns = np.atleast_1d(np.asarray(timestamp_ns, dtype=np.int64))
        frame_id = np.atleast_1d(np.asarray(frame_id, dtype=np.uint64))
        if not len(frames) == len(light_index) == len(timestamp_ns) == len(frame_id):
            raise SessionError(f"head {head!r}: frames, light_index, timestamp_ns and frame_id differ in length")
        self._append_frames(ds["frames"], frames.astype(ds["frames"].dtype, copy=False))
        self._append(ds["light_index"], light_index)
        self._append(ds["timestamp_ns"], timestamp_ns)
        self._append(ds["frame_id"], frame_id)

    def configure_flow(self, *, sample_rate_hz: float, adc_bits: int, sensor: str, conditions: str = "ATPS",
                       gain_lps: float | None = None, offset_lps: float | None = None,
                       extra_attrs: dict[str, Any] | None = None) -> None:
        if conditions not in ("ATPS", "BTPS"):
            raise SessionError(f"flow conditions must be ATPS or BTPS, got {conditions!r}")
        g = self._file.create_group("flow")
        g.attrs["sample_rate_hz"] = float(sample_rate_hz)
        g.attrs["adc_bits"] = int(adc_bits)
        g.attrs["sensor"] = sensor
        g.attrs["conditions"] = conditions
        if (gain_lps is None) != (offset_lps is None):
            raise SessionError("flow_gain_lps and flow_offset_lps go together")
        if gain_lps is not None:
            g.attrs["flow_gain_lps"] = float(gain_lps)
            g.attrs["flow_offset_lps"] = float(offset_lps)
        for key, value in (extra_attrs or {}).items():
            g.attrs[key] = value
        self._flow = {
            "adc": g.create_dataset("adc", shape=(0,), dtype=np.int32, maxshape=(None,), chunks=(8192,)),
            "timestamp_ns": g.create_dataset("timestamp_ns", shape=(0,), dtype=np.int64, maxshape=(None,),
                                             chunks=(8192,)),
        }

    def append_flow(self, adc: np.ndarray, timestamp_ns: np.ndarray) -> None:
        if self._flow is None:
            raise SessionError("configure_flow() before append_flow()")
        adc = np.atleast_1d(np.asarray(adc, dtype=np.int32))
        timestamp_ns = np.atleast_1d(np.asarray(timestamp_ns, dtype=np.int64))
        if len(adc) != len(timestamp_ns):
            raise SessionError("flow adc and timestamp_ns differ in length")
        self._append(self._flow["adc"], adc)
        self._append(self._flow["timestamp_ns"], timestamp_ns)

    def add_event(self, timestamp_ns: int, label: str) -> None:
        self._append(self._event_time, np.array([timestamp_ns], dtype=np.int64))
        self._append(self._event_label, np.array([label], dtype=object))

    def write_truth(self, timestamp_ns: np.ndarray, volume_l: np.ndarray,
                    heads: dict[str, dict[str, np.ndarray]], extra: dict[str, np.ndarray] | None = None,
                    attrs: dict[str, object] | None = None) -> None:
        """/truth: volume and, per head, true light positions and maps (keys as in the spec);
        `attrs` describe the simulated world (e.g. the body's parameters as JSON)."""
        g = self._file.require_group("truth")
        for key, value in (attrs or {}).items():
            g.attrs[key] = value
        g.create_dataset("timestamp_ns", data=np.asarray(timestamp_ns, dtype=np.int64))
        g.create_dataset("volume_l", data=np.asarray(volume_l, dtype=np.float64))
        for key, value in (extra or {}).items():
            g.create_dataset(key, data=value)
        for name, items in heads.items():
            h = g.require_group(name)
            h.create_dataset("light_positions_mm", data=np.asarray(items["light_positions_mm"], np.float64))
            h.create_dataset("map_frame_index", data=np.asarray(items["map_frame_index"], np.int64))
            shape = items["depth_mm"].shape
            h.create_dataset("normals", data=np.asarray(items["normals"], np.float32),
                             chunks=(1, *shape[1:], 3) if shape[0] else None, compression="gzip")
            h.create_dataset("depth_mm", data=np.asarray(items["depth_mm"], np.float32),
                             chunks=(1, *shape[1:]) if shape[0] else None, compression="gzip")
            for key, value in items.items():
                if key not in ("light_positions_mm", "map_frame_index", "normals", "depth_mm"):
                    h.create_dataset(key, data=value)

    def set_root_attr(self, key: str, value: Any) -> None:
        self._file.attrs[key] = value

    def start_swmr(self) -> None:
        """Single-writer/multiple-reader mode: from here on, appends and flushes keep the file readable
        even if the writer dies (HDF5 SWMR). Every dataset must exist before; attributes are final."""
        self._file.swmr_mode = True

    def flush(self) -> None:
        """Everything written so far handed to the system, and the file's pages that are on disk let
        go from the page cache (the rest at the next flush): a recording is written once and read
        later (27 GB for 10 minutes at half resolution), and kept cached it would push every other
        program's memory out (measured: the page cache held 0.7 GB after a minute of recording at half
        resolution, which wrote 2.7 GB)."""
        self._file.flush()
        if hasattr(os, "posix_fadvise") and self._file.driver == "sec2":
            os.posix_fadvise(self._file.id.get_vfd_handle(), 0, 0, os.POSIX_FADV_DONTNEED)


# --------------------------------------------------------------------------- reading


def read_head(name: str, attrs: h5py.AttributeManager) -> Head:
    optional = {key: np.asarray(attrs[key]) for key in ("light_axis", "light_mu") if key in attrs}
    return Head(
        name=name,
        width=int(attrs["width"]),
        height=int(attrs["height"]),
        fx=float(attrs["fx"]),
        fy=float(attrs["fy"]),
        cx=float(attrs["cx"]),
        cy=float(attrs["cy"]),
        pixel_size_mm=float(attrs["pixel_size_mm"]),
        bit_depth=int(attrs["bit_depth"]),
        light_positions_mm=np.asarray(attrs["light_positions_mm"], dtype=float),
        light_intensity=np.asarray(attrs["light_intensity"], dtype=float),
        dist_coeffs=np.asarray(attrs["dist_coeffs"], dtype=float),
        vignetting=float(attrs.get("vignetting", 0.0)),
        calibrated="" if int(attrs.get("lights_calibrated", 1)) == 0 else _str(attrs.get("calibrated", "")),
        **optional,
    )


def _frame_rate_from_timestamps(f: h5py.File) -> float:
    ts = np.asarray(f["heads/front/timestamp_ns"][:64], dtype=np.int64)
    ids = np.asarray(f["heads/front/frame_id"][:64], dtype=np.int64)
    if len(ts) < 2:
        return 110.0
    period_ns = np.median(np.diff(ts) / np.maximum(np.diff(ids), 1))
    return float(1e9 / period_ns)


def read_rig(f: h5py.File) -> Rig:
    g = f["rig"]
    heads = {name: read_head(name, g[name].attrs) for name in HEAD_NAMES if name in g}
    rate = float(g.attrs["frame_rate_hz"]) if "frame_rate_hz" in g.attrs else _frame_rate_from_timestamps(f)
    sequence = tuple(int(i) for i in np.asarray(g.attrs.get("sequence", [0, 1, 2, 3, -1])))
    baseline = float(g.attrs["head_baseline_mm"]) if "head_baseline_mm" in g.attrs else None
    mains = float(g.attrs["mains_hz"]) if "mains_hz" in g.attrs else Rig.mains_hz
    return Rig(name=_str(g.attrs.get("name", "")), heads=heads, frame_rate_hz=rate, sequence=sequence,
               baseline_mm=baseline, mains_hz=mains)


class SessionFile(_OwnsFile):
    """A session file opened for reading. Frames stay on disk until asked for."""

    def __init__(self, path: str | os.PathLike, *, check: bool = True) -> None:
        self.path = Path(path)
        if check:
            problems = _validated(self.path)
            if problems:
                raise SessionError(f"{self.path} is not a valid session file: " + "; ".join(problems[:5])
                                   + (f" (and {len(problems) - 5} more)" if len(problems) > 5 else ""))
        try:
            self._file = h5py.File(self.path, "r")
        except OSError as exc:
            raise SessionError(f"cannot open {self.path}: {exc}") from exc
        f = self._file
        self.kind = _str(f.attrs["kind"])
        self.created = _str(f.attrs["created"])
        self.software = _str(f.attrs["software"])
        self.attrs = {k: f.attrs[k] for k in f.attrs}
        self.rig = read_rig(f)
        self.subject = None
        if "subject" in f:
            s = f["subject"].attrs
            self.subject = SubjectRecord(_str(s["id"]), _str(s["sex"]), float(s["age_years"]),
                                         float(s["height_cm"]), float(s["weight_kg"]))

    @property
    def heads(self) -> list[str]:
        return list(self.rig.heads)

    def _head(self, head: str) -> h5py.Group:
        if head not in self.rig.heads:
            raise SessionError(f"{self.path} has no head {head!r} (heads: {', '.join(self.heads)})")
        return self._file[f"heads/{head}"]

    def frames(self, head: str) -> h5py.Dataset:
        return self._head(head)["frames"]

    def light_index(self, head: str) -> np.ndarray:
        return np.asarray(self._head(head)["light_index"][:], dtype=np.int8)

    def timestamp_ns(self, head: str) -> np.ndarray:
        return np.asarray(self._head(head)["timestamp_ns"][:], dtype=np.int64)

    def frame_id(self, head: str) -> np.ndarray:
        return np.asarray(self._head(head)["frame_id"][:], dtype=np.uint64)

    def n_frames(self, head: str) -> int:
        return int(self._head(head)["frames"].shape[0])

    def start_ns(self) -> int:
        """The session's time origin: its first camera frame, or its first flow sample where no head
        recorded a frame. A session with neither (a recording stopped before anything arrived) has none."""
        firsts = [int(self._head(h)["timestamp_ns"][0]) for h in self.heads if self.n_frames(h)]
        if not firsts and "flow" in self._file and self._file["flow"]["timestamp_ns"].shape[0]:
            firsts = [int(self._file["flow"]["timestamp_ns"][0])]
        if not firsts:
            raise SessionError(f"{self.path} holds no camera frame and no flow sample: nothing was recorded")
        return min(firsts)

    def frame_span_ns(self) -> tuple[int, int] | None:
        """(first, last) frame time over the heads, None where no head recorded a frame."""
        spans = [self.timestamp_ns(h) for h in self.heads if self.n_frames(h)]
        if not spans:
            return None
        return min(int(t[0]) for t in spans), max(int(t[-1]) for t in spans)

    def lost_frames(self, head: str) -> int:
        ids = self.frame_id(head).astype(np.int64)
        return int(np.sum(np.diff(ids) - 1)) if len(ids) > 1 else 0

    def events(self) -> list[tuple[int, str]]:
        if "events" not in self._file:
            return []
        g = self._file["events"]
        return [(int(t), _str(label)) for t, label in zip(g["timestamp_ns"][:], g["label"][:])]

    @property
    def flow(self) -> FlowInfo | None:
        if "flow" not in self._file:
            return None
        g = self._file["flow"]
        a = g.attrs
        gain = float(a["flow_gain_lps"]) if "flow_gain_lps" in a else None
        offset = float(a["flow_offset_lps"]) if "flow_offset_lps" in a else None
        return FlowInfo(float(a["sample_rate_hz"]), int(a["adc_bits"]), _str(a["sensor"]), _str(a["conditions"]),
                        gain, offset, int(g["adc"].shape[0]), {k: a[k] for k in a})

    def flow_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """(adc counts, timestamp_ns)."""
        if "flow" not in self._file:
            raise SessionError(f"{self.path} has no flow sensor recording (/flow)")
        g = self._file["flow"]
        return np.asarray(g["adc"][:], dtype=np.int32), np.asarray(g["timestamp_ns"][:], dtype=np.int64)

    @property
    def has_truth(self) -> bool:
        return "truth" in self._file

    def truth(self) -> h5py.Group:
        if not self.has_truth:
            raise SessionError(f"{self.path} has no /truth (only simulations carry it)")
        return self._file["truth"]


# --------------------------------------------------------------------------- validation


class _Checker:
    def __init__(self) -> None:
        self.problems: list[str] = []

    def add(self, message: str) -> None:
        self.problems.append(message)

    def attr(self, obj: h5py.HLObject, name: str, kind: str, shape: tuple | None = None,
             choices: tuple | None = None, required: bool = True) -> Any:
        where = f"{obj.name.rstrip('/') or ''}@{name}" if obj.name != "/" else f"/@{name}"
        if name not in obj.attrs:
            if required:
                self.add(f"missing attribute {where}")
            return None
        value = obj.attrs[name]
        if kind == "str":
            if not isinstance(value, (str, bytes)):
                self.add(f"attribute {where} must be a string, found {type(value).__name__}")
                return None
            value = _str(value)
        elif kind in ("int", "float"):
            arr = np.asarray(value)
            ok = np.issubdtype(arr.dtype, np.integer) if kind == "int" else np.issubdtype(arr.dtype, np.number)
            if not ok:
                self.add(f"attribute {where} must be {'an integer' if kind == 'int' else 'a number'}, "
                         f"found {arr.dtype}")
                return None
            if shape is None and arr.ndim != 0 and arr.size != 1:
                self.add(f"attribute {where} must be a single value, found shape {arr.shape}")
                return None
            if shape is not None and arr.shape != shape:
                self.add(f"attribute {where} must have shape {shape}, found {arr.shape}")
                return None
            value = arr if shape is not None else arr.reshape(()).item()
            if not np.all(np.isfinite(arr)):
                self.add(f"attribute {where} holds non-finite values")
                return None
        if choices is not None and value not in choices:
            self.add(f"attribute {where} is {value!r}, must be one of {', '.join(map(str, choices))}")
        return value

    def dataset(self, group: h5py.Group, name: str, dtypes: tuple, ndim: int) -> h5py.Dataset | None:
        where = f"{group.name.rstrip('/')}/{name}"
        if name not in group:
            self.add(f"missing dataset {where}")
            return None
        ds = group[name]
        if not isinstance(ds, h5py.Dataset):
            self.add(f"{where} must be a dataset")
            return None
        if ds.ndim != ndim:
            self.add(f"dataset {where} must have {ndim} dimension(s), found shape {ds.shape}")
            return None
        if dtypes and not any(ds.dtype == np.dtype(d) if not isinstance(d, str) else _dtype_is(ds.dtype, d)
                              for d in dtypes):
            names = ", ".join(d if isinstance(d, str) else np.dtype(d).name for d in dtypes)
            self.add(f"dataset {where} has dtype {ds.dtype}, must be {names}")
            return None
        return ds


def _dtype_is(dtype: np.dtype, name: str) -> bool:
    if name == "str":
        return h5py.check_string_dtype(dtype) is not None
    if name == "int":
        return np.issubdtype(dtype, np.integer)
    if name == "float":
        return np.issubdtype(dtype, np.floating)
    return False


def _read_all(c: _Checker, ds: h5py.Dataset) -> np.ndarray | None:
    try:
        return ds[()]
    except (OSError, ValueError, RuntimeError) as exc:
        c.add(f"dataset {ds.name} cannot be read (truncated or corrupt file?): {exc}")
        return None


def _check_rig(c: _Checker, f: h5py.File) -> dict[str, tuple[int, int, int]]:
    """Checks /rig; returns each head's (height, width, bit_depth)."""
    if "rig" not in f:
        c.add("missing group /rig")
        return {}
    rig = f["rig"]
    c.attr(rig, "name", "str")
    rate = c.attr(rig, "frame_rate_hz", "float", required=False)
    if rate is not None and not 0 < rate <= 10_000:
        c.add(f"attribute /rig@frame_rate_hz must be a positive frame rate, found {rate}")
    baseline = c.attr(rig, "head_baseline_mm", "float", required=False)
    if baseline is not None and not 0 < baseline < 100_000:
        c.add(f"attribute /rig@head_baseline_mm must be a positive distance, found {baseline}")
    mains = c.attr(rig, "mains_hz", "float", required=False)
    if mains is not None and not 40 <= mains <= 70:
        c.add(f"attribute /rig@mains_hz must be a mains frequency (50 or 60 Hz), found {mains}")
    sequence = None
    if "sequence" not in rig.attrs:
        c.add("missing attribute /rig@sequence")
    else:
        seq = np.atleast_1d(np.asarray(rig.attrs["sequence"]))
        if not np.issubdtype(seq.dtype, np.integer) or seq.ndim != 1:
            c.add(f"attribute /rig@sequence must be an int array, found {seq.dtype} {seq.shape}")
        elif sorted(int(i) for i in seq if i != DARK) != [0, 1, 2, 3] or DARK not in seq:
            c.add(f"attribute /rig@sequence {seq.tolist()} must hold lights 0-3 once each and a dark slot (-1)")
        else:
            sequence = seq
    heads: dict[str, tuple[int, int, int]] = {}
    if "front" not in rig:
        c.add("missing group /rig/front")
    for name in rig:
        if name not in HEAD_NAMES:
            c.add(f"unexpected group /rig/{name}: heads are front and back")
    for name in HEAD_NAMES:
        if name not in rig:
            continue
        g = rig[name]
        width = c.attr(g, "width", "int")
        height = c.attr(g, "height", "int")
        for key in ("fx", "fy", "cx", "cy", "pixel_size_mm"):
            value = c.attr(g, key, "float")
            if value is not None and key in ("fx", "fy", "pixel_size_mm") and not value > 0:
                c.add(f"attribute /rig/{name}@{key} must be positive, found {value}")
        c.attr(g, "dist_coeffs", "float", shape=(5,))
        bits = c.attr(g, "bit_depth", "int", choices=(8, 10, 12, 16))
        positions = c.attr(g, "light_positions_mm", "float", shape=(4, 3))
        if positions is not None and np.all(np.isfinite(positions)):
            for problem in light_position_problems(positions):
                c.add(f"attribute /rig/{name}@light_positions_mm: {problem}")
        intensity = c.attr(g, "light_intensity", "float", shape=(4,))
        if intensity is not None and np.any(np.asarray(intensity) <= 0):
            c.add(f"attribute /rig/{name}@light_intensity must be positive, found {np.asarray(intensity).tolist()}")
        c.attr(g, "light_axis", "float", shape=(4, 3), required=False)
        c.attr(g, "light_mu", "float", shape=(4,), required=False)
        vignetting = c.attr(g, "vignetting", "float", required=False)
        if vignetting is not None and not 0.0 <= float(np.asarray(vignetting)) < 0.9:
            c.add(f"attribute /rig/{name}@vignetting must be in [0, 0.9), found {float(np.asarray(vignetting))}")
        calibrated = c.attr(g, "calibrated", "str")
        if calibrated is not None:
            try:
                parse_iso(calibrated)
            except ValueError:
                c.add(f"attribute /rig/{name}@calibrated {calibrated!r} is not ISO 8601 with a UTC offset")
        if width is not None and height is not None and bits is not None:
            if width <= 0 or height <= 0:
                c.add(f"/rig/{name}: sensor size {width} x {height} must be positive")
            else:
                heads[name] = (int(height), int(width), int(bits))
    c.rig_sequence = sequence
    return heads


FRAMES_READ_AT_ONCE = 32


def _check_frame_checksums(c: _Checker, frames: h5py.Dataset, head: str) -> None:
    """Every frame read once, so that each chunk's Fletcher-32 checksum is checked: the first frame
    that fails is named (a file written before frames carried checksums is read for nothing)."""
    if not frames.fletcher32:
        return
    for start in range(0, frames.shape[0], FRAMES_READ_AT_ONCE):
        stop = min(start + FRAMES_READ_AT_ONCE, frames.shape[0])
        try:
            frames[start:stop]
        except (OSError, RuntimeError):
            for k in range(start, stop):
                try:
                    frames[k]
                except (OSError, RuntimeError):
                    c.add(f"dataset /heads/{head}/frames: frame {k} fails its checksum (its bytes changed "
                          f"on disk after it was recorded)")
                    return


def _check_heads(c: _Checker, f: h5py.File, heads: dict[str, tuple[int, int, int]]) -> None:
    if "heads" not in f:
        c.add("missing group /heads")
        return
    for name in f["heads"]:
        if name not in heads and name in HEAD_NAMES and "rig" in f and name not in f["rig"]:
            c.add(f"/heads/{name} has no matching /rig/{name}")
        elif name not in HEAD_NAMES:
            c.add(f"unexpected group /heads/{name}: heads are front and back")
    sequence = getattr(c, "rig_sequence", None)
    for name, (height, width, bits) in heads.items():
        if name not in f["heads"]:
            c.add(f"missing group /heads/{name} (the rig has a {name} head)")
            continue
        g = f["heads"][name]
        frames = c.dataset(g, "frames", (np.uint8, np.uint16), 3)
        light = c.dataset(g, "light_index", (np.int8,), 1)
        ts = c.dataset(g, "timestamp_ns", (np.int64,), 1)
        ids = c.dataset(g, "frame_id", (np.uint64,), 1)
        if frames is not None:
            if frames.shape[1:] != (height, width):
                c.add(f"dataset /heads/{name}/frames has frames of {frames.shape[1]} x {frames.shape[2]} "
                      f"(rows x columns), the rig says {height} x {width}")
            if bits > 8 and frames.dtype == np.uint8:
                c.add(f"dataset /heads/{name}/frames is uint8 but /rig/{name}@bit_depth is {bits}")
            if frames.shape[0] > 0:
                try:
                    frames[frames.shape[0] - 1]
                    frames[0]
                except (OSError, ValueError, RuntimeError) as exc:
                    c.add(f"dataset /heads/{name}/frames cannot be read to the end (truncated or corrupt "
                          f"file?): {exc}")
                else:
                    _check_frame_checksums(c, frames, name)
        lengths = {d.name.rsplit("/", 1)[1]: d.shape[0] for d in (frames, light, ts, ids) if d is not None}
        if len(set(lengths.values())) > 1:
            c.add(f"/heads/{name}: datasets differ in length: "
                  + ", ".join(f"{k} {v}" for k, v in lengths.items()))
            continue
        li = _read_all(c, light) if light is not None else None
        if li is not None and len(li) and (li.min() < -1 or li.max() > 3):
            c.add(f"dataset /heads/{name}/light_index holds values outside -1..3")
        t = _read_all(c, ts) if ts is not None else None
        if t is not None and len(t) > 1 and np.any(np.diff(t) <= 0):
            c.add(f"dataset /heads/{name}/timestamp_ns is not strictly increasing")
        fid = _read_all(c, ids) if ids is not None else None
        if fid is not None and len(fid) > 1 and np.any(np.diff(fid.astype(np.int64)) <= 0):
            c.add(f"dataset /heads/{name}/frame_id is not strictly increasing")
        if li is not None and fid is not None and sequence is not None and len(li) >= len(sequence):
            _check_light_cycle(c, name, li, fid, sequence)


def _check_light_cycle(c: _Checker, head: str, light_index: np.ndarray, frame_id: np.ndarray,
                       sequence: np.ndarray) -> None:
    """light_index must follow /rig@sequence along frame_id (a lost frame is a gap, not a shift)."""
    n = len(sequence)
    ids = frame_id.astype(np.int64)
    for phase in range(n):
        if np.array_equal(sequence[(ids + phase) % n], light_index):
            return
    c.add(f"dataset /heads/{head}/light_index does not follow /rig@sequence {sequence.tolist()} along frame_id")


def _check_flow(c: _Checker, f: h5py.File) -> None:
    if "flow" not in f:
        return
    g = f["flow"]
    adc = c.dataset(g, "adc", (np.int32,), 1)
    ts = c.dataset(g, "timestamp_ns", (np.int64,), 1)
    if adc is not None and ts is not None and adc.shape != ts.shape:
        c.add(f"/flow: adc has {adc.shape[0]} samples, timestamp_ns {ts.shape[0]}")
    rate = c.attr(g, "sample_rate_hz", "float")
    if rate is not None and not rate > 0:
        c.add(f"attribute /flow@sample_rate_hz must be positive, found {rate}")
    c.attr(g, "adc_bits", "int")
    c.attr(g, "sensor", "str")
    c.attr(g, "conditions", "str", choices=("ATPS", "BTPS"))
    gain = c.attr(g, "flow_gain_lps", "float", required=False)
    offset = c.attr(g, "flow_offset_lps", "float", required=False)
    if (gain is None) != (offset is None):
        c.add("/flow: flow_gain_lps and flow_offset_lps must be both present or both absent")
    if ts is not None and ts.shape[0] > 1:
        t = _read_all(c, ts)
        if t is not None and np.any(np.diff(t) <= 0):
            c.add("dataset /flow/timestamp_ns is not strictly increasing")


def _check_subject(c: _Checker, f: h5py.File, kind: str | None) -> None:
    if "subject" not in f:
        if kind in ("patient", "simulation"):
            c.add(f"missing group /subject (required in a {kind} session)")
        return
    s = f["subject"]
    c.attr(s, "id", "str")
    c.attr(s, "sex", "str", choices=SEXES)
    for name, lo, hi in (("age_years", 0, 130), ("height_cm", 30, 260), ("weight_kg", 1, 400)):
        value = c.attr(s, name, "float")
        if value is not None and not lo <= value <= hi:
            c.add(f"attribute /subject@{name} = {value} is outside {lo}-{hi}")


def _check_events(c: _Checker, f: h5py.File, kind: str | None) -> None:
    if "events" not in f:
        c.add("missing group /events")
        return
    g = f["events"]
    ts = c.dataset(g, "timestamp_ns", (np.int64,), 1)
    labels = c.dataset(g, "label", ("str",), 1)
    if ts is not None and labels is not None:
        if ts.shape != labels.shape:
            c.add(f"/events: timestamp_ns has {ts.shape[0]} entries, label {labels.shape[0]}")
        elif kind == "sphere-calibration":
            values = [_str(v) for v in labels[()]]
            if "placement" not in values:
                c.add("/events has no 'placement' event (required in a sphere-calibration session)")


def _check_truth(c: _Checker, f: h5py.File, heads: dict[str, tuple[int, int, int]]) -> None:
    if "truth" not in f:
        return
    g = f["truth"]
    ts = c.dataset(g, "timestamp_ns", (np.int64,), 1)
    vol = c.dataset(g, "volume_l", (np.float64,), 1)
    if ts is not None and vol is not None and ts.shape != vol.shape:
        c.add(f"/truth: timestamp_ns has {ts.shape[0]} samples, volume_l {vol.shape[0]}")
    for name, (height, width, _) in heads.items():
        if name not in g:
            continue
        h = g[name]
        lp = c.dataset(h, "light_positions_mm", ("float",), 2)
        if lp is not None and lp.shape != (4, 3):
            c.add(f"dataset /truth/{name}/light_positions_mm must be 4 x 3, found {lp.shape}")
        idx = c.dataset(h, "map_frame_index", ("int",), 1)
        normals = c.dataset(h, "normals", (np.float32,), 4)
        depth = c.dataset(h, "depth_mm", (np.float32,), 3)
        k = idx.shape[0] if idx is not None else None
        if normals is not None and normals.shape[1:] != (height, width, 3):
            c.add(f"dataset /truth/{name}/normals must be (K, {height}, {width}, 3), found {normals.shape}")
        if depth is not None and depth.shape[1:] != (height, width):
            c.add(f"dataset /truth/{name}/depth_mm must be (K, {height}, {width}), found {depth.shape}")
        for ds in (normals, depth):
            if ds is not None and k is not None and ds.shape[0] != k:
                c.add(f"dataset {ds.name} holds {ds.shape[0]} maps, map_frame_index {k}")


def session_plausibility(path: str | os.PathLike) -> list[str]:
    """What in a session that follows the format no instrument could have recorded (core/io/plausibility.py):
    each problem refuses the values it touches, not the session. Call on a file validate_session passes."""
    problems = []
    with SessionFile(path, check=False) as s:
        for name, head in s.rig.heads.items():
            problems += [f"/rig/{name}: {p} (no optical value)" for p in head_intrinsics_problems(head)]
        if any(s.n_frames(h) for h in s.heads):
            times = {h: s.timestamp_ns(h) for h in s.heads if s.n_frames(h)}
            problems += [f"/heads: {g.reason} (its optical values refused)"
                         for g in frame_gaps_in_manoeuvres(times, s.events(), s.start_ns())]
        if s.flow is not None and s.flow.n_samples:
            adc, stamps = s.flow_samples()
            refused = flow_refusal(adc, stamps, s.flow.adc_bits, s.flow.sample_rate_hz, s.flow.gain_lps,
                                   s.flow.offset_lps, s.frame_span_ns())
            if refused:
                problems.append(f"/flow: {refused} (no flow sensor value)")
            else:
                problems += [f"/flow: {g.reason} (its values refused)"
                             for g in gaps_in_manoeuvres(flow_gaps(stamps), s.events(), s.start_ns())]
    return problems


# files this process found valid, by (path, size, modification time): a session opened again by the same
# command (analysis, report, review) is not read through a second time for its checksums
_VALID: dict[tuple[str, int, int], bool] = {}
_VALID_KEPT = 64


def _validated(path: Path) -> list[str]:
    """validate_session, once for each version of a file in this process."""
    try:
        status = path.stat()
        key = (str(path.resolve()), status.st_size, status.st_mtime_ns)
    except OSError:
        return validate_session(path)
    if key in _VALID:
        return []
    problems = validate_session(path)
    if not problems:
        if len(_VALID) >= _VALID_KEPT:
            _VALID.pop(next(iter(_VALID)))
        _VALID[key] = True
    return problems


def validate_session(path: str | os.PathLike) -> list[str]:
    """Every way the file departs from the spec, each naming the item; empty when it conforms."""
    path = Path(path)
    if not path.exists():
        return [f"{path}: no such file"]
    probe(path)
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        if "already open for write" in str(exc):
            return [f"{path} was being recorded and was never closed (the recorder stopped or the machine "
                    f"crashed): recover it with `photopft recover {path}`"]
        return [f"{path} cannot be opened as HDF5 (truncated, corrupt or not a session file): {exc}"]
    c = _Checker()
    try:
        with f:
            fmt = c.attr(f, "format", "str")
            if fmt is not None and fmt != FORMAT:
                c.add(f"attribute /@format is {fmt!r}, must be {FORMAT!r}")
                return c.problems
            version = c.attr(f, "format_version", "int")
            if version is not None and version != FORMAT_VERSION:
                c.add(f"attribute /@format_version is {version}, this reader knows version {FORMAT_VERSION}")
            kind = c.attr(f, "kind", "str", choices=KINDS)
            created = c.attr(f, "created", "str")
            if created is not None:
                try:
                    parse_iso(created)
                except ValueError:
                    c.add(f"attribute /@created {created!r} is not ISO 8601 with a UTC offset")
            c.attr(f, "software", "str")
            if kind == "sphere-calibration":
                radius = c.attr(f, "sphere_radius_mm", "float")
                if radius is not None and not radius > 0:
                    c.add(f"attribute /@sphere_radius_mm must be positive, found {radius}")
                c.attr(f, "sphere_finish", "str", choices=("specular", "matte"))
            heads = _check_rig(c, f)
            _check_heads(c, f, heads)
            _check_flow(c, f)
            _check_subject(c, f, kind)
            _check_events(c, f, kind)
            _check_truth(c, f, heads)
    except (OSError, RuntimeError, KeyError) as exc:
        c.add(f"{path} could not be read to the end (truncated or corrupt?): {exc}")
    return c.problems
