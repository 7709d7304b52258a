"""Interpretation of spirometry by the ERS/ATS 2022 strategy (Stanojevic et al., Eur Respir J 2022;60:2101499).

Everything is by z-score against the reference equations: the lower limit of normal is z = -1.645;
there is no fixed 80 % predicted or 0.70 FEV1/FVC cut-off. Severity of an abnormality is graded by
the FEV1 z-score (mild -1.65 to -2.5, moderate -2.5 to -4, severe below -4). Restriction needs a
total lung capacity, which spirometry does not measure: a low FVC with a preserved ratio is
"possible restriction" and the text says how to confirm it. A bronchodilator response is a change
of FEV1 or FVC of more than 10 % of the predicted value.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from core.analysis.reference import Z_LLN, Reference

NORMAL = "normal"
OBSTRUCTION = "obstruction"
PRISM = "PRISm"
NOT_INTERPRETED = "not interpreted"
SEVERITY_BOUNDS = ((-2.5, "mild"), (-4.0, "moderate"))  # z above the bound; below -4 severe
USABLE_GRADES = ("A", "B", "C")  # ATS/ERS 2019: D, E and U may be usable with caution, F not at all
BDR_THRESHOLD_PERCENT = 10.0


def severity(z_fev1: float) -> str | None:
    """Severity of a spirometric abnormality by the FEV1 z-score; None when FEV1 is not below the LLN."""
    if z_fev1 >= Z_LLN:
        return None
    for bound, name in SEVERITY_BOUNDS:
        if z_fev1 >= bound:
            return name
    return "severe"


@dataclass(frozen=True)
class Interpretation:
    pattern: str  # NORMAL, OBSTRUCTION, PRISM or NOT_INTERPRETED
    severity: str | None  # mild, moderate, severe, by the FEV1 z-score
    z: dict[str, float]  # FEV1, FVC, FEV1_FVC
    statements: list[str] = field(default_factory=list)  # the sentences a report prints, in order

    @property
    def summary(self) -> str:
        if self.pattern == NOT_INTERPRETED:
            return "Not interpreted"
        if self.pattern == NORMAL:
            return "Normal spirometry"
        text = "Obstruction" if self.pattern == OBSTRUCTION else "Preserved ratio impaired spirometry (PRISm)"
        return f"{text}, {self.severity}" if self.severity else text


def interpret(values: dict[str, float], references: dict[str, Reference], grade: str | None = None,
              source: str = "") -> Interpretation:
    """Interpret FEV1, FVC and FEV1/FVC (keys FEV1_l, FVC_l, FEV1_FVC of SessionValues.parameters())
    against their references (keys FEV1, FVC, FEV1_FVC)."""
    keys = {"FEV1": "FEV1_l", "FVC": "FVC_l", "FEV1_FVC": "FEV1_FVC"}
    if grade == "F":
        return Interpretation(NOT_INTERPRETED, None, {}, [
            "Not interpreted: session quality grade F, no usable manoeuvre (ATS/ERS 2019); repeat the test."])
    missing = [name for name, key in keys.items() if key not in values or name not in references]
    if missing:
        why = ", ".join(f"{name} ({'no value' if keys[name] not in values else 'no predicted value'})"
                        for name in missing)
        return Interpretation(NOT_INTERPRETED, None, {}, [f"Not interpreted: {why}."])
    z = {name: references[name].zscore(float(values[key])) for name, key in keys.items()}
    low = {name: z[name] < Z_LLN for name in z}
    grade_of = severity(z["FEV1"])
    statements = []
    by = f" ({source})" if source else ""
    if low["FEV1_FVC"]:
        pattern = OBSTRUCTION
        statements.append(f"FEV1/FVC below the lower limit of normal (z {z['FEV1_FVC']:.2f}){by}: obstruction"
                          + (f", {grade_of} by the FEV1 z-score ({z['FEV1']:.2f})." if grade_of else
                             " with FEV1 within normal limits."))
        if low["FVC"]:
            statements.append(f"FVC is also low (z {z['FVC']:.2f}): a mixed disorder or hyperinflation; only a "
                              f"total lung capacity (body plethysmography) tells them apart.")
    elif low["FEV1"] or low["FVC"]:
        pattern = PRISM
        which = " and ".join(name for name in ("FEV1", "FVC") if low[name])
        statements.append(f"{which} below the lower limit of normal with FEV1/FVC preserved (z "
                          f"{z['FEV1_FVC']:.2f}){by}: preserved ratio impaired spirometry (PRISm)"
                          + (f", {grade_of} by the FEV1 z-score ({z['FEV1']:.2f})." if grade_of else "."))
        if low["FVC"]:
            statements.append("Possible restriction: a low FVC with a preserved ratio can be restriction, which "
                              "needs a total lung capacity (body plethysmography or gas dilution) to confirm; "
                              "spirometry alone cannot.")
    else:
        pattern = NORMAL
        statements.append(f"FEV1 (z {z['FEV1']:.2f}), FVC (z {z['FVC']:.2f}) and FEV1/FVC (z "
                          f"{z['FEV1_FVC']:.2f}) within normal limits{by}.")
    if grade is not None and grade not in USABLE_GRADES:
        statements.append(f"Session quality grade {grade}: " + (
            "no acceptable manoeuvre, the values are from usable ones only (ATS/ERS 2019); interpret with "
            "caution and repeat the test when the patient can." if grade == "U" else
            "usable with caution only (ATS/ERS 2019)."))
    return Interpretation(pattern, grade_of, z, statements)


@dataclass(frozen=True)
class BronchodilatorChange:
    parameter: str  # FEV1 or FVC
    pre_l: float
    post_l: float
    predicted_l: float

    @property
    def change_ml(self) -> float:
        return 1000.0 * (self.post_l - self.pre_l)

    @property
    def change_percent_predicted(self) -> float:
        return 100.0 * (self.post_l - self.pre_l) / self.predicted_l

    @property
    def response(self) -> bool:
        return self.change_percent_predicted > BDR_THRESHOLD_PERCENT


def bronchodilator_response(pre: dict[str, float], post: dict[str, float],
                            references: dict[str, Reference]) -> list[BronchodilatorChange]:
    """The change of FEV1 and FVC from a pre- to a post-bronchodilator session, as ERS/ATS 2022 asks:
    in mL and as a percentage of the predicted value (the pre session's references)."""
    out = []
    for name, key in (("FEV1", "FEV1_l"), ("FVC", "FVC_l")):
        if key in pre and key in post and name in references:
            out.append(BronchodilatorChange(name, float(pre[key]), float(post[key]), references[name].predicted))
    return out


def bronchodilator_statement(changes: list[BronchodilatorChange]) -> str:
    if not changes:
        return "No bronchodilator response can be given: FEV1 and FVC are missing from one of the sessions."
    parts = [f"{c.parameter} {c.change_ml:+.0f} mL ({c.change_percent_predicted:+.1f} % of predicted)"
             for c in changes]
    responders = [c.parameter for c in changes if c.response]
    verdict = (f"a significant bronchodilator response ({' and '.join(responders)} > "
               f"{BDR_THRESHOLD_PERCENT:.0f} % of predicted)" if responders else
               f"no significant bronchodilator response (neither change > {BDR_THRESHOLD_PERCENT:.0f} % of predicted)")
    return "After bronchodilator: " + ", ".join(parts) + f": {verdict}."
