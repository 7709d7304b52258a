"""Rig configurations (TOML): which camera, sequencer and flow sensor each part of the rig is.

A device is "sim" (the simulated rig), "emulator" (serial emulators on pseudo-terminals) or
real (a camera's id, serial number or address; a serial port's path).
"""

from __future__ import annotations

import difflib
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.io.session import FRAME_COMPRESSION
from core.rig import Head, thesis_head
from drivers.camera import CameraSettings

RIGS = Path(__file__).resolve().parents[1] / "resources" / "rigs"
DEFAULT_RIG = RIGS / "simulated.toml"


class RigConfigError(ValueError):
    """A rig configuration that cannot be used; the message names the file and the field."""


_OPTICS_KEYS = ("focal_length_mm", "pixel_size_um", "fx_px", "fy_px", "cx_px", "cy_px", "dist_coeffs")
KNOWN_KEYS: dict[str, tuple[str, ...]] = {
    "": ("name", "mains_hz", "camera", "heads", "sequencer", "flowsensor", "simulation", "calibration", "recording"),
    "camera": ("width", "height", "offset_x", "offset_y", "binning", "pixel_format", "exposure_us", "frame_rate_hz",
               "trigger"),
    "heads": ("front", "back"),
    "heads.front": ("camera",) + _OPTICS_KEYS,
    "heads.back": ("camera",) + _OPTICS_KEYS,
    "sequencer": ("port",),
    "flowsensor": ("port", "gain_lps", "offset_lps"),
    "simulation": ("scale", "seed", "protocol"),
    "recording": ("compression",),
}
_TABLES = ("camera", "heads", "heads.front", "heads.back", "sequencer", "flowsensor", "simulation", "recording")


def _check_keys(path: Path, data: dict, table: str = "") -> None:
    """Every key known, every table a table: a misspelt key is refused with the nearest valid one,
    never silently ignored."""
    known = KNOWN_KEYS[table]
    for key, value in data.items():
        where = f"[{table}] " if table else ""
        if key not in known and table == "heads":
            raise RigConfigError(f"{path}: unknown head [heads.{key}]: heads are front and back")
        if key not in known:
            near = difflib.get_close_matches(key, known, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else f"; known keys: {', '.join(known)}"
            raise RigConfigError(f"{path}: {where}unknown key {key!r}{hint}")
        inner = f"{table}.{key}" if table else key
        if inner in _TABLES:
            if not isinstance(value, dict):
                raise RigConfigError(f"{path}: {inner} must be a table ([{inner}]), found {value!r}")
            _check_keys(path, value, inner)


def _number(path: Path, table: str, key: str, value: Any, low: float, high: float, integer: bool = False) -> None:
    kind = int if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kind) or not low <= value <= high:
        raise RigConfigError(f"{path}: [{table}] {key} must be {'a whole number' if integer else 'a number'} "
                             f"from {low:g} to {high:g}, found {value!r}")


@dataclass(frozen=True)
class RigConfig:
    path: Path
    name: str
    cameras: dict[str, str]  # head -> "sim" or an Aravis identifier
    sequencer_port: str
    flow_port: str | None
    flow_gain_lps: float | None
    flow_offset_lps: float | None
    camera: CameraSettings = field(default_factory=CameraSettings)  # [camera], parsed and checked once
    simulation: dict[str, Any] = field(default_factory=dict)
    calibration: Path | None = None
    optics: dict[str, dict[str, Any]] = field(default_factory=dict)  # head -> lens and sensor (see template.toml)
    mains_hz: float = 50.0  # the room's mains: its lamps flicker at twice this (core/reconstruction/ambient.py)
    compression: str = "blosc-lz4"  # the frames' lossless filter (core/io/session.py FRAME_COMPRESSION)

    @property
    def simulated(self) -> bool:
        return all(c == "sim" for c in self.cameras.values())


