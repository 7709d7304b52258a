"""The photopft command line, run as a user runs it."""

from __future__ import annotations

import json
import subprocess
import sys

import h5py
import pytest

from app.cli import build_parser, main


def photopft(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "app", *args], capture_output=True, text=True, timeout=300)


def test_simulate_info_validate(tmp_path):
    out = tmp_path / "s.h5"
    r = photopft("simulate", "--protocol", "tidal", "--seconds", "0.5", "--scale", "0.05", "--seed", "2", "-o", str(out))
    assert r.returncode == 0, r.stderr
    assert "wrote" in r.stdout
    r = photopft("validate", str(out))
    assert r.returncode == 0 and "valid photopft session" in r.stdout
    r = photopft("info", str(out))
    assert r.returncode == 0
    for text in ("simulation session", "front: 70 x 51 px", "back:", "flow sensor:", "subject SIM-0001", "tidal-start"):
        assert text in r.stdout, text


def test_validate_lists_problems_and_exits_1(small_session, tmp_path):
    broken = tmp_path / "broken.h5"
    broken.write_bytes(small_session.read_bytes())
    with h5py.File(broken, "r+") as f:
        del f["rig/front"].attrs["fy"]
        f.attrs["kind"] = "party"
    r = photopft("validate", str(broken))
    assert r.returncode == 1
    assert "/rig/front@fy" in r.stdout and "/@kind" in r.stdout


def test_front_only(tmp_path):
    out = tmp_path / "f.h5"
    assert main(["simulate", "--heads", "front", "--seconds", "0.1", "--scale", "0.05", "-o", str(out)]) == 0
    with h5py.File(out) as f:
        assert list(f["rig"]) == ["front"] and list(f["heads"]) == ["front"]


@pytest.mark.parametrize("args, message", [
    (["simulate", "--age", "300", "-o", "x.h5"], "age_years"),
    (["simulate", "--scale", "2", "-o", "x.h5"], "scale"),
    (["simulate", "--placements", "1", "--scene", "specular-sphere", "-o", "x.h5"], "placements"),
    (["info", "missing.h5"], "no such file"),
])
def test_bad_input_gives_one_clear_line(tmp_path, capsys, args, message):
    args = [a if a != "x.h5" else str(tmp_path / a) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_every_verb_has_help(capsys):
    parser = build_parser()
    verbs = parser._subparsers._group_actions[0].choices
    assert {"simulate", "info", "validate"} <= set(verbs)
    for verb in verbs:
        with pytest.raises(SystemExit) as exit_info:
            main([verb, "--help"])
        assert exit_info.value.code == 0
        assert "usage: photopft " + verb in capsys.readouterr().out


def test_demo_runs_end_to_end(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path), "--seconds", "12", "--scale", "0.05"]) == 0
    out = capsys.readouterr().out
    for text in ("valid", "reconstructed", "volume summary", "gradient volume", "optical volume in litres",
                 "key values", "TV"):
        assert text in out, text
    assert (tmp_path / "session.h5").exists() and (tmp_path / "results.h5").exists()
    # the results file analysed: its session's flow sensor and truth, and the optical volume beside them
    assert main(["analyze", str(tmp_path / "results.h5")]) == 0
    header = next(line for line in capsys.readouterr().out.splitlines() if line.strip().startswith("value"))
    assert "flow sensor" in header and "optical" in header and "truth" in header


def test_a_negative_prefilter_is_refused_by_name(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["process", str(tmp_path / "x.h5"), "-o", str(tmp_path / "y.h5"), "--prefilter-px", "-1"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "--prefilter-px" in err and "0 or more pixels" in err


def test_an_output_that_was_not_written_is_named_alone(tmp_path):
    """A bench whose scratch session went missing said '<the --waveforms folder>: <the session> was
    not written', naming an input that had nothing to do with it; an OutputError names its output."""
    import argparse

    from app.cli import _one_line_naming_the_input
    from core.io.outputs import OutputError

    args = argparse.Namespace(waveforms=tmp_path / "waveforms", verb="bench")
    missing = tmp_path / "scratch" / "15-session.h5"
    assert _one_line_naming_the_input(OutputError(f"{missing} was not written"), args) == f"{missing} was not written"
    assert _one_line_naming_the_input(OSError("bad header"), args).startswith(str(tmp_path / "waveforms"))


def test_the_world_choices_are_the_simulators_worlds():
    from app.args import WORLD_NAMES
    from core.sim.simulate import WORLDS

    assert WORLD_NAMES == tuple(WORLDS)


def test_an_option_given_explicitly_wins_over_the_world_s_value(tmp_path):
    path = tmp_path / "plane.h5"
    assert main(["simulate", "-o", str(path), "--scene", "plane", "--seconds", "0.1", "--scale", "0.05",
                 "--world", "clinic", "--specular", "0.02", "--drop-rate", "0"]) == 0
    with h5py.File(path, "r") as f:
        world = json.loads(f["truth"].attrs["world"])
    assert world["specular"] == 0.02 and world["drop_rate"] == 0.0  # given
    assert world["led_mu"] == 2.0 and world["led_offset_mm"] == 10.0  # the clinic's


def test_numba_as_the_application_configures_it():
    """numba's coloured messages swap `sys.stderr` through colorama in whatever thread compiles; a
    line the command printed afterwards could reach a stream no longer the process's (CI, 2026-11-29:
    the error line of `simulate --scale 2` reached a finished test's capture). Its parallel kernels,
    called from several threads at once in the live view, run on a thread-safe layer (numba's
    workqueue layer aborts the process on that)."""
    probe = ("import app.cli, sys, numba, numpy, numba.core.errors as e\n"
             "kernel = numba.njit(parallel=True)(lambda a: a.sum())\n"
             "kernel(numpy.ones(8))\n"
             "sys.stdout.write(type(e.termcolor()).__name__ + ' ' + numba.threading_layer())")
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    scheme, layer = done.stdout.split()
    assert scheme == "NOPColorScheme" and layer in ("omp", "tbb")
