"""The displacement sums `process` keeps give back the optical signal it wrote, without the maps."""

from __future__ import annotations

import h5py
import numpy as np

from core.io.results import ResultsFile
from core.volume.maps import REGIONS, metric_head_volume_l, smooth_in_time
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
