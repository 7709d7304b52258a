"""Exports: the research copy keeps the data and loses the links back to the clinic; the CSV
files hold the same curves and values as the report."""

from __future__ import annotations

import csv

import h5py
import numpy as np
import pytest

from app.cli import main
from app.export import study_pseudonym
from core.io.session import SessionFile, validate_session


def test_research_copy(small_session, tmp_path, capsys):
    key = tmp_path / "study.key"
    key.write_bytes(b"a study secret of enough length")
    copy = tmp_path / "research.h5"
    with h5py.File(small_session, "r") as f:
        clinic_id = str(f["subject"].attrs["id"])
    assert main(["export", str(small_session), "--research", str(copy), "--study-key-file", str(key),
                 "--study", "TRIAL-1"]) == 0
    assert validate_session(copy) == []
    with SessionFile(small_session) as original, SessionFile(copy) as research:
        assert research.subject.id == study_pseudonym(clinic_id, key.read_bytes().strip()) != clinic_id
        assert research.subject.age_years == round(original.subject.age_years)
        assert research.created.endswith("T00:00:00+00:00") and research.created[:10] == original.created[:10]
        assert research.attrs["study"] == "TRIAL-1"
        for head in original.heads:
            np.testing.assert_array_equal(research.frames(head)[-1], original.frames(head)[-1])
            np.testing.assert_array_equal(research.frame_id(head), original.frame_id(head))
        np.testing.assert_array_equal(research.flow_samples()[0], original.flow_samples()[0])
    # the same patient gets the same study id from every session, and a short key is refused
    assert study_pseudonym(clinic_id, b"a study secret of enough length") == research.subject.id
    key.write_bytes(b"short")
    assert main(["export", str(small_session), "--research", str(tmp_path / "x.h5"), "--study-key-file",
                 str(key)]) == 2
    assert "at least 16 bytes" in capsys.readouterr().err
    assert not (tmp_path / "x.h5").exists()


def test_csv_of_curves_and_values(processed_full_session, tmp_path):
    session, results = processed_full_session
    assert main(["export", str(results), "--csv", str(tmp_path / "out")]) == 0
    with open(tmp_path / "out" / "volume.csv", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["time_s", "optical_volume_l", "flow_sensor_volume_l"]
    t = np.array([float(r[0]) for r in rows[1:]])
    assert np.allclose(np.diff(t), 0.01, atol=1e-3) and t[-1] > 50
    with open(tmp_path / "out" / "values.csv", encoding="utf-8") as f:
        values = {(r["parameter"], r["source"]): r for r in csv.DictReader(f)}
    with h5py.File(results, "r") as r:
        p = r["parameters"].attrs
        assert float(values[("FEV1_l", "flow sensor")]["value"]) == pytest.approx(float(p["FEV1_l"]), rel=1e-5)
        assert float(values[("TV_l", "flow sensor")]["value"]) == pytest.approx(float(p["TV_l"]), rel=1e-5)
        assert values[("grade", "flow sensor")]["value"] == p["grade"]
    fev1 = values[("FEV1_l", "flow sensor")]
    assert float(fev1["predicted"]) == pytest.approx(4.065, abs=0.002)  # GLI Global, male, 30 y, 175 cm
    assert fev1["equations"] == "gli-global"


def test_patients_on_the_command_line(small_session, tmp_path, capsys):
    db = tmp_path / "r.sqlite3"
    assert main(["patients", "--records", str(db), "add", "--family-name", "Ødegård", "--given-name", "Åse",
                 "--sex", "female", "--birth-date", "1961-02-03", "--height", "165", "--weight", "60",
                 "--pseudonym", "SIM-0001"]) == 0
    assert capsys.readouterr().out.strip() == "SIM-0001"
    assert main(["patients", "--records", str(db), "register", str(small_session)]) == 0
    capsys.readouterr()
    assert main(["patients", "--records", str(db), "history", "SIM-0001"]) == 0
    out = capsys.readouterr().out
    assert "Ødegård, Åse" in out and "analysed" in out and str(small_session.name) in out
    assert main(["patients", "--records", str(db), "add", "--family-name", "X", "--sex", "female",
                 "--birth-date", "1961-02-30", "--height", "165", "--weight", "60"]) == 2
    assert "birth date" in capsys.readouterr().err
    assert main(["patients", "--records", str(db), "add", "--family-name", "X", "--sex", "female",
                 "--birth-date", "1961-02-03", "--height", "16.5", "--weight", "60"]) == 2
    assert "height" in capsys.readouterr().err
