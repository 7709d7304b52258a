"""Where calibration profiles live ($XDG_CONFIG_HOME/photopft/calibration/RIG), which are in
force, the ones they replaced, and going back to one of those.

The wizards save a rig's profiles in its folder under fixed names (the ones in force); saving a new
one moves the one in force aside as name-YYYYmmdd-HHMMSS.json (its history). drivers/assembly.py
applies the profiles in force whenever the rig is opened (`gui`, `record`), so every recording's
/rig holds them, and the report names them.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from app.paths import config_dir
from app.records import Records, RecordsError, existing_records

RIG_PROFILE = "rig-calibration.json"
FLOW_PROFILE = "flow-calibration.json"
VOLUME_PROFILE = "volume-calibration.json"


PROFILES = {RIG_PROFILE: "lights (sphere calibration)", FLOW_PROFILE: "flow sensor",
            VOLUME_PROFILE: "volume regression"}


def calibration_dir(rig_name: str = "simulated") -> Path:
    """The folder of one rig's profiles (a rig file's `name`)."""
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", rig_name).strip("-.") or "rig"
    return config_dir() / "calibration" / slug


@dataclass(frozen=True)
class ProfilesInForce:
    lights: Path | None
    flow: Path | None
    volume: Path | None


def in_force(rig_name: str) -> ProfilesInForce:
    folder = calibration_dir(rig_name)

    def present(name: str) -> Path | None:
        path = folder / name
        return path if path.is_file() else None

    return ProfilesInForce(present(RIG_PROFILE), present(FLOW_PROFILE), present(VOLUME_PROFILE))


def history(rig_name: str, profile: str) -> list[Path]:
    """The profiles of one kind that were in force before, newest first."""
    stem, suffix = Path(profile).stem, Path(profile).suffix
    kept = calibration_dir(rig_name).glob(f"{stem}-[0-9]*{suffix}")
    return sorted(kept, key=lambda p: p.name, reverse=True)


def restore(rig_name: str, kept: Path, records: Records | None = None) -> Path:
    """Put an earlier profile back in force; the one in force goes to the history (nothing is
    deleted). Logged in the records as a calibration saved."""
    folder = calibration_dir(rig_name)
    kind = next((name for name in PROFILES if kept.name.startswith(Path(name).stem + "-")), None)
    if kind is None or kept.parent.resolve() != folder.resolve():
        raise ValueError(f"{kept} is not an earlier calibration profile of the rig {rig_name!r}")
    target = folder / kind
    previous = keep_previous(target)
    shutil.copy2(kept, target.with_suffix(".part"))
    target.with_suffix(".part").replace(target)
    if records is not None:
        records.log("calibration saved", str(target.resolve()),
                    {"kind": PROFILES[kind], "restored_from": str(kept),
                     "previous": str(previous) if previous else None})
    return target


def to_factory(rig_name: str, profile: str, records: Records | None = None) -> Path | None:
    """No profile of this kind in force: the rig opens with its own (the rig file's calibration, or its
    lights and flow line as built); the one in force goes to the history, from which it can be put back.
    Returns where it went, or None where none was in force. Logged as a calibration saved."""
    if profile not in PROFILES:
        raise ValueError(f"{profile} is not a kind of calibration profile ({', '.join(PROFILES)})")
    previous = keep_previous(calibration_dir(rig_name) / profile)
    if records is not None and previous is not None:
        records.log("calibration saved", str((calibration_dir(rig_name) / profile).resolve()),
                    {"kind": PROFILES[profile], "factory": True, "previous": str(previous)})
    return previous


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


SYRINGE_LOG = "syringe-checks.jsonl"


def log_syringe_check(rig_name: str, check, flow_from: str, records: Records | None = None) -> dict:
    """Append a 3 L syringe check to the rig's log (one JSON line each, never rewritten) and to
    the records' audit trail; returns the entry."""
    entry = {"time": datetime.now().astimezone().isoformat(timespec="seconds"), "passed": check.passed,
             "syringe_l": check.syringe_l, "volumes_l": [round(s.volume_l, 4) for s in check.strokes],
             "verdict": check.verdict(), "flow_calibration": flow_from}
    folder = calibration_dir(rig_name)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / SYRINGE_LOG, "a", encoding="utf-8") as log:
        log.write(json.dumps(entry) + "\n")
        log.flush()
        os.fsync(log.fileno())
    if records is not None:
        records.log("syringe check", str(folder / SYRINGE_LOG), entry)
    return entry


def syringe_checks(rig_name: str) -> list[dict]:
    """The rig's syringe checks, oldest first (a line that cannot be read is skipped)."""
    path = calibration_dir(rig_name) / SYRINGE_LOG
    if not path.is_file():
        return []
    out = []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict) and "time" in entry:
            out.append(entry)
    return out


def syringe_status(rig_name: str) -> tuple[str, bool]:
    """(the day's syringe check in words, whether it is missing or failed)."""
    today = datetime.now().astimezone().date().isoformat()
    done = [c for c in syringe_checks(rig_name) if str(c["time"]).startswith(today)]
    if not done:
        return "3 L syringe check: none today", True
    last = done[-1]
    return f"3 L syringe check: {'passed' if last.get('passed') else 'FAILED'} at {str(last['time'])[11:16]}", \
        not last.get("passed")
