"""What the clinician gets, end to end on the command line: a pre- and a post-bronchodilator session of
one patient on record, the review signed, and the report read back: interpretation, response, review, trend."""

from __future__ import annotations

import json
from datetime import date

import pytest
from pypdf import PdfReader

from app.cli import main
from app.records import Records
from core.sim.breathing import Subject
from core.sim.simulate import SimConfig, simulate


def _text(pdf) -> str:
    pages = [page.extract_text(extraction_mode="layout") for page in PdfReader(pdf).pages]
    return "\n".join(" ".join(line.split()) for page in pages for line in page.splitlines() if line.strip())


@pytest.fixture(scope="module")
def visits(tmp_path_factory):
    """(records, pre, post): an obstructed patient (FEV1/FVC 0.5) whose FEV1 rises 0.6 L after the bronchodilator."""
    folder = tmp_path_factory.mktemp("visits")
    records = folder / "records.sqlite3"
    with Records(records, user="otto") as r:
        r.add_patient("Muster", "Max", "male", date(1966, 5, 1), 175.0, 80.0, pseudonym="P-OBST")
    sessions = {}
    for name, fev1, hour in (("pre", 2.0, 9), ("post", 2.6, 10)):
        subject = Subject(id="P-OBST", sex="male", age_years=60.5, height_cm=175.0, weight_kg=80.0, fvc_l=4.0,
                          fev1_l=fev1)
        sessions[name] = folder / f"{name}.h5"
        simulate(sessions[name], SimConfig(protocol="forced", scale=0.05, seed=3, subject=subject,
                                           created=f"2026-11-02T{hour:02d}:00:00+00:00"))
        assert main(["patients", "--records", str(records), "register", str(sessions[name]), "--operator",
                     "otto"]) == 0
    assert main(["review", str(sessions["post"]), "--post-bronchodilator-of", str(sessions["pre"]), "--records",
                 str(records)]) == 0
    return records, sessions["pre"], sessions["post"]


def test_review_sign_and_report(visits, tmp_path, capsys, monkeypatch, typed):
    records, pre, post = visits
    monkeypatch.setenv("PHOTOPFT_USER", "dr-lee")
    rec = ["--records", str(records)]
    typed("ed-secret")  # the first user's own password
    assert main(["users", "--user", "ed"] + rec + ["add", "ed", "--role", "engineer"]) == 0
    typed("ed-secret", "lee-secret")  # the engineer's password, then the new user's
    assert main(["users", "--user", "ed"] + rec + ["add", "dr-lee", "--role", "clinician"]) == 0
    typed("lee-secret")
    assert main(["review", str(post), "--comment", "Reversible obstruction; asthma likely."] + rec) == 0
    assert main(["review", str(post), "--sign", "--user", "otto"] + rec) == 2
    assert "report signed: otto is not a registered user; this needs the role clinician" in capsys.readouterr().err
    typed("otto-guessed")
    assert main(["review", str(post), "--sign"] + rec) == 2
    assert "dr-lee: wrong password; nothing was done" in capsys.readouterr().err
    typed("lee-secret")
    assert main(["review", str(post), "--sign"] + rec) == 0
    typed("lee-secret")
    assert main(["review", str(post), "--comment", "changed"] + rec) == 2
    assert "read-only; add an amendment" in capsys.readouterr().err
    typed("lee-secret")
    assert main(["review", str(post), "--amend", "Repeat in 3 months."] + rec) == 0
    pdf = tmp_path / "post.pdf"
    assert main(["report", str(post), "-o", str(pdf)] + rec) == 0
    text = _text(pdf).replace("\n", " ")
    assert "Interpretation (ERS/ATS 2022, z-scores)" in text
    assert "FEV1/FVC below the lower limit of normal" in text and ": obstruction" in text
    assert "Operator otto" in text
    assert "After bronchodilator: FEV1 +" in text and "significant bronchodilator response (FEV1" in text
    assert "Signed by dr-lee on" in text and "Reversible obstruction; asthma likely." in text
    assert "Amendment by dr-lee" in text and "Repeat in 3 months." in text
    assert "Trend over the patient's visits" in text and "2026-11-02" in text
    assert "Every blow (flow sensor)" in text
    assert main(["audit", "--verify"] + rec) == 0
    out = capsys.readouterr().out
    for action in ("patient registered", "session recorded", "values stored", "user added", "sessions linked",
                   "comment edited", "report signed", "report amended", "authentication failed"):
        assert action in out, action
    assert "the hash chain is whole" in out


