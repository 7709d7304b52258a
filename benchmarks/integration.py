"""`photopft bench integration`: normals to depth on real data (DiLiGenT bear): error and time."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DILIGENT_BEAR, write_section


def run_integration(folder: Path, write: bool, repeat: int = 10) -> str:
    """Both integrators of depth_from_normals on real normals with their true depth: the mean
    absolute depth error after the offset, and the median time of `repeat` runs."""
    import numba

    from core.io.diligent import load_real_surface, mean_abs_depth_error_mm
    from core.reconstruction.integrate import ROBUST_ITERATIONS, depth_from_normals

    surface = load_real_surface(folder)
    anchor = float(np.median(surface.depth_mm[surface.mask]))
    rows = []
    for method, label in (("masked", f"accurate: masked least squares, reweighted {ROBUST_ITERATIONS} times "
                                     "(the default)"),
                          ("dct", "fast: DCT Poisson on the whole image, gradients zeroed off the mask "
                                  "(`--integrator dct`)")):
        times = []
        for _ in range(repeat):
            started = time.perf_counter()
            depth = depth_from_normals(surface.normals, surface.mask, *surface.intrinsics, anchor, method)
            times.append(time.perf_counter() - started)
        error, given = mean_abs_depth_error_mm(depth, surface.depth_mm, surface.mask)
        rows.append(f"| {label} | {error:.3f} | {100 * given:.2f} % | {1000 * np.median(times):.0f} ms |")
    h, w = surface.mask.shape
    lines = ["## Integration on real data (`photopft bench integration`)", "",
             f"{folder.name} ({folder.parent.name}): real normals and depth, {w} x {h}, "
             f"{int(surface.mask.sum())} pixels on the object; perspective, metric, anchored at the median true "
             f"depth; error: mean absolute depth error after removing the offset; time: median of {repeat} runs, "
             f"{numba.get_num_threads()} numba threads.", "",
             "| integrator | error (mm) | pixels given a depth | time |", "|---|---|---|---|", *rows, "",
             "Target: the accurate solver at most 1.0 mm. For reference (the data's README): BiNI 0.334 mm in about "
             "1.3 s; a plain orthographic DCT Poisson solve 3.27 mm in about 20 ms."]
    text = "\n".join(lines)
    if write:
        write_section("integration", text)
    return text


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench integration`: its arguments and what it runs."""
    ig = what.add_parser("integration", help="normals to depth on real data (DiLiGenT bear): error and time")
    ig.add_argument("--data", type=Path, default=None,
                    help=f"a folder of real normals and depth (default {DILIGENT_BEAR})")
    ig.add_argument("--no-write", action="store_true", help="print only")
    ig.set_defaults(run=lambda args: print(run_integration(args.data or DILIGENT_BEAR, not args.no_write)) or 0)
