"""ERS/ATS 2022 interpretation: patterns and severity from z-scores, bronchodilator response."""

import pytest

from core.analysis.interpretation import (NORMAL, NOT_INTERPRETED, OBSTRUCTION, PRISM, bronchodilator_response,
                                 bronchodilator_statement, interpret, severity)
from core.analysis.reference import reference


def _refs():
    return {p: reference(p, "female", 45.0, 165.0) for p in ("FEV1", "FVC", "FEV1_FVC")}


def _at(ref, z):
    """The value with z-score z (inverse of the LMS z-score)."""
    return ref.predicted * (1.0 + z * ref.l * ref.s) ** (1.0 / ref.l)


def _values(refs, z_fev1, z_fvc, z_ratio):
    return {"FEV1_l": _at(refs["FEV1"], z_fev1), "FVC_l": _at(refs["FVC"], z_fvc),
            "FEV1_FVC": _at(refs["FEV1_FVC"], z_ratio)}


@pytest.mark.parametrize("z, expected", [(-1.0, None), (-1.64, None), (-1.7, "mild"), (-2.49, "mild"),
                                         (-2.51, "moderate"), (-3.99, "moderate"), (-4.01, "severe")])
def test_severity_by_fev1_z(z, expected):
    assert severity(z) == expected


def test_patterns():
    refs = _refs()
    normal = interpret(_values(refs, -0.5, -0.3, -0.4), refs)
    assert normal.pattern == NORMAL and normal.severity is None and normal.summary == "Normal spirometry"
    assert normal.z["FEV1"] == pytest.approx(-0.5, abs=1e-9)
    obstruction = interpret(_values(refs, -3.0, -0.5, -2.5), refs)
    assert (obstruction.pattern, obstruction.severity) == (OBSTRUCTION, "moderate")
    assert obstruction.summary == "Obstruction, moderate"
    mild_ratio_only = interpret(_values(refs, -1.0, 0.5, -2.0), refs)
    assert mild_ratio_only.pattern == OBSTRUCTION and mild_ratio_only.severity is None
    prism = interpret(_values(refs, -2.0, -2.2, 0.0), refs)
    assert (prism.pattern, prism.severity) == (PRISM, "mild")
    assert any("restriction" in s and "total lung capacity" in s for s in prism.statements)
    mixed = interpret(_values(refs, -4.5, -3.0, -2.0), refs)
    assert (mixed.pattern, mixed.severity) == (OBSTRUCTION, "severe")
    assert any("mixed" in s for s in mixed.statements)


def test_no_fixed_cutoffs():
    """An elderly subject's FEV1/FVC of 0.68 is above the LLN: not obstruction (the 0.70 rule would say so)."""
    refs = {p: reference(p, "male", 80.0, 175.0) for p in ("FEV1", "FVC", "FEV1_FVC")}
    assert refs["FEV1_FVC"].lln < 0.68
    values = {"FEV1_l": refs["FEV1"].predicted * 0.95, "FVC_l": refs["FVC"].predicted, "FEV1_FVC": 0.68}
    assert interpret(values, refs).pattern == NORMAL


def test_missing_or_unusable():
    refs = _refs()
    result = interpret({"FEV1_l": 2.5}, refs)
    assert result.pattern == NOT_INTERPRETED and "FVC (no value)" in result.statements[0]
    failed = interpret(_values(refs, 0, 0, 0), refs, grade="F")
    assert failed.pattern == NOT_INTERPRETED and failed.z == {}
    assert failed.statements == ["Not interpreted: session quality grade F, no usable manoeuvre (ATS/ERS 2019); "
                                 "repeat the test."]


def test_grade_u_is_interpreted_with_caution():
    """ATS/ERS 2019 Table 10: grade U is no acceptable but at least one usable manoeuvre; its values may
    be interpreted, with caution, and the quality line must not contradict the interpretation above it."""
    refs = _refs()
    usable_only = interpret(_values(refs, -3.0, -0.5, -2.5), refs, grade="U")
    assert usable_only.pattern == OBSTRUCTION
    assert "not usable" not in " ".join(usable_only.statements)
    assert usable_only.statements[-1].startswith("Session quality grade U: no acceptable manoeuvre")
    assert "caution" in usable_only.statements[-1]
    assert interpret(_values(refs, -3.0, -0.5, -2.5), refs, grade="A").statements == usable_only.statements[:-1]


def test_bronchodilator_response():
    refs = _refs()
    predicted = refs["FEV1"].predicted
    pre = {"FEV1_l": 2.0, "FVC_l": 3.0}
    post = {"FEV1_l": 2.0 + 0.12 * predicted, "FVC_l": 3.05}
    changes = bronchodilator_response(pre, post, refs)
    fev1, fvc = changes
    assert fev1.response and not fvc.response
    assert fev1.change_percent_predicted == pytest.approx(12.0)
    assert fvc.change_ml == pytest.approx(50.0)
    assert "significant bronchodilator response (FEV1" in bronchodilator_statement(changes)
    assert "no significant" in bronchodilator_statement(bronchodilator_response(pre, pre, refs))
