"""Patient records: patients and their sessions in an SQLite database.

Names and other direct identifiers live only here; a session file carries the patient's
pseudonym (`/subject@id`). A session row points at its session file (and results file) and keeps
its summary values, so a patient's history and trends need no session file opened.

The database uses write-ahead logging and `synchronous=FULL`, so a committed transaction survives
a crash of the application or the machine, and one cut off half way leaves no trace. The schema
is versioned with `PRAGMA user_version`; `MIGRATIONS[k]` takes version k to k + 1.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import secrets
import sqlite3
import sys
import time
from dataclasses import dataclass
from datetime import date, datetime, timezone
from pathlib import Path

from app import audit, auth, paths
from app.paths import SiteConfigError, config_dir, configured_records, data_dir

SEXES = ("male", "female")

MIGRATIONS: tuple[str, ...] = (
    # 0 -> 1: patients and sessions.
    """
    CREATE TABLE patients (
        id INTEGER PRIMARY KEY,
        pseudonym TEXT NOT NULL UNIQUE,
        patient_number TEXT UNIQUE,
        family_name TEXT NOT NULL,
        given_name TEXT NOT NULL DEFAULT '',
        sex TEXT NOT NULL CHECK (sex IN ('male', 'female')),
        birth_date TEXT NOT NULL,
        height_cm REAL NOT NULL CHECK (height_cm BETWEEN 40 AND 250),
        weight_kg REAL NOT NULL CHECK (weight_kg BETWEEN 2 AND 400),
        created TEXT NOT NULL
    );
    CREATE TABLE sessions (
        id INTEGER PRIMARY KEY,
        patient_id INTEGER NOT NULL REFERENCES patients(id) ON DELETE RESTRICT,
        session_path TEXT NOT NULL UNIQUE,
        results_path TEXT,
        recorded TEXT NOT NULL,
        operator TEXT NOT NULL DEFAULT '',
        rig TEXT NOT NULL DEFAULT '',
        calibration TEXT NOT NULL DEFAULT '',
        status TEXT NOT NULL DEFAULT 'recorded',
        summary TEXT NOT NULL DEFAULT '{}'
    );
    CREATE INDEX sessions_by_patient ON sessions(patient_id, recorded);
    """,
    # 1 -> 2: one row per summary value, for trends across sessions.
    """
    CREATE TABLE session_values (
        session_id INTEGER NOT NULL REFERENCES sessions(id) ON DELETE CASCADE,
        name TEXT NOT NULL,
        source TEXT NOT NULL,
        value REAL NOT NULL,
        PRIMARY KEY (session_id, name, source)
    );
    """,
    # 2 -> 3: users and roles, the audit trail, report sign-off and amendments, bronchodilator pairs.
    """
    CREATE TABLE users (
        name TEXT PRIMARY KEY,
        role TEXT NOT NULL CHECK (role IN ('operator', 'clinician', 'engineer')),
        active INTEGER NOT NULL DEFAULT 1,
        created TEXT NOT NULL
    );
    CREATE TABLE audit_log (
        id INTEGER PRIMARY KEY,
        time TEXT NOT NULL,
        user TEXT NOT NULL,
        role TEXT NOT NULL,
        action TEXT NOT NULL,
        target TEXT NOT NULL,
        details TEXT NOT NULL,
        previous_hash TEXT NOT NULL,
        hash TEXT NOT NULL
    );
    CREATE TRIGGER audit_log_no_update BEFORE UPDATE ON audit_log
    BEGIN SELECT RAISE(ABORT, 'the audit trail is append-only'); END;
    CREATE TRIGGER audit_log_no_delete BEFORE DELETE ON audit_log
    BEGIN SELECT RAISE(ABORT, 'the audit trail is append-only'); END;
    CREATE TABLE reports (
        session_id INTEGER PRIMARY KEY REFERENCES sessions(id) ON DELETE RESTRICT,
        comment TEXT NOT NULL DEFAULT '',
        signed_by TEXT,
        signed_at TEXT
    );
    CREATE TABLE report_amendments (
        id INTEGER PRIMARY KEY,
        session_id INTEGER NOT NULL REFERENCES sessions(id) ON DELETE RESTRICT,
        time TEXT NOT NULL,
        user TEXT NOT NULL,
        text TEXT NOT NULL
    );
    ALTER TABLE sessions ADD COLUMN pre_session_id INTEGER REFERENCES sessions(id);
    """,
    # 3 -> 4: what a signature signed (the files' SHA-256 and the values), users' password hashes.
    """
    ALTER TABLE reports ADD COLUMN signed_content TEXT;
    ALTER TABLE users ADD COLUMN password_hash TEXT;
    """,
)
SEALED_AT = 4  # from this version on every clinical row's state is in the audit trail
SCHEMA_VERSION = len(MIGRATIONS)


class RecordsError(ValueError):
    """A record that cannot be stored or found; the message names the field or the row."""


def _fold(text: str | None) -> str:
    """Case-folded text for searches (SQLite's own lower() knows ASCII only)."""
    return text.casefold() if text else ""


def _statements(script: str) -> list[str]:
    """The SQL statements of a script (a trigger's body holds semicolons of its own)."""
    out, pending = [], ""
    for part in script.split(";"):
        pending += part + ";"
        if sqlite3.complete_statement(pending):
            if pending.strip(" \n;"):
                out.append(pending.strip())
            pending = ""
    return out


def _first_line(exc: Exception) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__


def _check_intact(path: Path) -> None:
    """SQLite's own quick check, on a read-only connection: a damaged database is refused before
    anything (a journal mode, a migration) is written to it."""
    try:
        db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            result = str(db.execute("PRAGMA quick_check").fetchone()[0])
        finally:
            db.close()
    except (sqlite3.DatabaseError, UnicodeDecodeError) as exc:
        raise RecordsError(f"{path}: not a usable records database ({_first_line(exc)})") from exc
    if result != "ok":
        raise RecordsError(f"{path}: the records database is damaged ({result.splitlines()[0]}); restore it from "
                           f"its backup")


@dataclass(frozen=True)
class Patient:
    id: int
    pseudonym: str
    patient_number: str | None
    family_name: str
    given_name: str
    sex: str
    birth_date: date
    height_cm: float
    weight_kg: float

    @property
    def display_name(self) -> str:
        return f"{self.family_name}, {self.given_name}" if self.given_name else self.family_name

    def age_years(self, on: date | datetime) -> float:
        day = on.date() if isinstance(on, datetime) else on
        return (day - self.birth_date).days / 365.25

    def subject_attrs(self, on: date | datetime) -> dict[str, str | float]:
        """The session file's /subject attributes: the pseudonym, never the name."""
        return {"id": self.pseudonym, "sex": self.sex, "age_years": round(self.age_years(on), 2),
                "height_cm": float(self.height_cm), "weight_kg": float(self.weight_kg)}


@dataclass(frozen=True)
class SessionRecord:
    id: int
    patient_id: int
    session_path: Path
    results_path: Path | None
    recorded: datetime
    operator: str
    rig: str
    calibration: str
    status: str
    summary: dict


def existing_records(path: Path | None = None, user: str | None = None, may: str | None = None) -> Records | None:
    """The records database at `path` (default: the user's), or None where there is none yet;
    with `may`, refused (RecordsError, nothing opened) when the acting user's role does not allow
    that action: checked before the work it logs starts."""
    path = path or default_path()
    configured = _configured_records()
    if not path.exists():
        if may is not None and configured is not None:
            raise RecordsError(f"{may}: no records database at {configured}, the location {paths.SITE_CONFIG} "
                               f"configures: role-bound actions need it")
        return None
    records = Records(path, user=user)
    if may is not None:
        try:
            records.check_permitted(may)
            records.require_password(may)
        except (RecordsError, auth.AuthenticationError) as exc:
            records.close()
            raise RecordsError(str(exc)) from exc
    return records


@dataclass(frozen=True)
class Amendment:
    time: datetime
    user: str
    text: str


@dataclass(frozen=True)
class ReportState:
    session_id: int
    session_path: Path
    comment: str
    signed_by: str | None
    signed_at: datetime | None
    amendments: list[Amendment]
    # where the data a signature signed changed since: what every reader says instead of the signature
    signature_broken: str | None = None

    @property
    def signed(self) -> bool:
        """A signature was given (the report is read-only), whether or not its data changed since."""
        return self.signed_by is not None

    @property
    def signature_valid(self) -> bool:
        return self.signed and self.signature_broken is None


def file_sha256(path: str | os.PathLike) -> str | None:
    """SHA-256 of a file's bytes, None where it cannot be read."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                digest.update(block)
    except OSError:
        return None
    return digest.hexdigest()


def _create_private(path: Path) -> None:
    """A new database readable by its owner only (0600; SQLite gives its -wal and -shm files the same)."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return
    except OSError as exc:
        raise RecordsError(f"{path}: cannot create the records database ({exc})") from exc
    os.close(fd)


def _configured_records() -> Path | None:
    """paths.configured_records, its problem as a RecordsError."""
    try:
        return configured_records()
    except SiteConfigError as exc:
        raise RecordsError(str(exc)) from exc


def default_path() -> Path:
    """The site configuration's records database where there is one, else the user's."""
    return _configured_records() or data_dir() / "records.sqlite3"


def make_data_dir(folder: Path) -> None:
    """The user's data folder, made on first use readable by its owner only (0700)."""
    if not folder.is_dir():
        try:
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)
            os.chmod(folder, 0o700)  # mkdir's mode is masked by the umask
        except OSError as exc:
            raise RecordsError(f"{folder}: cannot make the data folder ({exc})") from exc


