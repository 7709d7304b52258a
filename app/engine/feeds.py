"""What the live engine shows: each head's newest map and rates, the curves, the checks' verdicts
(Snapshot, which the GUI pulls on its own timer), and what it knows of its source (EngineInfo)."""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.limits import Refusal
from core.analysis.optical_litres import ESTIMATE
from core.pipeline.quality import MAX_OCCLUDED_SIDE_SHARE
from core.rig import Rig

WINDOW_S = 30.0  # what the live view's curves show


@dataclass
class HeadView:
    height_mm: np.ndarray | None = None  # above the subject's mean surface, NaN off the subject
    distance_mm: float = float("nan")
    frame_id: int = -1
    occluded_side_share: float = float("nan")  # core.reconstruction.pipeline.occluded_side_share of the last map
    reconstructed: int = 0
    frames: int = 0
    lost: int = 0
    fps: float = 0.0

    @property
    def arm_against_trunk(self) -> bool:
        """The last map shows an arm against the trunk hiding its side (core/pipeline/quality.py's rule)."""
        return bool(self.occluded_side_share > MAX_OCCLUDED_SIDE_SHARE)


@dataclass
class Snapshot:
    heads: dict[str, HeadView]
    optical_t_s: np.ndarray
    optical: np.ndarray  # gradient volume (sum of heads, thesis eq. 3.26), un-normalised
    flow_t_s: np.ndarray
    flow_volume_l: np.ndarray
    recording: Path | None
    recorded_frames: dict[str, int]
    dropped: int
    problems: list[str]
    elapsed_s: float
    metric_t_s: np.ndarray
    metric_volume_l: np.ndarray  # the metric optical volume (litres, both heads)
    flow_until_ns: int = 0  # the recording's newest flow sample (no limit without a recording or flow sensor)
    replay_finished: bool = False
    # why `process` would refuse the optical volume of what the heads see now (skin, bent maps), or None
    optical_refused: Refusal | None = None
    optical_checked: bool = False  # whether the heads' last seconds gave those checks anything to judge by
    # what the optical litres are now: calibrated on the subject (its residual) or an estimate
    optical_litres: str = ESTIMATE
    replay_position_s: float = float("nan")  # a replay's position and length in its recording, and pause
    replay_length_s: float = float("nan")
    replay_paused: bool = False

    @classmethod
    def empty(cls, heads) -> "Snapshot":
        """Before the engine has anything to show."""
        none = np.zeros(0)
        return cls({h: HeadView() for h in heads}, none, none, none, none, None, {}, 0, [], 0.0, none, none)


@dataclass(frozen=True)
class EngineInfo:
    """What the GUI knows of the source an engine runs on."""
    rig: Rig
    heads: tuple[str, ...]
    name: str
    replay: bool
    simulated: bool  # the simulated rig: its subject follows the operator's prompts (LiveRig.perform)
    calibration: str = ""  # the calibrations in force, in words; "" for a replay (the file's /rig holds them)
    flow_calibration: tuple[float, float] | None = None  # the flow line in force (gain, offset L/s)
    flow_from: str = ""  # where that line comes from


class Rate:
    def __init__(self) -> None:
        self._times: collections.deque = collections.deque(maxlen=200)

    def tick(self) -> None:
        self._times.append(time.monotonic())

    def per_s(self) -> float:
        if len(self._times) < 2 or time.monotonic() - self._times[-1] > 1.0:
            return 0.0
        return (len(self._times) - 1) / (self._times[-1] - self._times[0])
