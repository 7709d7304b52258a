"""The tidal volumes of an optical curve calibrated on the subject, read with the gain of the subject's
own quiet breathing through the flow sensor.

The subject's calibration (core/volume/subject_calibration.py) fits one set of regional gains over quiet
breathing and a slow VC. Least squares leans on the VC's litres, and a trunk does not show a quiet breath
and a deep one in the same proportion: on the development population's subject 1001 and the test
population's mesh 101002 (subset draws, scale 0.25, true lights) the calibrated curve read the
calibration's own quiet breaths 1.07 and 1.19 times what the flow sensor read of them, and the later,
mouthpiece-free ones +13 % and +14 % (docs/history/volume-log.md, "Quiet breathing's own gain").
Respiratory inductance plethysmographs calibrate their tidal volume on the subject's quiet breathing for
the same reason. So the tidal volumes (TV, VE) are multiplied by the flow sensor's mean tidal volume over
the optical curve's, both read alike (core/analysis/values.py) over the calibration's quiet breathing;
the later breaths then read +6 % and -4 %. Times, rates and flow ratios do not change.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from core.analysis.optical_labels import calibrated_on_subject
from core.analysis.values import SessionValues, tidal_stretches, tidal_values
from core.volume.subject_calibration import calibration_segment

# The calibrated curve reading the calibration's own quiet breaths more than this factor off the flow
# sensor's (either way) does not measure quiet breathing: its tidal values are not given
MAX_QUIET_BREATHING_FACTOR = 1.5


@dataclass(frozen=True)
class QuietBreathingGain:
    """The flow sensor's mean tidal volume over the optical curve's, over the calibration's quiet
    breathing (`breaths`: those the optical curve read)."""

    factor: float
    breaths: int

    @property
    def plausible(self) -> bool:
        return 1.0 / MAX_QUIET_BREATHING_FACTOR <= self.factor <= MAX_QUIET_BREATHING_FACTOR

    def note(self) -> str:
        if not self.plausible:
            return (f"tidal values not given: the optical volume read the calibration's quiet breathing "
                    f"{1.0 / self.factor:.2f} times the flow sensor's")
        return (f"tidal volumes read with the subject's quiet-breathing gain (x{self.factor:.2f}, from "
                f"{self.breaths} breaths through the flow sensor)")


def quiet_breathing_gain(flow_t_s: np.ndarray, flow_volume_l: np.ndarray, optical_t_s: np.ndarray,
                         optical_volume_l: np.ndarray, events: list[tuple[float, str]],
                         segment: tuple[float, float] | None = None) -> QuietBreathingGain | None:
    """The gain over the quiet breathing of the calibration segment (default: the session's,
    calibration_segment; times in s on one clock); None where the flow sensor covers no calibration or
    either curve reads fewer than two breaths there."""
    flow_t = np.asarray(flow_t_s, dtype=float)
    if not len(flow_t):
        return None
    if segment is None:
        segment = calibration_segment(events, float(flow_t[-1]))
    if segment is None:
        return None
    inside = [(t, label) for t, label in events if t <= segment[1]]

    def read(t_s: np.ndarray, volume_l: np.ndarray):
        t, v = np.asarray(t_s, dtype=float), np.asarray(volume_l, dtype=float)
        kept = (t >= segment[0]) & (t <= segment[1])
        return tidal_values(tidal_stretches(t[kept], v[kept], inside)) if kept.sum() > 10 else None

    flow, optical = read(flow_t, flow_volume_l), read(optical_t_s, optical_volume_l)
    if flow is None or optical is None or not optical.tidal_volume_l > 0:
        return None
    return QuietBreathingGain(flow.tidal_volume_l / optical.tidal_volume_l, optical.breaths)


def with_quiet_breathing_gain(values: SessionValues, gain: QuietBreathingGain | None) -> SessionValues:
    """The values with their tidal volumes multiplied by the gain, and a note saying so; the tidal values
    withheld, with the reason, where the gain is implausible; unchanged without a gain or tidal values."""
    if gain is None or values.tidal is None:
        return values
    if not gain.plausible:
        return replace(values, tidal=None, problems=[*values.problems, gain.note()])
    t = values.tidal
    tidal = replace(t, tidal_volume_l=t.tidal_volume_l * gain.factor,
                    minute_ventilation_lpm=t.minute_ventilation_lpm * gain.factor)
    return replace(values, tidal=tidal, problems=[*values.problems, gain.note()])


def calibrated_tidal_values(values: SessionValues, optical_label: str | None,
                            flow_curve: tuple[np.ndarray, np.ndarray] | None,
                            optical_curve: tuple[np.ndarray, np.ndarray],
                            events: list[tuple[float, str]]) -> tuple[SessionValues, QuietBreathingGain | None]:
    """An optical curve's values (read off `optical_curve`, (s, L)) with the quiet-breathing gain where
    its label says it is calibrated on the subject and the flow sensor's curve (s, L) is there; and the
    gain taken (None where none was)."""
    if flow_curve is None or not calibrated_on_subject(optical_label):
        return values, None
    gain = quiet_breathing_gain(*flow_curve, *optical_curve, events)
    return with_quiet_breathing_gain(values, gain), gain