# How long a write waits for another program's transaction before it is refused, and after how long
# the wait is said: a clinician's action should neither fail at once nor hang unexplained.
BUSY_WAIT_S = 30.0
BUSY_SAY_AFTER_S = 2.0


def _is_busy(exc: sqlite3.OperationalError) -> bool:
    text = str(exc)
    return "locked" in text or "busy" in text


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _check_patient(family_name: str, sex: str, birth_date: date, height_cm: float, weight_kg: float) -> None:
    if not family_name.strip():
        raise RecordsError("family name: required")
    if sex not in SEXES:
        raise RecordsError(f"sex: must be male or female, got {sex!r}")
    if not isinstance(birth_date, date):
        raise RecordsError(f"birth date: expected a date, got {birth_date!r}")
    today = date.today()
    if birth_date > today or (today - birth_date).days > 120 * 366:
        raise RecordsError(f"birth date: {birth_date.isoformat()} is not a plausible birth date")
    if not 40.0 <= height_cm <= 250.0:
        raise RecordsError(f"height: {height_cm:g} cm is outside 40-250 cm")
    if not 2.0 <= weight_kg <= 400.0:
        raise RecordsError(f"weight: {weight_kg:g} kg is outside 2-400 kg")


class Records:
    """The records database. One connection per thread: open a Records where it is used."""

    def __init__(self, path: str | os.PathLike | None = None, read_only: bool = False, user: str | None = None):
        """`read_only`: for commands that only look (a list, a history, a report's names): nothing,
        not even the journal mode or a schema upgrade, is written to the file. `user`: who acts
        (default $PHOTOPFT_USER or the computer account); their role decides what they may do."""
        self._user = user
        self._pending: list[tuple[str, str, dict | None]] = []
        self.path = Path(path) if path is not None else default_path()
        if self.path.absolute() == default_path().absolute():
            make_data_dir(self.path.parent)
        elif not self.path.parent.is_dir():
            raise RecordsError(f"{self.path}: the folder {self.path.parent} does not exist (records are never "
                               "started in a folder made by mistake)")
        if self.path.is_file() and self.path.stat().st_size:
            _check_intact(self.path)
        if read_only:
            self._open_read_only()
            return
        _create_private(self.path)
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None, timeout=BUSY_SAY_AFTER_S / 4)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=FULL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.create_function("fold", 1, _fold, deterministic=True)
            self._migrate()
        except sqlite3.DatabaseError as exc:
            raise RecordsError(f"{self.path}: not a usable records database ({exc})") from exc

    def _open_read_only(self) -> None:
        try:
            self._db = sqlite3.connect(f"file:{self.path}?mode=ro", uri=True, isolation_level=None, timeout=10.0)
            self._db.create_function("fold", 1, _fold, deterministic=True)
            version = self.schema_version
        except sqlite3.DatabaseError as exc:
            raise RecordsError(f"{self.path}: not a usable records database ({_first_line(exc)})") from exc
        if version != SCHEMA_VERSION:
            self._db.close()
            raise RecordsError(f"{self.path}: schema version {version}, this photopft reads {SCHEMA_VERSION}: "
                               + ("update photopft" if version > SCHEMA_VERSION else
                                  "any command that writes records (patients add or register) upgrades it"))

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Records:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def schema_version(self) -> int:
        return int(self._db.execute("PRAGMA user_version").fetchone()[0])

    def _migrate(self) -> None:
        version = self.schema_version
        if version > SCHEMA_VERSION:
            raise RecordsError(f"{self.path}: schema version {version} is newer than this photopft "
                               f"({SCHEMA_VERSION}); update photopft")
        for step in range(version, SCHEMA_VERSION):
            with _Transaction(self._db, self.path):
                for statement in _statements(MIGRATIONS[step]):
                    self._db.execute(statement)
                if step + 1 == SEALED_AT and (rows := audit.changed_rows(self._db)):  # rows as they stand
                    audit.append(self._db, audit.Actor("photopft", "system"), "records sealed", str(self.path),
                                 {"rows": rows}, checked=True)
                self._db.execute(f"PRAGMA user_version = {step + 1}")
            if step + 1 >= SEALED_AT:
                self._write_head()

    def transaction(self):
        self._pending = []  # entries of a transaction rolled back are not carried into the next
        return _Transaction(self._db, self.path, self._entries_with_rows, self._write_head)

    @property
    def head_file(self) -> Path:
        """The audit trail's anchored head, beside the database."""
        return self.path.with_name(self.path.name + ".audit-head")

    @staticmethod
    def head_key_file() -> Path:
        return config_dir() / "audit-head.key"

    def _entries_with_rows(self) -> None:
        """At the end of a transaction: its audit entries written, the last holding the state of every
        row the transaction changed (app/audit.py)."""
        pending, self._pending = self._pending, []
        rows = audit.changed_rows(self._db) if self.schema_version >= SEALED_AT else {}
        if not pending and rows:
            pending = [("records changed", str(self.path), {})]
        for k, (action, target, details) in enumerate(pending):
            details = dict(details or {})
            if k == len(pending) - 1 and rows:
                details["rows"] = rows
            audit.append(self._db, self.actor, action, target, details, checked=True)

    def _write_head(self) -> None:
        try:
            audit.write_head(self._db, self.head_file, self.head_key_file())
        except OSError as exc:
            print(f"{self.head_file}: the audit trail's head could not be written ({exc})", file=sys.stderr)

    def integrity(self) -> str:
        return str(self._db.execute("PRAGMA integrity_check").fetchone()[0])

    # Patients
    def add_patient(self, family_name: str, given_name: str, sex: str, birth_date: date, height_cm: float,
                    weight_kg: float, patient_number: str | None = None, pseudonym: str | None = None) -> Patient:
        """A new patient, with a new random pseudonym unless one is given (a patient whose sessions
        were recorded elsewhere under that pseudonym)."""
        _check_patient(family_name, sex, birth_date, height_cm, weight_kg)
        number = patient_number.strip() if patient_number and patient_number.strip() else None
        if pseudonym is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{2,39}", pseudonym):
            raise RecordsError(f"pseudonym: 3-40 letters, digits, '-', '_' or '.', got {pseudonym!r}")
        with self.transaction():
            if number is not None and self._db.execute("SELECT 1 FROM patients WHERE patient_number = ?",
                                                       (number,)).fetchone():
                raise RecordsError(f"patient number {number} is already on record")
            if pseudonym is not None and self._db.execute("SELECT 1 FROM patients WHERE pseudonym = ?",
                                                          (pseudonym,)).fetchone():
                raise RecordsError(f"pseudonym {pseudonym} is already on record")
            while pseudonym is None:
                candidate = f"P-{secrets.token_hex(4).upper()}"
                if not self._db.execute("SELECT 1 FROM patients WHERE pseudonym = ?", (candidate,)).fetchone():
                    pseudonym = candidate
            cursor = self._db.execute(
                "INSERT INTO patients (pseudonym, patient_number, family_name, given_name, sex, birth_date, "
                "height_cm, weight_kg, created) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (pseudonym, number, family_name.strip(), given_name.strip(), sex, birth_date.isoformat(),
                 float(height_cm), float(weight_kg), _now()))
            self._log("patient registered", f"patient {pseudonym}")
        return self.patient(cursor.lastrowid)

    def update_patient(self, patient_id: int, *, height_cm: float | None = None,
                       weight_kg: float | None = None) -> Patient:
        p = self.patient(patient_id)
        height = p.height_cm if height_cm is None else height_cm
        weight = p.weight_kg if weight_kg is None else weight_kg
        _check_patient(p.family_name, p.sex, p.birth_date, height, weight)
        with self.transaction():
            self._db.execute("UPDATE patients SET height_cm = ?, weight_kg = ? WHERE id = ?",
                             (float(height), float(weight), patient_id))
            self._log("patient edited", f"patient {p.pseudonym}",
                      {"height_cm": [p.height_cm, float(height)], "weight_kg": [p.weight_kg, float(weight)]})
        return self.patient(patient_id)

    _PATIENT_COLUMNS = ("id, pseudonym, patient_number, family_name, given_name, sex, birth_date, height_cm, "
                        "weight_kg")

    def _patient(self, row) -> Patient:
        try:
            return Patient(row[0], row[1], row[2], row[3], row[4], row[5], date.fromisoformat(row[6]), row[7], row[8])
        except (TypeError, ValueError) as exc:
            raise RecordsError(f"{self.path}: the record of patient {row[0]!r} is damaged ({exc}); restore the "
                               f"database from its backup") from exc

    def patient(self, patient_id: int) -> Patient:
        row = self._db.execute(f"SELECT {self._PATIENT_COLUMNS} FROM patients WHERE id = ?",
                               (patient_id,)).fetchone()
        if row is None:
            raise RecordsError(f"no patient with record id {patient_id}")
        return self._patient(row)

    def patient_by_pseudonym(self, pseudonym: str) -> Patient | None:
        row = self._db.execute(f"SELECT {self._PATIENT_COLUMNS} FROM patients WHERE pseudonym = ?",
                               (pseudonym,)).fetchone()
        return self._patient(row) if row else None

    def find_patients(self, text: str = "") -> list[Patient]:
        """Patients whose name, patient number or pseudonym contains `text`, in any case (all with
        an empty text)."""
        needle = text.strip().casefold()
        rows = self._db.execute(
            f"SELECT {self._PATIENT_COLUMNS} FROM patients WHERE instr(fold(family_name || ' ' || given_name "
            "|| ' ' || ifnull(patient_number, '') || ' ' || pseudonym), ?) > 0 ORDER BY family_name, given_name, id",
            (needle,)).fetchall()
        return [self._patient(r) for r in rows]

    # Sessions
    def add_session(self, patient_id: int, session_path: str | os.PathLike, recorded: datetime, *,
                    operator: str = "", rig: str = "", calibration: str = "", status: str = "recorded") -> int:
        self.patient(patient_id)
        path = str(Path(session_path).resolve())
        with self.transaction():
            if self._db.execute("SELECT 1 FROM sessions WHERE session_path = ?", (path,)).fetchone():
                raise RecordsError(f"{path} is already on record")
            cursor = self._db.execute(
                "INSERT INTO sessions (patient_id, session_path, recorded, operator, rig, calibration, status) "
                "VALUES (?, ?, ?, ?, ?, ?, ?)",
                (patient_id, path, recorded.isoformat(), operator, rig, calibration, status))
            self._log("session recorded", path, {"operator": operator, "rig": rig, "status": status})
        return int(cursor.lastrowid)

    def set_results(self, session_id: int, results_path: str | os.PathLike | None,
                    values: dict[str, dict[str, float | str | int]], status: str = "processed") -> None:
        """Store the summary values of a session: {source: {name: value}}, e.g. {"flow sensor": {"FEV1_l": 4.1}}."""
        def plain(value):
            value = value.item() if hasattr(value, "item") else value
            return None if isinstance(value, float) and not math.isfinite(value) else value

        summary = {source: {k: plain(v) for k, v in named.items()} for source, named in values.items()}
        with self.transaction():
            updated = self._db.execute(
                "UPDATE sessions SET results_path = ?, summary = ?, status = ? WHERE id = ?",
                (str(Path(results_path).resolve()) if results_path else None, json.dumps(summary), status,
                 session_id)).rowcount
            if not updated:
                raise RecordsError(f"no session with record id {session_id}")
            self._log("values stored", self._session_path(session_id),
                      {"results": str(results_path) if results_path else None, "status": status})
            self._db.execute("DELETE FROM session_values WHERE session_id = ?", (session_id,))
            self._db.executemany(
                "INSERT INTO session_values (session_id, name, source, value) VALUES (?, ?, ?, ?)",
                [(session_id, name, source, float(value)) for source, named in summary.items()
                 for name, value in named.items()
                 if isinstance(value, (int, float)) and not isinstance(value, bool) and value is not None])

    _SESSION_COLUMNS = ("id, patient_id, session_path, results_path, recorded, operator, rig, calibration, status, "
                        "summary")

    @staticmethod
    def _session(row) -> SessionRecord:
        return SessionRecord(row[0], row[1], Path(row[2]), Path(row[3]) if row[3] else None,
                             datetime.fromisoformat(row[4]), row[5], row[6], row[7], row[8], json.loads(row[9]))

    def history(self, patient_id: int) -> list[SessionRecord]:
        rows = self._db.execute(f"SELECT {self._SESSION_COLUMNS} FROM sessions WHERE patient_id = ? "
                                "ORDER BY recorded, id", (patient_id,)).fetchall()
        return [self._session(r) for r in rows]

    def session_by_path(self, session_path: str | os.PathLike) -> SessionRecord | None:
        row = self._db.execute(f"SELECT {self._SESSION_COLUMNS} FROM sessions WHERE session_path = ?",
                               (str(Path(session_path).resolve()),)).fetchone()
        return self._session(row) if row else None

    def trend(self, patient_id: int, name: str, source: str) -> list[tuple[datetime, float]]:
        rows = self._db.execute(
            "SELECT s.recorded, v.value FROM session_values v JOIN sessions s ON s.id = v.session_id "
            "WHERE s.patient_id = ? AND v.name = ? AND v.source = ? ORDER BY s.recorded", (patient_id, name, source))
        return [(datetime.fromisoformat(t), float(v)) for t, v in rows]

    # Who acts, and the audit trail
    @property
    def actor(self) -> audit.Actor:
        return audit.actor_of(self._db, self._user)

    @property
    def roles_enforced(self) -> bool:
        return audit.roles_enforced(self._db)

    def _log(self, action: str, target: str, details: dict | None = None) -> None:
        """Inside the transaction that does the action: refused (and rolled back) when the actor's
        role does not allow it."""
        try:
            audit.check_permitted(self._db, self.actor, action)
        except audit.NotPermitted as exc:
            raise RecordsError(str(exc)) from exc
        if self._needs_password(action) and auth.proven_user() != self.actor.name:
            raise RecordsError(f"{action}: {self.actor.name} has not given their password: a role-bound action "
                               f"is done only after it")
        self._pending.append((action, target, details))

    def log(self, action: str, target: str, details: dict | None = None) -> None:
        """Log an action done outside the database (a calibration saved, an export written)."""
        with self.transaction():
            self._log(action, target, details)

    def check_permitted(self, action: str) -> None:
        """Refuse before the work starts when the actor may not do `action`."""
        try:
            audit.check_permitted(self._db, self.actor, action)
        except audit.NotPermitted as exc:
            raise RecordsError(str(exc)) from exc

    # Authentication (app/auth.py)
    def _needs_password(self, action: str) -> bool:
        """Role-bound, once users are registered and passwords introduced (a database from before
        them has none until an engineer sets the first: `photopft users password NAME`)."""
        return action in auth.NEEDS_PASSWORD and self.roles_enforced and self.passwords_in_use

    @property
    def passwords_in_use(self) -> bool:
        return self._db.execute("SELECT 1 FROM users WHERE active = 1 AND password_hash IS NOT NULL "
                                "LIMIT 1").fetchone() is not None

    def _check_location(self, action: str) -> None:
        """Role-bound actions only against the records the site configures, where it configures any."""
        configured = _configured_records()
        if configured is not None and self.path.resolve() != configured.resolve():
            raise RecordsError(f"{action}: {self.path} is not the records database {paths.SITE_CONFIG} configures "
                               f"({configured}): it cannot authorise role-bound actions")

    def require_password(self, action: str, ask=None) -> None:
        """Ask the acting user's password (auth.ask_password by default) unless this process has
        proven who they are; refused in one line when it is wrong."""
        if action in auth.NEEDS_PASSWORD:
            self._check_location(action)
        if not self._needs_password(action) or auth.proven_user() == self.actor.name:
            return
        try:
            password = (ask or auth.asker())(self.actor.name)
        except auth.AuthenticationError as exc:
            raise RecordsError(f"{action}: {exc}") from exc
        self.authenticate(password)

    def authenticate(self, password: str) -> None:
        """Prove the acting user for this process; a wrong password is refused and audited."""
        who = self.actor
        row = self._db.execute("SELECT password_hash FROM users WHERE name = ? AND active = 1",
                               (who.name,)).fetchone()
        if row is not None and auth.password_matches(password, row[0]):
            auth.prove(who.name, time.time())
            return
        reason = "not a registered user" if row is None else \
            "has no password yet (an engineer sets it: photopft users password NAME)" if not row[0] else \
            "wrong password"
        with _Transaction(self._db, self.path, None, self._write_head):
            audit.append(self._db, who, "authentication failed", f"user {who.name}", {"reason": reason}, checked=True)
        raise RecordsError(f"{who.name}: {reason}; nothing was done (the attempt is in the audit trail)")

    def audit_trail(self, target: str | None = None, limit: int | None = None) -> list[audit.AuditEntry]:
        return audit.entries(self._db, target, limit)

    def audit_problems(self) -> list[str]:
        """Every way the records depart from their audit trail (app/audit.py); empty when they agree."""
        return audit.verify(self._db, self.head_file, self.head_key_file())

    def verify_audit_trail(self) -> str | None:
        problems = self.audit_problems()
        return None if not problems else problems[0] + (f" (and {len(problems) - 1} more)" if len(problems) > 1
                                                         else "")

    def add_user(self, name: str, role: str, password: str) -> None:
        """A user with a role and a password. The first user added must be an engineer (who then adds
        the others, after giving their own password)."""
        name = name.strip()
        try:
            password_hash = auth.hash_password(password)
        except ValueError as exc:
            raise RecordsError(f"user {name}: {exc}") from exc
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.@ -]{0,63}", name):
            raise RecordsError(f"user name: 1-64 letters, digits, ' ', '.', '_', '@' or '-', got {name!r}")
        if role not in audit.ROLES:
            raise RecordsError(f"role: one of {', '.join(audit.ROLES)}, got {role!r}")
        with self.transaction():
            if not audit.roles_enforced(self._db) and role != "engineer":
                raise RecordsError("the first user must be an engineer (roles are enforced from the first user on)")
            if self._db.execute("SELECT 1 FROM users WHERE name = ?", (name,)).fetchone():
                raise RecordsError(f"user {name} is already on record")
            self._log("user added", f"user {name}", {"role": role})
            self._db.execute("INSERT INTO users (name, role, created, password_hash) VALUES (?, ?, ?, ?)",
                             (name, role, _now(), password_hash))

    def set_password(self, name: str, password: str) -> None:
        """A user's new password: their own (once they have proven the old one), or anyone's by an engineer."""
        row = self._db.execute("SELECT 1 FROM users WHERE name = ? AND active = 1", (name,)).fetchone()
        if row is None:
            raise RecordsError(f"no active user {name}")
        actor = self.actor
        if actor.name != name and actor.role != "engineer":
            raise RecordsError(f"password set: {actor.name} may set only their own password; an engineer sets others'")
        try:
            password_hash = auth.hash_password(password)
        except ValueError as exc:
            raise RecordsError(f"user {name}: {exc}") from exc
        with self.transaction():
            self._log("password set", f"user {name}")
            self._db.execute("UPDATE users SET password_hash = ? WHERE name = ?", (password_hash, name))

    def users(self) -> list[tuple[str, str]]:
        return [(r[0], r[1]) for r in self._db.execute("SELECT name, role FROM users WHERE active = 1 ORDER BY name")]

    # Reports: the clinician's comment, sign-off and amendments
    def _session_path(self, session_id: int) -> str:
        row = self._db.execute("SELECT session_path FROM sessions WHERE id = ?", (session_id,)).fetchone()
        if row is None:
            raise RecordsError(f"no session with record id {session_id}")
        return str(row[0])

    def report_state(self, session_id: int, verify: bool = True) -> ReportState:
        """The review, with what changed since signing where anything did (the files are read again,
        unless `verify` is False: a signature just given)."""
        path = self._session_path(session_id)
        row = self._db.execute("SELECT comment, signed_by, signed_at, signed_content FROM reports "
                               "WHERE session_id = ?", (session_id,)).fetchone()
        amendments = [Amendment(datetime.fromisoformat(t), u, text) for t, u, text in self._db.execute(
            "SELECT time, user, text FROM report_amendments WHERE session_id = ? ORDER BY id", (session_id,))]
        if row is None:
            return ReportState(session_id, Path(path), "", None, None, amendments)
        signed_at = datetime.fromisoformat(row[2]) if row[2] else None
        broken = None
        if row[1] is not None and verify:
            changed = self._changed_since_signing(session_id, row[3])
            if changed:
                broken = (f"the signed data has changed since it was signed (by {row[1]}, "
                          f"{signed_at:%Y-%m-%d %H:%M} UTC): {changed}")
        return ReportState(session_id, Path(path), row[0], row[1], signed_at, amendments, broken)

    def _signed_content(self, session_id: int) -> dict:
        """What a signature binds: the session and results files' SHA-256 and the stored values."""
        record = self.session(session_id)
        return {"session_sha256": file_sha256(record.session_path),
                "results_sha256": file_sha256(record.results_path) if record.results_path else None,
                "values": record.summary}

    def _changed_since_signing(self, session_id: int, signed_content: str | None) -> str | None:
        if not signed_content:
            return "the signature holds no record of what it signed (signed before photopft bound signatures)"
        signed, now = json.loads(signed_content), self._signed_content(session_id)
        what = [label for key, label in (("session_sha256", "the session file"), ("results_sha256", "the results file"),
                                         ("values", "the stored values")) if signed.get(key) != now.get(key)]
        return " and ".join(what) + (" differ" if len(what) > 1 else " differs") if what else None

    def set_comment(self, session_id: int, comment: str) -> None:
        """The clinician's comment, while the report is not signed (afterwards: amend)."""
        state = self.report_state(session_id)
        if state.signed:
            raise RecordsError(f"the report of {state.session_path.name} was signed by {state.signed_by} on "
                               f"{state.signed_at:%Y-%m-%d %H:%M}: it is read-only; add an amendment instead")
        with self.transaction():
            self._log("comment edited", str(state.session_path), {"comment": comment})
            self._db.execute("INSERT INTO reports (session_id, comment) VALUES (?, ?) ON CONFLICT(session_id) "
                             "DO UPDATE SET comment = excluded.comment", (session_id, comment))

    def sign_report(self, session_id: int) -> ReportState:
        """Sign the report as the acting clinician; from then on it is read-only."""
        state = self.report_state(session_id)
        if state.signed:
            raise RecordsError(f"the report of {state.session_path.name} is already signed by {state.signed_by}")
        who = self.actor.name
        content = self._signed_content(session_id)
        if content["session_sha256"] is None:
            raise RecordsError(f"{state.session_path}: the session file cannot be read: a report is signed with "
                               f"its data")
        with self.transaction():
            self._log("report signed", str(state.session_path), {"comment": state.comment,
                                                                  "session_sha256": content["session_sha256"],
                                                                  "results_sha256": content["results_sha256"]})
            self._db.execute("INSERT INTO reports (session_id, comment, signed_by, signed_at, signed_content) "
                             "VALUES (?, ?, ?, ?, ?) ON CONFLICT(session_id) DO UPDATE SET signed_by = "
                             "excluded.signed_by, signed_at = excluded.signed_at, signed_content = "
                             "excluded.signed_content",
                             (session_id, state.comment, who, _now(), json.dumps(content, sort_keys=True)))
        return self.report_state(session_id, verify=False)  # its files were hashed just now

    def amend_report(self, session_id: int, text: str) -> None:
        state = self.report_state(session_id)
        if not state.signed:
            raise RecordsError(f"the report of {state.session_path.name} is not signed: edit its comment")
        if not text.strip():
            raise RecordsError("an amendment needs its text")
        with self.transaction():
            self._log("report amended", str(state.session_path), {"text": text})
            self._db.execute("INSERT INTO report_amendments (session_id, time, user, text) VALUES (?, ?, ?, ?)",
                             (session_id, _now(), self.actor.name, text.strip()))

    # Bronchodilator pairs
    def link_bronchodilator(self, pre_session_id: int, post_session_id: int) -> None:
        """Mark `post` as the post-bronchodilator session of `pre` (same patient, recorded after it)."""
        pre, post = self.session(pre_session_id), self.session(post_session_id)
        if pre.patient_id != post.patient_id:
            raise RecordsError("pre- and post-bronchodilator sessions must be of the same patient")
        if post.recorded <= pre.recorded:
            raise RecordsError(f"the post-bronchodilator session ({post.recorded:%Y-%m-%d %H:%M}) must be recorded "
                               f"after the pre one ({pre.recorded:%Y-%m-%d %H:%M})")
        if pre_session_id == post_session_id:
            raise RecordsError("a session cannot be its own post-bronchodilator session")
        if pre.status in ("recording", "discarded"):
            raise RecordsError(f"{pre.session_path.name} is {pre.status}: recover it first, or choose another visit")
        with self.transaction():
            self._log("sessions linked", str(post.session_path), {"pre_session": str(pre.session_path)})
            self._db.execute("UPDATE sessions SET pre_session_id = ? WHERE id = ?", (pre_session_id, post_session_id))

    def session(self, session_id: int) -> SessionRecord:
        row = self._db.execute(f"SELECT {self._SESSION_COLUMNS} FROM sessions WHERE id = ?",
                               (session_id,)).fetchone()
        if row is None:
            raise RecordsError(f"no session with record id {session_id}")
        return self._session(row)

    def post_bronchodilator(self, session_id: int) -> SessionRecord | None:
        """The post-bronchodilator session that follows this one, if it is a pre one."""
        row = self._db.execute("SELECT id FROM sessions WHERE pre_session_id = ? ORDER BY recorded DESC LIMIT 1",
                               (session_id,)).fetchone()
        return self.session(row[0]) if row else None

    def pre_bronchodilator(self, session_id: int) -> SessionRecord | None:
        """The pre-bronchodilator session this one follows, if it is a post one."""
        row = self._db.execute("SELECT pre_session_id FROM sessions WHERE id = ?", (session_id,)).fetchone()
        return self.session(row[0]) if row and row[0] is not None else None


