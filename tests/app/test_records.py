"""Patient records in a real SQLite file: validation, history, trends, migrations, crashes."""

from __future__ import annotations

import signal
import sqlite3
import subprocess
import sys
import textwrap
from datetime import date, datetime, timezone

import pytest

from app.records import MIGRATIONS, SCHEMA_VERSION, Records, RecordsError


def _patient(records: Records, number: str = "H-1", **changes):
    fields = dict(family_name="Łukasiewicz", given_name="Zoë", sex="female", birth_date=date(1980, 5, 17),
                  height_cm=168.0, weight_kg=61.5, patient_number=number)
    fields.update(changes)
    return records.add_patient(**fields)


def test_patients_sessions_history_and_trends(tmp_path):
    with Records(tmp_path / "r.sqlite3") as records:
        p = _patient(records)
        assert p.pseudonym.startswith("P-") and p.display_name == "Łukasiewicz, Zoë"
        assert [q.id for q in records.find_patients("łUKAS")] == [p.id]
        assert records.find_patients("nobody") == []
        assert records.find_patients("H-1")[0].pseudonym == p.pseudonym
        assert records.patient_by_pseudonym(p.pseudonym) == p
        for k, fev1 in enumerate((2.9, 2.8, 2.6)):
            when = datetime(2026, 1 + k, 10, 9, 30, tzinfo=timezone.utc)
            sid = records.add_session(p.id, tmp_path / f"s{k}.h5", when, operator="op", rig="simulated")
            records.set_results(sid, tmp_path / f"r{k}.h5", {"flow sensor": {"FEV1_l": fev1, "grade": "A",
                                                                             "IE50": float("nan")}})
        history = records.history(p.id)
        assert [s.summary["flow sensor"]["FEV1_l"] for s in history] == [2.9, 2.8, 2.6]
        assert history[0].summary["flow sensor"]["IE50"] is None  # not a number: stored as missing
        assert history[0].status == "processed" and history[0].session_path == (tmp_path / "s0.h5").resolve()
        assert [v for _, v in records.trend(p.id, "FEV1_l", "flow sensor")] == [2.9, 2.8, 2.6]
        attrs = p.subject_attrs(datetime(2026, 5, 17, tzinfo=timezone.utc))
        assert attrs["id"] == p.pseudonym and attrs["age_years"] == pytest.approx(46.0, abs=0.01)
        assert "Zoë" not in str(attrs)


@pytest.mark.parametrize("change, field", [(dict(sex="x"), "sex"), (dict(height_cm=20.0), "height"),
                                           (dict(weight_kg=0.5), "weight"), (dict(family_name=" "), "family name"),
                                           (dict(birth_date=date(2999, 1, 1)), "birth date")])
def test_bad_patient_fields_are_named(tmp_path, change, field):
    with Records(tmp_path / "r.sqlite3") as records:
        with pytest.raises(RecordsError, match=field):
            _patient(records, **change)
        assert records.find_patients() == []


def test_duplicates_are_refused(tmp_path):
    with Records(tmp_path / "r.sqlite3") as records:
        p = _patient(records)
        with pytest.raises(RecordsError, match="already on record"):
            _patient(records)
        records.add_session(p.id, tmp_path / "s.h5", datetime.now(timezone.utc))
        with pytest.raises(RecordsError, match="already on record"):
            records.add_session(p.id, tmp_path / "s.h5", datetime.now(timezone.utc))


def test_migration_from_version_1_keeps_the_rows(tmp_path):
    path = tmp_path / "old.sqlite3"
    db = sqlite3.connect(path)
    db.executescript(MIGRATIONS[0])
    db.execute("INSERT INTO patients (pseudonym, family_name, sex, birth_date, height_cm, weight_kg, created) "
               "VALUES ('P-OLD', 'Old', 'male', '1950-01-01', 170, 70, '2025-01-01T00:00:00+00:00')")
    db.execute("PRAGMA user_version = 1")
    db.commit()
    db.close()
    with Records(path) as records:
        assert records.schema_version == SCHEMA_VERSION == 4
        assert [e.action for e in records.audit_trail()] == ["records sealed"]  # the old rows enter the trail
        assert records.audit_problems() == []
        p = records.patient_by_pseudonym("P-OLD")
        sid = records.add_session(p.id, tmp_path / "s.h5", datetime.now(timezone.utc))
        records.set_results(sid, None, {"optical": {"TV_l": 0.5}})
        assert records.trend(p.id, "TV_l", "optical")[0][1] == 0.5


def test_newer_or_foreign_databases_are_refused(tmp_path):
    newer = tmp_path / "newer.sqlite3"
    db = sqlite3.connect(newer)
    db.execute("PRAGMA user_version = 99")
    db.close()
    with pytest.raises(RecordsError, match="newer than this photopft"):
        Records(newer)
    junk = tmp_path / "junk.sqlite3"
    junk.write_bytes(b"this is not a database" * 100)
    with pytest.raises(RecordsError, match="not a usable records database"):
        Records(junk)


CRASHER = textwrap.dedent("""
    import os, signal, sys
    from datetime import date, datetime, timezone
    from app.records import Records
    records = Records(sys.argv[1])
    p = records.add_patient("Kept", "", "male", date(1970, 1, 1), 180, 80)
    with records.transaction() as db:
        for k in range(500):
            db.execute("INSERT INTO sessions (patient_id, session_path, recorded) VALUES (?, ?, ?)",
                       (p.id, f"/lost/{k}.h5", datetime.now(timezone.utc).isoformat()))
        os.kill(os.getpid(), signal.SIGKILL)
""")


def test_the_database_survives_a_crash_mid_transaction(tmp_path):
    path = tmp_path / "r.sqlite3"
    run = subprocess.run([sys.executable, "-c", CRASHER, str(path)], capture_output=True)
    assert run.returncode == -signal.SIGKILL
    with Records(path) as records:
        assert records.integrity() == "ok"
        (kept,) = records.find_patients()
        assert kept.family_name == "Kept"
        assert records.history(kept.id) == []
        records.add_session(kept.id, tmp_path / "after.h5", datetime.now(timezone.utc))
        assert len(records.history(kept.id)) == 1
