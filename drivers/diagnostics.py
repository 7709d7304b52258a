"""Is each device of a rig there? One line per camera, the sequencer and the flow sensor, with
what to do about a missing one: for `photopft devices` and the window's diagnostics page when
the rig cannot start."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from drivers.camera import CameraError, find_aravis_device
from drivers.rig import RigConfig


@dataclass(frozen=True)
class DeviceCheck:
    device: str  # "front camera", "sequencer", "flow sensor"
    address: str  # the identifier or port the rig file names
    state: str  # in words: "found as ...", "simulated", "MISSING: ..."
    ok: bool
    advice: str = ""  # what to do when not ok


CAMERA_ADVICE = ("Check the camera's power (PoE) and network cable, and that this computer's network port is on "
                 "the cameras' subnet; `arv-tool-0.8` lists the cameras this computer sees.")


def seen_cameras() -> list[str]:
    """The GigE Vision cameras this computer sees, or why it cannot look."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis

        Aravis.update_device_list()
        return [f"{Aravis.get_device_id(i)} (serial {Aravis.get_device_serial_nbr(i)}, "
                f"{Aravis.get_device_address(i)})" for i in range(Aravis.get_n_devices())]
    except (ImportError, ValueError) as exc:
        return [f"Aravis unavailable: {exc}"]


def check_rig(config: RigConfig) -> list[DeviceCheck]:
    checks = []
    for head, identifier in config.cameras.items():
        name = f"{head} camera"
        if identifier == "sim":
            checks.append(DeviceCheck(name, "sim", "simulated", True))
            continue
        try:
            checks.append(DeviceCheck(name, identifier, f"found as {find_aravis_device(identifier)}", True))
        except CameraError as exc:
            checks.append(DeviceCheck(name, identifier, f"MISSING: {exc}", False, CAMERA_ADVICE))
    for name, port in (("sequencer", config.sequencer_port), ("flow sensor", config.flow_port)):
        if port in (None, "sim", "emulator"):
            checks.append(DeviceCheck(name, str(port or "none"), {"sim": "simulated", "emulator": "emulated",
                                                                  None: "none fitted"}[port], True))
        elif Path(port).exists():
            checks.append(DeviceCheck(name, port, "present", True))
        else:
            checks.append(DeviceCheck(name, port, "MISSING", False,
                                      f"Check the {name}'s USB cable and power: the port {port} does not exist; "
                                      "`photopft devices` lists the serial ports this computer has."))
    return checks
