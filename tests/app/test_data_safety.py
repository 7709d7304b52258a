"""No command destroys an input or a recording, and none leaves a half-written output (issue 28)."""

from __future__ import annotations

import argparse
import hashlib
import json
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from app.cli import build_parser, main
from core.io.outputs import OutputError, check_output
from core.io.recovery import recover_session
from core.io.session import SessionFile, validate_session
from tests.waiting import wait_until


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture()
def session(small_session, tmp_path) -> Path:
    """A private copy of the small session, so that a test which wrongly destroyed it would show."""
    copy = tmp_path / "session.h5"
    copy.write_bytes(small_session.read_bytes())
    return copy


def run(args: list[str], capsys) -> tuple[int, str]:
    code = main(args)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


@pytest.mark.parametrize("verb", [
    ["report", "{s}", "-o", "{s}"],
    ["process", "{s}", "-o", "{s}"],
    ["calibrate", "flow", "{s}", "-o", "{s}"],
    ["calibrate", "volume", "{s}", "-o", "{s}"],
    ["calibrate", "lights", "{s}", "-o", "{s}"],
    ["export", "{s}", "--research", "{s}", "--study-key-file", "{s}"],
])
def test_an_output_equal_to_an_input_is_refused(session, capsys, verb):
    before = digest(session)
    code, err = run([a.format(s=session) for a in verb], capsys)
    assert code == 2 and "input of this command" in err and str(session) in err
    assert digest(session) == before


@pytest.mark.parametrize("verb", [
    ["simulate", "--seconds", "0.1", "--scale", "0.05", "-o", "{other}"],
    ["simulate", "--seconds", "0.1", "--scale", "0.05", "--force", "-o", "{other}"],
    ["process", "{s}", "-o", "{other}", "--force"],
    ["record", "--seconds", "1", "-o", "{other}"],
    ["report", "{s}", "-o", "{other}", "--force"],
])
def test_a_recorded_session_is_never_replaced(session, tmp_path, capsys, verb):
    other = tmp_path / "other.h5"
    other.write_bytes(session.read_bytes())
    before = digest(other)
    code, err = run([a.format(s=session, other=other) for a in verb], capsys)
    assert code == 2 and "never replaced" in err and str(other) in err
    assert digest(other) == before


def test_other_outputs_are_replaced_only_with_force(session, tmp_path, capsys):
    pdf = tmp_path / "report.pdf"
    pdf.write_text("an older report")
    code, err = run(["report", str(session), "-o", str(pdf)], capsys)
    assert code == 2 and "--force" in err and pdf.read_text() == "an older report"
    code, _ = run(["report", str(session), "-o", str(pdf), "--force"], capsys)
    assert code == 0 and pdf.read_bytes().startswith(b"%PDF")


def test_the_terminal_is_asked_and_a_no_keeps_the_file(tmp_path):
    target = tmp_path / "profile.json"
    target.write_text("{}")
    with pytest.raises(OutputError, match="--force"):
        check_output(target, ask=lambda question: False)
    assert check_output(target, ask=lambda question: True) == target
    with pytest.raises(OutputError, match="does not exist"):
        check_output(tmp_path / "missing" / "x.json", force=True)


def test_the_demo_never_replaces_its_earlier_session(tmp_path, capsys):
    (tmp_path / "session.h5").write_text("placeholder")
    code, err = run(["demo", "-o", str(tmp_path), "--seconds", "1"], capsys)
    assert code == 2 and "choose another folder" in err
    assert (tmp_path / "session.h5").read_text() == "placeholder"


