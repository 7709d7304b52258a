"""`photopft bench record`: recording from two fake GigE cameras and the simulated rig."""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from app.args import positive
from benchmarks.common import write_section


def run_record(seconds: float, write: bool, rate_hz: float = 110.0, compression: str = "blosc-lz4") -> str:
    """Two fake GigE cameras at 1400 x 1024 with the flow emulator, then the simulated rig at 700 x 512."""
    import resource
    import shutil
    import subprocess

    from core.rig import Rig, thesis_head
    from core.io.session import SubjectRecord
    from drivers.camera import AravisCamera, CameraSettings, find_aravis_device
    from drivers.flowsensor import FlowSensor, FlowSensorEmulator
    from drivers.light_phase import LightPhase
    from drivers.recorder import Recorder

    def cpu_s() -> float:
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return usage.ru_utime + usage.ru_stime

    lines = [f"## Recording (`photopft bench record --seconds {seconds:g} --compression {compression}`)", ""]
    fake = shutil.which("arv-fake-gv-camera-0.8")
    rows, sizes = [], []  # sizes: the file's MB per second recorded, as it landed on the disk
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)

        def record_aravis(identifiers: dict[str, str], interfaces: tuple[str, ...]):
            cameras = {}
            for head, identifier in identifiers.items():
                camera = AravisCamera(identifier, buffers=64, interfaces=interfaces, name=head)
                camera.configure(CameraSettings(width=1400, height=1024, pixel_format="Mono8", frame_rate_hz=rate_hz))
                cameras[head] = camera
            heads = {h: thesis_head(h, bit_depth=8) for h in cameras}
            rig = Rig("bench-aravis", heads, frame_rate_hz=rate_hz)
            with FlowSensorEmulator() as emulator:
                flow = FlowSensor(emulator.port)
                recorder = Recorder(folder / "aravis.h5", rig, cameras, LightPhase(rig, first_trigger=0), flow,
                                    (0.0075, -15.36), SubjectRecord("BENCH", "male", 30, 175, 75), queue_items=4000,
                                    compression=compression)
                cpu0 = cpu_s()
                summary = recorder.run(seconds)
                cpu = (cpu_s() - cpu0) / summary.elapsed_s
                flow.close()
            sizes.append(summary.path.stat().st_size / summary.elapsed_s / 1e6)
            summary.path.unlink()  # a minute at 1400 x 1024 is about 19 GB: one recording on the disk at a time
            for camera in cameras.values():
                camera.close()
            return summary, cpu

        # Aravis' in-process Fake interface: each opening of Fake_1 is a camera of its own
        rows.append(("two in-process Aravis Fake cameras, 1400 x 1024 Mono8, flow emulator",
                     *record_aravis({"front": "Fake_1", "back": "Fake_1"}, ("Fake",))))
        if fake is not None:
            subprocess.run(["ip", "addr", "add", "127.0.0.2/8", "dev", "lo"], capture_output=True)
            processes = [subprocess.Popen([fake, "-i", a, "-s", s], stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL)
                         for a, s in (("127.0.0.1", "BENCHF"), ("127.0.0.2", "BENCHB"))]
            try:
                for serial in ("BENCHF", "BENCHB"):
                    for _ in range(50):
                        try:
                            find_aravis_device(serial)
                            break
                        except Exception:
                            time.sleep(0.2)
                rows.append(("two fake GigE cameras (arv-fake-gv-camera on the loopback), 1400 x 1024 Mono8, "
                             "flow emulator", *record_aravis({"front": "BENCHF", "back": "BENCHB"}, ())))
            finally:
                for process in processes:
                    process.kill()
                    process.wait()
        from core.sim.breathing import Sway
        from core.sim.simulate import SimConfig
        from drivers.simulated import SimCamera, SimFlowSensor, SimulatedRigState

        for loop_cycles, name in ((0, "simulated rig, 700 x 512 (binned size for a gigabit link), 12-bit, flow "
                                      "sensor, every frame rendered on the same 2 cores"),
                                  (22, "simulated rig as above, 22 light cycles (1 s) rendered beforehand and "
                                       "delivered in a loop, so the renderer does not limit the rate")):
            state = SimulatedRigState.build(SimConfig(protocol="tidal", seconds=seconds + 5, scale=0.5, sway=Sway()))
            cameras = {h: SimCamera(state, h, loop_cycles=loop_cycles) for h in state.rig.heads}
            for camera in cameras.values():
                camera.start()
            state.start_ns = time.monotonic_ns()  # the clock starts once the loops are rendered
            recorder = Recorder(folder / "sim.h5", state.rig, cameras, LightPhase(state.rig),
                                SimFlowSensor(state), (0.0075, -15.36), SubjectRecord("BENCH", "male", 30, 175, 75),
                                kind="simulation", queue_items=4000, compression=compression)
            cpu0 = cpu_s()
            summary = recorder.run(seconds)
            rows.append((name, summary, (cpu_s() - cpu0) / summary.elapsed_s))
            sizes.append(summary.path.stat().st_size / summary.elapsed_s / 1e6)
            summary.path.unlink()
    lines += [f"Each for {seconds:g} s at {rate_hz:g} frames/s asked, frames written with compression "
              f"{compression}; 2 cores. Written: frame data handed to the file; on disk: the file's size.", "",
              "| source | frames per head (rate) | lost at the cameras | dropped by the software | flow samples (lost) "
              "| queue peak | CPU (cores) | written | on disk |", "|---|---|---|---|---|---|---|---|---|"]
    for (name, s, cpu), disk in zip(rows, sizes):
        per_head = ", ".join(f"{h} {n} ({n / s.elapsed_s:.1f}/s)" for h, n in s.frames.items())
        lost = ", ".join(f"{h} {s.camera_failed[h]} failed, {s.camera_lost[h]} gaps" for h in s.frames)
        lines.append(f"| {name} | {per_head} | {lost} | {s.dropped_by_software} | {s.flow_samples} ({s.flow_lost}) | "
                     f"{100 * s.max_queue_fill:.0f} % | {cpu:.2f} | {s.written_mb / s.elapsed_s:.0f} MB/s | "
                     f"{disk:.0f} MB/s ({disk * 60 / 1000:.1f} GB/min) |")
        for problem in s.problems:
            lines.append(f"| | stopped: {problem} | | | | | | | |")
    if fake is None:
        lines.append("(arv-fake-gv-camera-0.8 not installed: the GigE row is missing)")
    text = "\n".join(lines)
    if write:
        write_section("record" if compression == "none" else f"record-{compression}", text)
    return text


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench record`: its arguments and what it runs."""
    rec = what.add_parser("record", help="record from two fake GigE cameras and the simulated rig")
    rec.add_argument("--seconds", type=positive, default=60.0)
    rec.add_argument("--rate", type=positive, default=110.0, help="frames/s asked of the fake cameras")
    rec.add_argument("--compression", choices=("none", "blosc-lz4"), default="blosc-lz4",
                     help="the frames' filter, as a rig file's [recording] compression (default blosc-lz4)")
    rec.add_argument("--no-write", action="store_true", help="print only")
    rec.set_defaults(run=lambda args: print(run_record(args.seconds, not args.no_write, args.rate,
                                                       args.compression)) or 0)
