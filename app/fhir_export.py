"""A session's results as a FHIR R4 Bundle: Patient, DiagnosticReport and one Observation per value.

Codes: LOINC for the spirometry study and each value, its predicted value and its percentage of
predicted (as the German Medical Informatics Initiative's lung-function module uses them); the
z-score component carries SNOMED CT's "Z-score calculation technique", as that module does, since
LOINC has no z-score codes for spirometry. FEV1 carries the LOINC pre/post-bronchodilator code
where the session is one of a bronchodilator pair. Units are UCUM. The patient is pseudonymous
(the session's pseudonym only) unless the export is asked to identify them.
"""

from __future__ import annotations

import json
import os
import uuid
from datetime import datetime, timezone
from pathlib import Path

from app.report_data import ReportData
from core.analysis.interpretation import NORMAL, NOT_INTERPRETED
from core.io.outputs import atomic_output
from core.analysis.reference import Z_LLN
from core.analysis import registry

LOINC = "http://loinc.org"
SNOMED = "http://snomed.info/sct"
UCUM = "http://unitsofmeasure.org"
PSEUDONYM_SYSTEM = "urn:photopft:pseudonym"
PATIENT_NUMBER_SYSTEM = "urn:photopft:patient-number"
SPIROMETRY_STUDY = ("18759-1", "Spirometry study")
Z_SCORE = ("1078210003", "Z-score calculation technique")

BRONCHODILATOR_FEV1 = {"pre": ("20157-4", "FEV1 --pre bronchodilation"),
                       "post": ("20155-8", "FEV1 --post bronchodilation")}


def _coding(system: str, code: str, display: str) -> dict:
    return {"system": system, "code": code, "display": display}


def _quantity(value: float, unit: str) -> dict:
    return {"value": round(float(value), 4), "unit": {"1": "ratio"}.get(unit, unit), "system": UCUM, "code": unit}


def _urn() -> str:
    return f"urn:uuid:{uuid.uuid4()}"


def _effective(data: ReportData) -> str:
    try:
        moment = datetime.fromisoformat(data.recorded)
    except ValueError:
        return datetime.now(timezone.utc).isoformat(timespec="seconds")
    return (moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)).isoformat(timespec="seconds")


def _patient(data: ReportData, identified: bool) -> dict:
    subject = data.subject or {}
    resource: dict = {"resourceType": "Patient",
                      "identifier": [{"system": PSEUDONYM_SYSTEM, "value": str(subject.get("id", "unknown"))}]}
    if subject.get("sex") in ("male", "female"):
        resource["gender"] = subject["sex"]
    patient = data.patient
    if identified:
        if patient is None:
            raise ValueError("--identified needs the patient on record in the records database (--records)")
        resource["name"] = [{"family": patient.family_name, **({"given": [patient.given_name]}
                                                                 if patient.given_name else {})}]
        resource["birthDate"] = patient.birth_date.isoformat()
        if patient.patient_number:
            resource["identifier"].append({"system": PATIENT_NUMBER_SYSTEM, "value": patient.patient_number})
    return resource


def _bronchodilator_state(data: ReportData) -> str | None:
    if data.bronchodilator is not None:
        return "post"
    return "pre" if data.post_bronchodilator_session is not None else None


