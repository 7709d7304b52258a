"""The rig calibration profile (JSON, shared/spec/session-format.md): write, read, validate, apply."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from core.io.jsonfile import load_checked, read_json_object
from core.io.outputs import write_text_atomic

from core.rig import Rig, light_position_problems

PROFILE_FORMAT = "photopft-rig-calibration"


class ProfileError(Exception):
    """A calibration profile that is missing, malformed or for another rig."""


@dataclass
class HeadCalibration:
    light_positions_mm: np.ndarray  # (4, 3)
    light_intensity: np.ndarray  # (4,)
    light_position_sigma_mm: np.ndarray  # (4, 3)
    residual_mm: np.ndarray  # (4,)
    pseudo_light_vectors: np.ndarray  # (4, 3)
    extra: dict[str, Any] = field(default_factory=dict)
    light_axis: np.ndarray | None = None  # (4, 3) each LED's axis; None: isotropic point sources
    light_mu: np.ndarray | None = None  # (4,) each LED's cos^mu falloff about its axis


@dataclass
class RigCalibration:
    created: str
    sessions: list[str]
    heads: dict[str, HeadCalibration]
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        heads = {}
        for name, h in self.heads.items():
            heads[name] = {
                "light_positions_mm": np.round(h.light_positions_mm, 4).tolist(),
                "light_intensity": np.round(h.light_intensity, 6).tolist(),
                "light_position_sigma_mm": np.round(h.light_position_sigma_mm, 4).tolist(),
                "residual_mm": np.round(h.residual_mm, 4).tolist(),
                "pseudo_light_vectors": np.round(h.pseudo_light_vectors, 8).tolist(),
                **h.extra,
            }
            if h.light_axis is not None and h.light_mu is not None:
                heads[name]["light_axis"] = np.round(h.light_axis, 8).tolist()
                heads[name]["light_mu"] = np.round(h.light_mu, 6).tolist()
        return {"format": PROFILE_FORMAT, "format_version": 1, "created": self.created, "sessions": self.sessions,
                "heads": heads, **self.extra}

    def save(self, path: str | os.PathLike) -> None:
        write_text_atomic(path, json.dumps(self.to_json(), indent=2) + "\n")

    def apply(self, rig: Rig) -> Rig:
        """The rig with this profile's lights in force on every head it names."""
        missing = [h for h in rig.heads if h not in self.heads]
        if missing:
            raise ProfileError(f"the calibration profile has no head {missing[0]!r} (it has {', '.join(self.heads)})")
        heads = {name: replace(head, light_positions_mm=self.heads[name].light_positions_mm,
                               light_intensity=self.heads[name].light_intensity, light_axis=self.heads[name].light_axis,
                               light_mu=self.heads[name].light_mu, calibrated=self.created)
                 for name, head in rig.heads.items()}
        return replace(rig, heads=heads)


def _array(value: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ProfileError(f"{where} must be numbers: {exc}") from exc
    if arr.shape != shape:
        raise ProfileError(f"{where} must have shape {shape}, found {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ProfileError(f"{where} holds non-finite values")
    return arr


def load_profile(path: str | os.PathLike) -> RigCalibration:
    return load_checked(Path(path), _load_profile, ProfileError)


def _load_profile(path: Path) -> RigCalibration:
    data = read_json_object(path, ProfileError, "calibration profile")
    if data.get("format") != PROFILE_FORMAT:
        raise ProfileError(f"{path}: 'format' must be {PROFILE_FORMAT!r}")
    if data.get("format_version") != 1:
        raise ProfileError(f"{path}: format_version {data.get('format_version')!r}, this reader knows 1")
    heads_data = data.get("heads")
    if not isinstance(heads_data, dict) or not heads_data:
        raise ProfileError(f"{path}: 'heads' must name at least one head")
    heads = {}
    known = ("light_positions_mm", "light_intensity", "light_position_sigma_mm", "residual_mm",
             "pseudo_light_vectors", "light_axis", "light_mu")
    for name, h in heads_data.items():
        if name not in ("front", "back"):
            raise ProfileError(f"{path}: unknown head {name!r}")
        where = f"{path}: heads.{name}"
        if "light_positions_mm" not in h:
            raise ProfileError(f"{where}.light_positions_mm is missing")
        positions = _array(h["light_positions_mm"], (4, 3), f"{where}.light_positions_mm")
        if problems := light_position_problems(positions):
            raise ProfileError(f"{where}.light_positions_mm: {'; '.join(problems)}")
        intensity = _array(h.get("light_intensity", [1, 1, 1, 1]), (4,), f"{where}.light_intensity")
        if np.any(intensity <= 0):
            raise ProfileError(f"{where}.light_intensity must be positive")
        pseudo = _array(h.get("pseudo_light_vectors", np.zeros((4, 3))), (4, 3), f"{where}.pseudo_light_vectors")
        axis = mu = None
        if ("light_axis" in h) != ("light_mu" in h):
            raise ProfileError(f"{where}: light_axis and light_mu go together (an LED's axis and its falloff)")
        if "light_axis" in h:
            axis = _array(h["light_axis"], (4, 3), f"{where}.light_axis")
            mu = _array(h["light_mu"], (4,), f"{where}.light_mu")
            if np.any(axis[:, 2] <= 0) or np.any(np.abs(np.linalg.norm(axis, axis=1) - 1) > 1e-3):
                raise ProfileError(f"{where}.light_axis must be unit vectors pointing at the subject (z > 0)")
            if np.any(mu < 0) or np.any(mu > 20):
                raise ProfileError(f"{where}.light_mu must be in 0-20, found {mu.tolist()}")
        heads[name] = HeadCalibration(
            positions, intensity,
            _array(h.get("light_position_sigma_mm", np.zeros((4, 3))), (4, 3), f"{where}.light_position_sigma_mm"),
            _array(h.get("residual_mm", np.zeros(4)), (4,), f"{where}.residual_mm"), pseudo,
            {k: v for k, v in h.items() if k not in known}, axis, mu)
    return RigCalibration(str(data.get("created", "")), list(data.get("sessions", [])), heads,
                          {k: v for k, v in data.items() if k not in ("format", "format_version", "created",
                                                                       "sessions", "heads")})
