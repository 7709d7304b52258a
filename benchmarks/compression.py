"""`photopft bench compression`: lossless HDF5 filters on the rig's frames, for choosing how
recordings are stored: compression ratio, write and read MB/s (one frame per chunk, as the
session format asks), and the GB a minute of two-head recording takes with each."""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from app.args import positive
from benchmarks.common import publish


def _filters() -> dict[str, dict]:
    """The candidates: HDF5's own (every reader has them) and, where hdf5plugin is installed,
    Blosc and Blosc2 (readers need the plugin)."""
    filters = {"none": {}, "gzip 1 + shuffle (HDF5's own)": dict(compression="gzip", compression_opts=1, shuffle=True),
               "lzf + shuffle (h5py's own)": dict(compression="lzf", shuffle=True)}
    try:
        import hdf5plugin
    except ImportError:
        return filters
    filters["Blosc2 lz4 5 + bitshuffle"] = dict(hdf5plugin.Blosc2(cname="lz4", clevel=5,
                                                                  filters=hdf5plugin.Blosc2.BITSHUFFLE))
    filters["Blosc2 zstd 1 + bitshuffle"] = dict(hdf5plugin.Blosc2(cname="zstd", clevel=1,
                                                                   filters=hdf5plugin.Blosc2.BITSHUFFLE))
    filters["Blosc lz4 5 + bitshuffle"] = dict(hdf5plugin.Blosc(cname="lz4", clevel=5,
                                                                shuffle=hdf5plugin.Blosc.BITSHUFFLE))
    return filters


def measure(frames: np.ndarray, folder: Path) -> list[tuple[str, float, float, float]]:
    """(filter, ratio, write MB/s, read MB/s) for each filter, frames written one at a time."""
    import h5py

    rows = []
    for name, options in _filters().items():
        path = folder / "frames.h5"
        started = time.perf_counter()
        with h5py.File(path, "w") as f:
            data = f.create_dataset("frames", shape=frames.shape, dtype=frames.dtype,
                                    chunks=(1,) + frames.shape[1:], **options)
            for i, frame in enumerate(frames):
                data[i] = frame
        written = time.perf_counter() - started
        size = path.stat().st_size
        started = time.perf_counter()
        with h5py.File(path, "r") as f:
            back = f["frames"][()]
        read = time.perf_counter() - started
        if not np.array_equal(back, frames):
            raise RuntimeError(f"{name} did not give the frames back")
        path.unlink()
        rows.append((name, frames.nbytes / size, frames.nbytes / 1e6 / written, frames.nbytes / 1e6 / read))
    return rows


def run_compression_bench(scale: float, frame_count: int) -> str:
    from core.io.session import SessionFile
    from core.sim.simulate import SimConfig, simulate

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        session = folder / "session.h5"
        simulate(session, SimConfig(protocol="tidal", seconds=frame_count / 110.0 + 0.05, scale=scale, seed=9,
                                    heads=("front",)))
        with SessionFile(session) as s:
            frames = s.frames("front")[:frame_count]
            rate_hz = s.rig.frame_rate_hz
        session.unlink()
        rows = measure(frames, folder)
    needed = 2 * rate_hz * frames[0].nbytes / 1e6  # two heads at the rig's rate
    lines = [f"{len(frames)} simulated frames of the front head, {frames.shape[2]} x {frames.shape[1]} "
             f"{frames.dtype} (12-bit), written one frame per chunk as the recorder does; two heads at "
             f"{rate_hz:g} frames/s need {needed:.0f} MB/s; {os.cpu_count()} cores.", "",
             "| filter | ratio | write MB/s | read MB/s | two heads: headroom | GB per minute, two heads |",
             "|---|---|---|---|---|---|"]
    for name, ratio, write, read in rows:
        lines.append(f"| {name} | {ratio:.2f} | {write:.0f} | {read:.0f} | {write / needed:.2f} x | "
                     f"{needed * 60 / 1000 / ratio:.1f} |")
    lines += ["", "Headroom: write MB/s over what two heads deliver, on an otherwise idle machine (the recorder "
                  "shares the cores with capture and the live view)."]
    return "\n".join(lines)


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench compression`: its arguments and what it runs."""
    co = what.add_parser("compression", help="lossless HDF5 filters on the rig's frames: ratio, MB/s, GB a minute")
    co.add_argument("--scale", type=positive, default=1.0)
    co.add_argument("--frames", type=int, default=110)
    co.add_argument("--no-write", action="store_true", help="print only")

    def run_compression(args: argparse.Namespace) -> int:
        text = run_compression_bench(args.scale, max(1, args.frames))
        return publish(args, "compression", "Compression (`photopft bench compression`"
                        + (f" --scale {args.scale:g}" if args.scale != 1 else "") + ")", text)

    co.set_defaults(run=run_compression)
