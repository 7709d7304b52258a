"""Predicted values, lower limits of normal, z-scores and percent predicted (GLI).

The coefficients are pyspiro's (MIT licence; GLI-2012, Quanjer et al. 2012, and GLI Global,
Bowerman et al. 2023, from their published tables). From its L, M, S:
predicted = M; z = ((value / M)^L - 1) / (L S); LLN = M (1 - 1.645 L S)^(1 / L), the 5th percentile.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

EQUATIONS = ("gli-global", "gli-2012")
Z_LLN = -1.6449  # 5th percentile
PARAMETERS = {"FEV1": "FEV1", "FVC": "FVC", "FEV1_FVC": "FEV1FVC", "FEF2575": "FEF25_75", "FEV075": "FEV075"}
GLI_2012_ETHNICITIES = {"caucasian": 1, "african-american": 2, "north-east-asian": 3, "south-east-asian": 4,
                        "other": 5}


class ReferenceUnavailable(ValueError):
    """No reference value for this subject or parameter; the message says why."""


@dataclass(frozen=True)
class Reference:
    parameter: str
    equations: str
    predicted: float
    lln: float
    l: float
    s: float

    def zscore(self, value: float) -> float:
        return float(((value / self.predicted) ** self.l - 1.0) / (self.l * self.s))

    def percent(self, value: float) -> float:
        return float(100.0 * value / self.predicted)


@lru_cache(maxsize=2)
def _equations(name: str):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from pyspiro import BOWERMAN_2022, GLI_2012  # here: its import warns, silenced above

    return BOWERMAN_2022() if name == "gli-global" else GLI_2012()


def reference(parameter: str, sex: str, age_years: float, height_cm: float, equations: str = "gli-global",
              ethnicity: str = "caucasian") -> Reference:
    """The reference of one parameter (FEV1, FVC, FEV1_FVC, FEF2575, FEV075) for one subject."""
    if equations not in EQUATIONS:
        raise ReferenceUnavailable(f"unknown reference equations {equations!r}: {', '.join(EQUATIONS)}")
    if parameter not in PARAMETERS:
        raise ReferenceUnavailable(f"no reference for {parameter!r}: {', '.join(PARAMETERS)}")
    if sex not in ("male", "female"):
        raise ReferenceUnavailable(f"sex must be male or female for the reference equations, got {sex!r}")
    if not 3.0 <= age_years <= 95.0:
        raise ReferenceUnavailable(f"the GLI equations cover ages 3-95 years, got {age_years:g}")
    if not 80.0 <= height_cm <= 250.0:
        raise ReferenceUnavailable(f"height {height_cm:g} cm is outside the equations' range")
    model = _equations(equations)
    enum = type(model).Parameters
    name = PARAMETERS[parameter]
    if not hasattr(enum, name):
        raise ReferenceUnavailable(f"{equations} has no equation for {parameter}")
    code = 1 if sex == "male" else 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if equations == "gli-2012":
            if ethnicity not in GLI_2012_ETHNICITIES:
                raise ReferenceUnavailable(f"GLI-2012 ethnicity must be one of {', '.join(GLI_2012_ETHNICITIES)}")
            l, m, s = model.lms(code, age_years, height_cm, GLI_2012_ETHNICITIES[ethnicity], getattr(enum, name), 1.0)
        else:
            l, m, s = model.lms(code, age_years, height_cm, getattr(enum, name), 1.0)
    l, m, s = float(l), float(m), float(s)
    if not (np.isfinite(m) and m > 0):
        raise ReferenceUnavailable(f"no {equations} reference for {parameter} at age {age_years:g}, {height_cm:g} cm")
    lln = m * (1.0 + Z_LLN * l * s) ** (1.0 / l)
    return Reference(parameter, equations, m, float(lln), l, s)
