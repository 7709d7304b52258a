"""Shared fixtures: small simulated sessions, made once per test run."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# Qt draws offscreen, and the application's settings, records and logs go to a folder of this
# test run, never the user's own.
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
# numba's OpenMP threads sleep when idle instead of spinning: with two xdist workers, their
# subprocesses and the GUI tests' threads on two cores, spinning threads took the CPU from the work
# (two heavy tests side by side: 138 s by default, 64 s passive)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Each xdist worker runs at the lowest priority, so that the live engine's threads, which set their
# own (app/engine/live_rig.py WORKER_NICENESS), keep the simulated rig's pace as on a clinic PC with nothing
# else to run: beside the other worker's tests at their default priority, the whole patient session
# recorded 14 frames/s a head and its optical values were refused for the missing frames.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.setpriority(os.PRIO_PROCESS, 0, 19)
_HOME = Path(os.environ.get("PHOTOPFT_TEST_HOME", "")) if os.environ.get("PHOTOPFT_TEST_HOME") else None
if _HOME is None:
    import atexit
    import shutil
    import tempfile

    _HOME = Path(tempfile.mkdtemp(prefix="photopft-test-home-"))
    atexit.register(shutil.rmtree, _HOME, True)  # each run's settings and records go with it
for _name in ("XDG_CONFIG_HOME", "XDG_DATA_HOME", "XDG_STATE_HOME"):
    os.environ[_name] = str(_HOME / _name.lower())

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
if "PHOTOPFT_SHARED" in os.environ:
    SHARED = Path(os.environ["PHOTOPFT_SHARED"])


# fixtures built once per run (_built_once): the tests that use one run on one xdist worker
# (--dist loadgroup in pyproject.toml), so no other worker sits waiting for the build
_GROUPED_FIXTURES = ("processed_full_session",)


# the two longest tests, the installer's build (3-4 minutes) and the whole patient session in real
# time (2 minutes), go first, one to each worker, so that each runs beside the rest instead of
# after it (xdist keeps this order: --no-loadscope-reorder in pyproject.toml; its default puts the
# groups of many tests first, and these began when the other worker had little left). Three workers
# on CI's two cores were tried (2026-11-29): 564 s on a warm clone against 644 s with two (the cores
# busy 189 % against 166 %), but on a fresh clone 617 s and the installed bundle's first maps came
# after 300 s, its kernels compiling beside three workers compiling theirs: the smoke test failed.
_LONG_FIRST = ("tests/e2e/", "tests/app/test_gui.py::test_a_whole_patient_session")


def _started_at(item) -> int:
    nodeid = item.nodeid.replace("\\", "/")
    return next((rank for rank, prefix in enumerate(_LONG_FIRST) if nodeid.startswith(prefix)), len(_LONG_FIRST))


def pytest_collection_modifyitems(items) -> None:
    items.sort(key=_started_at)
    for item in items:
        for name in _GROUPED_FIXTURES:
            if name in getattr(item, "fixturenames", ()):
                item.add_marker(pytest.mark.xdist_group(name))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    data = SHARED / "data"
    if not data.is_dir():
        pytest.fail(f"reference data not found at {data}: clone the project with ../shared beside it")
    return data


@pytest.fixture(scope="session")
def small_session(tmp_path_factory) -> Path:
    """Two heads, 1 s of tidal breathing at scale 0.1, with the flow sensor."""
    from core.sim.simulate import SimConfig, simulate

    path = tmp_path_factory.mktemp("sessions") / "small.h5"
    simulate(path, SimConfig(protocol="tidal", seconds=1.0, scale=0.1, seed=3))
    return path


def _built_once(tmp_path_factory, name: str, build) -> Path:
    """A file made once per test run and shared by the xdist workers (a lock file serialises them)."""
    import fcntl

    run_id = os.environ.get("PYTEST_XDIST_TESTRUNUID")
    base = tmp_path_factory.getbasetemp()
    folder = (base.parent / f"shared-{run_id}") if run_id else (base / "shared")
    folder.mkdir(parents=True, exist_ok=True)
    target = folder / name
    with open(folder / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not target.exists():
            partial = folder / f"partial-{name}"
            partial.mkdir(exist_ok=True)
            build(partial)
            partial.rename(target)
    return target


@pytest.fixture(scope="session")
def processed_full_session(tmp_path_factory) -> tuple[Path, Path]:
    """(session, results with an optical /volume): the full protocol at scale 0.1 with the flow
    sensor, processed every 22nd cycle window (5 maps/s); the optical volume is the metric one (a
    volume regression's path is tested on its own, test_report). One xdist worker runs every test
    that uses it (pytest_collection_modifyitems)."""
    from app.cli import main

    def build(folder: Path) -> None:
        from core.sim.simulate import SimConfig, simulate

        simulate(folder / "full.h5", SimConfig(protocol="full", scale=0.1, seed=5))
        assert main(["process", str(folder / "full.h5"), "-o", str(folder / "results.h5"), "--every", "22"]) == 0

    folder = _built_once(tmp_path_factory, "processed-full", build)
    return folder / "full.h5", folder / "results.h5"


@pytest.fixture(autouse=True)
def _nobody_proven():
    """Each test starts with no user proven by a password (app/auth.py keeps it per process)."""
    from app.auth import forget

    forget()
    yield
    forget()


@pytest.fixture()
def typed(monkeypatch):
    """typed(*lines): what a script gives on standard input (passwords, one a line)."""
    import io
    import sys

    def give(*lines: str) -> None:
        monkeypatch.setattr(sys, "stdin", io.StringIO("".join(f"{line}\n" for line in lines)))

    return give
