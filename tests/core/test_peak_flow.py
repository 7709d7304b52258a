"""A forced blow's peak flow read on maps at every frame through it (core/pipeline/volume_stage.py,
peak_flow_pass; core/analysis/values.py, peak_flow_of_frames), beside the session's map a cycle."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from scipy import ndimage

from benchmarks.blows import CYCLE_S, FRAME_S, maps_of
from app.cli import main
from core.analysis.session_analysis import analyse_session
from core.sim.truth import truth_values
from core.analysis.spirometry import forced_values
from core.analysis.values import (ANALYSIS_RATE_HZ, MAX_PEF_NOISE_RATIO_FRAMES, PEAK_FLOW_REACH_S, PEAK_FLOW_SIGMAS_S,
                                  analyse_volume, flow_noise_gain, peak_flow_spans_s)
from core.io.results import optical_inputs
from core.pipeline.process import process_session
from core.sim.breathing import RATE_HZ, ForcedBlow, Subject, Sway, forced
from core.sim.simulate import SimConfig, simulate
from core.analysis.optical_litres import POPULATION_GAIN
from core.volume.maps import smooth_in_time, uneven_steps


def test_smoothing_in_time_weighs_a_stretch_of_maps_at_every_frame_by_time_not_by_sample():
    """A 4 Hz sine sampled a map a cycle with a second of maps at every frame in the middle: smoothed
    with sigma 30 ms, both stretches keep the Gaussian's exp(-(2 pi f sigma)^2 / 2) = 0.75 of it (within
    0.003 of the amplitude, as on even steps); within 4 sigma of where the steps change, within 0.08
    (a Gaussian mean without the line: 0.39). Taking sigma in samples of the median step (as an even
    series is smoothed) the dense second kept 0.99."""
    coarse = np.arange(0.0, 10.0, CYCLE_S)
    dense = np.arange(4.0, 5.0, FRAME_S)
    t = np.union1d(coarse, dense)
    x = np.sin(2 * np.pi * 4.0 * t)
    assert uneven_steps(t) and not uneven_steps(coarse) and not uneven_steps(dense)
    smoothed = smooth_in_time(t, x, 0.03)
    kept = np.exp(-0.5 * (2 * np.pi * 4.0 * 0.03) ** 2)
    inner = (t > 1.0) & (t < 9.0)
    near = inner & ((np.abs(t - 4.0) < 0.12) | (np.abs(t - 5.0) < 0.12))
    error = np.abs(smoothed - kept * x)
    assert error[inner & ~near].max() < 0.005 and error[near].max() < 0.08
    even = smooth_in_time(coarse, np.sin(2 * np.pi * 4.0 * coarse), 0.03)  # an even series: unchanged path
    step = float(np.median(np.diff(coarse)))
    assert np.array_equal(even, ndimage.gaussian_filter1d(np.sin(2 * np.pi * 4.0 * coarse), 0.03 / step,
                                                          mode="nearest"))


def _blow(effort: float = 1.0) -> tuple[np.ndarray, np.ndarray, list[tuple[float, str]], float]:
    """(t, volume at RATE_HZ, events, true PEF) of one good forced expiration from the simulator's subject."""
    exhaled, events = forced(Subject(), ForcedBlow(effort=effort), np.random.default_rng(3))
    t = np.arange(len(exhaled)) / RATE_HZ
    start = next(s for s, label in events if label == "forced-start")
    blow = exhaled[int(start * RATE_HZ):]
    truth = forced_values(blow[0] - blow[: int(6.0 * RATE_HZ)], RATE_HZ)
    return t, exhaled, events, truth.pef_lps


def _sampled(t: np.ndarray, volume: np.ndarray, step_s: float, phase_s: float) -> tuple[np.ndarray, np.ndarray]:
    times, values = maps_of(volume, RATE_HZ, phase_s, step_s)
    return times, values


