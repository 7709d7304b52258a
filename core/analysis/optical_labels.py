"""What an optical curve's litres are, as its label says (core/analysis/optical_litres.py gives it)."""

from __future__ import annotations

CALIBRATED = "optical, calibrated on the subject"
ESTIMATE = "optical estimate, not calibrated"


def calibrated_on_subject(optical_label: str | None) -> bool:
    """Whether an optical curve's litres come from the subject's own calibration."""
    return bool(optical_label) and optical_label.startswith(CALIBRATED)
