"""What the GUI may ask of a live engine: the calls the in-process engine (LiveRig) and the engine in
its own process (EngineProcess) both answer alike (tests/app/test_live_engine_contract.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from app.engine.feeds import EngineInfo, Snapshot
from core.io.session import SubjectRecord
from core.rig import Rig


@runtime_checkable
class LiveEngine(Protocol):
    info: EngineInfo
    rig: Rig
    recording: bool

    def snapshot(self) -> Snapshot: ...

    def stop(self): ...

    def start_recording(self, path: str | Path, subject: SubjectRecord | None, kind: str = "patient",
                        root_attrs: dict | None = None, heads: list[str] | None = None) -> None: ...

    def stop_recording(self): ...

    def mark(self, label: str) -> int: ...

    def flow_reaches(self, timestamp_ns: int) -> bool: ...

    def recorded_values(self, age_years: float | None = None): ...

    def perform(self, manoeuvre: str) -> float: ...

    def flow_since(self, monotonic_ns: int) -> tuple[np.ndarray, np.ndarray]: ...

    def preview(self, head: str) -> np.ndarray | None: ...

    def replay_control(self, action: str, position_s: float | None = None) -> None: ...

    def blow_trace(self, mark_ns: int, before_s: float = 2.5) -> dict: ...

    def flow_adc_mean(self, seconds: float = 2.0) -> float: ...

    def calibrate_on_subject(self, start_ns: int): ...

    @property
    def replay_finished(self) -> bool: ...