def test_the_spans_lie_about_the_blows_steepest_fall_and_hold_its_peak_flow():
    t, volume, events, _ = _blow()
    tc, vc = _sampled(t, volume, CYCLE_S, 0.0)
    spans = peak_flow_spans_s(tc, vc, events)
    assert len(spans) == 1
    a, b = spans[0]
    assert b - a == pytest.approx(2 * PEAK_FLOW_REACH_S)
    peak_at = t[1:][np.argmax(-np.diff(volume))]
    assert a + 0.1 < peak_at < b - 0.1
    assert peak_flow_spans_s(tc, vc, [(e, label) for e, label in events if label != "forced-start"]) == []


def test_a_blows_pef_is_read_on_its_maps_at_every_frame_where_they_hold_its_peak():
    """Over 10 phases of the light cycle, one map a cycle reads this blow's PEF 6-10 % low; the same curve
    with maps at every frame through the span reads it 3.6-3.9 % low at every phase (each map the mean
    over its cycle, as the bench samples them), and says it did (pef_step_s)."""
    t, volume, events, true_pef = _blow()
    errors_cycle, errors_frames = [], []
    for phase in np.arange(10) * CYCLE_S / 10:
        tc, vc = _sampled(t, volume, CYCLE_S, phase)
        (a, b), = peak_flow_spans_s(tc, vc, events)
        tf, vf = _sampled(t, volume, FRAME_S, phase)
        inside = (tf >= a) & (tf <= b)
        per_cycle = analyse_volume(tc, vc, events, fitted=True)
        per_frame = analyse_volume(tc, vc, events, fitted=True, peak_flow_volume=(tf[inside], vf[inside]))
        assert np.isnan(per_cycle.forced.pef_step_s)
        assert per_frame.forced.pef_step_s == pytest.approx(FRAME_S, rel=1e-3)
        assert per_frame.forced.fev1_l == per_cycle.forced.fev1_l  # only the PEF is read on them
        errors_cycle.append(per_cycle.forced.pef_lps / true_pef - 1)
        errors_frames.append(per_frame.forced.pef_lps / true_pef - 1)
    assert min(errors_cycle) < -0.08 and np.ptp(errors_cycle) > 0.04
    assert max(np.abs(errors_frames)) < 0.045 and np.ptp(errors_frames) < 0.005


def test_a_blow_read_on_its_maps_at_every_frame_is_drawn_through_them_and_its_loop_peaks_at_its_pef():
    """The report's flow-volume loop is drawn from forced_curves: read on maps at every frame, a blow's curve
    runs through them, so its flow peaks at the PEF given (within 1 %; the fitted curve alone peaks 3 %
    lower); outside their span it is the fitted curve, and its end (FVC) is where it was."""
    t, volume, events, true_pef = _blow()
    tc, vc = _sampled(t, volume, CYCLE_S, 0.0)
    (a, b), = peak_flow_spans_s(tc, vc, events)
    tf, vf = _sampled(t, volume, FRAME_S, 0.0)
    inside = (tf >= a) & (tf <= b)
    per_cycle = analyse_volume(tc, vc, events, fitted=True)
    per_frame = analyse_volume(tc, vc, events, fitted=True, peak_flow_volume=(tf[inside], vf[inside]))
    fitted, drawn = per_cycle.forced_curves[0], per_frame.forced_curves[0]
    pef = per_frame.forced.manoeuvres[0].pef_lps
    drawn_peak = float(np.gradient(drawn, 1.0 / ANALYSIS_RATE_HZ).max())
    assert drawn_peak == pytest.approx(pef, rel=0.01)
    assert float(np.gradient(fitted, 1.0 / ANALYSIS_RATE_HZ).max()) < 0.98 * pef
    assert len(drawn) == len(fitted) and drawn[-1] == fitted[-1]
    changed = np.nonzero(drawn != fitted)[0]
    assert (len(changed) / ANALYSIS_RATE_HZ) <= b - a + 0.01
    step_at_seams = np.abs(np.diff(drawn))[[changed[0] - 1, changed[-1]]]
    assert step_at_seams.max() < pef / ANALYSIS_RATE_HZ  # no jump where the maps join the fitted curve


