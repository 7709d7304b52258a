"""Litres from the optical volume: the subject's own calibration where the session has one, else an
estimate with the population's gain and its measured uncertainty (docs/history/volume-log.md, "Calibrated litres").

The plain optical signal is each head's trunk displacement in its quadrants (core/volume/metric.py);
with a calibration its chest and abdomen are weighed by the gains fitted through the flow sensor
(core/volume/subject_calibration.py), else their sum is multiplied by POPULATION_GAIN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.analysis.optical_labels import CALIBRATED, ESTIMATE
from core.analysis.session_analysis import session_flow_volume
from core.io.session import SessionFile
from core.volume.metric import MetricVolume
from core.volume.subject_calibration import (SubjectCalibration, calibration_segment, fit_subject_calibration,
                                             regional_signals)

# The estimate's gain, from the development population's sessions; its uncertainty, the widest 95 %
# limit of the estimate's errors on either population's processed rows (docs/constants.md)
POPULATION_GAIN = 1.20
ESTIMATE_UNCERTAINTY = 0.60


@dataclass
class OpticalLitres:
    """How the optical volume is turned into litres: `calibration` when the subject's holds, else the
    population's gain; `not_calibrated` says why not."""

    calibration: SubjectCalibration | None
    not_calibrated: str | None = None

    @property
    def calibrated(self) -> bool:
        return self.calibration is not None and self.calibration.refused is None

    def volume_l(self, metric: MetricVolume) -> np.ndarray:
        if self.calibrated:
            return self.calibration.volume_l(regional_signals(metric.head_regions))
        return POPULATION_GAIN * np.asarray(metric.volume_l, dtype=float)

    @property
    def method(self) -> str:
        return CALIBRATED if self.calibrated else ESTIMATE

    def label(self) -> str:
        if self.calibrated:
            return self.calibration.label()
        return estimate_label(ESTIMATE_UNCERTAINTY)

    def attrs(self) -> dict:
        """/volume's attributes saying how its litres were made."""
        out: dict = {"label": self.label()}
        if self.calibrated:
            c = self.calibration
            out.update(calibration_residual_l=c.residual_l, calibration_range_l=c.range_l,
                       calibration_expected_error=c.expected_error,
                       calibration_segment_s=np.asarray(c.segment_s, dtype=float),
                       calibration_grouping=c.extra.get("grouping", ""), calibration_curvature_per_l=c.curvature_per_l,
                       **{f"calibration_gain_{n.replace(' ', '_')}": g for n, g in c.gains.items()})
        else:
            out.update(population_gain=POPULATION_GAIN, estimate_uncertainty=ESTIMATE_UNCERTAINTY,
                       not_calibrated=self.not_calibrated or "")
        return out


def estimate_label(uncertainty: float) -> str:
    return f"{ESTIMATE} (±{100 * uncertainty:.0f} %)"


def subject_litres(session: SessionFile, metric: MetricVolume) -> OpticalLitres:
    """The subject's calibration over the session's calibration segment (calibration_segment), or why
    there is none."""
    start = session.start_ns()
    events = sorted(((t - start) / 1e9, label) for t, label in session.events())
    flow = session_flow_volume(session, events)
    if flow is None:
        return OpticalLitres(None, "the session has no flow sensor")
    if flow.refused is not None:
        return OpticalLitres(None, f"the flow sensor's samples are refused: {flow.refused}")
    segment = calibration_segment(events, float(flow.t_s[-1]))
    if segment is None:
        return OpticalLitres(None, "the flow sensor covers no quiet breathing and slow VC at the session's start")
    signals = regional_signals(metric.head_regions)
    map_t = (np.asarray(metric.timestamp_ns, dtype=np.int64) - start) / 1e9
    calibration = fit_subject_calibration(map_t, signals, flow.t_s, flow.volume_l, segment)
    return OpticalLitres(calibration, None if calibration.refused is None
                         else f"the subject's calibration is refused: {calibration.refused}")
