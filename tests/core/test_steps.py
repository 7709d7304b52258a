"""Steps found in the body's in-plane shift (core/volume/steps.py)."""

import numpy as np

from core.sim.breathing import Sway
from core.volume.steps import STEP_MARGIN_S, maps_in_steps, step_spans_s

MAP_PERIOD_S = 5 / 110  # a map a light cycle


def shifts(seconds: np.ndarray, sway: Sway, noise_mm: float, seed: int = 0) -> np.ndarray:
    """The body's shift across and down the image (mm) as the body frame measures it."""
    shift = sway.at(seconds)[:, :2]
    return shift + np.random.default_rng(seed).normal(0.0, noise_mm, shift.shape)


def test_a_step_leaves_out_its_maps_and_sway_leaves_out_none():
    seconds = np.arange(0.0, 30.0, MAP_PERIOD_S)
    stamps = (seconds * 1e9).astype(np.int64)
    swaying = Sway(axial_mm=50.0, lateral_mm=15.0, vertical_mm=3.0, seed=4)
    still = maps_in_steps(stamps, shifts(seconds, swaying, 0.8))
    assert not still.any()

    stepping = Sway(axial_mm=50.0, lateral_mm=15.0, vertical_mm=3.0, seed=4, steps=3, steps_span_s=30.0)
    truth = np.linalg.norm(stepping.at(seconds) - swaying.at(seconds), axis=1)
    moving = np.abs(np.gradient(truth, seconds)) > 5.0  # mm/s of the steps alone
    sideways = np.abs(np.gradient(stepping.at(seconds)[:, 0] - swaying.at(seconds)[:, 0], seconds)).max()
    assert sideways > 60.0  # the draw holds steps with a sideways part the image plane shows
    found = maps_in_steps(stamps, shifts(seconds, stepping, 0.8))
    fast = np.abs(np.gradient(stepping.at(seconds)[:, 0] - swaying.at(seconds)[:, 0], seconds)) > 40.0
    assert found[fast].all()  # every map where the body moved sideways fast
    assert found.sum() < 1.2 * moving.sum() + 2 * STEP_MARGIN_S / MAP_PERIOD_S * 3
    spans = step_spans_s(stamps, found)
    assert 1 <= len(spans) <= 3
    assert all(b - a < 1.0 for a, b in spans)


def test_maps_without_a_shift_are_neither_steps_nor_an_error():
    seconds = np.arange(0.0, 5.0, MAP_PERIOD_S)
    stamps = (seconds * 1e9).astype(np.int64)
    shift = np.full((len(seconds), 2), np.nan)
    assert not maps_in_steps(stamps, shift).any()
    shift[::2] = 0.0
    assert not maps_in_steps(stamps, shift).any()


