"""Records a hospital can trust (issue 76): exports that cannot be injected, identified files private,
amendments carried, the data folder private from its first use, a busy database waited for and then
refused in one line, and the leftovers of a killed command cleaned by the next one."""

from __future__ import annotations

import json
import sqlite3
import stat
import subprocess
import sys
from datetime import date, datetime, timezone

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


# ------------------------------------------------------------------ plausibility before any value

@pytest.fixture(scope="module")
def breathing(tmp_path_factory):
    """12 s of quiet breathing with the flow sensor (enough breaths for TV and RR)."""
    path = tmp_path_factory.mktemp("breathing") / "tidal.h5"
    simulate(path, SimConfig(protocol="tidal", seconds=12.0, scale=0.05, seed=4))
    return path


def _rewrite_flow(path, adc=None, stamps=None, **attrs):
    import h5py
    import numpy as np

    with h5py.File(path, "r+") as f:
        g = f["flow"]
        for key, value in (("adc", adc), ("timestamp_ns", stamps)):
            if value is not None:
                del g[key]
                g.create_dataset(key, data=np.asarray(value, dtype=np.int32 if key == "adc" else np.int64),
                                 maxshape=(None,), chunks=True)
        for key, value in attrs.items():
            g.attrs[key] = value


def _flow(path):
    from core.io.session import SessionFile

    with SessionFile(path) as s:
        return s.flow_samples()