def load_rig_config(path: str | os.PathLike | None = None) -> RigConfig:
    path = Path(path) if path is not None else DEFAULT_RIG
    try:
        data = tomllib.loads(path.read_text())
    except UnicodeDecodeError as exc:
        raise RigConfigError(f"{path} is not a text file ({exc.reason} at byte {exc.start})") from exc
    except OSError as exc:
        raise RigConfigError(f"cannot read rig configuration {path}: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise RigConfigError(f"{path} is not valid TOML: {exc}") from exc
    _check_keys(path, data)
    heads = data.get("heads")
    if not isinstance(heads, dict) or "front" not in heads:
        raise RigConfigError(f"{path}: [heads.front] is required")
    cameras, optics = {}, {}
    for name, head in heads.items():
        if name not in ("front", "back"):
            raise RigConfigError(f"{path}: unknown head [heads.{name}]: heads are front and back")
        if not isinstance(head, dict) or not isinstance(head.get("camera"), str) or not head["camera"]:
            raise RigConfigError(f"{path}: [heads.{name}] needs camera = \"sim\", an id, a serial number or an address")
        cameras[name] = head["camera"]
        optics[name] = _optics(path, name, head)
    kinds = {c == "sim" for c in cameras.values()}
    if len(kinds) > 1:
        raise RigConfigError(f"{path}: mixing simulated and real cameras is not supported")
    sequencer = data.get("sequencer", {}).get("port", "sim")
    flow = data.get("flowsensor")
    flow_port = flow.get("port") if isinstance(flow, dict) else None
    gain = offset = None
    if flow_port is not None:
        gain, offset = flow.get("gain_lps"), flow.get("offset_lps")
        if (gain is None) != (offset is None):
            raise RigConfigError(f"{path}: [flowsensor] gain_lps and offset_lps go together")
        if gain is not None and not (isinstance(gain, (int, float)) and gain > 0):
            raise RigConfigError(f"{path}: [flowsensor] gain_lps must be a positive number, found {gain!r}")
    camera = data.get("camera", {})
    rate = camera.get("frame_rate_hz", 110.0)
    if not isinstance(rate, (int, float)) or not 1.0 <= rate <= 500.0:
        raise RigConfigError(f"{path}: [camera] frame_rate_hz must be between 1 and 500, found {rate!r}")
    if camera.get("pixel_format", "Mono12") not in ("Mono8", "Mono12"):
        raise RigConfigError(f"{path}: [camera] pixel_format must be Mono8 or Mono12")
    for key, low, high, integer in (("width", 1, 100_000, True), ("height", 1, 100_000, True),
                                    ("offset_x", 0, 100_000, True), ("offset_y", 0, 100_000, True),
                                    ("binning", 1, 8, True), ("exposure_us", 1, 1_000_000, False)):
        if key in camera:
            _number(path, "camera", key, camera[key], low, high, integer)
    if camera.get("trigger", "free") not in ("free", "line", "software"):
        raise RigConfigError(f"{path}: [camera] trigger must be free, line or software, found "
                             f"{camera['trigger']!r}")
    simulation = data.get("simulation", {})
    if "scale" in simulation:
        _number(path, "simulation", "scale", simulation["scale"], 0.01, 1.0)
    if "seed" in simulation:
        _number(path, "simulation", "seed", simulation["seed"], 0, 2**32 - 1, integer=True)
    if "protocol" in simulation:
        # the simulator (numba kernels) only where the simulated rig needs it
        from core.sim.breathing import PROTOCOLS

        if simulation["protocol"] not in PROTOCOLS:
            raise RigConfigError(f"{path}: [simulation] protocol must be one of {', '.join(PROTOCOLS)}, found "
                                 f"{simulation['protocol']!r}")
    calibration = data.get("calibration")
    mains = data.get("mains_hz", 50.0)
    if mains not in (50, 60):
        raise RigConfigError(f"{path}: mains_hz must be 50 or 60 (the room's mains frequency), found {mains!r}")

    compression = data.get("recording", {}).get("compression", "blosc-lz4")
    if compression not in FRAME_COMPRESSION:
        raise RigConfigError(f"{path}: [recording] compression must be one of {', '.join(FRAME_COMPRESSION)}, found "
                             f"{compression!r}")
    return RigConfig(path, str(data.get("name", path.stem)), cameras, str(sequencer), flow_port,
                     None if gain is None else float(gain), None if offset is None else float(offset),
                     _camera_settings(camera),
                     simulation, Path(calibration) if calibration else None, optics, float(mains), compression)


_POSITIVE_OPTICS = ("focal_length_mm", "pixel_size_um", "fx_px", "fy_px")
_NON_NEGATIVE_OPTICS = ("cx_px", "cy_px")


def _optics(path: Path, name: str, head: dict) -> dict[str, Any]:
    """A head's lens and sensor: focal length and pixel size, or an OpenCV calibration of the whole
    sensor (fx_px, fy_px, cx_px, cy_px, dist_coeffs), each checked."""
    optics = {}
    for key in _POSITIVE_OPTICS + _NON_NEGATIVE_OPTICS:
        if key in head:
            value = head[key]
            positive = key in _POSITIVE_OPTICS
            if not isinstance(value, (int, float)) or isinstance(value, bool) or (value <= 0 if positive else value < 0):
                raise RigConfigError(f"{path}: [heads.{name}] {key} must be a "
                                     f"{'positive' if positive else 'non-negative'} number, found {value!r}")
            optics[key] = float(value)
    given = [k for k in ("fx_px", "fy_px", "cx_px", "cy_px") if k in optics]
    if given and len(given) != 4:
        raise RigConfigError(f"{path}: [heads.{name}] fx_px, fy_px, cx_px and cy_px go together")
    if "dist_coeffs" in head:
        coeffs = head["dist_coeffs"]
        if not (isinstance(coeffs, list) and len(coeffs) == 5 and all(isinstance(c, (int, float)) for c in coeffs)):
            raise RigConfigError(f"{path}: [heads.{name}] dist_coeffs must be OpenCV's five numbers "
                                 f"[k1, k2, p1, p2, k3], found {coeffs!r}")
        optics["dist_coeffs"] = [float(c) for c in coeffs]
    return optics


def _camera_settings(camera: dict[str, Any]) -> CameraSettings:
    """The [camera] table (checked by load_rig_config) as the cameras take it."""
    return CameraSettings(width=camera.get("width"), height=camera.get("height"),
                          offset_x=int(camera.get("offset_x", 0)), offset_y=int(camera.get("offset_y", 0)),
                          binning=int(camera.get("binning", 1)), pixel_format=camera.get("pixel_format", "Mono12"),
                          exposure_us=float(camera.get("exposure_us", 1000.0)),
                          frame_rate_hz=float(camera.get("frame_rate_hz", 110.0)),
                          trigger=camera.get("trigger", "free"))


def camera_head(name: str, optics: dict[str, Any], sensor_size: tuple[int, int],
                region: tuple[int, int, int, int], binning: int, bit_depth: int) -> Head:
    """The head's geometry for the image the camera delivers.

    `optics` describes the whole, unbinned sensor (the rig file's [heads.<name>]; the thesis' 25 mm
    lens on 7.4 um pixels where it says nothing); `region` is the camera's (x, y, width, height) in
    binned pixels. Binning b scales the focal length in pixels by 1/b and the principal point
    (pixel centres) to (c + 0.5) / b - 0.5; the region's offset moves it.
    """
    pixel_mm = optics.get("pixel_size_um", 7.4) * 1e-3
    focal_mm = optics.get("focal_length_mm", 25.0)
    fx = optics.get("fx_px", focal_mm / pixel_mm)
    fy = optics.get("fy_px", focal_mm / pixel_mm)
    cx = optics.get("cx_px", (sensor_size[0] - 1) / 2.0)
    cy = optics.get("cy_px", (sensor_size[1] - 1) / 2.0)
    x, y, width, height = region
    template = thesis_head(name)
    return Head(name=name, width=width, height=height, fx=fx / binning, fy=fy / binning,
                cx=(cx + 0.5) / binning - 0.5 - x, cy=(cy + 0.5) / binning - 0.5 - y,
                pixel_size_mm=pixel_mm * binning, bit_depth=bit_depth,
                light_positions_mm=template.light_positions_mm,
                dist_coeffs=np.asarray(optics.get("dist_coeffs", np.zeros(5)), dtype=float))
