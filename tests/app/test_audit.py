"""The audit trail (append-only, hash-chained), roles, report sign-off and bronchodilator pairs, on a real SQLite file."""

import sqlite3
from datetime import date, datetime, timedelta, timezone

import pytest

from app.records import Records, RecordsError


def tamper(path, *statements: str) -> None:
    """What another program could do to the file: SQL past photopft (triggers dropped first)."""
    db = sqlite3.connect(path)
    for statement in statements:
        db.execute(statement)
    db.commit()
    db.close()


def _patient(records):
    return records.add_patient("Muster", "Erika", "female", date(1970, 5, 1), 165.0, 60.0)


def _session(records, patient, tmp_path, name, hours=0):
    (tmp_path / name).write_bytes(f"the recording {name}".encode())  # what a signature binds
    return records.add_session(patient.id, tmp_path / name, datetime(2026, 11, 1, 9, tzinfo=timezone.utc)
                               + timedelta(hours=hours))


def test_every_action_is_logged_and_the_chain_verifies(tmp_path):
    with Records(tmp_path / "r.sqlite3", user="erika") as records:
        p = _patient(records)
        sid = _session(records, p, tmp_path, "s.h5")
        records.set_results(sid, None, {"flow sensor": {"FEV1_l": 2.5}})
        records.set_comment(sid, "good effort")
        records.sign_report(sid)
        records.amend_report(sid, "FVC repeat advised")
        records.log("export", str(tmp_path / "s.h5"), {"fhir": "out.json"})
        actions = [e.action for e in records.audit_trail()]
        assert actions == ["patient registered", "session recorded", "values stored", "comment edited",
                           "report signed", "report amended", "export"]
        assert {e.user for e in records.audit_trail()} == {"erika"}
        assert records.audit_trail()[0].role == "unregistered"
        assert records.verify_audit_trail() is None
        assert [e.action for e in records.audit_trail(str((tmp_path / "s.h5").resolve()))][:2] == \
            ["session recorded", "values stored"]


def test_the_trail_cannot_be_changed_through_sql_and_tampering_shows(tmp_path):
    path = tmp_path / "r.sqlite3"
    with Records(path, user="erika") as records:
        p = _patient(records)
        for k in range(3):
            _session(records, p, tmp_path, f"s{k}.h5", k)
    db = sqlite3.connect(path)
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        db.execute("UPDATE audit_log SET user = 'mallory' WHERE id = 2")
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        db.execute("DELETE FROM audit_log WHERE id = 2")
    db.close()
    tamper(path, "DROP TRIGGER audit_log_no_update", "UPDATE audit_log SET user = 'mallory' WHERE id = 3")
    with Records(path, read_only=True) as records:
        assert records.verify_audit_trail() == f"audit entry 3 (session recorded, {records.audit_trail()[2].time}) " \
                                               "was changed after it was written"
    tamper(path, "DROP TRIGGER audit_log_no_delete", "DELETE FROM audit_log WHERE id = 2")
    with Records(path, read_only=True) as records:
        assert "audit entry 3 does not follow" in records.verify_audit_trail()


def test_roles_decide_who_may_do_what(tmp_path):
    path = tmp_path / "r.sqlite3"
    with Records(path, user="anna") as records:
        with pytest.raises(RecordsError, match="first user must be an engineer"):
            records.add_user("anna", "clinician", "anna-secret")
        records.add_user("ed", "engineer", "ed-secret")
        with pytest.raises(RecordsError, match="user added: anna is not a registered user; this needs the role "
                                               "engineer"):
            records.add_user("anna", "clinician", "anna-secret")
    with Records(path, user="ed") as records:
        with pytest.raises(RecordsError, match="user added: ed has not given their password"):
            records.add_user("anna", "clinician", "anna-secret")
        records.authenticate("ed-secret")
        records.add_user("anna", "clinician", "anna-secret")
        records.add_user("otto", "operator", "otto-secret")
        records.log("calibration saved", "sphere.json")
    with Records(path, user="otto") as records:
        records.authenticate("otto-secret")
        p = _patient(records)
        sid = _session(records, p, tmp_path, "s.h5")
        with pytest.raises(RecordsError, match="report signed: otto is an operator; this needs the role clinician"):
            records.sign_report(sid)
        with pytest.raises(RecordsError, match="calibration saved"):
            records.log("calibration saved", "sphere.json")
        assert not records.report_state(sid).signed  # refused: nothing written
    with Records(path, user="anna") as records:
        with pytest.raises(RecordsError, match="report signed: anna has not given their password"):
            records.sign_report(sid)
        records.authenticate("anna-secret")
        state = records.sign_report(sid)
        assert state.signed_by == "anna" and state.signed_at is not None
        with pytest.raises(RecordsError, match="signed by anna .* read-only; add an amendment"):
            records.set_comment(sid, "changed afterwards")
        with pytest.raises(RecordsError, match="already signed"):
            records.sign_report(sid)
        records.amend_report(sid, "correction")
        assert [a.text for a in records.report_state(sid).amendments] == ["correction"]
        assert records.verify_audit_trail() is None
        assert [(e.user, e.role) for e in records.audit_trail()][-1] == ("anna", "clinician")


def test_bronchodilator_pair(tmp_path):
    with Records(tmp_path / "r.sqlite3") as records:
        p = _patient(records)
        other = records.add_patient("Other", "", "male", date(1960, 1, 1), 180.0, 80.0)
        pre = _session(records, p, tmp_path, "pre.h5")
        post = _session(records, p, tmp_path, "post.h5", 1)
        stranger = _session(records, other, tmp_path, "x.h5", 2)
        with pytest.raises(RecordsError, match="same patient"):
            records.link_bronchodilator(pre, stranger)
        with pytest.raises(RecordsError, match="must be recorded after"):
            records.link_bronchodilator(post, pre)
        records.link_bronchodilator(pre, post)
        assert records.pre_bronchodilator(post).id == pre
        assert records.pre_bronchodilator(pre) is None


def test_calibrations_are_logged_and_need_an_engineer(tmp_path, monkeypatch, capsys, typed):
    """`photopft calibrate flow` against the records in the user's data folder: refused for an operator
    before anything is written, logged for the engineer."""
    from app.cli import main
    from app.records import default_path

    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))  # users here must not reach other tests' records
    csv = tmp_path / "steps.csv"
    csv.write_text("reference_lps,adc_mean\n-4,1500\n0,2048\n2,2315\n6,2848\n")
    path = default_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    with Records(path, user="ed") as records:
        records.add_user("ed", "engineer", "ed-secret")
        records.authenticate("ed-secret")
        records.add_user("otto", "operator", "otto-secret")
    monkeypatch.setenv("PHOTOPFT_USER", "otto")
    out = tmp_path / "flow.json"
    assert main(["calibrate", "flow", str(csv), "-o", str(out)]) == 2
    assert "calibration saved: otto is an operator; this needs the role engineer" in capsys.readouterr().err
    assert not out.exists()
    monkeypatch.setenv("PHOTOPFT_USER", "ed")
    typed("not-eds-password")
    assert main(["calibrate", "flow", str(csv), "-o", str(out)]) == 2
    assert "ed: wrong password; nothing was done" in capsys.readouterr().err and not out.exists()
    typed("ed-secret")
    assert main(["calibrate", "flow", str(csv), "-o", str(out)]) == 0
    with Records(path, read_only=True) as records:
        entry = records.audit_trail()[-1]
        assert (entry.action, entry.user, entry.target, entry.details["kind"]) == \
            ("calibration saved", "ed", str(out.resolve()), "flow sensor")
