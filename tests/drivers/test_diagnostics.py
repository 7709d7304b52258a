"""`photopft devices`: each device of a rig with its state, and what to do about a missing one."""

from __future__ import annotations

from app.cli import main


def test_devices_names_what_is_missing_and_what_to_do(tmp_path, capsys):
    rig = tmp_path / "clinic.toml"
    rig.write_text('name = "clinic"\n[camera]\n[heads.front]\ncamera = "NO-SUCH-CAMERA-42"\n'
                   '[sequencer]\nport = "/dev/ttyNOPE0"\n[flowsensor]\nport = "emulator"\n')
    assert main(["devices", "--rig", str(rig)]) == 1
    lines = capsys.readouterr().out.splitlines()
    camera = next(line for line in lines if line.strip().startswith("front camera"))
    assert "NO-SUCH-CAMERA-42: MISSING" in camera and "network cable" in camera
    sequencer = next(line for line in lines if line.strip().startswith("sequencer"))
    assert "MISSING" in sequencer and "USB cable" in sequencer
    assert any(line.strip() == "flow sensor: emulated" for line in lines)


def test_the_simulated_rig_has_everything(capsys):
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "front camera: simulated" in out and "MISSING" not in out
