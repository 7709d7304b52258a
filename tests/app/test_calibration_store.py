"""The calibrations in force: a rig's profiles are what `record` opens the rig with, an earlier
one can be put back (nothing is deleted), and a broken profile is refused with its name."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.calibration_store import (FLOW_PROFILE, RIG_PROFILE, calibration_dir, history, in_force, keep_previous,
                                   restore)
from app.cli import main
from core.calibration.rig_profile import HeadCalibration, RigCalibration
from core.rig import thesis_rig
from core.io.session import SessionFile


def _profile(shift_mm: float, created: str) -> RigCalibration:
    heads = {}
    for name, head in thesis_rig(0.1).heads.items():
        lights = head.light_positions_mm + shift_mm
        heads[name] = HeadCalibration(lights, np.ones(4), np.full((4, 3), 0.1), np.full(4, 0.1), lights / 1000.0)
    return RigCalibration(created, ["sphere.h5"], heads)


@pytest.fixture
def config(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    folder = calibration_dir("simulated")
    folder.mkdir(parents=True)
    return folder


def test_history_and_putting_an_earlier_profile_back(config):
    first = _profile(2.0, "2026-11-01T09:00:00+00:00")
    first.save(config / RIG_PROFILE)
    assert in_force("simulated").lights == config / RIG_PROFILE and in_force("simulated").flow is None
    kept = keep_previous(config / RIG_PROFILE)
    _profile(5.0, "2026-11-20T09:00:00+00:00").save(config / RIG_PROFILE)
    assert history("simulated", RIG_PROFILE) == [kept]
    restored = restore("simulated", kept)
    assert json.loads(restored.read_text())["created"] == first.created
    assert len(history("simulated", RIG_PROFILE)) == 2  # the one replaced is kept too
    with pytest.raises(ValueError, match="not an earlier calibration profile"):
        restore("simulated", config / RIG_PROFILE)


def test_record_opens_the_rig_with_the_profiles_in_force(config, tmp_path, capsys):
    profile = _profile(3.0, "2026-11-24T10:00:00+00:00")
    profile.save(config / RIG_PROFILE)
    flow = {"format": "photopft-flow-calibration", "format_version": 1, "created": "2026-11-24T10:30:00+00:00",
            "sources": ["flow bench"], "gain_lps": 0.0076, "offset_lps": -15.5, "r_squared": 0.9999,
            "residuals_lps": [0.0, 0.0, 0.0], "range_lps": [-6.0, 6.0], "points": 3}
    (config / FLOW_PROFILE).write_text(json.dumps(flow))
    out = tmp_path / "s.h5"
    assert main(["record", "-o", str(out), "--seconds", "0.5"]) == 0
    assert f"lights {RIG_PROFILE} of 2026-11-24 10:00; flow sensor {FLOW_PROFILE} of 2026-11-24 10:30" \
        in capsys.readouterr().err
    with SessionFile(out) as s:
        assert np.allclose(s.rig.heads["front"].light_positions_mm, profile.heads["front"].light_positions_mm)
        assert s.rig.heads["back"].calibrated == profile.created
        assert s.flow.gain_lps == pytest.approx(0.0076) and s.flow.offset_lps == pytest.approx(-15.5)


def test_a_broken_profile_in_force_is_one_line_naming_it(config, tmp_path):
    (config / RIG_PROFILE).write_text("{not json")
    # the command in its own process, as a user runs it: in a full run its line twice reached pytest's own
    # capture instead of the stderr handed to it in this process (2026-11-27; numba's coloured messages
    # swapped `sys.stderr` from another thread, core/__init__.py)
    done = subprocess.run([sys.executable, "-m", "app.cli", "record", "-o", str(tmp_path / "s.h5"), "--seconds", "0.5"],
                          capture_output=True, text=True, cwd=Path(__file__).resolve().parents[2], timeout=120)
    assert done.returncode != 0
    err = done.stderr.strip().splitlines()
    assert len(err) == 1 and RIG_PROFILE in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "s.h5").exists()
