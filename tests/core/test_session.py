"""Session files: every field round-trips, and broken files are rejected with named problems."""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest

from core.rig import thesis_rig
from core.io.session import SessionError, SessionFile, SessionWriter, SubjectRecord, validate_session


def _rig():
    rig = thesis_rig(scale=0.02)
    front = rig.heads["front"]
    from dataclasses import replace

    axis = np.tile([0.0, 0.0, 1.0], (4, 1))
    heads = {"front": replace(front, light_axis=axis, light_mu=np.full(4, 1.5), light_intensity=[1, 1.1, 0.9, 1.05],
                              calibrated="2026-11-01T10:00:00+00:00"),
             "back": rig.heads["back"]}
    return replace(rig, heads=heads)


def write_example(path, n=12, drop=()):
    rig = _rig()
    subject = SubjectRecord("P-17", "female", 41.5, 163.0, 58.2)
    rng = np.random.default_rng(0)
    frames = {h: rng.integers(0, 4096, (n, rig.heads[h].height, rig.heads[h].width), dtype=np.uint16)
              for h in rig.heads}
    ids = np.array([i for i in range(n + len(drop)) if i not in drop])[:n]
    lights = np.array([rig.sequence[i % 5] for i in ids])
    stamps = 5_000 + ids * 9_090_909
    with SessionWriter(path, kind="patient", rig=rig, subject=subject, created="2026-11-22T09:00:00+01:00") as w:
        for h in rig.heads:
            for i in range(n):  # streaming, frame by frame
                w.append_frames(h, frames[h][i], [lights[i]], [stamps[i]], [ids[i]])
        w.configure_flow(sample_rate_hz=1000.0, adc_bits=12, sensor="test", conditions="ATPS",
                         gain_lps=0.002085, offset_lps=-4.007)
        w.append_flow(np.arange(100, dtype=np.int32), 5_000 + np.arange(100) * 1_000_000)
        w.add_event(5_000, "tidal-start")
        w.add_event(55_000_000, "maneuver-end")
    return rig, subject, frames, lights, stamps, ids


def test_every_field_round_trips(tmp_path):
    path = tmp_path / "s.h5"
    rig, subject, frames, lights, stamps, ids = write_example(path, drop=(3,))
    assert validate_session(path) == []
    with SessionFile(path) as s:
        assert s.kind == "patient" and s.created == "2026-11-22T09:00:00+01:00"
        assert s.subject == subject
        assert s.rig.sequence == rig.sequence and s.rig.name == rig.name
        assert s.rig.frame_rate_hz == pytest.approx(rig.frame_rate_hz)
        for name, head in rig.heads.items():
            got = s.rig.heads[name]
            for attr in ("width", "height", "fx", "fy", "cx", "cy", "pixel_size_mm", "bit_depth"):
                assert getattr(got, attr) == pytest.approx(getattr(head, attr)), attr
            for attr in ("light_positions_mm", "light_intensity", "dist_coeffs"):
                np.testing.assert_allclose(getattr(got, attr), getattr(head, attr))
            np.testing.assert_array_equal(s.frames(name)[:], frames[name])
            np.testing.assert_array_equal(s.light_index(name), lights)
            np.testing.assert_array_equal(s.timestamp_ns(name), stamps)
            np.testing.assert_array_equal(s.frame_id(name), ids)
            assert s.lost_frames(name) == 1
        np.testing.assert_allclose(s.rig.heads["front"].light_axis, rig.heads["front"].light_axis)
        np.testing.assert_allclose(s.rig.heads["front"].light_mu, 1.5)
        assert s.rig.heads["front"].calibrated == "2026-11-01T10:00:00+00:00"
        assert s.rig.heads["back"].light_axis is None
        flow = s.flow
        assert (flow.gain_lps, flow.offset_lps, flow.conditions, flow.adc_bits) == (0.002085, -4.007, "ATPS", 12)
        adc, ts = s.flow_samples()
        np.testing.assert_array_equal(adc, np.arange(100))
        assert s.events() == [(5_000, "tidal-start"), (55_000_000, "maneuver-end")]
    with h5py.File(path) as f:  # the spec's exact types
        assert f["heads/front/light_index"].dtype == np.int8
        assert f["heads/front/frame_id"].dtype == np.uint64
        assert f["heads/front/frames"].chunks == (1, *frames["front"].shape[1:])
        assert f.attrs["format"] == "photopft-session" and f.attrs["format_version"] == 1


def test_simulated_session_round_trips_truth(small_session):
    assert validate_session(small_session) == []
    with SessionFile(small_session) as s:
        truth = s.truth()
        assert truth["volume_l"].shape == truth["timestamp_ns"].shape
        for head in s.heads:
            k = truth[f"{head}/map_frame_index"].shape[0]
            assert truth[f"{head}/normals"].shape == (k, *s.rig.heads[head].shape, 3)
            n = truth[f"{head}/normals"][0]
            on = np.isfinite(n[..., 2])
            np.testing.assert_allclose(np.linalg.norm(n[on], axis=-1), 1.0, atol=1e-5)
            assert np.all(n[on][:, 2] < 0), "normals point towards the camera"