def _saturated(path):
    adc, _ = _flow(path)
    adc[len(adc) // 2] = 2 ** 31 - 1
    _rewrite_flow(path, adc=adc)


def _negative_gain(path):
    _rewrite_flow(path, flow_gain_lps=-0.0075)


def _gap(path):
    adc, stamps = _flow(path)
    keep = slice(None, len(adc) // 2), slice(len(adc) // 2 + 300, None)  # 300 ms lost inside the breathing
    import numpy as np

    _rewrite_flow(path, adc=np.concatenate([adc[k] for k in keep]), stamps=np.concatenate([stamps[k] for k in keep]))


def _shifted(path):
    adc, stamps = _flow(path)
    _rewrite_flow(path, stamps=stamps + 5_000_000_000)


@pytest.mark.parametrize("damage, validate_says, refusal, code", [
    (_saturated, "outside what a 12-bit converter gives (-2048 to 4095), the first 2147483647",
     "flow sensor values refused", "flow-adc-range"),
    (_negative_gain, "gain is -0.0075 L/s per count: it must be positive", "flow sensor values refused", "flow-gain"),
    (_gap, "301 ms of flow samples missing inside the tidal manoeuvre", "the tidal values not given", None),
    (_shifted, "its clock is not the cameras'", "flow sensor values refused", "flow-clock"),
])
def test_impossible_flow_data_refuses_its_values_not_the_session(breathing, tmp_path, capsys, damage,
                                                                 validate_says, refusal, code):
    from core.io.plausibility import CHECK_FLOW_CLOCK, CHECK_FLOW_SETUP, RECALIBRATE_FLOW

    path = tmp_path / "s.h5"
    path.write_bytes(breathing.read_bytes())
    assert main(["analyze", "--json", str(path)]) == 0
    assert "TV_l" in json.loads(capsys.readouterr().out)["values"]["flow sensor"]
    damage(path)
    assert main(["validate", str(path)]) == 1
    assert validate_says in capsys.readouterr().out
    assert main(["analyze", str(path)]) == 0  # the simulation's truth is still analysed
    out = capsys.readouterr().out
    assert refusal in out
    assert main(["analyze", "--json", str(path)]) == 0
    analysed = json.loads(capsys.readouterr().out)
    assert "TV_l" not in analysed["values"].get("flow sensor", {})
    assert analysed["flow_refused_code"] == code  # the rule, for programs; the words say what to do
    actions = (RECALIBRATE_FLOW, CHECK_FLOW_SETUP, CHECK_FLOW_CLOCK)
    assert code is None or any(analysed["flow_refused"].endswith(action) for action in actions)
    fhir = tmp_path / "s.json"
    assert main(["export", str(path), "--fhir", str(fhir)]) == 0
    kinds = [e["resource"]["resourceType"] for e in json.loads(fhir.read_text())["entry"]]
    assert "Observation" not in kinds  # the only values were the flow sensor's


def test_impossible_intrinsics_are_named_and_process_refuses_in_one_line(small_session, tmp_path, capsys):
    import h5py

    path = tmp_path / "s.h5"
    path.write_bytes(small_session.read_bytes())
    with h5py.File(path, "r+") as f:
        f["rig/back"].attrs["fy"] = 1e-300
    assert main(["validate", str(path)]) == 1
    assert "/rig/back: fy = 1e-300 px gives a field of view of 180 deg" in capsys.readouterr().out
    assert main(["process", str(path), "-o", str(tmp_path / "r.h5")]) == 2
    err = capsys.readouterr().err
    assert "the back head's intrinsics are impossible" in err and "Traceback" not in err
    assert not (tmp_path / "r.h5").exists()


# ------------------------------------------------------------------ signatures bind their data

def test_a_signature_is_void_once_its_data_changed(signed_visit, breathing, tmp_path, capsys):
    records = tmp_path / "records.sqlite3"
    session = tmp_path / "visit.h5"
    session.write_bytes(signed_visit[1].read_bytes())
    with Records(records, user="otto") as r:
        r.add_patient("Muster", "Erika", "female", date(1970, 3, 1), 166.0, 60.0, pseudonym="P-TRUST")
    rec = ["--records", str(records)]
    assert main(["patients"] + rec + ["register", str(session)]) == 0
    assert main(["review", str(session), "--sign", "--user", "dr.keller"] + rec) == 0
    capsys.readouterr()
    assert main(["review", str(session)] + rec) == 0
    assert "signed by dr.keller" in capsys.readouterr().out
    session.write_bytes(breathing.read_bytes())  # another recording copied over the signed one
    assert main(["review", str(session)] + rec) == 0
    out = capsys.readouterr().out
    assert "the signed data has changed since it was signed (by dr.keller," in out
    assert "the session file differs" in out and "signed by dr.keller on" not in out
    fhir = tmp_path / "x.json"
    assert main(["export", str(session), "--fhir", str(fhir)] + rec) == 0
    report = next(e["resource"] for e in json.loads(fhir.read_text())["entry"]
                  if e["resource"]["resourceType"] == "DiagnosticReport")
    assert report["status"] == "preliminary" and "resultsInterpreter" not in report
    assert "Not signed: the signed data has changed since it was signed" in report["conclusion"]
    with Records(records, read_only=True) as r:
        state = r.report_state(r.session_by_path(session).id)
    assert state.signed and not state.signature_valid


# ------------------------------------------------------------------ tampering with the records

def _clinic_users(path) -> None:
    """An engineer (ed), a clinician (anna) and an operator (otto), each with a password NAME-secret."""
    with Records(path, user="ed") as r:
        r.add_user("ed", "engineer", "ed-secret")
        r.authenticate("ed-secret")
        r.add_user("anna", "clinician", "anna-secret")
        r.add_user("otto", "operator", "otto-secret")


@pytest.fixture()
def kept_records(tmp_path):
    """A records database as a clinic leaves it: users, a patient, a session with stored values, a
    signed and amended report; the audit trail and its head beside it."""
    path = tmp_path / "records.sqlite3"
    session = tmp_path / "s.h5"
    session.write_bytes(b"a recording")
    _clinic_users(path)
    with Records(path, user="otto") as r:
        p = r.add_patient("Muster", "Max", "male", date(1966, 5, 1), 175.0, 80.0, pseudonym="P-KEPT")
        sid = r.add_session(p.id, session, datetime(2026, 11, 1, 9, tzinfo=timezone.utc))
        r.set_results(sid, None, {"flow sensor": {"FEV1_l": 3.1, "FVC_l": 4.0}})
    with Records(path, user="anna") as r:
        r.authenticate("anna-secret")
        r.set_comment(sid, "Normal spirometry.")
        r.sign_report(sid)
        r.amend_report(sid, "Reviewed again.")
        assert r.audit_problems() == []
    return path


def _sql(path, *statements):
    db = sqlite3.connect(path)
    for statement in statements:
        db.execute(statement)
    db.commit()
    db.close()


def _rechain(path, first_id):
    """Recompute every hash from `first_id` on, as a forger who knows the scheme would."""
    from app.audit import entry_hash

    db = sqlite3.connect(path)
    db.execute("DROP TRIGGER IF EXISTS audit_log_no_update")
    rows = db.execute("SELECT id, time, user, role, action, target, details, previous_hash FROM audit_log "
                      "ORDER BY id").fetchall()
    previous = next(r[7] for r in rows if r[0] == first_id)
    for r in rows:
        if r[0] < first_id:
            continue
        digest = entry_hash(previous, *r[1:7])
        db.execute("UPDATE audit_log SET previous_hash = ?, hash = ? WHERE id = ?", (previous, digest, r[0]))
        previous = digest
    db.commit()
    db.close()


def _edit_and_rechain(path):
    _sql(path, "DROP TRIGGER audit_log_no_update", "UPDATE audit_log SET user = 'mallory' WHERE id = 4")
    _rechain(path, 4)


def _append_forged_entry(path):
    from app.audit import entry_hash

    db = sqlite3.connect(path)
    last = db.execute("SELECT hash FROM audit_log ORDER BY id DESC LIMIT 1").fetchone()[0]
    digest = entry_hash(last, "2026-12-01T00:00:00+00:00", "mallory", "clinician", "report signed", "x", "{}")
    db.execute("INSERT INTO audit_log (time, user, role, action, target, details, previous_hash, hash) VALUES "
               "('2026-12-01T00:00:00+00:00', 'mallory', 'clinician', 'report signed', 'x', '{}', ?, ?)",
               (last, digest))
    db.commit()
    db.close()


# (what was done, how, what `audit --verify` says)
TAMPERINGS = [
    ("an audit entry edited", lambda p: _sql(p, "DROP TRIGGER audit_log_no_update",
                                             "UPDATE audit_log SET user = 'mallory' WHERE id = 3"),
     "audit entry 3 (user added"),
    ("an audit entry deleted", lambda p: _sql(p, "DROP TRIGGER audit_log_no_delete", "DELETE FROM audit_log WHERE id = 3"),
     "audit entry 4 does not follow"),
    ("the whole audit log deleted", lambda p: _sql(p, "DROP TRIGGER audit_log_no_delete", "DELETE FROM audit_log"),
     "the log was deleted, cut short or rebuilt"),
    ("an entry edited and the chain recomputed", _edit_and_rechain, "the log was deleted, cut short or rebuilt"),
    ("the trail's last entries cut off", lambda p: _sql(p, "DROP TRIGGER audit_log_no_delete",
                                                        "DELETE FROM audit_log WHERE id > 5"),
     "the log was deleted, cut short or rebuilt"),
    ("an entry appended by another program", _append_forged_entry, "1 entry after the anchored head"),
    ("a stored FEV1 edited", lambda p: _sql(p, "UPDATE session_values SET value = 9.9 WHERE name = 'FEV1_l'"),
     "FEV1_l: changed outside photopft"),
    ("a session's stored summary edited", lambda p: _sql(p, "UPDATE sessions SET summary = '{}'"),
     "session /"),
    ("a patient edited", lambda p: _sql(p, "UPDATE patients SET birth_date = '1990-05-01'"),
     "patient P-KEPT: changed outside photopft"),
    ("a signed comment edited", lambda p: _sql(p, "UPDATE reports SET comment = 'Severe obstruction.'"),
     "report /"),
    ("a report unsigned", lambda p: _sql(p, "UPDATE reports SET signed_by = NULL, signed_at = NULL"), "report /"),
    ("an amendment deleted", lambda p: _sql(p, "DELETE FROM report_amendments"), "amendment 1: removed outside"),
    ("a user inserted", lambda p: _sql(p, "INSERT INTO users (name, role, created) VALUES ('mallory', 'clinician', "
                                          "'2026-12-01T00:00:00+00:00')"), "user mallory: added outside photopft"),
    ("a user deactivated", lambda p: _sql(p, "UPDATE users SET active = 0 WHERE name = 'anna'"),
     "user anna: changed outside photopft"),
    ("a user's role changed", lambda p: _sql(p, "UPDATE users SET role = 'engineer' WHERE name = 'otto'"),
     "user otto: changed outside photopft"),
    ("the head file replaced by a forged one", lambda p: p.with_name(p.name + ".audit-head").write_text(
        '{"last_id": 1, "hash": "00", "mac": "00"}'), "its HMAC does not match"),
]


@pytest.mark.parametrize("what, tamper, says", TAMPERINGS, ids=[t[0] for t in TAMPERINGS])
def test_audit_verify_catches_each_tampering(kept_records, capsys, what, tamper, says):
    tamper(kept_records)
    assert main(["audit", "--verify", "--records", str(kept_records)]) == 1
    out = capsys.readouterr().out
    assert says in out, out
    assert "every record matches" not in out


def test_what_the_trail_cannot_see_an_older_copy_restored_whole(kept_records, tmp_path, capsys):
    """Undetectable (docs/trust.md): the database and its head file put back together from an older
    backup agree with each other; only a copy of the head kept elsewhere would show it."""
    head = kept_records.with_name(kept_records.name + ".audit-head")
    older, older_head = tmp_path / "older.sqlite3", head.read_bytes()
    older.write_bytes(kept_records.read_bytes())
    with Records(kept_records, user="anna") as r:
        r.authenticate("anna-secret")
        r.amend_report(1, "A later amendment.")
    kept_records.write_bytes(older.read_bytes())
    head.write_bytes(older_head)
    assert main(["audit", "--verify", "--records", str(kept_records)]) == 0



# ------------------------------------------------------------------ identity is authenticated

def test_a_claimed_name_proves_nothing(kept_records, tmp_path, capsys, typed):
    rec = ["--records", str(kept_records)]
    second = tmp_path / "s2.h5"
    second.write_bytes(b"a second recording")
    with Records(kept_records, user="otto") as r:
        r.authenticate("otto-secret")
        sid = r.add_session(r.patient_by_pseudonym("P-KEPT").id, second, datetime(2026, 11, 2, 9, tzinfo=timezone.utc))
    typed()  # the operator at a script, no password for dr. anna
    assert main(["review", str(second), "--sign", "--user", "anna"] + rec) == 2
    assert "this needs the password of anna" in capsys.readouterr().err
    typed("otto-secret")  # the operator's own password is not the clinician's
    assert main(["review", str(second), "--sign", "--user", "anna"] + rec) == 2
    assert "anna: wrong password; nothing was done (the attempt is in the audit trail)" in capsys.readouterr().err
    typed("otto-secret")
    assert main(["review", str(second), "--sign", "--user", "otto"] + rec) == 2
    assert "report signed: otto is an operator; this needs the role clinician" in capsys.readouterr().err
    typed("anything", "mallory-secret")
    assert main(["users", "--user", "admin"] + rec + ["add", "mallory", "--role", "engineer"]) == 2
    assert "user added: admin is not a registered user" in capsys.readouterr().err
    typed("otto-secret", "mallory-secret")
    assert main(["users", "--user", "ed"] + rec + ["add", "mallory", "--role", "engineer"]) == 2
    assert "ed: wrong password" in capsys.readouterr().err
    with Records(kept_records, read_only=True) as r:
        assert not r.report_state(sid).signed
        assert [u for u, _ in r.users()] == ["anna", "ed", "otto"]
        failed = [e for e in r.audit_trail() if e.action == "authentication failed"]
        assert [(e.user, e.details["reason"]) for e in failed] == [("anna", "wrong password"), ("ed", "wrong password")]
    typed("anna-secret")
    assert main(["review", str(second), "--sign", "--user", "anna"] + rec) == 0
    assert main(["audit", "--verify"] + rec) == 0


def test_passwords_are_kept_as_scrypt_hashes(kept_records):
    db = sqlite3.connect(kept_records)
    stored = dict(db.execute("SELECT name, password_hash FROM users"))
    db.close()
    assert all(h.startswith("scrypt$32768$8$1$") for h in stored.values())
    assert not any(pw.encode() in kept_records.read_bytes() for pw in ("ed-secret", "anna-secret", "otto-secret"))


def test_role_bound_actions_need_the_records_the_site_configures(kept_records, tmp_path, monkeypatch, capsys, typed):
    import app.paths

    site = tmp_path / "site.toml"
    site.write_text(f'[records]\npath = "{kept_records}"\n')
    monkeypatch.setattr(app.paths, "SITE_CONFIG", site)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "empty"))  # an empty data folder moves nothing
    monkeypatch.setenv("PHOTOPFT_USER", "otto")
    csv = tmp_path / "steps.csv"
    csv.write_text("reference_lps,adc_mean\n-4,1500\n0,2048\n2,2315\n6,2848\n")
    out = tmp_path / "flow.json"
    typed("otto-secret")
    assert main(["calibrate", "flow", str(csv), "-o", str(out)]) == 2
    assert "calibration saved: otto is an operator" in capsys.readouterr().err and not out.exists()
    mine = tmp_path / "mine.sqlite3"  # records of one's own, where nobody is registered
    with Records(mine, user="mallory") as r:
        p = r.add_patient("Doe", "", "female", date(1980, 1, 1), 165.0, 60.0)
        r.add_session(p.id, tmp_path / "s.h5", datetime(2026, 11, 3, 9, tzinfo=timezone.utc))
    assert main(["review", str(tmp_path / "s.h5"), "--sign", "--user", "mallory", "--records", str(mine)]) == 2
    assert f"is not the records database {site} configures" in capsys.readouterr().err
    site.write_text(f'[records]\npath = "{tmp_path / "gone.sqlite3"}"\n')
    monkeypatch.setenv("PHOTOPFT_USER", "ed")
    assert main(["calibrate", "flow", str(csv), "-o", str(out)]) == 2
    assert "no records database at" in capsys.readouterr().err and not out.exists()


