"""Where photopft keeps its data, logs and calibrations (XDG base directories)."""

from __future__ import annotations

import os
import sys
import tomllib
from pathlib import Path

# The clinic's own settings, written by whoever installs photopft for a clinic (docs/trust.md); no
# environment variable moves it, so a user cannot point the application at records of their own.
SITE_CONFIG = Path("/etc/photopft/site.toml")


class SiteConfigError(ValueError):
    """The site configuration cannot be read; the message names the file."""


def configured_records() -> Path | None:
    """The records database the site configuration names (`[records] path`), None where there is none."""
    if not SITE_CONFIG.is_file():
        return None
    try:
        value = tomllib.loads(SITE_CONFIG.read_text(encoding="utf-8")).get("records", {}).get("path")
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, AttributeError) as exc:
        raise SiteConfigError(f"{SITE_CONFIG}: cannot be read ({exc})") from exc
    if not isinstance(value, str) or not Path(value).is_absolute():
        raise SiteConfigError(f"{SITE_CONFIG}: [records] path must be an absolute path, found {value!r}")
    return Path(value)


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
    bundle = getattr(sys, "_MEIPASS", None)
    return Path(bundle) / "resources" if bundle else Path(__file__).resolve().parents[1] / "resources"
