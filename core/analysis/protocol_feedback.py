"""When a patient session's manoeuvre is done, and what to tell the operator after each one: the
ATS/ERS rules for the patient-session wizard, which only displays what this says.

Forced expirations (ATS/ERS 2019): at least three blows, up to eight, until two acceptable FVC and
FEV1 each agree within the repeatability tolerance. Slow VC (ATS/ERS 2005): at least three
manoeuvres, up to four, until the two largest acceptable agree within 150 mL. Tidal breathing:
five breaths or more, the period extended 15 s at a time up to a minute.
"""

from __future__ import annotations

from dataclasses import dataclass

from core.analysis.values import VC_REPEATABILITY_L, SessionValues, pef_not_given, vc_repeatability_l
from core.analysis.spirometry import repeatability_tolerance_l

MAX_BLOWS = 8
MIN_BLOWS = 3
MIN_VC = 3
MAX_VC = 4
FAR_BELOW_PREDICTED = 0.5  # a VC under half the predicted FVC: effort, leak or the wrong patient?
MIN_TIDAL_BREATHS = 5  # tidal indices are averaged over breaths: fewer than five say little
TIDAL_EXTENSION_S = 15.0  # a tidal period with too few breaths goes on this much longer, ...
MAX_TIDAL_EXTENSION_S = 60.0  # ... at most this much in all


@dataclass(frozen=True)
class Feedback:
    text: str  # what the operator reads after the manoeuvre
    finished: bool  # enough of this manoeuvre: the session may go on


def tidal_extension_s(breaths: int | None, extended_s: float) -> float:
    """How much longer the tidal period goes on (0: it may end)."""
    if breaths is None or breaths >= MIN_TIDAL_BREATHS or extended_s >= MAX_TIDAL_EXTENSION_S:
        return 0.0
    return TIDAL_EXTENSION_S


def forced_feedback(values: SessionValues, count: int, age_years: float | None) -> Feedback:
    """After blow number `count` (the blows kept so far): the verdict on the last blow marked, never
    on an earlier one where the last was left out (its maps not there yet, too few of them)."""
    grade = values.forced
    marked = values.forced_marks_s[-1] if values.forced_marks_s else None
    last = None if grade is None else next((m for m in grade.manoeuvres if m.mark_s == marked), None)
    if last is None:
        forced = [p for p in values.problems if p.startswith("forced expiration")]
        why = ([p for p in forced if marked is not None and f"{marked:.1f} s" in p] or forced or values.problems)[-1:]
        return Feedback(f"Blow {count}: not analysable ({'; '.join(why) or 'no forced expiration found'}); "
                        "do another.", count >= MAX_BLOWS)
    verdict = "acceptable" if last.fvc_acceptable else ("FEV1 acceptable" if last.fev1_acceptable
                                                        else "not acceptable")
    why_no_pef = pef_not_given(last)
    pef = f"PEF {last.pef_lps:.1f} L/s" if why_no_pef is None else f"PEF not given ({why_no_pef})"
    text = (f"Blow {count}: FVC {last.fvc_l:.2f} L, FEV1 {last.fev1_l:.2f} L, {pef}: "
            f"{verdict}" + (f" ({'; '.join(last.problems)})" if last.problems else "") + ".")
    repeatable = grade.fvc_grade in ("A", "B") and grade.fev1_grade in ("A", "B")  # two acceptable, within tolerance
    finished = count >= MAX_BLOWS or (count >= MIN_BLOWS and repeatable)
    if finished:
        text += (f" Grade {grade.grade}: enough blows." if count < MAX_BLOWS or repeatable else
                 f" Grade {grade.grade}: {MAX_BLOWS} blows, the most the standard allows.")
    elif count >= MIN_BLOWS and min(grade.acceptable_fvc, grade.acceptable_fev1) < 2:
        text += (f" {grade.acceptable_fvc} acceptable FVC and {grade.acceptable_fev1} acceptable FEV1 so far; "
                 "two of each are needed: another blow, please.")
    elif count >= MIN_BLOWS:
        text += (f" Repeatability not met yet (FVC within {grade.fvc_repeatability_l:.3f} L, needs "
                 f"{repeatability_tolerance_l(grade.fvc_l, age_years):.3f} L; FEV1 within "
                 f"{grade.fev1_repeatability_l:.3f} L, needs {repeatability_tolerance_l(grade.fev1_l, age_years):.3f} L):"
                 " another blow, please.")
    return Feedback(text, finished)


def vc_feedback(values: SessionValues, count: int, predicted_fvc_l: float | None) -> Feedback:
    """After slow VC number `count`: its verdict, a plausibility warning, the repeatability so far."""
    manoeuvres = values.vc_manoeuvres
    if len(manoeuvres) < count:
        return Feedback(f"Slow VC {count}: not analysable; do it again.", count >= MAX_VC)
    last = manoeuvres[-1]
    text = f"Slow VC {count}: VC {last.vc_l:.2f} L, " + (
        "acceptable" if last.acceptable else "not acceptable: " + "; ".join(last.problems))
    if predicted_fvc_l and last.vc_l < FAR_BELOW_PREDICTED * predicted_fvc_l:
        text += (f". Far below the predicted FVC ({predicted_fvc_l:.2f} L): check the effort, the nose clip and "
                 "the mouthpiece")
    acceptable = sum(m.acceptable for m in manoeuvres)
    spread = vc_repeatability_l(manoeuvres)
    repeatable = acceptable >= 2 and spread <= VC_REPEATABILITY_L
    if acceptable >= 2:
        text += (f". The two largest within {1000 * spread:.0f} mL "
                 f"({'met' if repeatable else 'not met'}: tolerance {1000 * VC_REPEATABILITY_L:.0f} mL)")
    finished = (count >= MIN_VC and repeatable) or count >= MAX_VC
    if finished:
        text += (f". VC {values.vital_capacity.vc_l:.2f} L (the largest acceptable): enough." if repeatable else
                 f". {MAX_VC} manoeuvres, the most asked for: VC {values.vital_capacity.vc_l:.2f} L, not repeatable.")
    else:
        text += f". Another, please ({acceptable} acceptable of {count}; {MIN_VC} manoeuvres at least)."
    return Feedback(text, finished)
