"""Calibrations: the lights from sphere sessions, the rig profile, the flow sensor and volume regression, the syringe check."""