def _front_shifts(sway, seconds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The body frame's in-plane shift (mm) of a breathing average man's true front maps at these times."""
    from core.reconstruction.pipeline import trunk_mask
    from core.rig import thesis_head
    from core.sim.bodies import PRESETS, body_surfaces
    from core.sim.render import CameraModel
    from core.sim.scene import Digitiser, HeightFieldScene
    from core.volume.maps import DisplacementTracker

    surfaces = body_surfaces(PRESETS["average-man"], 4.0)
    scene = HeightFieldScene(surfaces, 2100.0, 4200.0,
                             mode_amplitudes=lambda t: 8.0 * np.sin(2 * np.pi * t / 4.0) * np.ones(3), sway=sway)
    digitiser = Digitiser(CameraModel(noise=False), 12)
    head = thesis_head("front", scale=0.25)
    tracker = DisplacementTracker(head)
    shift = []
    for t in seconds:
        maps = scene.render(head, float(t), 1, np.uint64(0), digitiser, want_maps=True)[1]
        trunk = trunk_mask(np.isfinite(maps.depth_mm), maps.normals)
        shift.append(tracker.add(maps.depth_mm, trunk, trunk, 2100.0).body_shift_mm)
    return (seconds * 1e9).astype(np.int64), np.array(shift)


def test_the_body_frame_follows_a_step_sideways_on_true_maps_and_only_the_step_is_left_out():
    """A 40 mm step sideways within 0.5 s, on maps rendered from a breathing body with slow sway: the
    body frame's shift follows it in millimetres, and only the maps about the step are left out."""
    seconds = np.arange(0.0, 4.0, 2 * MAP_PERIOD_S)

    def sway(t):
        progress = np.clip((t - 2.0) / 0.5, 0.0, 1.0)
        step = 40.0 * progress * progress * (3.0 - 2.0 * progress)
        return np.array([5.0 * np.sin(1.3 * t) + step, 0.0, 10.0 * np.sin(0.9 * t)])

    stamps, shift = _front_shifts(sway, seconds)
    moved = shift[-1, 0] - shift[0, 0]
    assert abs(abs(moved) - (40.0 + 5.0 * np.sin(1.3 * seconds[-1]))) < 4.0  # mm, the step and the sway
    found = maps_in_steps(stamps, shift)
    assert found[(seconds > 2.15) & (seconds < 2.35)].all()
    assert not found[(seconds < 1.8) | (seconds > 2.7)].any()


def test_the_live_view_blanks_a_step_as_it_happens_and_not_sway():
    """StepWatch, causal: the maps where the body moves sideways fast are blanked as they come (lagging by
    about 0.1 s, the line's half-width), sway is not."""
    from core.volume.steps import StepWatch

    seconds = np.arange(0.0, 30.0, MAP_PERIOD_S)
    swaying = Sway(seed=4)
    stepping = Sway(seed=4, steps=3, steps_span_s=30.0)
    for sway, steps in ((swaying, False), (stepping, True)):
        watch = StepWatch()
        shift = shifts(seconds, sway, 0.8)
        blanked = np.array([watch.moving(t, tuple(s)) for t, s in zip(seconds, shift)])
        if not steps:
            assert not blanked.any()
            continue
        fast = np.abs(np.gradient(stepping.at(seconds)[:, 0] - swaying.at(seconds)[:, 0], seconds)) > 45.0
        # causal, it lags by about a tenth of a second: from its fastest maps on, and some of every step
        runs = np.split(np.flatnonzero(fast), np.flatnonzero(np.diff(np.flatnonzero(fast)) > 1) + 1)
        assert all(blanked[run].any() for run in runs)
        assert blanked[fast].mean() >= 0.6
        assert blanked.mean() < 0.1


def test_the_maps_series_are_not_smoothed_across_a_step_s_gap():
    """The two heads' distances are smoothed over 0.3 s; across the half second of maps a step leaves
    out, the body stands 50 mm further after it than before. Smoothed as one series, the maps beside
    the gap took in the other side's distance (over 15 mm off); in pieces (MAX_SMOOTHED_GAP_S) each
    keeps its own. A single map missing (91 ms) is smoothed across."""
    from core.volume.maps import smooth_in_time
    from core.volume.metric import MAX_SMOOTHED_GAP_S, WIDTH_SMOOTHING_S

    t = np.arange(0.0, 10.0, MAP_PERIOD_S)
    t = t[(t < 5.0) | (t > 5.5)]
    distance = np.where(t < 5.0, 2000.0, 2050.0)
    assert np.abs(smooth_in_time(t, distance, WIDTH_SMOOTHING_S) - distance).max() > 15.0
    assert np.abs(smooth_in_time(t, distance, WIDTH_SMOOTHING_S, MAX_SMOOTHED_GAP_S) - distance).max() < 1e-9
    one_missing = np.delete(np.arange(0.0, 10.0, MAP_PERIOD_S), 100)
    ramp = one_missing * 3.0
    assert np.array_equal(smooth_in_time(one_missing, ramp, WIDTH_SMOOTHING_S, MAX_SMOOTHED_GAP_S),
                          smooth_in_time(one_missing, ramp, WIDTH_SMOOTHING_S))