def _partials(folder: Path) -> list[Path]:
    return [p for p in folder.iterdir() if ".partial" in p.name]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_an_interrupted_process_leaves_no_results_file(session, tmp_path, sig):
    out = tmp_path / "results.h5"
    proc = subprocess.Popen([sys.executable, "-m", "app", "process", str(session), "-o", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    wait_until(lambda: _partials(tmp_path) or proc.poll() is not None, 60, "the results' temporary file")
    assert proc.poll() is None, "process ended before it could be interrupted"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode in (130, 143) and "Traceback" not in err, err
    assert "nothing half-written" in err
    assert not out.exists() and not _partials(tmp_path)


def test_a_library_failing_after_the_stop_is_reported_as_the_stop(session, tmp_path, capsys, monkeypatch):
    """Ctrl-C while numba compiles: its handler's exception is swallowed inside the compiler, which
    then fails in its own words (caching a kernel it never finished). Seen with an empty numba cache."""
    from core.io.outputs import request_stop, stop_if_requested
    from core.pipeline import process

    def cut_short(*args, **kwargs):
        request_stop(KeyboardInterrupt())
        raise RuntimeError("no compiled object yet for <Library '_log_depth_gradients'>")

    monkeypatch.setattr(process, "process_session", cut_short)
    out = tmp_path / "results.h5"
    code, err = run(["process", str(session), "-o", str(out)], capsys)
    assert code == 130 and "interrupted; nothing half-written was left" in err
    assert not out.exists() and not _partials(tmp_path)
    stop_if_requested()  # the stop was answered: nothing is left to stop the next command in this process


def test_every_number_on_the_command_line_is_finite():
    """No verb takes a bare float: `finite` or `positive` refuse nan and inf everywhere."""
    def actions(parser):
        for action in parser._actions:
            yield parser, action
            if isinstance(action, argparse._SubParsersAction):
                for sub in action.choices.values():
                    yield from actions(sub)

    bare = [f"{p.prog} {a.option_strings}" for p, a in actions(build_parser()) if a.type is float]
    assert not bare


@pytest.mark.parametrize("args", [
    ["simulate", "--seconds", "inf", "-o", "x.h5"],
    ["simulate", "--seconds", "nan", "-o", "x.h5"],
    ["record", "--seconds", "nan", "-o", "x.h5"],
    ["simulate", "--sway-mm", "nan", "-o", "x.h5"],
])
def test_nan_and_inf_are_refused(tmp_path, capsys, args):
    args = [a if a != "x.h5" else str(tmp_path / a) for a in args]
    with pytest.raises(SystemExit) as exit_:
        main(args)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "finite" in err and "Traceback" not in err
    assert not (tmp_path / "x.h5").exists()


# ------------------------------------------------------------------------- recover


def _crashed_copy(source: Path, target: Path, frames: int = 40) -> Path:
    """A session whose writer died (HDF5's open-for-writing flags left set), in a child process."""
    code = f"""
import os
from core.io.session import SessionFile, SessionWriter
with SessionFile({str(source)!r}) as s:
    rig, subject = s.rig, s.subject
    parts = {{h: (s.frames(h)[:{frames}], s.light_index(h)[:{frames}], s.timestamp_ns(h)[:{frames}],
                 s.frame_id(h)[:{frames}]) for h in s.heads}}
w = SessionWriter({str(target)!r}, kind="simulation", rig=rig, subject=subject)
w.start_swmr()
for k in range(0, {frames}, 5):
    for h, (f, li, ts, ids) in parts.items():
        w.append_frames(h, f[k:k + 5], li[k:k + 5], ts[k:k + 5], ids[k:k + 5])
    w.flush()
os._exit(0)
"""
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
    return target


def test_recover_twice_keeps_every_original(session, tmp_path):
    path = _crashed_copy(session, tmp_path / "cut.h5")
    original = digest(path)
    first = recover_session(path)
    assert first.original == tmp_path / "cut.crashed.h5" and digest(first.original) == original
    assert validate_session(path) == []
    with pytest.raises(Exception, match="nothing to recover"):
        recover_session(path)  # a complete session: refused, nothing renamed
    assert digest(first.original) == original
    # another crash under the same name: its original goes beside the first, not over it
    path.rename(tmp_path / "kept.h5")
    _crashed_copy(session, path, frames=20)
    second = recover_session(path)
    assert second.original == tmp_path / "cut.crashed-2.h5" and digest(first.original) == original


@pytest.mark.parametrize("share", [0.5, 0.6, 0.95])
def test_recover_a_file_truncated_on_disk_ends_in_seconds(session, tmp_path, capsys, share):
    crashed = _crashed_copy(session, tmp_path / "crashed.h5")
    closed = tmp_path / "closed.h5"
    closed.write_bytes(session.read_bytes())
    for path in (crashed, closed):
        with open(path, "r+b") as fh:
            fh.truncate(int(path.stat().st_size * share))
        before = digest(path)
        started = time.monotonic()
        code, err = run(["recover", str(path)], capsys)
        assert time.monotonic() - started < 20
        if code == 0:  # what could be read back is a valid session, the truncated original kept beside it
            assert validate_session(path) == []
            assert digest(path.with_name(path.stem + ".crashed.h5")) == before
        else:
            assert code == 2 and str(path) in err and "truncated on disk" in err and "nothing was changed" in err
            assert digest(path) == before


def test_recover_a_file_missing_a_dataset_says_which(session, tmp_path, capsys):
    path = _crashed_copy(session, tmp_path / "cut.h5")
    recover_session(path)
    with h5py.File(path, "r+") as f:
        del f["heads/back/timestamp_ns"]
    code = main(["recover", str(path)])
    captured = capsys.readouterr()
    assert code == 0 and "Traceback" not in captured.err
    assert "head back: timestamp_ns lost" in captured.out
    with SessionFile(path) as s:
        assert s.n_frames("front") == 40 and s.n_frames("back") == 0
    other = tmp_path / "text.h5"
    other.write_text("not HDF5")
    code, err = run(["recover", str(other)], capsys)
    assert code == 2 and "not an HDF5 file" in err and str(other) in err


def test_recover_a_file_whose_dataset_header_was_cut_mid_write_keeps_the_other_head(session, tmp_path, capsys):
    """A writer killed while writing a dataset's object header leaves it failing its checksum (seen when
    the capture engine was killed under load): that head's frames are lost, the other head's kept."""
    path = _crashed_copy(session, tmp_path / "cut.h5")
    with h5py.File(path, "r", swmr=True) as f:  # its writer's flags still set, as a dead writer leaves them
        header = h5py.h5o.get_info(f["heads/back/frame_id"].id).addr
    with open(path, "r+b") as fh:
        fh.seek(header + 20)
        byte = fh.read(1)[0]
        fh.seek(header + 20)
        fh.write(bytes([byte ^ 0xFF]))
    code = main(["recover", str(path)])
    captured = capsys.readouterr()
    assert code == 0 and "Traceback" not in captured.err
    assert "head back: frame_id lost or unreadable" in captured.out
    assert validate_session(path) == []
    with SessionFile(path) as s:
        assert s.n_frames("front") == 40 and s.n_frames("back") == 0


# ------------------------------------------------------------------------- impossible values


@pytest.mark.parametrize("change, message", [
    (lambda f: f["rig"].attrs.__setitem__("frame_rate_hz", 0.0), "/rig@frame_rate_hz"),
    (lambda f: f["rig"].attrs.__setitem__("frame_rate_hz", -110.0), "/rig@frame_rate_hz"),
    (lambda f: f["rig"].attrs.__setitem__("frame_rate_hz", float("nan")), "/rig@frame_rate_hz"),
    (lambda f: f["rig/front"].attrs.__setitem__("light_positions_mm", np.zeros((4, 3))), "light_positions_mm"),
    (lambda f: f["rig/back"].attrs.__setitem__("light_positions_mm", np.full((4, 3), 300.0)), "apart"),
    (lambda f: f["rig/front"].attrs.__setitem__("fx", float("inf")), "/rig/front@fx"),
])
def test_impossible_session_values_are_refused_by_name(session, capsys, change, message):
    with h5py.File(session, "r+") as f:
        change(f)
    for verb in (["validate"], ["info"], ["process", "-o", str(session.with_name("r.h5"))]):
        code = main([verb[0], str(session)] + verb[1:])
        captured = capsys.readouterr()
        assert code in (1, 2) and message in captured.out + captured.err
        assert "Traceback" not in captured.err
    assert not session.with_name("r.h5").exists()


def test_a_recording_stopped_before_any_frame_is_one_line_for_every_verb(tmp_path, capsys):
    """A valid session file that holds no frame and no flow sample (a recording stopped at once): each
    verb names the file and says nothing was recorded, writes nothing, and the replay refuses it."""
    from app.engine.sources import replay_source
    from core.io.session import SessionError, SessionWriter, SubjectRecord
    from core.rig import thesis_rig

    empty = tmp_path / "empty.h5"
    with SessionWriter(empty, kind="patient", rig=thesis_rig(0.1),
                       subject=SubjectRecord("E-1", "female", 40.0, 165.0, 60.0)):
        pass
    assert validate_session(empty) == []
    for verb, said in ((["analyze"], "no camera frame and no flow sample"),
                       (["report", "-o", str(tmp_path / "r.pdf")], "no camera frame and no flow sample"),
                       (["process", "-o", str(tmp_path / "r.h5")], "no camera frame: nothing to reconstruct")):
        code, err = run([verb[0], str(empty)] + verb[1:], capsys)
        assert code == 2 and str(empty) in err and said in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "r.pdf").exists() and not (tmp_path / "r.h5").exists()
    with pytest.raises(SessionError, match="no camera frame to replay"):
        replay_source(empty)


def test_a_profile_with_coincident_lights_is_refused(tmp_path, session, capsys):
    from core.calibration.rig_profile import PROFILE_FORMAT

    profile = tmp_path / "rig.json"
    profile.write_text(json.dumps({"format": PROFILE_FORMAT, "format_version": 1, "heads": {
        "front": {"light_positions_mm": [[0, 0, 0]] * 4}}}))
    code, err = run(["process", str(session), "--rig", str(profile), "-o", str(tmp_path / "r.h5")], capsys)
    assert code == 2 and str(profile) in err and "light_positions_mm" in err and "camera's centre" in err


@pytest.mark.parametrize("text, message", [
    ('[camera]\nframe_rate_hz = 110\nexposure_uss = 1000\n[heads.front]\ncamera = "sim"\n',
     "unknown key 'exposure_uss'; did you mean 'exposure_us'?"),
    ('nmae = "x"\n[heads.front]\ncamera = "sim"\n', "unknown key 'nmae'; did you mean 'name'?"),
    ('[heads.front]\ncamera = "sim"\nfocal_lenght_mm = 25\n', "did you mean 'focal_length_mm'?"),
    ('[heads.front]\ncamera = "sim"\n[simulation]\nscale = 5\n', "[simulation] scale must be a number from"),
    ('[heads.front]\ncamera = "sim"\n[simulation]\nprotocol = "jog"\n', "[simulation] protocol"),
    ('[heads.front]\ncamera = "sim"\n[camera]\nframe_rate_hz = 0\n', "frame_rate_hz"),
    ('camera = 3\n[heads.front]\ncamera = "sim"\n', "camera must be a table"),
])
def test_rig_files_with_unknown_keys_or_impossible_values_are_refused(tmp_path, capsys, text, message):
    rig = tmp_path / "rig.toml"
    rig.write_text(text)
    code, err = run(["record", "--rig", str(rig), "--seconds", "1", "-o", str(tmp_path / "s.h5")], capsys)
    assert code == 2 and message in err and str(rig) in err
    assert not (tmp_path / "s.h5").exists()


def test_records_in_a_missing_folder_are_refused_and_new_ones_are_private(tmp_path, capsys, monkeypatch):
    missing = tmp_path / "no-such-folder" / "records.sqlite3"
    args = ["--family-name", "Doe", "--sex", "female", "--birth-date", "1980-01-01", "--height", "165",
            "--weight", "60"]
    code, err = run(["patients", "--records", str(missing), "add"] + args, capsys)
    assert code == 2 and "does not exist" in err and not missing.parent.exists()
    code, err = run(["report", str(tmp_path / "x.h5"), "-o", str(tmp_path / "r.pdf"), "--records", str(missing)],
                    capsys)
    assert code == 2 and str(missing) in err
    path = tmp_path / "records.sqlite3"
    assert main(["patients", "--records", str(path), "add"] + args) == 0
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    from app.records import Records

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "fresh-home"))
    Records().close()
    folder = tmp_path / "fresh-home" / "photopft"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert stat.S_IMODE((folder / "records.sqlite3").stat().st_mode) == 0o600


