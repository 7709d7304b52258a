"""Records a hospital can trust (issue 76): exports that cannot be injected, identified files private,
amendments carried, the data folder private from its first use, a busy database waited for and then
refused in one line, and the leftovers of a killed command cleaned by the next one."""

from __future__ import annotations

import json
import sqlite3
import stat
import subprocess
import sys
from datetime import date

import pytest

from app.cli import main
from app.records import Records
from core.sim.breathing import Subject
from core.sim.simulate import SimConfig, simulate


@pytest.fixture(scope="module")
def signed_visit(tmp_path_factory):
    """(records, session): one patient's forced blows on record, commented, signed and amended."""
    folder = tmp_path_factory.mktemp("visit")
    records = folder / "records.sqlite3"
    with Records(records, user="otto") as r:
        r.add_patient("Muster", "Erika", "female", date(1970, 3, 1), 166.0, 60.0, patient_number="H-77",
                      pseudonym="P-TRUST")
    subject = Subject(id="P-TRUST", sex="female", age_years=56.0, height_cm=166.0, weight_kg=60.0)
    session = folder / "visit.h5"
    simulate(session, SimConfig(protocol="forced", scale=0.05, seed=5, subject=subject,
                                created="2026-11-20T09:00:00+00:00"))
    assert main(["patients", "--records", str(records), "register", str(session)]) == 0
    with Records(records, user="otto") as r:
        sid = r.session_by_path(session).id
        r.set_comment(sid, "Normal.\r\n3101Mallory\r\n" + "long text " * 150)
        r.sign_report(sid)
        r.amend_report(sid, "Repeat after the\r\ninfection.")
    return records, session


def test_gdt_fields_cannot_add_lines_and_stay_three_digits_long(signed_visit, tmp_path, capsys):
    from app.gdt_export import read_gdt

    records, session = signed_visit
    rec = ["--records", str(records)]
    out = tmp_path / "x.gdt"
    assert main(["export", str(session), "--gdt", str(out), "--receiver", "PRAXIS\r\n3101Mallory"] + rec) == 2
    assert "--receiver" in capsys.readouterr().err and not out.exists()
    assert main(["export", str(session), "--gdt", str(out)] + rec) == 0
    raw = out.read_bytes()
    lines = raw.split(b"\r\n")[:-1]
    assert all(len(line) + 2 <= 999 and len(line) + 2 == int(line[:3]) for line in lines)
    fields = read_gdt(out)
    assert [content for field, content in fields if field == "3101"] == ["Muster"]  # no injected name
    findings = "".join(content for field, content in fields if field == "6227")  # a long text continues
    assert "Normal.  3101Mallory" in findings and findings.count("long text") == 150
    assert "Amended by otto" in findings and "Repeat after the  infection." in findings
    assert max(len(line) + 2 for line in lines) == 999  # the long comment filled whole lines
    assert int(dict(fields)["8100"]) == len(raw)
    assert stat.S_IMODE(out.stat().st_mode) == 0o600  # names the patient


def test_fhir_sends_an_amended_report_as_amended_and_identified_files_private(signed_visit, tmp_path):
    records, session = signed_visit
    rec = ["--records", str(records)]
    pseudonymous, identified = tmp_path / "p.json", tmp_path / "i.json"
    assert main(["export", str(session), "--fhir", str(pseudonymous)] + rec) == 0
    assert main(["export", str(session), "--fhir", str(identified), "--identified"] + rec) == 0
    bundle = json.loads(identified.read_text())
    report = next(e["resource"] for e in bundle["entry"] if e["resource"]["resourceType"] == "DiagnosticReport")
    assert report["status"] == "amended"
    assert "Amended by otto" in report["conclusion"] and "Repeat after the\r\ninfection." in report["conclusion"]
    assert stat.S_IMODE(identified.stat().st_mode) == 0o600
    assert "Muster" not in pseudonymous.read_text()


def test_the_data_folder_is_made_private_on_first_use(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "first-run"))
    assert main(["patients", "add", "--family-name", "Doe", "--sex", "female", "--birth-date", "1980-01-01",
                 "--height", "165", "--weight", "60"]) == 0
    folder = tmp_path / "first-run" / "photopft"
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert stat.S_IMODE((folder / "records.sqlite3").stat().st_mode) == 0o600


def test_a_busy_database_is_waited_for_then_refused_in_one_line(tmp_path, monkeypatch, capsys):
    import app.records

    path = tmp_path / "records.sqlite3"
    add = ["patients", "--records", str(path), "add", "--family-name", "Doe", "--sex", "female", "--birth-date",
           "1980-01-01", "--height", "165", "--weight", "60"]
    assert main(add) == 0
    monkeypatch.setattr(app.records, "BUSY_WAIT_S", 1.5)
    monkeypatch.setattr(app.records, "BUSY_SAY_AFTER_S", 0.4)
    other = sqlite3.connect(path, isolation_level=None)
    other.execute("BEGIN IMMEDIATE")  # another program holds the write lock
    try:
        capsys.readouterr()
        assert main(add) == 2
        err = capsys.readouterr().err
    finally:
        other.execute("ROLLBACK")
        other.close()
    assert "waiting for another photopft writing to the records" in err
    assert "the records database is busy" in err and "Traceback" not in err
    assert main(add) == 0


def test_the_leftovers_of_a_killed_command_are_removed_by_the_next(small_session, tmp_path, capsys):
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    leftover = tmp_path / f".report.{dead.pid}.partial.pdf"
    leftover.write_bytes(b"%PDF-1.4 cut off")
    live = tmp_path / ".other.1.partial.pdf"  # pid 1 is alive: its writer may still be at work
    live.write_bytes(b"%PDF-1.4 being written")
    assert main(["report", str(small_session), "-o", str(tmp_path / "report.pdf")]) == 0
    assert not leftover.exists() and live.exists() and (tmp_path / "report.pdf").exists()


def test_a_byte_flipped_in_a_frame_is_found_by_validate(tmp_path, capsys):
    import h5py

    path = tmp_path / "s.h5"
    simulate(path, SimConfig(protocol="tidal", seconds=0.3, scale=0.05, seed=2))
    assert main(["validate", str(path)]) == 0
    with h5py.File(path) as f:
        info = f["heads/back/frames"].id.get_chunk_info(5)
    raw = bytearray(path.read_bytes())
    raw[info.byte_offset + info.size // 2] ^= 0x01
    path.write_bytes(bytes(raw))
    capsys.readouterr()
    assert main(["validate", str(path)]) == 1
    assert "/heads/back/frames: frame 5 fails its checksum" in capsys.readouterr().out
