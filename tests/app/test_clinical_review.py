"""What the clinician gets, end to end on the command line: a pre- and a post-bronchodilator session of
one patient on record, the review signed, and the report read back: interpretation, response, review, trend."""

from __future__ import annotations

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
    return records, sessions["pre"], sessions["post"]


def test_review_sign_and_report(visits, tmp_path, capsys, monkeypatch):
    records, pre, post = visits
    monkeypatch.setenv("PHOTOPFT_USER", "dr-lee")
    rec = ["--records", str(records)]
    assert main(["users", "add", "ed", "--role", "engineer", "--user", "ed"] + rec) == 0
    assert main(["users", "add", "dr-lee", "--role", "clinician", "--user", "ed"] + rec) == 0
    assert main(["review", str(post), "--post-bronchodilator-of", str(pre), "--comment",
                 "Reversible obstruction; asthma likely."] + rec) == 0
    assert main(["review", str(post), "--sign", "--user", "otto"] + rec) == 2
    assert "report signed: otto is not a registered user; this needs the role clinician" in capsys.readouterr().err
    assert main(["review", str(post), "--sign"] + rec) == 0
    assert main(["review", str(post), "--comment", "changed"] + rec) == 2
    assert "read-only; add an amendment" in capsys.readouterr().err
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
                   "comment edited", "report signed", "report amended"):
        assert action in out, action
    assert "the hash chain is whole" in out
