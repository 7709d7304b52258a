"""Where calibration profiles live ($XDG_CONFIG_HOME/photopft/calibration), and saving one so
that the previous one is kept beside it."""

from __future__ import annotations

import shutil
from datetime import datetime
from pathlib import Path

from app.paths import config_dir

RIG_PROFILE = "rig-calibration.json"
FLOW_PROFILE = "flow-calibration.json"
VOLUME_PROFILE = "volume-calibration.json"


def calibration_dir() -> Path:
    return config_dir() / "calibration"


def keep_previous(path: Path) -> Path | None:
    """Move the profile in force aside (name-YYYYmmdd-HHMMSS.json); returns where, or None."""
    if not path.exists():
        return None
    stamp = datetime.fromtimestamp(path.stat().st_mtime).strftime("%Y%m%d-%H%M%S")
    kept = path.with_name(f"{path.stem}-{stamp}{path.suffix}")
    k = 1
    while kept.exists():
        kept = path.with_name(f"{path.stem}-{stamp}-{k}{path.suffix}")
        k += 1
    shutil.move(path, kept)
    return kept
