"""One light cycle's signal (core/reconstruction/cycle.py), as process and the live view both make it."""

import numpy as np

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


def test_flicker_is_taken_out_of_every_frame():
    lit = [_frame(1000, 10 + k) for k in range(4)]
    def excess(f):
        return np.full((4, 6), 10.0 * (f.frame_id - 10))

    signal, _, dark = cycle_signal_of(lit, _frame(200, 14), excess=excess)
    np.testing.assert_allclose(dark, 200 - 40)
    np.testing.assert_allclose(signal[:, 0, 0], [1000 - 0 * 10 - 160, 1000 - 10 - 160, 1000 - 20 - 160, 1000 - 30 - 160])
