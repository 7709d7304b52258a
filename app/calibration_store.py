"""Where calibration profiles live ($XDG_CONFIG_HOME/photopft/calibration), and saving one so
that the previous one is kept beside it."""

from __future__ import annotations

import shutil
from datetime import datetime
from pathlib import Path

from app.paths import config_dir
from app.records import Records, RecordsError, existing_records

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


class CalibrationRefused(RecordsError):
    """The acting user may not save a calibration (roles are enforced in the records)."""


def calibration_audit(records_path: Path | None = None, user: str | None = None) -> Records | None:
    """The records database that logs calibrations (None where there is none yet); raises
    CalibrationRefused before any work when the acting user is not an engineer."""
    try:
        return existing_records(records_path, user, may="calibration saved")
    except RecordsError as exc:
        raise CalibrationRefused(str(exc)) from exc


def log_calibration(records: Records | None, kind: str, saved: Path, previous: Path | None = None) -> None:
    if records is not None:
        records.log("calibration saved", str(Path(saved).resolve()),
                    {"kind": kind, "previous": str(previous) if previous else None})
