"""The displacement sums `process` keeps give back the optical signal it wrote, without the maps."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from core.io.results import ResultsFile
from core.rig import thesis_head
from core.volume.maps import (REGIONS, DisplacementTracker,
                              metric_head_volume_l, smooth_in_time)
from core.volume.metric import VOLUME_SMOOTHING_S


def test_the_stored_sums_give_back_each_heads_volume(processed_full_session):
    _, results = processed_full_session
    with ResultsFile(results) as r:
        stored = r.displacement_sums()
    assert set(stored) == {"front", "back"}
    compared = 0
    with h5py.File(results, "r") as f:
        t = f["metric_volume/timestamp_ns"][:]
        for head, sums in stored.items():
            assert sums["parts"] == list(REGIONS) + ["all"]
            maps = len(sums["timestamp_ns"])
            assert sums["reference"].shape == sums["displaced"].shape == (maps, 5) and sums["levels_mm"].shape == (maps, 2)
            assert 0.5 < sums["shown"].mean() <= 1.0
            assert sums["neck_mm"].shape == (maps,) and np.isfinite(sums["neck_mm"][sums["shown"]]).mean() > 0.9
            if f.attrs[f"level_{head}"] != "each map's own":
                continue  # the session's level is fitted from the band's statistics, not kept here
            kept = sums["shown"]
            volume = metric_head_volume_l(sums["reference"][kept, -1], sums["current"][kept, -1], sums["side_mm"][kept],
                                          sums["side_target_mm"][kept])
            on_t = np.interp(t.astype(float), sums["timestamp_ns"][kept].astype(float), volume)
            on_t = smooth_in_time(t / 1e9, on_t, VOLUME_SMOOTHING_S)
            written = f[f"metric_volume/heads/{head}/volume_l"][:]
            good = np.isfinite(written)
            assert np.nanmax(np.abs((on_t - on_t[good][0])[good] - written[good])) < 0.005, head
            compared += 1
    assert compared >= 1


def test_the_neck_s_displacement_is_kept_and_takes_a_shift_of_the_whole_map_out():
    """neck_mm, the median displacement of the trunk's top tenth of rows: a part's plain displacement less
    neck_mm times its area is what moved against the neck, whatever shifted the whole map."""
    from tests.core.test_metric_volume import _trunk_map

    head = thesis_head("front", scale=0.25)
    depth, mask = _trunk_map(head, 0.0)
    tracker = DisplacementTracker(head)
    assert tracker.add(depth, mask).neck_mm == 0.0
    rows = np.nonzero(mask.any(axis=1))[0]
    chest = np.zeros_like(depth)
    chest[rows[len(rows) // 6]:] = 10.0  # all but the top sixth of the trunk 10 mm further: most of its pixels
    chest = np.where(mask, chest, 0.0)
    footprint = (depth / head.fx) * (depth / head.fy)
    for shift_mm in (0.0, 6.0, -25.0):  # the subject swayed, or the map's absolute scale is off by that
        sums = tracker.add(depth + chest + shift_mm, mask)
        assert sums.neck_mm == pytest.approx(shift_mm, abs=0.01)  # the body frame resampled: not bit for bit
        against_neck = sums.displaced["all"] - sums.neck_mm * sums.areas["all"]
        assert against_neck == pytest.approx(float(np.sum((chest * footprint)[mask])), rel=0.01)
