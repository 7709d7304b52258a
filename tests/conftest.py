"""Shared fixtures: small simulated sessions, made once per test run."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
if "PHOTOPFT_SHARED" in os.environ:
    SHARED = Path(os.environ["PHOTOPFT_SHARED"])


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
