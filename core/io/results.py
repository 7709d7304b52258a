"""Reading a results file (written by core.pipeline.process): the one reader every part of the program
goes through (`ResultsFile`, `optical_volume`, `optical_refusal`, `session_of_results`).

`check_results` reads every part once and refuses, in one line naming the file and the part,
anything the readers could not use: an unreadable or missing dataset, a series of the wrong type or
length, an infinite value, a parameter that should be a number and is not. The layout is in
shared/spec/session-format.md and docs/format-extensions.md.
"""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from core.io.hdf5_probe import probe
from core.io.session import SessionError
from core.limits import Refusal

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
    if "peak_flow_volume" in f:
        _group_of_series(path, f["peak_flow_volume"], {"timestamp_ns": "i", "volume_l": "f"})
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
    probe(path)
    try:
        with h5py.File(path, "r") as f:
            return str(f.attrs.get("format", "")) == RESULTS_FORMAT
    except READ_ERRORS:
        return False


# The figures `process` stores with the metric volume for its refusal (MetricVolume.refusal)


class ResultsFile:
    """An open results file, read by name rather than by HDF5 path."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._f = h5py.File(self.path, "r")

    def __enter__(self) -> ResultsFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._f.close()

    @property
    def heads(self) -> list[str]:
        return [h for h in ("front", "back") if h in self._f.get("heads", {})]

    @property
    def session_name(self) -> str:
        return str(self._f.attrs.get("session", ""))

    def series(self, head: str, name: str) -> np.ndarray:
        """A head's per-map series (timestamp_ns, distance_mm, gradient_volume, valid_pixels, ...)."""
        return self._f[f"heads/{head}/{name}"][:]

    def has_series(self, head: str, name: str) -> bool:
        return f"heads/{head}/{name}" in self._f

    def light_gain(self, head: str) -> tuple[np.ndarray, np.ndarray] | None:
        """(timestamp_ns, followed (n, 4)): the factors of the lights' intensities `process` followed the
        LEDs' drift with (ResultsWriter.light_gain), or None where it did not."""
        g = self._f.get(f"heads/{head}/light_gain")
        return None if g is None else (g["timestamp_ns"][:], g["followed"][:])

    def peak_flow_volume(self) -> tuple[np.ndarray, np.ndarray] | None:
        """/peak_flow_volume as (timestamp_ns, litres): the volume at every frame through each forced blow's
        peak flow (ResultsWriter.peak_flow_volume), or None where `process` made none."""
        g = self._f.get("peak_flow_volume")
        return None if g is None else (g["timestamp_ns"][:], g["volume_l"][:].astype(float))

    def volume(self) -> tuple[np.ndarray, np.ndarray] | None:
        """/volume as (timestamp_ns, litres), or None if there is none."""
        f = self._f
        return (f["volume/timestamp_ns"][:], f["volume/volume_l"][:].astype(float)) if "volume" in f else None

    def volume_attrs(self) -> dict:
        return dict(self._f["volume"].attrs) if "volume" in self._f else {}

    def metric_volume(self) -> tuple[np.ndarray, np.ndarray] | None:
        f = self._f
        return ((f["metric_volume/timestamp_ns"][:], f["metric_volume/volume_l"][:].astype(float))
                if "metric_volume" in f else None)

    def head_regions(self) -> dict[str, dict[str, np.ndarray]]:
        """Each head's trunk quadrants on the metric volume's times, {head: {region: litres}}; {} without."""
        heads = self._f.get("metric_volume/heads", {})
        return {name: {region: heads[f"{name}/regions/{region}/volume_l"][:].astype(float)
                       for region in heads[f"{name}/regions"]}
                for name in heads if "regions" in heads[name]}

    def displacement_sums(self) -> dict[str, dict[str, np.ndarray]]:
        """/displacement_sums: {head: {dataset: array, "parts": names}}; {} in files processed before it."""
        out = {}
        for head, g in self._f.get("displacement_sums", {}).items():
            out[head] = {key: g[key][:] for key in g}
            out[head]["parts"] = [str(p) for p in g.attrs["parts"]]
        return out

    @property
    def optical_refused(self) -> str | None:
        reason = self._f.attrs.get("optical_refused")
        return None if reason is None else str(reason)

    @property
    def optical_refused_code(self) -> str | None:
        """The rule that refused the optical volume (core/pipeline/quality.py), or None: files processed
        before 2026-12-05 carry the words only."""
        code = self._f.attrs.get("optical_refused_code")
        return None if code is None else str(code)

    @property
    def distance_refused(self) -> str | None:
        """Why the subject distance is not given (its maps are scaled to one all the same), or None."""
        reason = self._f.attrs.get("distance_refused")
        return None if reason is None else str(reason)

    def optical_label(self) -> str | None:
        """What /volume's litres are: "optical, calibrated on the subject (residual N mL)" or "optical
        estimate, not calibrated (±N %)" (core/analysis/optical_litres.py); None without a label."""
        label = self.volume_attrs().get("label")
        return label if isinstance(label, str) else None  # a damaged label is no label

    def subject_calibration(self) -> dict:
        """/subject_calibration's attributes (ResultsWriter.subject_calibration), {} without one."""
        g = self._f.get("subject_calibration")
        return {} if g is None else dict(g.attrs)

    def parameters(self) -> dict:
        """The stored pulmonary function values (/parameters), with their `source`."""
        return dict(self._f["parameters"].attrs) if "parameters" in self._f else {}

    def stored_values(self) -> dict[str, dict]:
        """The values `process` stored, by source: "flow sensor" (/parameters, where that was its
        source) and "optical" (/volume's parameter_* attributes)."""
        out: dict[str, dict] = {}
        stored = self.parameters()
        if stored.get("source") == "flow sensor":
            out["flow sensor"] = {k: v for k, v in stored.items() if k != "source"}
        optical = {k.removeprefix("parameter_"): v for k, v in self.volume_attrs().items() if k.startswith("parameter_")}
        if optical:
            out["optical"] = optical
        return out


