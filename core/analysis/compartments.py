"""The trunk's compartments in quiet breathing: each quadrant's share of the metric volume's breaths and the
thoraco-abdominal phase angle, over a session's stretches of tidal breathing (core/volume/compartments.py
measures them; this module finds the stretches)."""

from __future__ import annotations

from core.analysis.values import tidal_stretches, tidal_values, tidal_windows
from core.volume.compartments import compartment_shares, phase_angle_deg
from core.volume.metric import MetricVolume


def tidal_compartments(session, metric: MetricVolume) -> dict[str, float]:
    """Each quadrant's share of quiet breathing (`share_upper_left` ...) and the thoraco-abdominal
    phase angle (`phase_angle_deg`, upper against lower half of the trunk) of a session
    (core.io.session.SessionFile) over its stretches of quiet breathing."""
    t = (metric.timestamp_ns - metric.timestamp_ns[0]) / 1e9
    start = int(metric.timestamp_ns[0])
    events = sorted(((ts - start) / 1e9, label) for ts, label in session.events())
    windows = tidal_windows(events, float(t[-1]))
    out = {f"share_{k.replace(' ', '_')}": v for k, v in compartment_shares(t, metric.regions, windows).items()}
    tidal = tidal_values(tidal_stretches(t, metric.volume_l, events))
    if tidal is not None:
        chest = metric.regions["upper left"] + metric.regions["upper right"]
        abdomen = metric.regions["lower left"] + metric.regions["lower right"]
        out["phase_angle_deg"] = phase_angle_deg(t, chest, abdomen, windows, 60.0 / tidal.respiratory_rate_bpm)
    return out
