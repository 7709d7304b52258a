"""`photopft bench gui`: the live view's display rate, GUI-thread stalls, maps per second and
memory, in the real window on the simulated rig (offscreen unless a display is set)."""

from __future__ import annotations

import argparse
import os
import tempfile
from functools import partial
from pathlib import Path

from app.args import positive
from benchmarks.common import publish


def run_gui_bench(scale: float, seconds: float, record: bool, warmup_s: float = 30.0, loop_cycles: int = 0) -> str:
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtWidgets import QApplication

    from app.gui.main_window import MainWindow
    from app.gui.measure import measure_live_view
    from app.engine.sources import simulated_source
    from core.io.session import SubjectRecord

    app = QApplication.instance() or QApplication([])
    app.setApplicationName("photopft")  # as the application names itself (app/gui/app.py)
    window = MainWindow(partial(simulated_source, scale=scale, loop_cycles=loop_cycles))
    window.show()
    folder = Path(tempfile.mkdtemp(prefix="photopft-bench-gui-"))
    f = measure_live_view(window, seconds, folder / "bench.h5" if record else None,
                          SubjectRecord("BENCH", "male", 30.0, 175.0, 75.0), warmup_s=warmup_s)
    for path in folder.glob("*"):
        path.unlink()
    folder.rmdir()
    dropped = f.recording.dropped_by_software if f.recording is not None else 0
    rows = [
        f"scale {scale:g}, {'recording' if record else 'live view only'}, {f.elapsed_s:.0f} s after "
        f"{warmup_s:.0f} s of live view (as while positioning), simulated rig ("
        + (f"{loop_cycles} light cycles rendered beforehand and delivered in a loop, so the renderer does not "
           f"limit the rate" if loop_cycles else "its cameras rendered on the same cores")
        + f"), {os.cpu_count()} cores",
        "",
        "| display updates/s | GUI thread longest stall | maps/s per head | frames/s per head | dropped | memory |",
        "|---|---|---|---|---|---|",
        f"| {f.updates_per_s:.1f} | {f.longest_stall_ms:.0f} ms | "
        + ", ".join(f"{h} {r:.1f}" for h, r in f.maps_per_s.items()) + " | "
        + ", ".join(f"{h} {r:.0f}" for h, r in f.frames_per_s.items())
        + f" | {dropped} | {f.rss_mb[0]:.0f} -> {f.rss_mb[-1]:.0f} MB (peak {max(f.rss_mb):.0f}) |",
        "",
        "Memory: the GUI process and the engine process together, from the start of the measurement "
        f"to its end (GUI alone {f.gui_rss_mb[0]:.0f} -> {f.gui_rss_mb[-1]:.0f} MB); when every head had "
        f"its first map, before the warm-up: {f.rss_first_maps_mb:.0f} MB.",
    ]
    stalls = ", ".join(f"{s.ms:.0f} ms at {s.at_s:.0f} s (GUI thread busy {s.busy_ms:.0f} ms, preempted {s.preempted}x)"
                       for s in sorted(f.long_stalls, key=lambda s: -s.ms)[:5])
    rows += ["", f"GUI-thread stalls longer than a display interval (33 ms): {len(f.long_stalls)}"
             + (f"; the longest: {stalls}" if stalls else "")]
    if len(f.rss_mb) > 8:  # sampled every 10 s: a leak grows steadily, a heap settling levels off
        rows += ["", "memory each minute (MB): " + ", ".join(f"{m:.0f}" for m in f.rss_mb[::6])]
    return "\n".join(rows)


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench gui`: its arguments and what it runs."""
    gui = what.add_parser("gui", help="the live view: display updates/s, GUI-thread stalls, maps/s, memory")
    gui.add_argument("--scale", type=positive, default=0.5)
    gui.add_argument("--seconds", type=positive, default=20.0)
    gui.add_argument("--no-record", action="store_true", help="live view only (no session file written)")
    gui.add_argument("--warmup", type=positive, default=30.0,
                     help="seconds of live view before the measurement (as while positioning the patient)")
    gui.add_argument("--loop", type=int, default=0, metavar="CYCLES",
                     help="render this many light cycles once and deliver them in a loop (the renderer then does "
                          "not limit the rate; the images repeat)")
    gui.add_argument("--no-write", action="store_true", help="print only")

    def run_gui(args: argparse.Namespace) -> int:
        text = run_gui_bench(args.scale, args.seconds, not args.no_record, args.warmup, args.loop)
        return publish(args, f"gui-{args.scale:g}-{'live' if args.no_record else 'recording'}"
                              + (f"-loop{args.loop}" if args.loop else ""),
                        f"Live view (`photopft bench gui --scale {args.scale:g} --seconds {args.seconds:g}"
                        f"{' --no-record' if args.no_record else ''}{f' --loop {args.loop}' if args.loop else ''}`)",
                        text)

    gui.set_defaults(run=run_gui)
