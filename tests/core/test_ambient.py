"""The room light's mains flicker: measured on dark frames, taken out of every frame."""

from dataclasses import replace

import h5py
import numpy as np
import pytest

from core.reconstruction.ambient import FlickerCorrection, flicker_phase
from core.reconstruction.photometric import complete_cycles
from core.pipeline.head_maps import DarkFeed, cycle_signal
from core.io.session import SessionFile

FRAME_RATE_HZ, CYCLE = 110.0, 5


def _darks(flicker_hz: float, seconds: float, amplitude_image: np.ndarray, steady: np.ndarray, noise_dn: float,
           frame_rate_hz: float = FRAME_RATE_HZ, seed: int = 0, phase: float = 0.7):
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * frame_rate_hz))[CYCLE - 1::CYCLE] / frame_rate_hz
    frames = [steady + amplitude_image * np.cos(2 * np.pi * flicker_hz * ti - phase)
              + rng.normal(0, noise_dn, steady.shape) for ti in t]
    return t, frames


def test_the_flicker_of_the_frames_between_the_dark_frames_is_found_from_the_dark_frames():
    """A lamp-lit half and a daylight half: the flicker's amplitude is found per pixel, its phase
    from the mean level, and predicted at the lit frames' instants between the dark frames."""
    steady = np.full((20, 30), 200.0)
    amplitude = np.zeros((20, 30))
    amplitude[:, :15] = 60.0
    t, frames = _darks(100.0, 2.0, amplitude, steady, noise_dn=3.0)
    correction = FlickerCorrection(100.0)
    for ti, frame in zip(t, frames):
        correction.add_dark(ti, frame)
    for lit_t in (1.0 + 1 / FRAME_RATE_HZ, 1.0 + 3 / FRAME_RATE_HZ):
        excess = correction.excess(lit_t)
        truth = amplitude * np.cos(2 * np.pi * 100.0 * lit_t - 0.7)
        assert np.sqrt(np.mean((excess - truth) ** 2)) < 2.5  # the dark frames' noise is 3 DN per frame
        assert abs(np.mean(excess[:, :15]) - np.mean(truth[:, :15])) < 1.0
        # the daylight half is left as it is: its fitted amplitude is the dark frames' noise alone
        assert np.count_nonzero(excess[:, 15:]) <= 1
    assert correction.amplitudes[-1] == pytest.approx(30.0 / 200.0, abs=0.01)


def test_no_flicker_no_correction_and_a_frame_rate_locked_to_the_mains_is_not_corrected():
    steady = np.full((10, 10), 200.0)
    t, frames = _darks(100.0, 2.0, np.zeros((10, 10)), steady, noise_dn=3.0)
    assert flicker_phase(t, np.array([f.mean() for f in frames]), 100.0) is None
    # 100 frames/s, a dark frame every fifth: every dark frame sees the same phase of a 100 Hz flicker
    t, frames = _darks(100.0, 2.0, np.full((10, 10), 60.0), steady, noise_dn=3.0, frame_rate_hz=100.0)
    correction = FlickerCorrection(100.0)
    for ti, frame in zip(t, frames):
        correction.add_dark(ti, frame)
    assert correction.excess(1.0) is None


@pytest.fixture(scope="module")
def flickering_pair(tmp_path_factory):
    """The same second of breathing twice, in a room whose light flickers 30 % and in one whose light
    is steady (the same camera noise)."""
    from core.sim.simulate import SimConfig, simulate

    folder = tmp_path_factory.mktemp("flicker")
    config = SimConfig(protocol="tidal", seconds=1.0, scale=0.08, seed=4, heads=("front",))
    simulate(folder / "steady.h5", config)
    simulate(folder / "flicker.h5", replace(config, ambient_flicker=0.3))
    return folder / "steady.h5", folder / "flicker.h5"


def test_a_cycle_in_a_flickering_room_gives_the_signal_of_a_steady_room(flickering_pair):
    steady_path, flicker_path = flickering_pair
    errors: dict[bool, float] = {}
    for corrected in (False, True):
        worst = 0.0
        with SessionFile(steady_path) as steady, SessionFile(flicker_path) as flickering:
            assert flickering.rig.mains_hz == 50.0
            ids = flickering.frame_id("front")
            windows = complete_cycles(flickering.light_index("front"), ids, flickering.rig.cycle_length)
            darks = DarkFeed(flickering.frames("front"), flickering.light_index("front"),
                             flickering.timestamp_ns("front"), flickering.rig.mains_hz)
            for window in windows[5:-5]:
                flicker = darks.flicker_of(window) if corrected else None
                stamps = flickering.timestamp_ns("front")
                signal, _, _ = cycle_signal(flickering.frames("front"), window, None, 4095, {}, ids, stamps, flicker)
                truth, _, _ = cycle_signal(steady.frames("front"), window, None, 4095, {}, ids, stamps)
                subject = truth[0] > 100
                worst = max(worst, float(np.max(np.abs(np.median(signal[:, subject] - truth[:, subject], axis=1)))))
        errors[corrected] = worst
    assert errors[False] > 8.0  # DN: the flicker's share of a light's image, a few % of its signal
    assert errors[True] < 0.25 * errors[False]
    assert 0.15 < darks.flicker_share <= 0.3  # of the whole image's dark level; the background does not flicker


def test_the_results_file_says_how_much_the_room_light_flickered(flickering_pair, tmp_path):
    from core.pipeline.process import process_session

    _, flicker_path = flickering_pair
    process_session(flicker_path, tmp_path / "r.h5", every=10)
    with h5py.File(tmp_path / "r.h5", "r") as r:
        assert 0.15 < r["heads/front"].attrs["ambient_flicker"] <= 0.3