def test_the_research_copy_holds_no_clinic_pseudonym_or_time_in_its_bytes(session, tmp_path):
    with SessionFile(session) as s:
        clinic_id, created = s.subject.id, s.created
    with h5py.File(session) as f:
        calibrated = str(f["rig/front"].attrs["calibrated"])  # the time the spec asks, calibrated or not
    key = tmp_path / "study.key"
    key.write_bytes(b"0123456789abcdef0123")
    copy = tmp_path / "research.h5"
    assert main(["export", str(session), "--research", str(copy), "--study-key-file", str(key)]) == 0
    raw = copy.read_bytes()
    assert clinic_id.encode() not in raw
    assert created.encode() not in raw and created[11:19].encode() not in raw
    assert calibrated[11:19].encode() not in raw or calibrated[11:19] == "00:00:00"
    assert validate_session(copy) == []


# ------------------------------------------------------------------------- waveform and calibration inputs


def _wf(tmp_path: Path, header: str, samples: list[str], name: str = "w.wf") -> Path:
    path = tmp_path / name
    path.write_text("[Header]\n" + header + "\n[Parameters]\n[Data]\n" + "\n".join(samples) + "\n")
    return path


def _blow(rate: int = 100, seconds: float = 4.0) -> np.ndarray:
    t = np.arange(int(rate * seconds)) / rate
    return 4.0 * (1 - np.exp(-t / 0.5))