def test_maps_at_every_frame_that_miss_the_peak_or_hold_a_gap_leave_the_blow_its_map_a_cycle():
    t, volume, events, _ = _blow()
    tc, vc = _sampled(t, volume, CYCLE_S, 0.3 * CYCLE_S)
    (a, b), = peak_flow_spans_s(tc, vc, events)
    tf, vf = _sampled(t, volume, FRAME_S, 0.0)
    per_cycle = analyse_volume(tc, vc, events, fitted=True).forced.pef_lps
    late = (tf >= b) & (tf <= b + 0.6)  # after the peak: the flow only falls there
    assert np.isnan(analyse_volume(tc, vc, events, fitted=True, peak_flow_volume=(tf[late], vf[late])).forced.pef_step_s)
    inside = np.nonzero((tf >= a) & (tf <= b))[0]
    middle = len(inside) // 2
    gap = np.delete(inside, np.arange(middle, middle + 4))  # four maps left out (an arm): 45 ms without one
    read = analyse_volume(tc, vc, events, fitted=True, peak_flow_volume=(tf[gap], vf[gap])).forced
    assert np.isnan(read.pef_step_s) and read.pef_lps == per_cycle


def test_a_map_a_cycle_missing_outside_the_span_leaves_the_pef_its_maps_at_every_frame_hold():
    """A map of the session's missing within PEAK_FLOW_WITHIN_S of the blow's top refuses its PEF at one map a
    cycle (the peak may lie there); where the maps at every frame hold the peak with none missing, one
    missing between the top and their span takes nothing from it."""
    t, volume, events, true_pef = _blow()
    tc, vc = _sampled(t, volume, CYCLE_S, 0.0)
    (a, b), = peak_flow_spans_s(tc, vc, events)
    tf, vf = _sampled(t, volume, FRAME_S, 0.0)
    inside = (tf >= a) & (tf <= b)
    before = int(np.nonzero(tc < a - 0.01)[0][-1])  # the last map a cycle before the span: after the top
    holed = vc.copy()
    holed[before] = np.nan
    per_cycle = analyse_volume(tc, holed, events, fitted=True)
    assert per_cycle.pef_refused is not None and "a map is missing" in per_cycle.pef_refused
    per_frame = analyse_volume(tc, holed, events, fitted=True, peak_flow_volume=(tf[inside], vf[inside]))
    assert per_frame.pef_refused is None and per_frame.forced.pef_step_s == pytest.approx(FRAME_S, rel=1e-3)
    assert abs(per_frame.forced.pef_lps / true_pef - 1) < 0.05


def test_noisy_maps_at_every_frame_are_smoothed_as_little_as_their_noise_allows_and_refused_past_it():
    """10 mL of white noise a map (a flow noise of 15 % of this blow's peak over a frame step): smoothed
    over the least sigma that brings it under MAX_PEF_NOISE_RATIO_FRAMES, and read within 10 %. 100 mL:
    over it at the widest smoothing too, and the PEF is refused with the limit at a map every frame."""
    t, volume, events, true_pef = _blow()
    tc, vc = _sampled(t, volume, CYCLE_S, 0.0)
    (a, b), = peak_flow_spans_s(tc, vc, events)
    tf, vf = _sampled(t, volume, FRAME_S, 0.0)
    inside = (tf >= a) & (tf <= b)
    draw = np.random.default_rng(0).normal(0.0, 1.0, inside.sum())
    values = analyse_volume(tc, vc, events, fitted=True, peak_flow_volume=(tf[inside], vf[inside] + 0.010 * draw))
    blow = values.forced.manoeuvres[0]
    assert 0 < blow.pef_smoothing_s < PEAK_FLOW_SIGMAS_S[-1] and blow.pef_noise_ratio <= MAX_PEF_NOISE_RATIO_FRAMES
    assert values.pef_refused is None and abs(values.forced.pef_lps / true_pef - 1) < 0.10
    values = analyse_volume(tc, vc, events, fitted=True, peak_flow_volume=(tf[inside], vf[inside] + 0.100 * draw))
    assert values.forced.manoeuvres[0].pef_smoothing_s == PEAK_FLOW_SIGMAS_S[-1]
    assert values.forced.pef_noise_ratio > MAX_PEF_NOISE_RATIO_FRAMES
    assert values.pef_refused is not None and "at a map every 9 ms" in values.pef_refused


