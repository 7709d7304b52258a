"""No command destroys an input or a recording, and none leaves a half-written output (issue 28)."""

from __future__ import annotations

import argparse
import hashlib
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import pytest

from app.cli import build_parser, main
from core.outputs import OutputError, check_output
from core.recovery import recover_session
from core.session import SessionFile, validate_session


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
    deadline = time.monotonic() + 60
    while not _partials(tmp_path) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)
    assert proc.poll() is None, "process ended before it could be interrupted"
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode in (130, 143) and "Traceback" not in err, err
    assert "nothing half-written" in err
    assert not out.exists() and not _partials(tmp_path)


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
from core.session import SessionFile, SessionWriter
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