def test_fzoom_and_decimal_commas_are_read(tmp_path, capsys):
    plain = _wf(tmp_path, "Type=VT\nFreq=100", [f"{v:.5f}" for v in _blow()], "plain.wf")
    zoomed = _wf(tmp_path, "Type=VT\nFreq=100,0\nfZoom=0,001", [f"{round(v * 1000)}" for v in _blow()], "zoom.wf")
    outputs = []
    for path in (plain, zoomed):
        assert main(["analyze", "--waveform", str(path)]) == 0
        outputs.append(capsys.readouterr().out)
    values = [[line.split()[1] for line in out.splitlines() if line.strip().startswith(("FVC", "PEF"))]
              for out in outputs]
    plain_values, zoomed_values = ([float(x) for x in v] for v in values)
    assert zoomed_values == pytest.approx(plain_values, rel=0.01)  # samples rounded to whole mL
    assert plain_values[0] == pytest.approx(4.0, abs=0.01)


@pytest.mark.parametrize("header, samples, message", [
    ("Type=VT\nFreq=0", None, "Freq must be a positive"),
    ("Type=VT\nFreq=-100", None, "Freq must be a positive"),
    ("Type=VT\nFreq=nan", None, "Freq must be a finite number"),
    ("Type=VT\nFreq=100", ["0.1", "nan"] * 200, "must be a finite number"),
    ("Type=VT\nFreq=100", ["0"] * 400, "no forced expiration"),
    ("Type=VT\nFreq=100", [f"{v:.4f}" for v in _blow(seconds=0.6)], "lasts 0.60 s"),
])
def test_impossible_waveforms_are_refused_with_the_file_named(tmp_path, capsys, header, samples, message):
    path = _wf(tmp_path, header, samples or [f"{v:.5f}" for v in _blow()])
    code, err = run(["analyze", "--waveform", str(path)], capsys)
    assert code == 2 and message in err and str(path) in err


