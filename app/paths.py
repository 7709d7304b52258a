"""Where photopft keeps its data, logs and calibrations (XDG base directories)."""

from __future__ import annotations

import os
from pathlib import Path


def _xdg(variable: str, fallback: str) -> Path:
    value = os.environ.get(variable, "")
    base = Path(value) if value and Path(value).is_absolute() else Path.home() / fallback
    return base / "photopft"


def data_dir() -> Path:
    """Patient records and sessions: $XDG_DATA_HOME/photopft (~/.local/share/photopft)."""
    return _xdg("XDG_DATA_HOME", ".local/share")


def config_dir() -> Path:
    """Settings and calibration profiles: $XDG_CONFIG_HOME/photopft (~/.config/photopft)."""
    return _xdg("XDG_CONFIG_HOME", ".config")


def state_dir() -> Path:
    """Logs: $XDG_STATE_HOME/photopft (~/.local/state/photopft)."""
    return _xdg("XDG_STATE_HOME", ".local/state")


def resources_dir() -> Path:
    """The shipped resources: beside the packages in a checkout, inside the bundle when frozen."""
    import sys

    bundle = getattr(sys, "_MEIPASS", None)
    return Path(bundle) / "resources" if bundle else Path(__file__).resolve().parents[1] / "resources"
