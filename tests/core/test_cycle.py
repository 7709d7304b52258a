"""One light cycle's signal (core/reconstruction/cycle.py), as process and the live view both make it."""

import numpy as np
import pytest

from core.reconstruction.cycle import cycle_frame, cycle_signal_of


def _frame(value: float, frame_id: int, shape=(8, 12), saturate=False):
    raw = np.full(shape, value, dtype=np.uint16)
    if saturate:
        raw[0, 0] = 4095
    return cycle_frame(raw, 2, 4095, frame_id / 110.0, frame_id)


def test_binning_saturation_and_dark():
    lit = [_frame(1000 + 100 * k, 10 + k, saturate=k == 2) for k in range(4)]
    signal, saturated, dark = cycle_signal_of(lit, _frame(200, 14))
    assert signal.shape == (4, 4, 6) and dark.shape == (4, 6)
    np.testing.assert_allclose(signal[:, 1, 1], [800, 900, 1000, 1100])
    assert saturated[2, 0, 0] and saturated.sum() == 1  # the bin that holds the saturated pixel


def test_motion_compensation_brings_each_light_to_the_newest_frame():
    """A scene brightening by 5 counts a frame: each light's frame is carried to the cycle's newest
    instant (frame 14), so the four lights see one instant, not four."""
    def level(i: int) -> float:
        return 1000 + 5 * i

    lit = [_frame(level(10 + k), 10 + k) for k in range(4)]
    before = [_frame(level(5 + k), 5 + k) for k in range(4)]
    static, _, _ = cycle_signal_of(lit, _frame(0, 14))
    moving, _, _ = cycle_signal_of(lit, _frame(0, 14), before)
    np.testing.assert_allclose(static[:, 2, 2], [level(10), level(11), level(12), level(13)])
    np.testing.assert_allclose(moving[:, 2, 2], [level(14)] * 4)


def test_a_recorded_cycle_is_interpolated_between_its_own_frames_and_the_next_cycle_s():
    """A scene whose brightness curves in time (a blow speeding up): extrapolated from the cycle before,
    each light lands off by half the change's curvature over a period (f'' T^2 / 2) times ahead (1 + ahead),
    ahead being its share of a period before the newest frame; interpolated towards the cycle after, by
    the same times ahead (1 - ahead), at most a quarter of it. A straight change is met exactly by both."""
    def curved(i: float) -> float:
        return 1000 + 2.0 * i * i

    def straight(i: float) -> float:
        return 1000 + 5.0 * i

    for level, exact in ((straight, True), (curved, False)):
        lit = [_frame(level(10 + k), 10 + k) for k in range(4)]
        before = [_frame(level(5 + k), 5 + k) for k in range(4)]
        after = [_frame(level(15 + k), 15 + k) for k in range(4)]
        extrapolated, _, _ = cycle_signal_of(lit, _frame(0, 14), before)
        interpolated, _, _ = cycle_signal_of(lit, _frame(0, 14), before, following=after)
        error_extrapolated = extrapolated[:, 2, 2] - level(14)
        error_interpolated = interpolated[:, 2, 2] - level(14)
        if exact:
            np.testing.assert_allclose(error_interpolated, 0.0, atol=1e-9)
            np.testing.assert_allclose(error_extrapolated, 0.0, atol=1e-9)
        else:  # 2 i^2 between frames 5 apart: the curvature's share 2 * 25 = 50 counts
            ahead = (14 - np.arange(10, 14)) / 5.0
            np.testing.assert_allclose(error_extrapolated, -50 * ahead * (1 + ahead), rtol=1e-9)
            np.testing.assert_allclose(error_interpolated, 50 * ahead * (1 - ahead), rtol=1e-9)
            assert np.all(np.abs(error_interpolated) <= 50 / 4 + 1e-9)


def test_flicker_is_taken_out_of_every_frame():
    lit = [_frame(1000, 10 + k) for k in range(4)]
    def excess(f):
        return np.full((4, 6), 10.0 * (f.frame_id - 10))

    signal, _, dark = cycle_signal_of(lit, _frame(200, 14), excess=excess)
    np.testing.assert_allclose(dark, 200 - 40)
    np.testing.assert_allclose(signal[:, 0, 0], [1000 - 0 * 10 - 160, 1000 - 10 - 160, 1000 - 20 - 160, 1000 - 30 - 160])


def test_process_interpolates_where_a_cycle_follows_and_extrapolates_the_last():
    from core.pipeline.head_maps import motion_mode, neighbour_cycles

    windows = {14: "cycle 10-14", 19: "cycle 15-19", 24: "cycle 20-24"}
    assert motion_mode(True) == "interpolated" and motion_mode(False) == "none"
    assert neighbour_cycles(windows, 19, 5, "interpolated") == ("cycle 10-14", "cycle 20-24")
    assert neighbour_cycles(windows, 24, 5, "interpolated") == ("cycle 15-19", None)  # the recording's last
    assert neighbour_cycles(windows, 19, 5, "extrapolated") == ("cycle 10-14", None)
    assert neighbour_cycles(windows, 19, 5, "none") == (None, None)
    with pytest.raises(ValueError, match="motion_compensation must be one of"):
        motion_mode("centred")
