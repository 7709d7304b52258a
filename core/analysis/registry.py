"""Every pulmonary function value photopft reports, in one place: its key (as SessionValues.parameters()
and the results' /parameters name it), its labels, unit and decimals, the GLI parameter that predicts it,
and its codes for the exports (LOINC for FHIR, the test identifier for GDT). The report, `analyze`, the
patient session's review, FHIR and GDT iterate over VALUES, in this order, each taking the values its
fields give it; a new value is added here once."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SpirometricValue:
    key: str
    label: str  # short, as `analyze` and the tables print it
    name: str  # spelled out: the report's row and GDT's test name
    unit: str  # "" for a ratio or a count
    decimals: int  # as the report prints it
    table: str | None = None  # the report's table: "main" (with predicted values) or "tidal"
    reference: str | None = None  # the GLI parameter that predicts it (core/analysis/reference.py)
    loinc: tuple[str, str] | None = None  # the measured value's LOINC code and display (FHIR)
    loinc_predicted: str | None = None  # LOINC of its predicted value
    loinc_percent: str | None = None  # LOINC of its percentage of predicted
    gdt_test: str | None = None  # GDT field 8410, the test's identifier

    @property
    def ucum(self) -> str:
        """The unit as UCUM writes it ("1" for a ratio)."""
        return self.unit or "1"


_FVC_LOINC = ("19868-9", "Forced vital capacity [Volume] Respiratory system by Spirometry")
_PEF_LOINC = ("19935-6", "Maximum expiratory gas flow Respiratory system airway by Peak flow meter")

VALUES = (
    SpirometricValue("TV_l", "TV", "Tidal volume", "L", 2, "main", gdt_test="VT"),
    SpirometricValue("RR_bpm", "RR", "Respiratory rate", "/min", 0, "main", gdt_test="AF"),
    SpirometricValue("VE_lpm", "VE", "Minute ventilation", "L/min", 1, "main"),
    SpirometricValue("VC_l", "VC", "VC", "L", 2, "main", gdt_test="VC"),
    SpirometricValue("FVC_l", "FVC", "FVC", "L", 2, "main", "FVC", _FVC_LOINC, "19869-7", "19872-1", "FVC"),
    SpirometricValue("FEV1_l", "FEV1", "FEV1", "L", 2, "main", "FEV1", ("20150-9", "FEV1"), "20149-1", "20152-5",
                     "FEV1"),
    SpirometricValue("FEV1_FVC", "FEV1/FVC", "FEV1/FVC", "", 2, "main", "FEV1_FVC", ("19926-5", "FEV1/FVC"), "19925-7",
                     None, "FEV1FVC"),
    SpirometricValue("PEF_lps", "PEF", "PEF", "L/s", 2, "main", loinc=_PEF_LOINC, gdt_test="PEF"),
    SpirometricValue("FEF2575_lps", "FEF25-75", "FEF25-75", "L/s", 2, "main", "FEF2575", gdt_test="FEF2575"),
    SpirometricValue("Ti_s", "Ti", "Inspiratory time Ti", "s", 2, "tidal"),
    SpirometricValue("Te_s", "Te", "Expiratory time Te", "s", 2, "tidal"),
    SpirometricValue("IE_ratio", "Ti/Te", "Ti/Te", "", 2, "tidal"),
    SpirometricValue("tPTEF_tE", "tPTEF/tE", "tPTEF/tE", "", 2, "tidal"),
    SpirometricValue("IE50", "IE50", "IE50 (insp./exp. flow at half VT)", "", 2, "tidal"),
    SpirometricValue("breaths", "breaths", "Breaths analysed", "", 0, "tidal"),
    SpirometricValue("IC_l", "IC", "IC", "L", 2, "tidal"),
    SpirometricValue("ERV_l", "ERV", "ERV", "L", 2, "tidal"),
    SpirometricValue("IRV_l", "IRV", "IRV", "L", 2, "tidal"),
    SpirometricValue("FEV6_l", "FEV6", "FEV6", "L", 2, "tidal"),
    SpirometricValue("FEV075_l", "FEV0.75", "FEV0.75", "L", 2, "tidal"),
    SpirometricValue("FET_s", "FET", "FET", "s", 2, "tidal"),
)
BY_KEY = {v.key: v for v in VALUES}