def _observations(data: ReportData, status: str, patient_ref: str, effective: str,
                  bronchodilator: str | None) -> list[dict]:
    values = data.parameters(data.main_source) if data.main_source else {}
    references = {row.reference.parameter: row.reference for row in data.rows if row.reference is not None}
    method = {"text": "flow sensor (pneumotachometer)" if data.main_source == "flow sensor" else
              "optical (near-light photometric stereo, photopft): "
              + (data.optical_label or "made before its kind was recorded")}
    out = []
    for coded in (v for v in registry.VALUES if v.loinc is not None):
        key, ref_name, (code, display) = coded.key, coded.reference, coded.loinc
        predicted_code, percent_code, unit = coded.loinc_predicted, coded.loinc_percent, coded.ucum
        if key not in values:
            continue
        value = float(values[key])
        codings = [_coding(LOINC, code, display)]
        if key == "FEV1_l" and bronchodilator is not None:
            codings.append(_coding(LOINC, *BRONCHODILATOR_FEV1[bronchodilator]))
        obs: dict = {"resourceType": "Observation", "status": status,
                     "category": [{"coding": [_coding("http://terminology.hl7.org/CodeSystem/observation-category",
                                                      "procedure", "Procedure")]}],
                     "code": {"coding": codings, "text": display}, "subject": {"reference": patient_ref},
                     "effectiveDateTime": effective, "valueQuantity": _quantity(value, unit), "method": method}
        ref = references.get(ref_name) if ref_name else None
        if ref is not None:
            z = ref.zscore(value)
            obs["interpretation"] = [{"coding": [_coding(
                "http://terminology.hl7.org/CodeSystem/v3-ObservationInterpretation", *(("L", "Low") if z < Z_LLN
                                                                                        else ("N", "Normal")))]}]
            obs["referenceRange"] = [{"low": _quantity(ref.lln, unit),
                                      "text": f"lower limit of normal (z = -1.645), {ref.equations}"}]
            components = [{"code": {"coding": [_coding(LOINC, predicted_code, f"{display} Predicted")],
                                    "text": f"{display} predicted"}, "valueQuantity": _quantity(ref.predicted, unit)}]
            if percent_code:
                components.append({"code": {"coding": [_coding(LOINC, percent_code, f"{display} measured/predicted")],
                                            "text": f"{display} % predicted"},
                                   "valueQuantity": _quantity(ref.percent(value), "%")})
            components.append({"code": {"coding": [_coding(SNOMED, *Z_SCORE)], "text": f"{display} z-score"},
                               "valueQuantity": {"value": round(z, 3), "system": UCUM, "code": "1",
                                                 "unit": "z-score"}})
            obs["component"] = components
        out.append(obs)
    return out


def fhir_bundle(data: ReportData, identified: bool = False) -> dict:
    """The Bundle (type collection) of one session's report."""
    signed = data.review is not None and data.review.signature_valid  # data changed since: preliminary
    amended = signed and bool(data.review.amendments)
    status = "amended" if amended else "final" if signed else "preliminary"
    effective = _effective(data)
    patient_url = _urn()
    # an amendment adds to the report's text; the measured values stay final
    observations = [(_urn(), obs) for obs in _observations(data, "final" if amended else status, patient_url, effective,
                                                           _bronchodilator_state(data))]
    conclusion = []
    if data.interpretation is not None and data.interpretation.pattern != NOT_INTERPRETED:
        conclusion.append(data.interpretation.summary + ". " + " ".join(data.interpretation.statements))
    if data.bronchodilator is not None:
        conclusion.append(data.bronchodilator.statement)
    if data.review is not None and data.review.comment:
        conclusion.append(f"Clinician's comment: {data.review.comment}")
    if data.review is not None and data.review.signature_broken:
        conclusion.append(f"Not signed: {data.review.signature_broken}.")
    if amended:
        conclusion += [f"Amended by {a.user} on {a.time:%Y-%m-%d %H:%M} UTC: {a.text}" for a in data.review.amendments]
    report: dict = {"resourceType": "DiagnosticReport", "status": status,
                    "code": {"coding": [_coding(LOINC, *SPIROMETRY_STUDY)], "text": SPIROMETRY_STUDY[1]},
                    "subject": {"reference": patient_url}, "effectiveDateTime": effective,
                    "issued": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "result": [{"reference": url} for url, _ in observations]}
    if conclusion:
        report["conclusion"] = " ".join(conclusion)
    if data.interpretation is not None and data.interpretation.pattern not in (NOT_INTERPRETED,):
        report["conclusionCode"] = [{"text": data.interpretation.summary if data.interpretation.pattern != NORMAL
                                     else "Normal spirometry"}]
    if signed:
        report["resultsInterpreter"] = [{"display": data.review.signed_by}]
    if data.operator:
        report["performer"] = [{"display": data.operator}]
    entries = [{"fullUrl": patient_url, "resource": _patient(data, identified)}, {"fullUrl": _urn(), "resource": report}]
    entries += [{"fullUrl": url, "resource": obs} for url, obs in observations]
    return {"resourceType": "Bundle", "type": "collection",
            "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"), "entry": entries}


def write_fhir(data: ReportData, output: str | os.PathLike, identified: bool = False) -> Path:
    """An identified bundle is readable by its owner only."""
    bundle = fhir_bundle(data, identified)
    output = Path(output)
    with atomic_output(output, private=identified) as partial:
        Path(partial).write_text(json.dumps(bundle, indent=2, ensure_ascii=False), encoding="utf-8")
    return output