def test_the_identified_report_is_a_clinicians_and_every_report_is_audited(breathing, tmp_path, capsys, typed):
    from pypdf import PdfReader

    records = tmp_path / "records.sqlite3"
    session = tmp_path / "visit.h5"
    session.write_bytes(breathing.read_bytes())
    _clinic_users(records)
    with Records(records, user="otto") as r:
        r.authenticate("otto-secret")
        from core.io.session import SessionFile

        with SessionFile(session) as s:
            pseudonym = s.subject.id
        p = r.add_patient("Musterfrau", "Erika", "female", date(1980, 1, 1), 166.0, 60.0, patient_number="H-42",
                          pseudonym=pseudonym)
        r.add_session(p.id, session, datetime(2026, 12, 4, 9, tzinfo=timezone.utc))
    rec = ["--records", str(records)]
    by_operator, by_clinician = tmp_path / "operator.pdf", tmp_path / "clinician.pdf"
    assert main(["report", str(session), "-o", str(by_operator), "--user", "otto"] + rec) == 0
    assert "; pseudonymous" in capsys.readouterr().out
    text = " ".join(page.extract_text() for page in PdfReader(by_operator).pages)
    assert "Musterfrau" not in text and "H-42" not in text and pseudonym in text
    typed("anna-secret")
    assert main(["report", str(session), "-o", str(by_clinician), "--user", "anna"] + rec) == 0
    text = " ".join(page.extract_text() for page in PdfReader(by_clinician).pages)
    assert "Musterfrau" in text and "H-42" in text
    assert stat.S_IMODE(by_clinician.stat().st_mode) == 0o600
    with Records(records, read_only=True) as r:
        exports = [(e.user, e.details["identified"]) for e in r.audit_trail() if e.action == "report written"]
    assert exports == [("otto", False), ("anna", True)]