def optical_volume(results: str | os.PathLike) -> tuple[np.ndarray, np.ndarray] | None:
    """A results file's /volume as (timestamp_ns, litres), or None if it has none."""
    with ResultsFile(results) as r:
        return r.volume()


def optical_inputs(results: str | os.PathLike | None) -> dict:
    """What a results file gives the session's analysis (core.analysis.session_analysis.analyse_session's
    optical_volume, optical_label and optical_peak_flow), as its keywords; none for no results file."""
    if results is None:
        return {}
    with ResultsFile(results) as r:
        return {"optical_volume": r.volume(), "optical_label": r.optical_label(),
                "optical_peak_flow": r.peak_flow_volume()}


def optical_refusal(results: str | os.PathLike) -> str | None:
    """Why a results file holds no optical volume, when `process` refused one."""
    with ResultsFile(results) as r:
        return r.optical_refused


def session_of_results(results: str | os.PathLike) -> Path:
    """The session file a results file was made from: where it was, or beside the results file."""
    results = Path(results)
    with ResultsFile(results) as r:
        named = Path(r.session_name)
    for candidate in (named, results.parent / named.name):
        if candidate.name and candidate.exists():
            return candidate
    raise SessionError(f"{results}: its session file {named} is not there (nor beside the results file)")


def from_first(volume_l: np.ndarray) -> np.ndarray:
    """A volume from its first sample with a value (NaN where a map was left out stays NaN)."""
    volume_l = np.asarray(volume_l, dtype=np.float64)
    finite = np.flatnonzero(np.isfinite(volume_l))
    return volume_l - volume_l[finite[0]] if len(finite) else volume_l