def _broken(tmp_path, mutate):
    path = tmp_path / "broken.h5"
    write_example(path)
    with h5py.File(path, "r+") as f:
        mutate(f)
    return validate_session(path)


@pytest.mark.parametrize("mutate, expected", [
    (lambda f: f.attrs.__delitem__("kind"), "missing attribute /@kind"),
    (lambda f: f.attrs.__setitem__("format_version", 2), "format_version is 2"),
    (lambda f: f.attrs.__setitem__("created", "yesterday"), "/@created"),
    (lambda f: f["rig/front"].attrs.__setitem__("light_positions_mm", np.zeros((3, 3))), "light_positions_mm"),
    (lambda f: f["rig/front"].attrs.__delitem__("fx"), "missing attribute /rig/front@fx"),
    (lambda f: f["rig/back"].attrs.__setitem__("bit_depth", 7), "/rig/back@bit_depth"),
    (lambda f: f.__delitem__("heads/back"), "missing group /heads/back"),
    (lambda f: f.__delitem__("heads/front/frame_id"), "missing dataset /heads/front/frame_id"),
    (lambda f: f["heads/front/light_index"].__setitem__(0, 2), "does not follow /rig@sequence"),
    (lambda f: f["heads/front/timestamp_ns"].__setitem__(3, 0), "timestamp_ns is not strictly increasing"),
    (lambda f: f["heads/front/light_index"].resize((5,)), "differ in length"),
    (lambda f: f["subject"].attrs.__setitem__("sex", "unknown"), "/subject@sex"),
    (lambda f: f.__delitem__("subject"), "missing group /subject"),
    (lambda f: f["flow"].attrs.__delitem__("flow_offset_lps"), "flow_gain_lps and flow_offset_lps"),
    (lambda f: f["flow"].attrs.__setitem__("conditions", "STPD"), "/flow@conditions"),
    (lambda f: f.__delitem__("events"), "missing group /events"),
])
def test_nonconforming_files_name_the_problem(tmp_path, mutate, expected):
    problems = _broken(tmp_path, mutate)
    assert any(expected in p for p in problems), problems


def test_wrong_frame_dtype_and_shape(tmp_path):
    def mutate(f):
        del f["heads/front/frames"]
        f["heads/front/frames"] = np.zeros((12, 3, 3), dtype=np.float32)

    problems = _broken(tmp_path, mutate)
    assert any("/heads/front/frames has dtype float32" in p for p in problems), problems


def test_truncated_file_is_rejected_and_reader_refuses(tmp_path):
    path = tmp_path / "s.h5"
    write_example(path, n=40)
    size = path.stat().st_size
    for keep in (size // 2, size - 4096, 100):
        cut = tmp_path / f"cut{keep}.h5"
        shutil.copy(path, cut)
        with open(cut, "r+b") as fh:
            fh.truncate(keep)
        problems = validate_session(cut)
        assert problems and any("truncated" in p or "cannot" in p for p in problems), (keep, problems)
        with pytest.raises(SessionError, match="not a valid session file"):
            SessionFile(cut)


def test_not_hdf5(tmp_path):
    path = tmp_path / "x.h5"
    path.write_text("hello")
    assert "cannot be opened as HDF5" in validate_session(path)[0]


def test_writer_rejects_wrong_frames(tmp_path):
    rig = thesis_rig(scale=0.02)
    with SessionWriter(tmp_path / "w.h5", kind="simulation", rig=rig) as w:
        with pytest.raises(SessionError, match="frame shape"):
            w.append_frames("front", np.zeros((1, 3, 3), np.uint16), [0], [0], [0])
        with pytest.raises(SessionError, match="head 'side'"):
            w.append_frames("side", np.zeros((1, 3, 3), np.uint16), [0], [0], [0])


def test_lights_never_calibrated_read_as_not_calibrated_everywhere(small_session):
    """The simulated rig's lights are as built: the spec's @calibrated holds the recording's time, and
    every reader says "not calibrated" (issue 77, requirement 8)."""
    from datetime import datetime

    import h5py

    from app.report_data import build_report

    with h5py.File(small_session) as f:
        assert int(f["rig/front"].attrs["lights_calibrated"]) == 0
        datetime.fromisoformat(str(f["rig/front"].attrs["calibrated"]))  # still the time the spec asks
    with SessionFile(small_session) as s:
        assert {h.calibrated for h in s.rig.heads.values()} == {""}
    report = build_report(small_session, with_maps=False)
    assert "lights of the front head not calibrated (as built or drawn)" in report.calibration
