"""A simulated session's true values: the analysis run on its /truth volume.

Only the simulator knows the truth, so only what compares with it (benches, tests, and the simulated
rig's `demo` and `analyze`) reads it here; the analysis of a recording never does.
"""

from __future__ import annotations

import os

import numpy as np

from core.analysis.values import SessionValues, analyse_volume
from core.io.session import SessionFile


def truth_values(path: str | os.PathLike, from_s: float = float("-inf")) -> SessionValues | None:
    """The values of the session's true volume, read as the flow sensor's are; None without a truth.
    from_s: read from that time on (s from the first frame), as an optical curve calibrated on the subject
    is read (core/analysis/session_analysis.py, SessionReport.optical_from_s)."""
    with SessionFile(path) as s:
        if not s.has_truth:
            return None
        start = s.start_ns()
        events = sorted(((t - start) / 1e9, label) for t, label in s.events())
        age = s.subject.age_years if s.subject is not None else None
        truth = s.truth()
        t = (np.asarray(truth["timestamp_ns"]) - start) / 1e9
        read = t >= from_s
        return analyse_volume(t[read], np.asarray(truth["volume_l"])[read], events, age)