class ResultsWriter:
    """Writes a results file's parts into an open HDF5 file (the caller makes it atomic): plain
    arrays and values in, the layout of shared/spec/session-format.md and docs/format-extensions.md out."""

    def __init__(self, out: h5py.File, session_path: str | os.PathLike, software: str, **attrs) -> None:
        self.out = out
        out.attrs["format"] = RESULTS_FORMAT
        out.attrs["format_version"] = np.int64(1)
        out.attrs["session"] = str(session_path)
        out.attrs["software"] = software
        for key, value in attrs.items():
            out.attrs[key] = value

    def attr(self, key: str, value) -> None:
        self.out.attrs[key] = value

    def refuse(self, what: str, refusal: Refusal) -> None:
        """Why `what` ("optical": the optical volume; "distance": the subject distance; "flow": the flow sensor's values) is not given:
        /@<what>_refused in words (what was measured, then what to do), /@<what>_refused_code the rule."""
        self.out.attrs[f"{what}_refused"] = str(refusal)
        self.out.attrs[f"{what}_refused_code"] = refusal.code

    def photometric_survey(self, head: str, timestamp_ns: np.ndarray, distance_mm: np.ndarray,
                           geometric_distance_mm: np.ndarray, offset_mm: float | None) -> None:
        g = self.out.create_group(f"heads/{head}/photometric_survey")
        g.create_dataset("timestamp_ns", data=timestamp_ns)
        g.create_dataset("distance_mm", data=distance_mm)
        g.create_dataset("geometric_distance_mm", data=geometric_distance_mm)
        if offset_mm is not None:
            g.attrs["photometric_offset_mm"] = offset_mm

    def light_gain(self, head: str, timestamp_ns: np.ndarray, measured: np.ndarray, followed: np.ndarray) -> None:
        """/heads/<head>/light_gain: each light's output against the calibration's intensities as read from the
        four lights' redundancy on the survey's cycles (measured, NaN where not read) and as followed through
        the session (followed: smoothed, 1 at the session's median; the factors the maps were solved with);
        its attribute `largest_change` the largest range of a light's followed factor."""
        g = self.out.require_group(f"heads/{head}").create_group("light_gain")
        g.create_dataset("timestamp_ns", data=np.asarray(timestamp_ns, dtype=np.int64))
        g.create_dataset("measured", data=np.asarray(measured, dtype=np.float64))
        g.create_dataset("followed", data=np.asarray(followed, dtype=np.float64))
        g.attrs["largest_change"] = float(np.max(np.ptp(followed, axis=0))) if len(followed) else 0.0

    def peak_flow_volume(self, timestamp_ns: np.ndarray, volume_l: np.ndarray, spans_ns: list[tuple[int, int]],
                         maps: dict[str, int]) -> None:
        """/peak_flow_volume: the metric volume at every frame (the first head's) through each forced blow's
        peak flow (its attribute `spans_ns`, (start, end) pairs), on the same reference maps and levels as
        /metric_volume, a few mL off it at most (the session's level fitted with its maps too);
        `maps_<head>` the maps made for it beside the session's."""
        g = self.out.create_group("peak_flow_volume")
        g.create_dataset("timestamp_ns", data=np.asarray(timestamp_ns, dtype=np.int64))
        g.create_dataset("volume_l", data=np.asarray(volume_l, dtype=np.float64))
        g.attrs["spans_ns"] = np.asarray(spans_ns, dtype=np.int64).reshape(-1, 2)
        for name, count in maps.items():
            g.attrs[f"maps_{name}"] = np.int64(count)

    def head(self, head: str, series: dict[str, np.ndarray], attrs: dict, map_index: list[int],
             normals: list[np.ndarray], depth_mm: list[np.ndarray], shape: tuple[int, int]) -> None:
        """A head's per-map series (HEAD_SERIES and the shares), its attributes, and the full maps
        kept (normals and depth, every pixel)."""
        g = self.out.require_group(f"heads/{head}")
        for name, values in series.items():
            g.create_dataset(name, data=values)
        for key, value in attrs.items():
            g.attrs[key] = value
        m = g.create_group("maps")
        m.create_dataset("frame_index", data=np.asarray(map_index, dtype=np.int64))
        empty = (0, *shape)
        m.create_dataset("normals", data=np.stack(normals) if normals else np.zeros(empty + (3,), np.float32),
                         compression="gzip")
        m.create_dataset("depth_mm", data=np.stack(depth_mm) if depth_mm else np.zeros(empty, np.float32),
                         compression="gzip")

    def subject_calibration(self, calibration, not_calibrated: str | None) -> None:
        """/subject_calibration: the subject's calibration through the flow sensor
        (core/volume/subject_calibration.py, SubjectCalibration) with its gains, residual, expected error
        and, where refused, why; or only `not_calibrated`, why there is none."""
        g = self.out.create_group("subject_calibration")
        if not_calibrated:
            g.attrs["not_calibrated"] = not_calibrated
        if calibration is None:
            return
        g.attrs["segment_s"] = np.asarray(calibration.segment_s, dtype=float)
        g.attrs["residual_l"] = calibration.residual_l
        g.attrs["range_l"] = calibration.range_l
        g.attrs["expected_error"] = calibration.expected_error
        g.attrs["maps"] = np.int64(calibration.samples)
        g.attrs["signals"] = list(calibration.gains)
        g.attrs["gains"] = np.array(list(calibration.gains.values()), dtype=float)
        g.attrs["curvature_per_l"] = float(calibration.curvature_per_l)
        g.attrs["grouping"] = str(calibration.extra.get("grouping", ""))
        if calibration.refused:
            g.attrs["refused"] = str(calibration.refused)
            g.attrs["refused_code"] = calibration.refused.code

    def volume(self, timestamp_ns: np.ndarray, volume_l: np.ndarray, method: str, **attrs) -> None:
        """/volume: the optical volume in litres, from its first sample, and how it was made."""
        g = self.out.create_group("volume")
        g.create_dataset("timestamp_ns", data=np.asarray(timestamp_ns, dtype=np.int64))
        g.create_dataset("volume_l", data=from_first(volume_l))
        g.attrs["method"] = method
        for key, value in attrs.items():
            g.attrs[key] = value

    def has_volume(self) -> bool:
        return "volume" in self.out

    def written_volume(self) -> tuple[np.ndarray, np.ndarray] | None:
        return (self.out["volume/timestamp_ns"][:], self.out["volume/volume_l"][:]) if "volume" in self.out else None

    def written_peak_flow_volume(self) -> tuple[np.ndarray, np.ndarray] | None:
        g = self.out.get("peak_flow_volume")
        return None if g is None else (g["timestamp_ns"][:], g["volume_l"][:])

    def volume_parameters(self, values: dict) -> None:
        """The optical values beside the flow sensor's, as /volume's attributes parameter_*."""
        for key, value in values.items():
            self.out["volume"].attrs[f"parameter_{key}"] = value

    def metric_volume(self, timestamp_ns: np.ndarray, volume_l: np.ndarray, scale_from: str,
                      heads: dict[str, np.ndarray], side_distance_mm: dict[str, np.ndarray],
                      regions: dict[str, np.ndarray], attrs: dict,
                      head_regions: dict[str, dict[str, np.ndarray]] | None = None) -> None:
        """/metric_volume: the metric volume in total, per head and per trunk quadrant (each from its
        first sample), the distance each head's sides were scaled to, and `attrs` (compartments)."""
        g = self.out.create_group("metric_volume")
        g.attrs["scale_from"] = scale_from
        for key, value in attrs.items():
            g.attrs[key] = value
        g.create_dataset("timestamp_ns", data=np.asarray(timestamp_ns, dtype=np.int64))
        g.create_dataset("volume_l", data=from_first(volume_l))
        for name, values in heads.items():
            g.create_dataset(f"heads/{name}/volume_l", data=from_first(values))
            g.create_dataset(f"heads/{name}/side_distance_mm", data=side_distance_mm[name])
        for name, values in regions.items():
            g.create_dataset(f"regions/{name}/volume_l", data=from_first(values))
        for name, quadrants in (head_regions or {}).items():
            for region, values in quadrants.items():
                g.create_dataset(f"heads/{name}/regions/{region}/volume_l", data=from_first(values))

    def displacement_sums(self, head: str, timestamp_ns: np.ndarray, sums: list, side_target_mm: np.ndarray,
                          shown: np.ndarray, parts: tuple[str, ...]) -> None:
        """/displacement_sums/<head>: each map's footprint-weighted sums against its head's reference map
        (core/volume/maps.py, DisplacementSums) as they came from the maps, before any level, scale or
        gap is chosen, so another optical signal can be made from a results file without the maps:
        per part (`parts`, the attribute) `reference`, `current`, `areas`, `displaced` (maps x parts,
        mm^3 or mm^2); `levels_mm` (reference's, map's), `body_shift_mm`, `side_mm`, `width_px`,
        `width_ratio`, `neck_mm`; `side_target_mm`, the distance the sides were scaled to; `shown`, whether
        the map entered the volume."""
        g = self.out.create_group(f"displacement_sums/{head}")
        g.attrs["parts"] = list(parts)
        g.create_dataset("timestamp_ns", data=np.asarray(timestamp_ns, dtype=np.int64))
        for key in ("reference", "current", "areas", "displaced"):
            g.create_dataset(key, data=np.array([[getattr(s, key).get(p, np.nan) for p in parts] for s in sums],
                                                dtype=float).reshape(len(sums), len(parts)))
        for key in ("levels_mm", "body_shift_mm"):
            g.create_dataset(key, data=np.array([getattr(s, key) for s in sums], dtype=float).reshape(len(sums), 2))
        for key in ("side_mm", "width_px", "width_ratio", "neck_mm"):
            g.create_dataset(key, data=np.array([getattr(s, key) for s in sums], dtype=float))
        g.create_dataset("side_target_mm", data=np.asarray(side_target_mm, dtype=float))
        g.create_dataset("shown", data=np.asarray(shown, dtype=bool))

    def parameters(self, source: str, values: dict, flow_curve: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """/parameters: the pulmonary function values and their `source`; with the flow sensor's
        curve, /flow_sensor too."""
        g = self.out.create_group("parameters")
        g.attrs["source"] = source
        for key, value in values.items():
            g.attrs[key] = value
        if flow_curve is not None:
            f = self.out.create_group("flow_sensor")
            f.create_dataset("time_s", data=flow_curve[0])
            f.create_dataset("volume_l", data=flow_curve[1])


def processed_distance_mm(results_path: str | os.PathLike, head_name: str, frame_indices: list[int]) -> list[float]:
    """The subject's distance `process` reconstructed a head's maps at (from the two heads' geometry
    where it had both), at the given frames: interpolated between its maps; NaN where it has none."""
    with ResultsFile(results_path) as r:
        if head_name not in r.heads or not (r.has_series(head_name, "frame_index")
                                            and r.has_series(head_name, "distance_mm")):
            return [float("nan")] * len(frame_indices)
        frames = r.series(head_name, "frame_index").astype(float)
        distance = r.series(head_name, "distance_mm").astype(float)
    good = np.isfinite(distance)
    if not good.any():
        return [float("nan")] * len(frame_indices)
    return [float(d) for d in np.interp(np.asarray(frame_indices, dtype=float), frames[good], distance[good])]


def processed_light_gains(results_path: str | os.PathLike, head_name: str, timestamp_ns: np.ndarray) -> np.ndarray | None:
    """(len(timestamp_ns), 4) the lights' outputs `process` solved a head's maps with at those instants
    (interpolated between its readings, held beyond them), or None where it did not follow them."""
    with ResultsFile(results_path) as r:
        followed = r.light_gain(head_name)
    if followed is None or not len(followed[0]):
        return None
    t, gains = followed[0].astype(float), followed[1]
    at = np.asarray(timestamp_ns, dtype=float)
    return np.stack([np.interp(at, t, gains[:, k]) for k in range(gains.shape[1])], axis=1)
