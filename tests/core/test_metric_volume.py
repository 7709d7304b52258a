"""The metric optical volume on constructed geometry: a dome-shaped trunk that bulges by a known
volume, seen again after it swayed along the axis and sideways, and with a wrong absolute scale."""

from __future__ import annotations

import numpy as np
import pytest

from core.pipeline.quality import volume_refusal
from core.volume.metric import HeadDisplacements, MetricVolume, metric_volume, side_targets
from core.rig import thesis_head
from core.volume.maps import DisplacementSums, DisplacementTracker, metric_head_volume_l

RIM_MM = 2000.0
SEMI_AXES_MM = (200.0, 250.0)
DOME_MM = 80.0
BULGE_MM = 10.0
BULGE_VOLUME_L = BULGE_MM * np.pi * SEMI_AXES_MM[0] * SEMI_AXES_MM[1] / 2.0 * 1e-6  # integral of (1 - r^2)


def _trunk_map(head, bulge_mm: float, shift_mm=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Depth seen by `head` of the surface Z = rim + sz - (dome + bulge)(1 - r^2), r^2 over an
    ellipse in body coordinates (X - sx, Y - sy), found by fixed-point iteration along each ray."""
    u = (np.arange(head.width) - head.cx) / head.fx
    v = (np.arange(head.height) - head.cy) / head.fy
    u, v = np.meshgrid(u, v)
    sx, sy, sz = shift_mm
    z = np.full(u.shape, RIM_MM + sz)
    for _ in range(30):
        r2 = ((u * z - sx) / SEMI_AXES_MM[0]) ** 2 + ((v * z - sy) / SEMI_AXES_MM[1]) ** 2
        z = RIM_MM + sz - (DOME_MM + bulge_mm) * np.clip(1.0 - r2, 0.0, None)
    mask = r2 < 1.0
    return np.where(mask, z, np.nan), mask


def _volume_l(head, current: tuple[np.ndarray, np.ndarray], rim_mm: float, scale: float = 1.0) -> float:
    tracker = DisplacementTracker(head)
    first = tracker.add(*_trunk_map(head, 0.0))
    depth, mask = current
    second = tracker.add(depth * scale, mask)
    sums = [first, second]
    volume = metric_head_volume_l(np.array([s.reference["all"] for s in sums]),
                                  np.array([s.current["all"] for s in sums]),
                                  np.array([s.side_mm for s in sums]), np.array([RIM_MM, rim_mm]))
    return float(volume[1] - volume[0])


def test_a_bulge_of_known_volume_is_measured_in_litres():
    head = thesis_head("front", scale=0.25)
    assert _volume_l(head, _trunk_map(head, BULGE_MM), RIM_MM) == pytest.approx(BULGE_VOLUME_L, rel=0.03)
    assert abs(_volume_l(head, _trunk_map(head, 0.0), RIM_MM)) < 0.002


def test_sway_along_the_axis_and_sideways_is_not_breathing():
    """Counted as breathing, 40 mm along the axis would read as 6 L. What is left is the resampling:
    the dome's top and rim shift by different amounts in the image (parallax), and the level at the
    sides, extrapolated past the band, carries it; measured: +3.4 % for 40 mm along the axis, +8.7 %
    for 15 mm sideways, +4.0 % for both."""
    head = thesis_head("front", scale=0.25)
    swayed = _trunk_map(head, BULGE_MM, (15.0, -5.0, 40.0))
    assert _volume_l(head, swayed, RIM_MM + 40.0) == pytest.approx(BULGE_VOLUME_L, rel=0.06)
    # what is left of 40 mm along the axis and 15 mm sideways: the resampling near the silhouette
    assert abs(_volume_l(head, _trunk_map(head, 0.0, (15.0, -5.0, 40.0)), RIM_MM + 40.0)) < 0.03


def test_a_map_at_the_wrong_absolute_scale_is_brought_to_the_silhouette_distance():
    """The photometric distance of one map may be 10 mm out; the scale comes from the rim's target."""
    head = thesis_head("front", scale=0.25)
    measured = _volume_l(head, _trunk_map(head, BULGE_MM), RIM_MM, scale=1.005)
    assert measured == pytest.approx(BULGE_VOLUME_L, rel=0.03)


def test_two_heads_take_their_distances_from_the_silhouette_widths():
    front, back = thesis_head("front", scale=0.25), thesis_head("back", scale=0.25)
    baseline = 2 * RIM_MM
    heads = {}
    for head in (front, back):
        tracker = DisplacementTracker(head)
        maps = [_trunk_map(head, 0.0), _trunk_map(head, BULGE_MM)]
        sums = [tracker.add(depth * scale, mask) for (depth, mask), scale in zip(maps, (1.004, 0.996))]
        heads[head.name] = HeadDisplacements(np.array([0, 1_000_000_000], dtype=np.int64), sums)
    result = metric_volume(heads, baseline)
    assert result.side_distance_mm["front"] == pytest.approx([RIM_MM, RIM_MM], abs=2.0)
    gained = result.volume_l[1] - result.volume_l[0]
    assert gained == pytest.approx(2 * BULGE_VOLUME_L, rel=0.03)
    # the quadrants cover the trunk rows (60 % of the widest or more), not the narrow ends of the dome
    in_quadrants = sum(r[1] - r[0] for r in result.regions.values())
    assert 0.9 * gained < in_quadrants < gained
    assert volume_refusal(result) is None and max(result.scale_mismatch.values()) < 0.01
    # heads whose widths put the sides 12 % from where their own maps have them: not the same sides
    apart = metric_volume(heads, 2.24 * RIM_MM)
    assert "disagree by 12 %" in volume_refusal(apart).reason


def test_process_writes_the_metric_volume_and_uses_it_without_a_flow_sensor(tmp_path):
    """A simulated subject breathing quietly, no flow sensor: /volume is the metric volume as an optical
    estimate (no calibration on the subject, and says why), it follows the true volume, and /parameters
    come from it."""
    import h5py

    from core.pipeline.process import process_session
    from core.io.session import SessionFile
    from core.sim.breathing import Sway
    from core.sim.simulate import SimConfig, simulate

    session, results = tmp_path / "s.h5", tmp_path / "r.h5"
    simulate(session, SimConfig(protocol="tidal", seconds=12.0, scale=0.15, seed=5, flow_sensor=None,
                                sway=Sway(20.0, 5.0, 1.0, seed=5)))
    process_session(session, results, every=10)  # every other light cycle (11 maps/s)
    with h5py.File(results, "r") as r, SessionFile(session) as s:
        assert r["parameters"].attrs["source"] == "optical: optical estimate, not calibrated"
        assert r["volume"].attrs["label"].startswith("optical estimate, not calibrated (±")
        assert r["subject_calibration"].attrs["not_calibrated"] == "the session has no flow sensor"
        assert set(r["metric_volume/heads/front/regions"]) == set(r["metric_volume/regions"])
        assert r["parameters"].attrs["TV_l"] > 0.1
        t, volume = r["volume/timestamp_ns"][:], r["volume/volume_l"][:]
        truth = np.interp(t, s.truth()["timestamp_ns"][:], s.truth()["volume_l"][:])
        assert np.corrcoef(volume, truth)[0, 1] > 0.9  # 0.975 measured
        metric = r["metric_volume"]
        assert set(metric["regions"]) == {"upper left", "upper right", "lower left", "lower right"}
        assert np.isfinite(metric.attrs["phase_angle_deg"])
        shares = [metric.attrs[f"share_{k}"] for k in ("upper_left", "upper_right", "lower_left", "lower_right")]
        assert sum(shares) == pytest.approx(1.0, abs=1e-6) and min(shares) > 0.05


def test_the_live_volume_follows_the_maps_as_they_come():
    """Causal, map by map: NaN until each head has had a map scaled by both trunk widths; then the
    bulge's volume once both heads have seen it."""
    from core.volume.metric import LiveMetricVolume

    front, back = thesis_head("front", scale=0.25), thesis_head("back", scale=0.25)
    live = LiveMetricVolume({"front": front, "back": back}, 2 * RIM_MM)
    assert np.isnan(live.add("front", 0.0, *_trunk_map(front, 0.0)))
    assert np.isnan(live.add("back", 0.0, *_trunk_map(back, 0.0)))  # the front not yet scaled by both widths
    assert live.add("front", 0.1, *_trunk_map(front, 0.0)) == pytest.approx(0.0, abs=1e-3)
    live.add("front", 1.0, *_trunk_map(front, BULGE_MM))
    both = live.add("back", 1.0, *_trunk_map(back, BULGE_MM))
    assert both == pytest.approx(2 * BULGE_VOLUME_L, rel=0.03)


def test_the_live_volume_gives_each_head_the_distance_of_the_two_heads_geometry():
    """A map whose photometric distance (its median depth) was 1 % long: the two heads' widths put
    its sides back at the rim's distance, and the map's distance with them."""
    from core.volume.metric import LiveMetricVolume

    front, back = thesis_head("front", scale=0.25), thesis_head("back", scale=0.25)
    live = LiveMetricVolume({"front": front, "back": back}, 2 * RIM_MM)
    assert live.geometric_distance_mm("front") is None
    depth, mask = _trunk_map(front, 0.0)
    median = float(np.median(depth[mask]))
    live.add("back", 0.0, *_trunk_map(back, 0.0), None)
    live.add("front", 0.0, depth * 1.01, mask, 1.01 * median)
    assert live.geometric_distance_mm("front") == pytest.approx(median, rel=0.002)


def test_the_live_distances_do_not_follow_an_arm_joining_the_trunk():
    """The live view's two-head distances, like `process`'s, take the trunk's width from its rows'
    median ratio (one map late): an arm joining the front's trunk on some rows moves them by under
    a millimetre, where its mean width would have moved them by tens."""
    from core.volume.metric import LiveMetricVolume

    front, back = thesis_head("front", scale=0.25), thesis_head("back", scale=0.25)
    live = LiveMetricVolume({"front": front, "back": back}, 2 * RIM_MM)
    clean_front, clean_back = _trunk_map(front, 0.0), _trunk_map(back, 0.0)
    median = float(np.median(clean_front[0][clean_front[1]]))
    joined = _arm_joined(clean_front, int(round(0.25 * clean_front[1].any(axis=0).sum())))
    distances = []
    for k in range(12):
        t = 0.05 * k
        live.add("back", t, *clean_back, median)
        live.add("front", t, *(joined if k % 3 == 2 else clean_front), median)
        distances.append(live.geometric_distance_mm("front"))
    assert np.ptp(distances[2:]) < 1.0


def test_a_volume_curve_noisier_from_map_to_map_than_its_values_allow_is_refused():
    """Quiet breathing (0.5 L at 15/min) sampled at 22 maps/s: the noise estimate sees the noise
    added, not the breathing; above 50 mL the volume is refused with the figure."""
    from core.volume.noise import curve_noise_l
    from core.volume.metric import MAX_MAP_NOISE_L, MetricVolume

    t = np.arange(0, 30, 1 / 22)
    breathing = 0.25 * np.sin(2 * np.pi * t / 4.0)
    noise = np.random.default_rng(1).normal(0.0, 1.0, len(t))
    assert curve_noise_l(breathing) < 0.002
    assert curve_noise_l(breathing + 0.02 * noise) == pytest.approx(0.02, rel=0.15)

    def volume(values: np.ndarray) -> MetricVolume:
        return MetricVolume((t * 1e9).astype(np.int64), values, {}, {}, {}, "test", {"front": 0.0})

    assert volume_refusal(volume(breathing + 0.02 * noise)) is None
    refused = str(volume_refusal(volume(breathing + 0.3 * noise)))
    assert refused is not None and "noise from map to map is" in refused and f"{1000 * MAX_MAP_NOISE_L:.0f} mL" in refused


def test_a_volume_curve_that_jumps_away_and_back_is_refused():
    """Tidal breathing, a full inspiration (3 L over 1.6 s, its flow falling to nothing at the top,
    0.3 s held), then a forced blow (4 L out, 2.5 L of them in the first 0.4 s) at 22 maps/s with
    5 mL of noise: the running median follows the blow and nothing counts as a jump. The same curve with
    a jump of 0.6 L for two maps every two seconds (as a population subject's showed, where the
    trunk's sides glitched) is refused; its robust map-to-map noise stays under the noise limit."""
    from core.volume.noise import curve_noise_l
    from core.volume.metric import MAX_MAP_NOISE_L, MetricVolume, jump_share

    t = np.arange(0, 40, 1 / 22)
    curve = 0.25 * np.sin(2 * np.pi * t / 4.0)
    blow = t >= 30.0
    rise = np.clip((t - 28.1) / 1.6, 0.0, 1.0)
    curve = np.where(t >= 28.0, 0.25 + 3.0 * 0.5 * (1 - np.cos(np.pi * rise)), curve)
    curve = np.where(blow, 3.25 - 4.0 * (1 - np.exp(-(t - 30.0) / 0.4)), curve)
    curve = curve + np.random.default_rng(2).normal(0.0, 0.005, len(t))
    stamps = (t * 1e9).astype(np.int64)
    assert jump_share(stamps, curve)[0] == 0.0
    jumped = curve.copy()
    for start in range(10, len(t) - 2, 44):
        jumped[start:start + 2] += 0.6
    share, largest = jump_share(stamps, jumped)
    assert share > 0.03 and largest == pytest.approx(0.6, abs=0.05)
    assert curve_noise_l(jumped) < MAX_MAP_NOISE_L

    def volume(values: np.ndarray) -> MetricVolume:
        return MetricVolume(stamps, values, {}, {}, {}, "test", {"front": 0.0})

    assert volume_refusal(volume(curve)) is None
    refused = str(volume_refusal(volume(jumped)))
    assert refused is not None and "jumps away and back" in refused


def _widened(current: tuple[np.ndarray, np.ndarray], columns: int) -> tuple[np.ndarray, np.ndarray]:
    """The map with `columns` more pixels on one side of every row, at the rim's depth: an arm's
    edge taken for the trunk's side."""
    depth, mask = (a.copy() for a in current)
    for row in np.nonzero(mask.any(axis=1))[0]:
        last = np.nonzero(mask[row])[0][-1]
        stop = min(last + 1 + columns, mask.shape[1])
        mask[row, last + 1:stop] = True
        depth[row, last + 1:stop] = RIM_MM
    return depth, mask


def test_a_single_map_whose_trunk_widens_at_once_keeps_the_last_scale():
    """A map whose trunk reads 5 % wider than the one before (what an arm's edge did to a population
    subject's maps) would be resampled as if the subject had come 100 mm closer; its scale is held
    at the median of the last maps', and the volume stays that of the maps around it. A widening that
    lasts is taken once it fills half of SCALE_WINDOW_MAPS."""
    from core.volume.maps import SCALE_WINDOW_MAPS

    head = thesis_head("front", scale=0.25)
    tracker = DisplacementTracker(head)
    clean = _trunk_map(head, BULGE_MM)
    columns = int(round(0.05 * clean[1].any(axis=0).sum()))
    maps = [_trunk_map(head, 0.0), clean, _widened(clean, columns), clean]
    sums = [tracker.add(*m) for m in maps]
    volume = metric_head_volume_l(np.array([s.reference["all"] for s in sums]),
                                  np.array([s.current["all"] for s in sums]),
                                  np.array([s.side_mm for s in sums]), np.full(len(sums), RIM_MM))
    assert volume[1] == pytest.approx(BULGE_VOLUME_L, rel=0.03)
    assert volume[2] == pytest.approx(volume[1], abs=0.05)
    assert sums[2].width_px == pytest.approx(sums[1].width_px, rel=0.005)
    lasting = [tracker.add(*_widened(clean, columns)) for _ in range(SCALE_WINDOW_MAPS // 2 + 1)]
    assert lasting[-1].width_px > 1.03 * sums[1].width_px


def _arm_joined(current: tuple[np.ndarray, np.ndarray], columns: int) -> tuple[np.ndarray, np.ndarray]:
    """The map with an arm joined to the trunk's silhouette on a fifth of its rows: `columns` more
    pixels beyond one side, at the rim's depth."""
    depth, mask = (a.copy() for a in current)
    rows = np.nonzero(mask.any(axis=1))[0]
    for row in rows[int(0.3 * len(rows)):int(0.5 * len(rows))]:
        last = np.nonzero(mask[row])[0][-1]
        mask[row, last + 1:last + 1 + columns] = True
        depth[row, last + 1:last + 1 + columns] = RIM_MM
    return depth, mask


@pytest.mark.parametrize("arm_on_reference", [False, True])
def test_an_arm_joining_the_trunk_on_some_rows_moves_neither_width_nor_distance(arm_on_reference):
    """An arm that joins the trunk's silhouette on some of its rows widened the trunk's mean width:
    a population subject's read 141 px against 133 in a quarter of its maps, and the two heads'
    distances moved 60 mm with it over a slow VC. The widths are the rows' median ratio to the
    reference's, and the reference's width the maps' median, so neither such maps nor such a
    reference move them."""
    front, back = thesis_head("front", scale=0.25), thesis_head("back", scale=0.25)
    clean_front = _trunk_map(front, 0.0)
    columns = int(round(0.25 * clean_front[1].any(axis=0).sum()))
    arm = [arm_on_reference, False, True, False, True, False, False, True, False]
    heads = {}
    for head in (front, back):
        tracker = DisplacementTracker(head)
        clean = _trunk_map(head, 0.0)
        maps = [_arm_joined(clean, columns) if joined and head is front else clean for joined in arm]
        sums = [tracker.add(*m) for m in maps]
        heads[head.name] = HeadDisplacements(np.arange(len(sums), dtype=np.int64) * 50_000_000, sums)
    mean = np.array([s.width_px for s in heads["front"].sums])
    assert mean[np.array(arm)].min() > 1.03 * mean[~np.array(arm)].max()  # what the arm does to the mean
    assert heads["front"].width_px == pytest.approx(heads["back"].width_px, rel=0.003)
    distances, _ = side_targets(heads, 2 * RIM_MM)
    assert distances["front"] == pytest.approx(np.full(len(arm), RIM_MM), abs=4.0)


@pytest.mark.parametrize("arm_on_reference", [False, True])
def test_maps_whose_outline_took_in_an_arm_are_found_and_breathing_is_not_taken_for_one(arm_on_reference):
    """Such a map's sides, and the level they give, are the arm's on its rows: a mesh subject's front
    maps read 8-37 mm off in level and its volume jumped by up to 344 mL. They are the maps whose
    mean width exceeds what their rows' median ratio says; a trunk that widens on every row (ribs
    moving sideways, sway towards the head) is not one of them."""
    from core.pipeline.quality import maps_left_out_words
    from core.volume.metric import arm_in_outline

    front = thesis_head("front", scale=0.25)
    clean = _trunk_map(front, 0.0)
    width = clean[1].any(axis=0).sum()
    arm = [arm_on_reference, False, True, False, False, True, False, False, False]
    tracker = DisplacementTracker(front)
    maps = [_arm_joined(clean, int(round(0.25 * width))) if joined
            else _widened(clean, k % 3) if k else clean for k, joined in enumerate(arm)]
    displacements = HeadDisplacements(np.arange(len(arm), dtype=np.int64) * 50_000_000,
                                      [tracker.add(*m) for m in maps])
    assert np.abs(displacements.outline_excess[~np.array(arm)]).max() < 0.01
    assert list(arm_in_outline(displacements.outline_excess)) == arm
    words = maps_left_out_words({"front": displacements}, {"front": np.ones(len(arm), bool)},
                                {"front": np.zeros(len(arm), bool)}, {"front": arm_in_outline(displacements.outline_excess)})
    assert "an arm was taken into the trunk's outline: head front" in words


def test_an_arm_in_most_maps_outlines_is_still_found_and_the_volume_refused_with_what_to_do():
    """An arm that rests in the trunk's outline for most of the session widens most maps: measured
    against the narrower maps it is still found, and the volume is refused with the operator's remedy
    rather than for the jumps its maps would make."""
    from core.pipeline.quality import HOLD_ARMS_AWAY, outline_refusal
    from core.volume.metric import arm_in_outline

    front = thesis_head("front", scale=0.25)
    clean = _trunk_map(front, 0.0)
    joined = _arm_joined(clean, int(round(0.25 * clean[1].any(axis=0).sum())))
    arm = [False, True, True, False, True, True, True, False, True, True]
    tracker = DisplacementTracker(front)
    displacements = HeadDisplacements(np.arange(len(arm), dtype=np.int64) * 50_000_000,
                                      [tracker.add(*(joined if a else clean)) for a in arm])
    found = arm_in_outline(displacements.outline_excess)
    assert list(found) == arm
    refused = outline_refusal({"front": found})
    assert refused is not None and refused.code == "arm-in-outline" and refused.action == HOLD_ARMS_AWAY
    assert "70 % of the maps" in refused.reason
    assert outline_refusal({"front": np.array([False, True, False, False, False])}) is None


def test_the_live_volume_gives_no_value_for_a_map_whose_outline_took_in_an_arm():
    """As `process` leaves such maps out, the live view gives them no volume; the maps after them do."""
    from core.volume.metric import LiveMetricVolume

    front, back = thesis_head("front", scale=0.25), thesis_head("back", scale=0.25)
    live = LiveMetricVolume({"front": front, "back": back}, 2 * RIM_MM)
    clean_front, clean_back = _trunk_map(front, 0.0), _trunk_map(back, 0.0)
    joined = _arm_joined(clean_front, int(round(0.25 * clean_front[1].any(axis=0).sum())))
    volumes = []
    for k in range(9):
        live.add("back", 0.05 * k, *clean_back)
        volumes.append(live.add("front", 0.05 * k, *(joined if k in (4, 7) else clean_front)))
    assert np.isnan(volumes[4]) and np.isnan(volumes[7])
    assert np.abs(np.array(volumes)[[2, 3, 5, 6, 8]]).max() < 1e-3


def test_a_known_distance_keeps_the_flanks_lost_pixels_out_of_the_body_frame():
    """The bulged map loses the outermost pixel of every row (a flank steepening past the
    integrator's grazing limit): the trunk's widths then take the map for one farther away and
    shrink it. With the subject's distance given (from the two heads' geometry) the frame keeps its
    scale and the volume is the bulge's (measured 0.796 L for 0.785; from the widths 0.650)."""
    from scipy import ndimage

    head = thesis_head("front", scale=0.25)
    depth, mask = _trunk_map(head, BULGE_MM)
    thinned = mask & ndimage.binary_erosion(mask, structure=np.array([[1, 1, 1]]))
    volumes = {}
    for known in (None, RIM_MM):
        tracker = DisplacementTracker(head)
        first = tracker.add(*_trunk_map(head, 0.0), distance_mm=known)
        second = tracker.add(np.where(thinned, depth, np.nan), thinned, distance_mm=known)
        volumes[known] = float(np.diff(metric_head_volume_l(np.array([first.reference["all"], second.reference["all"]]),
                                                            np.array([first.current["all"], second.current["all"]]),
                                                            np.array([first.side_mm, second.side_mm]),
                                                            np.array([RIM_MM, RIM_MM])))[0])
    assert volumes[RIM_MM] == pytest.approx(BULGE_VOLUME_L, rel=0.03)
    assert abs(volumes[None] / BULGE_VOLUME_L - 1.0) > 0.05


def _band_sessions(noise_mm: float, seed: int = 3, blow_at_s: float | None = None):
    """A rim band of 60 edges of 20 pixels (hinge and stretch profiles as rim_model makes them), 240 maps
    at 22 a second: each map shifted (sway, and jumps of 3 mm), each edge breathing with amounts of its
    own times the rib cage's or the abdomen's course (a quarter period apart), plus pixel noise. With
    blow_at_s both courses also fall at once there, as in a forced expiration (0.1 in 0.2 s)."""
    rng = np.random.default_rng(seed)
    edges, width, maps = 60, 20, 240
    t = np.arange(maps) / 22.0
    from_side = np.arange(width, dtype=float)[None, :] * 2.4 + 6.0 + rng.uniform(0, 2, (edges, 1))
    hinge = from_side * (1.0 - from_side / 300.0)
    stretch = (150.0 - from_side) * np.exp(-from_side / 15.0)
    courses = np.stack([np.sin(2 * np.pi * t / 6.0), np.sin(2 * np.pi * t / 6.0 - np.pi / 2)], axis=1) * 0.03
    if blow_at_s is not None:
        courses -= 0.1 * np.clip((t[:, None] - blow_at_s) / 0.2, 0.0, 1.0)
    compartment = np.arange(edges) * 2 // edges  # upper edges follow the rib cage, lower the abdomen
    amounts = rng.uniform(0.5, 1.5, (edges, 2))
    shifts = 6.0 * np.sin(2 * np.pi * t / 23.0) + 3.0 * (rng.random(maps) < 0.05)
    sums = []
    for i in range(maps):
        course = courses[i, compartment][:, None]
        y = shifts[i] + course * (amounts[:, :1] * hinge + amounts[:, 1:] * stretch) + rng.normal(0, noise_mm, hinge.shape)
        band = np.stack([np.full(edges, float(width)), y.sum(1), hinge.sum(1), stretch.sum(1), (y * hinge).sum(1),
                         (y * stretch).sum(1), (hinge ** 2).sum(1), (hinge * stretch).sum(1), (stretch ** 2).sum(1)], 1)
        band_mean = y.mean()
        # each half's mean displacement: the band's mean plus its breathing (the interior moves more)
        displaced = {"upper left": band_mean + 40 * courses[i, 0], "upper right": band_mean + 40 * courses[i, 0],
                     "lower left": band_mean + 60 * courses[i, 1], "lower right": band_mean + 60 * courses[i, 1]}
        sums.append(DisplacementSums(2000.0, 120.0, {}, {}, {k: 1.0 for k in displaced}, displaced, (0.0, 0.0), band))
    return (t * 1e9).astype(np.int64), sums, shifts, (hinge, stretch, y)


def test_the_session_level_finds_each_maps_shift_with_the_noise_of_a_mean():
    """The band's breathing amounts held over the session leave each map one unknown, its shift: found
    to a few hundredths of a mm with 0.3 mm of pixel noise, where each map's own fit of a hinge and a
    stretch amount per edge (RimModel.level) is off by far more."""
    from core.volume.maps import _intercept_sums
    from core.volume.metric import session_shifts

    t, sums, shifts, (hinge, stretch, _) = _band_sessions(noise_mm=0.3)
    found = session_shifts(t, sums)
    session_error = np.sqrt(np.mean((found - shifts) ** 2))
    rng = np.random.default_rng(8)
    own = []
    for i, s in enumerate(sums[:40]):  # each map's own fit, on a map drawn the same way
        course = 0.03 * np.sin(2 * np.pi * (i / 22.0) / 6.0)
        y = shifts[i] + course * (hinge + stretch) + rng.normal(0, 0.3, hinge.shape)
        numerator, denominator = _intercept_sums(y, np.ones(y.shape, bool), [hinge, stretch])
        own.append(numerator / denominator - shifts[i])
    assert session_error < 0.05
    assert np.sqrt(np.mean(np.square(own))) > 4 * session_error


def test_the_session_level_follows_a_forced_expiration_without_spreading_it():
    """The halves' mean breathing is despiked, not smoothed: where the whole trunk falls at once (a
    blow), the session's level stays on each map's shift. Smoothed over 0.1 s (as before the fifteenth
    session) the fall was spread over +-0.3 s and the level took the difference for a shift."""
    from core.volume.metric import session_shifts

    t, sums, shifts, _ = _band_sessions(noise_mm=0.3, blow_at_s=5.0)
    found = session_shifts(t, sums)
    seconds = t / 1e9
    around = (seconds > 4.6) & (seconds < 5.6)
    assert np.max(np.abs(found - shifts)[around]) < 0.1


def test_a_single_map_off_its_neighbours_is_despiked_and_a_steep_fall_kept():
    from core.volume.metric import despiked

    seconds = np.arange(100) / 22.0
    fall = -np.clip((seconds - 2.0) / 0.2, 0.0, 1.0) * 3.0 + np.random.default_rng(1).normal(0, 0.01, 100)
    spiked = fall.copy()
    spiked[30] += 1.0
    cleaned = despiked(seconds, spiked, 0.2, 3.0)
    assert np.max(np.abs(np.delete(cleaned - fall, 30))) < 0.05  # the fall as it was, to the noise
    assert abs(cleaned[30] - fall[30]) < 0.05


def test_the_session_level_needs_enough_maps_with_a_band():
    from core.volume.metric import MIN_SESSION_MAPS, session_shifts

    t, sums, _, _ = _band_sessions(noise_mm=0.3)
    assert session_shifts(t[:MIN_SESSION_MAPS - 1], sums[:MIN_SESSION_MAPS - 1]) is None
    assert session_shifts(t[:MIN_SESSION_MAPS], sums[:MIN_SESSION_MAPS]) is not None


def test_a_map_with_nan_sums_is_left_out_of_the_session_level_not_the_session():
    from dataclasses import replace

    from core.volume.metric import COMPARTMENTS, session_shifts

    t, sums, shifts, _ = _band_sessions(noise_mm=0.3)
    band = sums[9].band.copy()
    band[:, 1] = np.nan
    sums[9] = replace(sums[9], band=band)
    sums[5] = replace(sums[5], levels_mm=(np.nan, np.nan))
    # a map whose lower half holds no trunk (an arm over it, the subject half out of view)
    sums[7] = replace(sums[7], areas={r: (0.0 if r in COMPARTMENTS[1] else a) for r, a in sums[7].areas.items()},
                      displaced={r: (0.0 if r in COMPARTMENTS[1] else d) for r, d in sums[7].displaced.items()})
    found = session_shifts(t, sums)
    assert np.isnan(found[[5, 7, 9]]).all()
    others = np.delete(np.arange(len(sums)), [5, 7, 9])
    assert np.sqrt(np.mean((found[others] - shifts[others]) ** 2)) < 0.05


def test_the_rims_outermost_pixels_are_left_out_in_millimetres():
    from core.volume.maps import RIM_SKIP_MM, RIM_SKIP_PX, rim_skip_px

    head = thesis_head("front", 1.0)
    depth = np.full((10, 10), 2000.0)
    valid = np.ones((10, 10), bool)
    assert rim_skip_px(depth, valid, head) == round(RIM_SKIP_MM * head.fx / 2000.0)
    assert rim_skip_px(depth, valid, thesis_head("front", 0.05)) == RIM_SKIP_PX


def test_the_session_level_is_checked_against_each_maps_own_for_gain_and_lag():
    """Two estimates of one breathing: a session level whose course lags (a band that breathes as the
    compartments do not) shows as a lag of the each-map volume on it, a share lost as a gain."""
    from core.volume.metric import level_agreement

    t = np.arange(0.0, 20.0, 1 / 22.0)
    rng = np.random.default_rng(2)
    session = 0.5 * np.sin(2 * np.pi * t / 4.0)
    each_map = 0.9 * 0.5 * np.sin(2 * np.pi * (t + 0.15) / 4.0) + rng.normal(0, 0.03, t.size) + 0.02
    gain, lag = level_agreement((t * 1e9).astype(np.int64), session, each_map)
    turn = 2 * np.pi * 0.15 / 4.0  # the rate term is the lag's first order: gain cos, lag sin
    assert gain == pytest.approx(0.9 * np.cos(turn), abs=0.02) and lag == pytest.approx(-0.15, abs=0.02)
    same = level_agreement((t * 1e9).astype(np.int64), session, session + rng.normal(0, 0.03, t.size))
    assert same[0] == pytest.approx(1.0, abs=0.02) and abs(same[1]) < 0.02


def test_the_two_heads_distances_follow_sway_as_fast_as_quiet_breathing():
    """Sway at 0.2 Hz, a quiet breath's rate: the distances each map is scaled to (and, in `process`, reconstructed
    at) follow at least 90 % of it. Smoothed over 1 s they followed 45 %, and a child's quiet breathing with
    50 mm of axial sway read 1.42 times the truth (docs/history/volume-log.md, "Axial sway read as breath")."""
    baseline_mm, width_px, sway_mm = 4000.0, 150.0, 25.0
    t = np.arange(0.0, 20.0, 1.0 / 22.0)
    front_mm = 2000.0 + sway_mm * np.sin(2.0 * np.pi * 0.2 * t)
    heads = {}
    for name, distance in (("front", front_mm), ("back", baseline_mm - front_mm)):
        sums = [DisplacementSums(float(d), width_px * 2000.0 / float(d), {}, {}) for d in distance]
        heads[name] = HeadDisplacements((t * 1e9).astype(np.int64), sums)
    targets, _ = side_targets(heads, baseline_mm)
    middle = (t > 5.0) & (t < 15.0)
    followed = np.polyfit(front_mm[middle], targets["front"][middle], 1)[0]
    assert followed > 0.9


def test_maps_left_out_for_an_arm_leave_gaps_in_the_volume_not_a_bridge():
    """A volume made from the maps no arm hid (core/pipeline/quality.py) goes back onto all the
    first head's maps with NaN where a map of either head was left out: the front's own, and the
    front's maps whose nearest back map was; the maps shown keep their values, each head's side
    distances go onto its own maps."""
    t_front = np.arange(10) * 100_000_000
    t_back = t_front + 40_000_000  # the back head's maps 40 ms later
    front_shown = np.ones(10, bool)
    front_shown[2] = False
    back_shown = np.ones(10, bool)
    back_shown[6:8] = False
    kept = t_front[front_shown]
    volume = np.linspace(0.0, 0.8, len(kept))
    made = MetricVolume(kept, volume, {"front": volume / 2, "back": volume / 2}, {"upper left": volume},
                        {"front": np.full(9, 2000.0), "back": np.full(8, 1900.0)}, "trunk widths and the baseline")
    full = made.with_gaps(t_front, {"front": (t_front, front_shown), "back": (t_back, back_shown)})
    gaps = np.isnan(full.volume_l)
    assert np.flatnonzero(gaps).tolist() == [2, 6, 7]
    assert np.array_equal(full.timestamp_ns, t_front)
    assert np.array_equal(full.volume_l[~gaps], volume[np.isin(kept, t_front[~gaps])])
    assert np.isnan(full.regions["upper left"][[2, 6, 7]]).all() and np.isnan(full.heads["back"][2])
    assert np.isnan(full.side_distance_mm["back"][[6, 7]]).all() and full.side_distance_mm["back"][5] == 1900.0
    assert np.flatnonzero(np.isnan(full.side_distance_mm["front"])).tolist() == [2]


def _true_map_volume(surfaces, amplitudes, seconds: float):
    """metric_volume of a simulated body's true depth maps from both heads at 5 maps/s, with 10 mm of
    axial sway out of step with the breath, and the truth at the same times."""
    from core.reconstruction.pipeline import trunk_mask
    from core.sim.render import CameraModel
    from core.sim.scene import Digitiser, HeightFieldScene

    times = np.arange(0.0, seconds, 0.2)
    scene = HeightFieldScene(surfaces, 2100.0, 4200.0, mode_amplitudes=amplitudes,
                             sway=lambda t: np.array([0.0, 0.0, 10.0 * np.sin(2.3 * t)]))
    digitiser = Digitiser(CameraModel(noise=False), 12)
    heads = {}
    for name in ("front", "back"):
        head, sums = thesis_head(name, scale=0.25), []
        tracker = DisplacementTracker(head)
        for t in times:
            maps = scene.render(head, float(t), 1, np.uint64(0), digitiser, want_maps=True)[1]
            trunk = trunk_mask(np.isfinite(maps.depth_mm), maps.normals)
            sums.append(tracker.add(maps.depth_mm, trunk, trunk))
        heads[name] = HeadDisplacements((times * 1e9).astype(np.int64), sums)
    return metric_volume(heads, 4200.0), times, scene.truth_volume_l(times)


def test_the_subject_s_calibration_gives_back_the_breath_the_unseen_flanks_move():
    """The flanks between the two heads' contours are in no map, and on a trunk that widens as it breathes
    they move out with it: the plain optical volume reads low (0.85-0.9 of the truth on such bodies). Fitted
    on the chest and abdomen of each head over a calibration through the flow sensor (here the truth: a
    deep breath led by the chest, then one by the abdomen), the same gains read a later breath whose
    chest and abdomen move in other proportions within 3 %."""
    from core.sim.bodies import PRESETS, body_surfaces
    from core.volume.subject_calibration import fit_subject_calibration, regional_signals

    def breath(t, start, length):
        return np.where((t >= start) & (t <= start + length),
                        np.sin(np.pi * np.clip((t - start) / length, 0, 1)) ** 2, 0.0)

    def amplitudes(t):  # chest left, chest right, abdomen (mm)
        t = float(t)
        chest = 14.0 * breath(t, 0.0, 6.0) + 5.0 * breath(t, 6.0, 6.0) + 9.0 * breath(t, 12.0, 6.0)
        abdomen = 4.0 * breath(t, 0.0, 6.0) + 14.0 * breath(t, 6.0, 6.0) + 9.0 * breath(t, 12.0, 6.0)
        return np.array([chest, chest, abdomen])

    surfaces = body_surfaces(PRESETS["average-man"], 2.0, widening=True)
    metric, t, truth = _true_map_volume(surfaces, amplitudes, 18.0)
    signals = regional_signals(metric.head_regions)
    calibration = fit_subject_calibration(t, signals, t, truth, (0.0, 12.0))
    assert calibration.refused is None, calibration.refused
    later = t >= 12.0
    calibrated = calibration.volume_l(signals)
    plain = np.ptp(metric.volume_l[later]) / np.ptp(truth[later])
    assert plain < 0.95  # what the flanks take from the plain volume
    assert np.ptp(calibrated[later]) / np.ptp(truth[later]) == pytest.approx(1.0, abs=0.03)