def test_frames_missing_inside_a_manoeuvre_refuse_its_optical_values(breathing, tmp_path, capsys):
    import h5py
    import numpy as np

    from core.analysis.session_analysis import analyse_session
    from core.io.session import SessionFile

    path = tmp_path / "s.h5"
    path.write_bytes(breathing.read_bytes())
    with SessionFile(path) as s:
        truth = s.truth()
        curve = (np.asarray(truth["timestamp_ns"]), np.asarray(truth["volume_l"]))  # an optical curve that holds
    assert analyse_session(path, optical_volume=curve).optical.tidal is not None
    with h5py.File(path, "r+") as f:
        g = f["heads/front"]
        n = g["frames"].shape[0]
        keep = np.r_[0:n // 4, n // 4 + 40:n // 2, n // 2 + 33:n]  # 364 ms, then 300 ms of the front camera's lost
        for key in ("frames", "light_index", "timestamp_ns", "frame_id"):
            data = g[key][:][keep]
            del g[key]
            g.create_dataset(key, data=data, maxshape=(None,) + data.shape[1:], chunks=(1,) + data.shape[1:]
                             if key == "frames" else True)
    assert main(["validate", str(path)]) == 1
    out = capsys.readouterr().out
    assert "of the front head's frames missing inside the tidal manoeuvre" in out and "the longest of 2 gaps" in out
    analysed = analyse_session(path, optical_volume=curve)
    assert analysed.optical.tidal is None and analysed.flow_sensor.tidal is not None
    assert [p for p in analysed.optical.problems if "the tidal values not given" in p] == [
        "the tidal values not given: 373 ms of the front head's frames missing inside the tidal manoeuvre at 0.0 s "
        "(the longest of 2 gaps; at most 250 ms)"]  # one line a manoeuvre, not one a gap


def test_a_password_for_nobody_is_refused_before_any_is_asked(kept_records, capsys, typed):
    typed("ed-secret", "new-secret")
    assert main(["users", "--user", "ed", "--records", str(kept_records), "password", "nobody"]) == 2
    assert "no active user nobody: nothing was changed" in capsys.readouterr().err
    typed("ed-secret", "anna-new-secret")
    assert main(["users", "--user", "ed", "--records", str(kept_records), "password", "anna"]) == 0
    with Records(kept_records, user="anna") as r:
        r.authenticate("anna-new-secret")
