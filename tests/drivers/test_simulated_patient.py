"""On the simulated rig the simulated subject is the registered patient (issue 77, requirement 10):
their sex, age, height and weight, and lung volumes at the GLI predicted values the report uses."""

from __future__ import annotations

import numpy as np
import pytest

from core.analysis.reference import reference
from drivers.assembly import simulated_rig


def test_the_simulated_subject_follows_the_patient_and_breathes_their_predicted_vc():
    rig = simulated_rig(scale=0.05, seconds=120.0, with_flow=False)
    state = rig.simulated
    before = state.config.subject
    assert (before.sex, before.height_cm) == ("male", 175.0)
    state.follow("female", 55.0, 166.0, 60.0, "P-NOWAK")
    subject = state.config.subject
    assert (subject.id, subject.sex, subject.age_years, subject.height_cm) == ("P-NOWAK", "female", 55.0, 166.0)
    predicted = reference("FVC", "female", 55.0, 166.0).predicted
    assert subject.fvc_l == pytest.approx(predicted) and 2.5 < predicted < 3.6
    start = state.now_s()
    seconds = state.perform("vc")
    t = np.arange(start, start + seconds, 0.01)
    vc = float(np.ptp([state.waveform.at(x) for x in t]))
    assert vc == pytest.approx(predicted, rel=0.10)  # a normal VC: near 100 % of the predicted FVC
