"""Binning for the live view: the binned head sees the same rays; averages and saturation per bin."""

from __future__ import annotations

import numpy as np
import pytest

from core.reconstruction.binning import bin_all, bin_any, bin_mean, binned_head, working_binning
from core.rig import thesis_head


def test_a_binned_pixel_sees_the_mean_ray_of_its_pixels():
    head = thesis_head(scale=0.5)
    binned = binned_head(head, 2)
    assert (binned.width, binned.height) == (350, 256)
    u, v = head.pixel_rays()
    bu, bv = binned.pixel_rays()
    np.testing.assert_allclose(bu, bin_mean(u, 2), atol=1e-12)
    np.testing.assert_allclose(bv, bin_mean(v, 2), atol=1e-12)
    assert binned.focal_length_mm == pytest.approx(head.focal_length_mm)
    np.testing.assert_array_equal(binned.light_positions_mm, head.light_positions_mm)


def test_bins_average_and_a_saturated_pixel_spoils_its_bin():
    image = np.arange(2 * 5 * 7, dtype=np.uint16).reshape(2, 5, 7)
    got = bin_mean(image, 2)
    assert got.shape == (2, 2, 3)
    assert got[1, 1, 2] == image[1, 2:4, 4:6].mean()
    flags = np.zeros((5, 7), bool)
    flags[3, 5] = True
    assert bin_any(flags, 2).tolist() == [[False, False, False], [False, False, True]]
    inside = ~flags
    assert bin_all(inside, 2).tolist() == [[True, True, True], [True, True, False]]


def test_working_binning_brings_a_head_near_the_live_width():
    assert [working_binning(thesis_head(scale=s)) for s in (0.25, 0.5, 1.0)] == [1, 2, 4]
    with pytest.raises(ValueError, match="positive whole number"):
        binned_head(thesis_head(scale=0.25), 0)


def test_frame_bins_equal_the_plain_reductions():
    """The one-pass kernel (mean and max of each bin) against numpy's reductions, remainders dropped."""
    from core.reconstruction.binning import _blocks, frame_bins

    rng = np.random.default_rng(4)
    for dtype, factor, shape in ((np.uint16, 4, (103, 141)), (np.uint8, 3, (50, 61)), (np.uint16, 1, (7, 9))):
        frame = rng.integers(0, np.iinfo(dtype).max, shape).astype(dtype)
        mean, peak = frame_bins(frame, factor)
        blocks = _blocks(frame, factor)
        np.testing.assert_allclose(mean, blocks.mean(axis=(-3, -1)), rtol=1e-12)
        np.testing.assert_array_equal(peak, blocks.max(axis=(-3, -1)))


def test_a_frames_mean_is_its_bins_mean_without_binning_it():
    from core.reconstruction.binning import frame_mean

    rng = np.random.default_rng(4)
    frame = rng.integers(0, 4096, size=(103, 141)).astype(np.uint16)  # remainders on both axes
    for factor in (1, 2, 4):
        assert frame_mean(frame, factor) == pytest.approx(bin_mean(frame, factor).mean(), rel=1e-12)
    assert frame_mean(frame.astype(float), 4) == pytest.approx(bin_mean(frame, 4).mean(), rel=1e-12)
