"""Rig configurations (TOML): which camera, sequencer and flow sensor each part of the rig is.

A device is "sim" (the simulated rig), "emulator" (serial emulators on pseudo-terminals) or
real (a camera's id, serial number or address; a serial port's path).
"""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

RIGS = Path(__file__).resolve().parents[1] / "resources" / "rigs"
DEFAULT_RIG = RIGS / "simulated.toml"


class RigConfigError(ValueError):
    """A rig configuration that cannot be used; the message names the file and the field."""


@dataclass(frozen=True)
class RigConfig:
    path: Path
    name: str
    cameras: dict[str, str]  # head -> "sim" or an Aravis identifier
    sequencer_port: str
    flow_port: str | None
    flow_gain_lps: float | None
    flow_offset_lps: float | None
    camera: dict[str, Any] = field(default_factory=dict)
    simulation: dict[str, Any] = field(default_factory=dict)
    calibration: Path | None = None

    @property
    def simulated(self) -> bool:
        return all(c == "sim" for c in self.cameras.values())


def load_rig_config(path: str | os.PathLike | None = None) -> RigConfig:
    path = Path(path) if path is not None else DEFAULT_RIG
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise RigConfigError(f"cannot read rig configuration {path}: {exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise RigConfigError(f"{path} is not valid TOML: {exc}") from exc
    heads = data.get("heads")
    if not isinstance(heads, dict) or "front" not in heads:
        raise RigConfigError(f"{path}: [heads.front] is required")
    cameras = {}
    for name, head in heads.items():
        if name not in ("front", "back"):
            raise RigConfigError(f"{path}: unknown head [heads.{name}]: heads are front and back")
        if not isinstance(head, dict) or not isinstance(head.get("camera"), str) or not head["camera"]:
            raise RigConfigError(f"{path}: [heads.{name}] needs camera = \"sim\", an id, a serial number or an address")
        cameras[name] = head["camera"]
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
    calibration = data.get("calibration")
    return RigConfig(path, str(data.get("name", path.stem)), cameras, str(sequencer), flow_port,
                     None if gain is None else float(gain), None if offset is None else float(offset), camera,
                     data.get("simulation", {}), Path(calibration) if calibration else None)
