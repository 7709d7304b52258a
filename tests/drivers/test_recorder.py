"""Recording from the simulated rig into a session file; rig configurations."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from app.cli import main
from core.io.session import SessionFile, validate_session
from drivers.rig import DEFAULT_RIG, RigConfigError, camera_head, load_rig_config


def test_shipped_rig_configs_load():
    sim = load_rig_config(DEFAULT_RIG)
    assert sim.simulated and sim.cameras == {"front": "sim", "back": "sim"} and sim.flow_gain_lps == 0.0075
    fake = load_rig_config(DEFAULT_RIG.parent / "fake-gige.toml")
    assert fake.cameras == {"front": "FRONT01", "back": "BACK01"} and fake.sequencer_port == "emulator"
    template = load_rig_config(DEFAULT_RIG.parent / "template.toml")
    assert template.camera.trigger == "line"
    assert template.optics["front"] == {"focal_length_mm": 25.0, "pixel_size_um": 7.4}


def test_head_geometry_follows_binning_and_region():
    """A point seen through the whole sensor lands on the same spot of the binned, cropped image."""
    optics = {"fx_px": 3391.2, "fy_px": 3389.8, "cx_px": 702.4, "cy_px": 509.1}
    full = camera_head("front", optics, (1400, 1024), (0, 0, 1400, 1024), 1, 12)
    cropped = camera_head("front", optics, (1400, 1024), (100, 40, 500, 400), 2, 8)
    point = np.array([120.0, -85.0, 1400.0])  # mm, camera frame
    u = full.fx * point[0] / point[2] + full.cx
    v = full.fy * point[1] / point[2] + full.cy
    # binned pixel k covers full pixels 2k and 2k+1: full coordinate u is binned (u + 0.5) / 2 - 0.5
    u2 = cropped.fx * point[0] / point[2] + cropped.cx
    v2 = cropped.fy * point[1] / point[2] + cropped.cy
    assert u2 == pytest.approx((u + 0.5) / 2 - 0.5 - 100) and v2 == pytest.approx((v + 0.5) / 2 - 0.5 - 40)
    assert (cropped.width, cropped.height, cropped.bit_depth) == (500, 400, 8)
    assert cropped.pixel_size_mm == pytest.approx(2 * full.pixel_size_mm)
    nominal = camera_head("back", {"focal_length_mm": 16.0, "pixel_size_um": 5.5}, (2048, 1536), (0, 0, 1024, 768), 2, 8)
    assert nominal.fx == pytest.approx(16.0 / 0.0055 / 2) and nominal.cx == pytest.approx(511.5)


@pytest.mark.parametrize("text, message", [
    ("name='x'\n", "[heads.front] is required"),
    ("[heads.front]\ncamera='sim'\n[heads.side]\ncamera='sim'\n", "unknown head [heads.side]"),
    ("[heads.front]\ncamera='sim'\n[heads.back]\ncamera='FRONT01'\n", "mixing simulated and real"),
    ("[heads.front]\ncamera='sim'\n[camera]\nframe_rate_hz=1000\n", "frame_rate_hz must be between"),
    ("[heads.front]\ncamera='sim'\n[flowsensor]\nport='sim'\ngain_lps=0.1\n", "go together"),
    ("[heads.front\n", "not valid TOML"),
    ("[heads.front]\ncamera='X'\nfocal_length_mm=-25\n", "focal_length_mm must be a positive number"),
    ("[heads.front]\ncamera='X'\nfx_px=3000.0\n", "fx_px, fy_px, cx_px and cy_px go together"),
    ("[heads.front]\ncamera='X'\ndist_coeffs=[0.1, 0.0]\n", "dist_coeffs must be OpenCV's five numbers"),
])
def test_bad_rig_configs_name_the_problem(tmp_path, text, message):
    path = tmp_path / "rig.toml"
    path.write_text(text)
    with pytest.raises(RigConfigError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_rig_config(path)


def test_record_the_simulated_rig(tmp_path, capsys):
    out = tmp_path / "rec.h5"
    assert main(["record", "-o", str(out), "--seconds", "1.5", "--subject", "P-9"]) == 0
    printed = capsys.readouterr().out
    assert "dropped by the software 0" in printed
    assert validate_session(out) == []
    with SessionFile(out) as s:
        assert s.subject.id == "P-9" and s.flow is not None and s.rig.baseline_mm is not None
        for head in ("front", "back"):
            n = s.n_frames(head)
            assert 30 <= n <= 180, n  # up to 110 frames/s for 1.5 s (fewer when the machine is busy rendering)
            ids = s.frame_id(head).astype(int)
            # in order and none twice; every frame the cameras delivered reached the file ("dropped by the
            # software 0" above; a busy machine's simulated cameras skip frames, as real ones drop them)
            assert np.all(np.diff(ids) >= 1)
            np.testing.assert_array_equal(s.light_index(head), np.array(s.rig.sequence)[ids % 5])
        adc, stamps = s.flow_samples()
        assert 1300 <= len(adc) <= 1700 and np.all(np.diff(stamps) == 1_000_000)
    with h5py.File(out, "r") as f:  # the shipped rig's [recording]: Blosc LZ4 with bit-shuffle (filter 32001)
        assert "32001" in f["heads/front/frames"]._filters


def test_compressed_and_plain_frames_read_back_the_same(tmp_path):
    """A session written with each frame filter reads back bit for bit; Blosc halves simulated frames."""
    from core.rig import Rig
    from core.io.session import FRAME_COMPRESSION, SessionWriter, SubjectRecord
    from core.sim.simulate import SimConfig, simulate

    source = tmp_path / "source.h5"
    simulate(source, SimConfig(protocol="tidal", seconds=0.3, scale=0.1, seed=2))
    with SessionFile(source) as s:
        frames, lights = s.frames("front")[:], s.light_index("front")
        stamps, ids, rig = s.timestamp_ns("front"), s.frame_id("front"), s.rig
    sizes = {}
    for name in FRAME_COMPRESSION:
        path = tmp_path / f"{name}.h5"
        with SessionWriter(path, kind="simulation", rig=Rig("t", {"front": rig.heads["front"]}, rig.frame_rate_hz),
                           subject=SubjectRecord("S", "male", 30, 175, 75), compression=name) as w:
            w.append_frames("front", frames, lights, stamps, ids)
        with SessionFile(path) as s:
            np.testing.assert_array_equal(s.frames("front")[:], frames)
        sizes[name] = path.stat().st_size
    assert sizes["blosc-lz4"] < 0.7 * sizes["none"], sizes


def test_record_refuses_a_missing_rig_file(tmp_path, capsys):
    assert main(["record", "-o", str(tmp_path / "x.h5"), "--rig", str(tmp_path / "none.toml")]) == 2
    assert "cannot read rig configuration" in capsys.readouterr().err


def test_simulated_camera_loops_prerendered_cycles_with_ids_running_on():
    from core.sim.simulate import SimConfig
    from drivers.simulated import SimCamera, SimulatedRigState

    state = SimulatedRigState.build(SimConfig(protocol="tidal", seconds=2.0, scale=0.1))
    camera = SimCamera(state, "front", realtime=False, loop_cycles=2)
    camera.start()
    frames = [camera.grab() for _ in range(25)]
    assert [f.frame_id for f in frames] == list(range(25))
    assert np.array_equal(frames[0].image, frames[10].image) and np.array_equal(frames[3].image, frames[23].image)
    assert not np.array_equal(frames[0].image, frames[5].image)  # the second cycle is its own render
    assert camera.stats.delivered == 25 and camera.stats.lost == 0


def test_a_simulated_camera_that_falls_behind_drops_whole_cycles_and_keeps_time():
    """Like a real camera: frames the renderer cannot deliver in time are skipped (and counted as
    lost), so every frame's stamp stays within MAX_LAG_S and a light cycle of the clock; it skips
    whole light cycles, so that what it delivers still makes complete cycles."""
    import time

    from core.sim.simulate import SimConfig
    from drivers.simulated import MAX_LAG_S, SimCamera, SimulatedRigState

    state = SimulatedRigState.build(SimConfig(protocol="tidal", seconds=5.0, scale=0.1))
    n = state.rig.cycle_length
    late_by_s = MAX_LAG_S + n / state.rig.frame_rate_hz
    state.start_ns = time.monotonic_ns() - 1_000_000_000  # the clock started a second ago
    camera = SimCamera(state, "front", loop_cycles=1)
    camera.start()
    first = camera.grab()
    assert first.frame_id >= 100 and first.frame_id % n == 0
    assert abs(time.monotonic_ns() - first.timestamp_ns) < late_by_s * 1e9
    time.sleep(0.5)  # a renderer (or a consumer) 0.5 s late, in the middle of a cycle
    rest = [camera.grab() for _ in range(n - 1)]
    assert [f.frame_id for f in rest] == list(range(first.frame_id + 1, first.frame_id + n))  # the cycle finished
    late = camera.grab()
    assert late.frame_id % n == 0 and abs(time.monotonic_ns() - late.timestamp_ns) < late_by_s * 1e9
    assert late.frame_id - first.frame_id >= 50 and camera.stats.lost == late.frame_id - first.frame_id - n