def test_the_flow_noise_of_a_smoothed_curve_is_what_its_kernel_gives_white_noise():
    rng = np.random.default_rng(1)
    noise = rng.normal(0.0, 1.0, 200_000)
    for sigma in (0.0, 0.55, 1.1, 2.2):
        smoothed = ndimage.gaussian_filter1d(noise, sigma, mode="nearest") if sigma else noise
        assert np.std(np.diff(smoothed)) == pytest.approx(flow_noise_gain(sigma), rel=0.01)


def test_process_makes_maps_at_every_frame_through_the_blow_and_the_analysis_reads_its_pef(tmp_path, capsys):
    """One forced blow of our torso at scale 0.05, processed a map a cycle: /peak_flow_volume holds a map
    at every frame over the span about the blow's steepest fall, the session's own maps among them,
    and the session's analysis reads the optical PEF on them, as did the values process stored. The
    progress counts those maps: it rises through them to its end, not to its end before them."""
    session, results = tmp_path / "forced.h5", tmp_path / "results.h5"
    simulate(session, SimConfig(protocol="forced", scale=0.05, seed=2, blows=[ForcedBlow()], sway=Sway(0, 0, 0),
                                truth_maps_at=[]))
    shares: list[float] = []
    summary = process_session(session, results, progress=shares.append)
    assert shares[-1] == 1.0 and np.all(np.diff(shares) >= 0)
    with h5py.File(results) as f:
        g = f["peak_flow_volume"]
        t = g["timestamp_ns"][:] / 1e9
        (a, b), = g.attrs["spans_ns"] / 1e9
        made = int(g.attrs["maps_front"])
        assert int(g.attrs["maps_back"]) == made
        pass_ticks = 2 * (made + 1)  # each head's reference again and its new maps; then the end
        assert shares[-pass_ticks - 2] == pytest.approx(1 - pass_ticks / (len(shares) - 1), abs=0.01)
        assert np.isfinite(g["volume_l"][:]).all()
        session_maps = f["heads/front/timestamp_ns"][:] / 1e9
        stored_pef_lps = float(f["volume"].attrs["parameter_PEF_lps"])  # the values process keeps
    assert summary.maps["front"] == len(session_maps)  # the session's own maps are as before
    steps = np.diff(t)
    assert steps.max() < 1.5 * FRAME_S and t[0] - a < 2 * FRAME_S and b - t[-1] < 2 * FRAME_S
    assert len(t) == made + np.count_nonzero((session_maps >= a) & (session_maps <= b))
    report = analyse_session(session, **optical_inputs(results))
    assert report.optical.forced.pef_step_s == pytest.approx(FRAME_S, rel=0.05)
    # no slow VC to calibrate on: the optical estimate, the plain volume times the population's gain
    assert report.optical.forced.pef_lps / POPULATION_GAIN == pytest.approx(truth_values(session).forced.pef_lps, rel=0.2)
    assert stored_pef_lps == pytest.approx(report.optical.forced.pef_lps, rel=1e-9)
    # a results file whose maps at every frame were cut short: one line naming the file and the series
    with h5py.File(results, "r+") as f:
        volume = f["peak_flow_volume/volume_l"][:]
        del f["peak_flow_volume/volume_l"]
        f["peak_flow_volume/volume_l"] = volume[:-3]
    assert main(["analyze", str(results)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(results) in err[0] and "/peak_flow_volume/volume_l has" in err[0], err
