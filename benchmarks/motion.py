"""`photopft bench motion`: maps and the volume through a forced expiration, as captured, extrapolated
and interpolated to one instant."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.accuracy import angular_error, depth_errors
from benchmarks.common import write_section


MOTION_LABELS = {"none": "as captured", "extrapolated": "extrapolated", "interpolated": "interpolated"}


def run_motion(write: bool, scale: float = 0.25) -> str:
    """Maps during a forced expiration, and the metric volume through it, with each light's frame as
    captured, extrapolated from the cycle before and interpolated towards the cycle after."""
    import h5py

    from core.io.results import optical_volume
    from core.io.session import SessionFile
    from core.reconstruction.pipeline import ReconstructionSettings
    from benchmarks.true_lights import with_true_lights
    from core.pipeline.head_maps import MOTION_MODES
    from core.pipeline.process import process_session
    from core.sim.breathing import Sway
    from core.sim.simulate import SimConfig, simulate

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        session = folder / "forced.h5"
        blow_frame = 692  # the blow starts 6.29 s in: one tidal breath, 1.6 s inhalation, 0.4 s hold
        frames = [blow_frame + k for k in (2, 7, 12, 17, 22, 27, 32, 42, 52, 62)]
        simulate(session, SimConfig(protocol="forced", seconds=8.0, scale=scale, heads=("front",),
                                    sway=Sway(0, 0, 0), truth_maps_at=frames))
        with SessionFile(session) as s:
            calibration = with_true_lights(s)
            truth = s.truth()
            true_normals = truth["front/normals"][:]
            true_depth = truth["front/depth_mm"][:]
        table = {}
        for mode in MOTION_MODES:
            out = folder / f"r-{mode}.h5"
            process_session(session, out, calibration=calibration, maps_at=frames, heads=["front"], every=1000,
                            motion_compensation=mode,
                            settings=ReconstructionSettings(integrator="masked", iterations=3))
            with h5py.File(out) as f:
                normals = f["heads/front/maps/normals"][:]
                depth = f["heads/front/maps/depth_mm"][:]
            angles, heights = [], []
            for k in range(len(frames)):
                ok = np.isfinite(normals[k][..., 2]) & np.isfinite(true_normals[k][..., 2])
                angles.append(angular_error(normals[k], true_normals[k], ok))
                heights.append(depth_errors(depth[k], true_depth[k], ok)[1])
            table[mode] = (angles, heights)
        # the volume through the blow: both heads, every light cycle, as `process` makes it
        both = folder / "forced-both.h5"
        simulate(both, SimConfig(protocol="forced", seconds=9.0, scale=scale, sway=Sway(0, 0, 0), truth_maps_at=[],
                                 seed=2))
        with SessionFile(both) as s:
            calibration = with_true_lights(s)
            truth_t, truth_v = s.truth()["timestamp_ns"][:], s.truth()["volume_l"][:]
        volumes = {}
        for mode in MOTION_MODES:
            out = folder / f"v-{mode}.h5"
            process_session(both, out, calibration=calibration, motion_compensation=mode)
            t_ns, volume = optical_volume(out)
            volumes[mode] = _volume_through_blow(t_ns, volume, np.interp(t_ns, truth_t, truth_v))
    lines = ["## Motion within a cycle (`photopft bench motion`)", "",
             f"A forced expiration (PEF 9.6 L/s), front head at {scale:g} x 1400 x 1024, true lights, no sway; maps "
             "during the first 0.6 s of the blow, against the true surface at the map's (newest) frame. "
             "Each light's frame as captured, extrapolated to the newest frame's instant along the same light's "
             "frame one cycle earlier (the live view), or interpolated towards its frame one cycle later "
             "(`process`); the change spatially smoothed, 2 px.", "",
             "| ms after the blow starts | " + " | ".join(f"{(f - blow_frame) / 0.11:.0f}" for f in frames) + " |",
             "|---|" + "---|" * len(frames)]
    for mode, label in MOTION_LABELS.items():
        angles, heights = table[mode]
        lines.append(f"| angular error (deg), {label} | " + " | ".join(f"{a:.2f}" for a in angles) + " |")
        lines.append(f"| height error (mm), {label} | " + " | ".join(f"{h:.2f}" for h in heights) + " |")
    lines += ["", "Mean height error " + ", ".join(f"{np.mean(table[m][1]):.2f} mm {label}"
                                                   for m, label in MOTION_LABELS.items())
              + "; mean angular error " + ", ".join(f"{np.mean(table[m][0]):.2f}" for m in MOTION_LABELS) + " deg.",
              "", "The metric volume through a forced expiration (our torso, both heads, 9 s, seed 2, true lights, "
              "no sway, every light cycle, `process` defaults but the motion), against the true volume at each "
              "map's instant after a straight-line fit (its slope the scale); PEF read straight from the samples "
              "against the truth sampled at the same instants:", "",
              "| frames | slope | residual rms (mL) | largest residual (mL) | PEF (L/s) | truth's PEF at those instants |",
              "|---|---|---|---|---|---|"]
    for mode, label in MOTION_LABELS.items():
        v = volumes[mode]
        lines.append(f"| {label} | {v['slope']:.4f} | {v['rms_ml']:.1f} | {v['largest_ml']:.1f} | {v['pef']:.2f} | "
                     f"{v['true_pef']:.2f} |")
    text = "\n".join(lines)
    if write:
        write_section("motion", text)
    return text


def _volume_through_blow(t_ns: np.ndarray, volume_l: np.ndarray, truth_l: np.ndarray) -> dict[str, float]:
    """A volume curve against the truth at its samples: the slope and residuals of a straight-line fit,
    and the largest fall in L/s between samples (PEF read straight) of each."""
    ok = np.isfinite(volume_l)
    t, v, true = t_ns[ok] / 1e9, volume_l[ok], truth_l[ok]
    design = np.c_[true, np.ones(len(true))]
    coef = np.linalg.lstsq(design, v, rcond=None)[0]
    residual = v - design @ coef
    return {"slope": float(coef[0]), "rms_ml": 1000 * float(residual.std()),
            "largest_ml": 1000 * float(np.abs(residual).max()),
            "pef": float(np.max(-np.diff(v) / np.diff(t))), "true_pef": float(np.max(-np.diff(true) / np.diff(t)))}


def add(what: argparse._SubParsersAction) -> None:
    """`photopft bench motion`: its arguments and what it runs."""
    mo = what.add_parser("motion", help="maps and the volume during a forced expiration, as captured, "
                                        "extrapolated and interpolated to one instant")
    mo.add_argument("--no-write", action="store_true", help="print only")
    mo.set_defaults(run=lambda args: print(run_motion(not args.no_write)) or 0)