class _Transaction:
    """BEGIN IMMEDIATE ... COMMIT, or ROLLBACK when the block raises. A database another program is
    writing is waited for (said on stderr after BUSY_SAY_AFTER_S), then refused with one line."""

    def __init__(self, db: sqlite3.Connection, path: Path, before_commit=None, after_commit=None):
        self._db, self._path = db, path
        self._before_commit, self._after_commit = before_commit, after_commit

    def __enter__(self):
        started, said = time.monotonic(), False
        while True:
            try:
                self._db.execute("BEGIN IMMEDIATE")
                return self._db
            except sqlite3.OperationalError as exc:
                if not _is_busy(exc):
                    raise RecordsError(f"{self._path}: {_first_line(exc)}") from exc
                waited = time.monotonic() - started
                if waited >= BUSY_WAIT_S:
                    raise RecordsError(f"{self._path}: the records database is busy (another photopft is "
                                       f"writing to it) and stayed so for {waited:.0f} s; try again") from exc
                if not said and waited >= BUSY_SAY_AFTER_S:
                    print(f"{self._path}: waiting for another photopft writing to the records (up to "
                          f"{BUSY_WAIT_S:.0f} s)...", file=sys.stderr, flush=True)
                    said = True

    def __exit__(self, kind, exc, tb) -> None:
        if kind is None and self._before_commit is not None:
            try:
                self._before_commit()
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        self._db.execute("COMMIT" if kind is None else "ROLLBACK")
        if kind is None and self._after_commit is not None:
            self._after_commit()