def test_calibration_inputs_of_the_wrong_kind_are_one_line(session, tmp_path, capsys):
    binary = tmp_path / "flows.csv"
    binary.write_bytes(bytes(range(256)) * 4)
    code, err = run(["calibrate", "flow", str(binary), "-o", str(tmp_path / "f.json")], capsys)
    assert code == 2 and str(binary) in err
    nan_rows = tmp_path / "nan.csv"
    nan_rows.write_text("reference_lps,adc_mean\n1,2100\nnan,2200\n3,2300\n")
    code, err = run(["calibrate", "flow", str(nan_rows), "-o", str(tmp_path / "f.json")], capsys)
    assert code == 2 and "line 3" in err
    code, err = run(["calibrate", "volume", str(session), "-o", str(tmp_path / "v.json")], capsys)
    assert code == 2 and "not a results file" in err and str(session) in err
    headless = tmp_path / "headless.h5"
    with h5py.File(headless, "w") as f:
        f.attrs["format"] = "photopft-results"
    for verb in (["analyze", str(headless)], ["report", str(headless), "-o", str(tmp_path / "r.pdf")]):
        code, err = run(verb, capsys)
        assert code == 2 and "without heads" in err


@pytest.mark.parametrize("text, message", [
    ("[heads.front]\ncamera='NOSUCH01'\n[sequencer]\nport='emulator'\n", "NOSUCH01"),
    ("[heads.front]\ncamera='NOSUCH01'\n[sequencer]\nport='/dev/photopft-no-such-port'\n", "NOSUCH01"),
])
def test_a_missing_device_is_one_line_naming_it(tmp_path, capsys, text, message):
    """A rig whose camera is not on the network: `record` ends at once with exit 2, no file left."""
    rig = tmp_path / "rig.toml"
    rig.write_text("name = 'clinic'\n" + text)
    out = tmp_path / "s.h5"
    code, err = run(["record", "--rig", str(rig), "-o", str(out), "--seconds", "1"], capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and message in lines[0], err
    assert not out.exists()


def test_a_missing_sequencer_port_is_one_line_naming_it(tmp_path):
    from drivers.sequencer import Sequencer, SequencerError

    with pytest.raises(SequencerError, match="cannot open the sequencer on /dev/photopft-no-such-port"):
        Sequencer("/dev/photopft-no-such-port")