def test_fhir_gdt_and_json_exports(visits, tmp_path, capsys, monkeypatch, typed):
    from fhir.resources.R4B.bundle import Bundle
    from fhir.resources.R4B.diagnosticreport import DiagnosticReport
    from fhir.resources.R4B.observation import Observation
    from fhir.resources.R4B.patient import Patient

    from app.gdt_export import read_gdt

    records, pre, post = visits
    monkeypatch.setenv("PHOTOPFT_USER", "dr-lee")  # a clinician where the review test added users first
    rec = ["--records", str(records)]
    out = tmp_path / "pre.json"
    assert main(["export", str(pre), "--fhir", str(out)] + rec) == 0
    bundle = json.loads(out.read_text())
    Bundle.model_validate(bundle)
    kinds = {"Patient": Patient, "DiagnosticReport": DiagnosticReport, "Observation": Observation}
    for entry in bundle["entry"]:
        kinds[entry["resource"]["resourceType"]].model_validate(entry["resource"])
        # the models check structure and types, not required value sets: the statuses by hand
        assert entry["resource"].get("status", "final") in ("registered", "preliminary", "final", "amended")
    resources = [e["resource"] for e in bundle["entry"]]
    patient = next(r for r in resources if r["resourceType"] == "Patient")
    assert "name" not in patient and "birthDate" not in patient  # pseudonymous unless asked
    assert patient["identifier"][0]["value"] == "P-OBST"
    observations = {c["code"]: r for r in resources if r["resourceType"] == "Observation"
                    for c in r["code"]["coding"]}
    assert {"20150-9", "19868-9", "19926-5", "19935-6", "20157-4"} <= set(observations)  # 20157-4: FEV1 pre-BD
    fev1 = observations["20150-9"]
    assert fev1["valueQuantity"]["code"] == "L" and fev1["valueQuantity"]["system"] == "http://unitsofmeasure.org"
    assert {c["code"]["coding"][0]["code"] for c in fev1["component"]} == {"20149-1", "20152-5", "1078210003"}
    assert fev1["interpretation"][0]["coding"][0]["code"] == "L"  # the pre FEV1 (2.0 L) is below the LLN
    capsys.readouterr()
    assert main(["analyze", "--json", str(pre)]) == 0
    analysis = json.loads(capsys.readouterr().out)
    assert fev1["valueQuantity"]["value"] == pytest.approx(analysis["values"]["flow sensor"]["FEV1_l"], abs=1e-4)
    assert analysis["interpretation"]["pattern"] == "obstruction"
    report = next(r for r in resources if r["resourceType"] == "DiagnosticReport")
    assert report["code"]["coding"][0]["code"] == "18759-1" and report["status"] == "preliminary"
    assert len(report["result"]) == len(observations) - 1  # FEV1 carries two codings
    identified = tmp_path / "identified.json"
    typed("lee-secret")  # identified data: the clinician's password, where users are registered
    assert main(["export", str(pre), "--fhir", str(identified), "--identified"] + rec) == 0
    person = json.loads(identified.read_text())["entry"][0]["resource"]
    assert person["name"][0]["family"] == "Muster" and person["birthDate"] == "1966-05-01"

    gdt = tmp_path / "post.gdt"
    typed("lee-secret")
    assert main(["export", str(post), "--gdt", str(gdt)] + rec) == 0
    fields = read_gdt(gdt)
    assert fields[0] == ("8000", "6310") and ("9218", "03.00") in fields
    assert int(dict(fields)["8100"]) == gdt.stat().st_size
    assert ("3101", "Muster") in fields and ("3103", "01051966") in fields
    tests = [content for field, content in fields if field == "8410"]
    assert tests[:3] == ["FVC", "FEV1", "FEV1FVC"]
    values = dict(zip(tests, [content for field, content in fields if field == "8420"]))
    assert float(values["FEV1"]) == pytest.approx(2.6, abs=0.1)
    assert any(field == "6220" and "bronchodilator" in content for field, content in fields)

    capsys.readouterr()
    assert main(["info", "--json", str(post)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["subject"]["id"] == "P-OBST" and summary["flow_sensor"]["sample_rate_hz"] == 1000.0
    assert main(["audit"] + rec) == 0
    assert capsys.readouterr().out.count("  export  ") == 3
