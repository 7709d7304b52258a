"""`photopft bench speed`: maps per second at 1400 x 1024 against plain numpy references."""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import write_section


def _rate(function, repeat: int) -> float:
    function()
    started = time.perf_counter()
    for _ in range(repeat):
        function()
    return repeat / (time.perf_counter() - started)


def numpy_near_normals(signal: np.ndarray, points: np.ndarray, positions: np.ndarray,
                       intensity: np.ndarray) -> np.ndarray:
    """Plain numpy reference: per-pixel light vectors and falloff, a 3 x 3 solve per pixel."""
    d = positions[None, None] - points[:, :, None, :]
    r2 = np.sum(d * d, axis=-1)
    rows = d / (np.sqrt(r2) * r2)[..., None] * intensity[None, None, :, None]
    normal = np.einsum("hwki,hwkj->hwij", rows, rows)
    rhs = np.einsum("hwki,khw->hwi", rows, signal)
    m = np.linalg.solve(normal, rhs[..., None])[..., 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        return m / np.linalg.norm(m, axis=-1, keepdims=True)


def numpy_poisson(gu: np.ndarray, gv: np.ndarray) -> np.ndarray:
    """Plain numpy reference: Poisson solve by FFT of the mirrored gradient field (Frankot-Chellappa)."""
    gu = np.nan_to_num(gu)
    gv = np.nan_to_num(gv)
    h, w = gu.shape
    gu_m = np.block([[gu, -gu[:, ::-1]], [gu[::-1, :], -gu[::-1, ::-1]]])
    gv_m = np.block([[gv, gv[:, ::-1]], [-gv[::-1, :], -gv[::-1, ::-1]]])
    fy = np.fft.fftfreq(2 * h)[:, None] * 2 * np.pi
    fx = np.fft.fftfreq(2 * w)[None, :] * 2 * np.pi
    denominator = fx**2 + fy**2
    denominator[0, 0] = 1.0
    z = (-1j * fx * np.fft.fft2(gu_m) - 1j * fy * np.fft.fft2(gv_m)) / denominator
    z[0, 0] = 0.0
    return np.real(np.fft.ifft2(z))[:h, :w]


def run_speed(write: bool, repeat: int = 20) -> str:
    import cv2
    import numba

    from core.reconstruction.integrate import ROBUST_ITERATIONS, integrate_masked, log_depth_dct, log_depth_gradients
    from core.reconstruction.lightfield import LightField, light_field, normals_from_field
    from core.reconstruction.photometric import distant_light_normals
    from core.reconstruction.pipeline import default_pseudo_light_vectors, subject_mask
    from core.reconstruction.prefilter import prefilter_frame, prefilter_sigma_px
    from core.io.session import SessionFile
    from core.sim.breathing import Sway
    from core.sim.simulate import SimConfig, simulate

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "torso.h5"
        simulate(path, SimConfig(scene="torso", protocol="static", seconds=5 / 110, scale=1.0, heads=("front",),
                                 sway=Sway(0, 0, 0), truth_maps_at=[4]))
        with SessionFile(path) as s:
            head = s.rig.heads["front"]
            frames = s.frames("front")[:5]
            truth_depth = np.asarray(s.truth()["front/depth_mm"][0], dtype=np.float64)
    lit = np.ascontiguousarray(frames[:4])
    dark = np.ascontiguousarray(frames[4])
    signal = lit.astype(np.float64) - dark.astype(np.float64)
    mask = subject_mask(signal, 0.1)
    depth = np.where(mask, np.nan_to_num(truth_depth, nan=2000.0), np.nan)
    pseudo = default_pseudo_light_vectors(head)
    field = light_field(head, depth)
    rows = np.broadcast_to((pseudo * head.light_intensity[:, None] / 2000.0**2)[None, None],
                           field.rows.shape).astype(np.float32)
    distant_field = LightField(field.step, np.ascontiguousarray(rows),
                               np.ascontiguousarray(np.broadcast_to(np.linalg.pinv(rows[0, 0]), field.pinv.shape)))
    full = float(head.max_value)
    normals = np.empty(head.shape + (3,), np.float32)
    albedo = np.empty(head.shape, np.float32)
    min_signal = 0.01 * full
    points = np.ascontiguousarray((np.stack(np.broadcast_arrays(
        ((np.arange(head.width) - head.cx) / head.fx)[None], ((np.arange(head.height) - head.cy) / head.fy)[:, None],
        1.0), -1) * np.nan_to_num(depth, nan=2000.0)[..., None]))
    figures = {
        "distant": _rate(lambda: normals_from_field(lit, dark, distant_field, min_signal, full, normals, albedo),
                         repeat),
        "distant_numpy": _rate(lambda: distant_light_normals(lit, dark, pseudo), 3),
        "near": _rate(lambda: normals_from_field(lit, dark, field, min_signal, full, normals, albedo), repeat),
        "near_numpy": _rate(lambda: numpy_near_normals(signal, points, head.light_positions_mm,
                                                       head.light_intensity), 2),
        "field": _rate(lambda: light_field(head, depth), 5),
    }
    # At 1400 px wide the pipeline solves from prefiltered images (core/reconstruction/prefilter.py): in a stream
    # each frame is filtered once as it arrives, so a map costs one frame's filter more.
    sigma_px = prefilter_sigma_px(head.width)
    filtered_lit = np.stack([prefilter_frame(frame, sigma_px) for frame in lit])
    filtered_dark = prefilter_frame(dark, sigma_px)
    arriving = itertools.count()

    def near_prefiltered() -> None:
        k = next(arriving) % 4
        prefilter_frame(lit[k], sigma_px, out=filtered_lit[k])
        normals_from_field(filtered_lit, filtered_dark, field, min_signal, full, normals, albedo)

    # OpenCV on one thread: its pool's threads, spinning after each call, held up numba's
    # (measured in a stream of frames: 96 maps/s with OpenCV's two threads, 106 with one)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        figures["near_prefiltered"] = _rate(near_prefiltered, repeat)
    finally:
        cv2.setNumThreads(threads)
    near_normals, _ = normals_from_field(lit, dark, field, min_signal, full)
    figures["depth_fast"] = _rate(lambda: log_depth_dct(near_normals, mask, head.fx, head.fy, head.cx, head.cy),
                                  repeat)

    def numpy_depth() -> None:
        g1, g2 = log_depth_gradients(near_normals.astype(np.float64), head.fx, head.fy, head.cx, head.cy)
        numpy_poisson(np.where(mask, g1, 0.0), np.where(mask, g2, 0.0))

    figures["depth_numpy"] = _rate(numpy_depth, 3)
    gradients = log_depth_gradients(near_normals, head.fx, head.fy, head.cx, head.cy)
    figures["depth_masked"] = _rate(lambda: integrate_masked(*gradients, mask, robust_iterations=0), 5)
    figures["depth_robust"] = _rate(lambda: integrate_masked(*gradients, mask), 3)

    lines = ["## Speed (`photopft bench speed`)", "",
             f"One head at {head.width} x {head.height}, a rendered torso cycle, {numba.get_num_threads()} threads, "
             "maps per second (higher is better); each against a plain numpy implementation of the same "
             "computation, timed in the same run.", "",
             "| what | photopft | numpy reference | ratio |", "|---|---|---|---|",
             f"| distant-light normal maps | {figures['distant']:.1f}/s | {figures['distant_numpy']:.1f}/s | "
             f"{figures['distant'] / figures['distant_numpy']:.1f}x |",
             f"| near-light normal maps (light field on a {field.step}-px grid) | {figures['near']:.1f}/s | "
             f"{figures['near_numpy']:.2f}/s (per-pixel solve) | {figures['near'] / figures['near_numpy']:.0f}x |",
             f"| the same from prefiltered frames (Gaussian, sigma {sigma_px:.2f} px; one frame filtered per map) | "
             f"{figures['near_prefiltered']:.1f}/s | | |",
             f"| light field update (when the depth changes) | {figures['field']:.1f}/s | | |",
             f"| depth maps, fast (DCT, log-depth) | {figures['depth_fast']:.1f}/s | {figures['depth_numpy']:.1f}/s "
             f"(FFT Poisson) | {figures['depth_fast'] / figures['depth_numpy']:.1f}x |",
             f"| depth maps, masked least squares (the default; conjugate gradients, DCT-preconditioned) | "
             f"{figures['depth_masked']:.1f}/s | | |",
             f"| the same, robust to depth steps (reweighted {ROBUST_ITERATIONS} times; a cycle's final depth) | "
             f"{figures['depth_robust']:.1f}/s | | |", "",
             "Targets: near-light normal maps >= 110/s per head (the camera rate), depth maps >= 25/s."]
    text = "\n".join(lines)
    if write:
        write_section("speed", text)
    return text


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench speed`: its arguments and what it runs."""
    sp = what.add_parser("speed", help="maps per second at 1400 x 1024 against numpy references")
    sp.add_argument("--no-write", action="store_true", help="print only")
    sp.set_defaults(run=lambda args: print(run_speed(not args.no_write)) or 0)
