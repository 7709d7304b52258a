"""The audit trail: who did what when, append-only and hash-chained; and the roles that decide who may do what.

Each entry's hash is SHA-256 over the previous entry's hash and the entry itself (time, user, role,
action, target, details as canonical JSON), so an entry changed, removed or inserted by anything but
this code breaks the chain from that entry on, and `verify` names it. SQLite triggers refuse UPDATE
and DELETE on the table; the chain catches what goes around them (another program editing the file).

Every clinical row is covered too: the transaction that changes patients, users, sessions, their
stored values, comments, signatures or amendments ends with its audit entry holding the SHA-256 of
each row it changed (`rows`), so the trail replayed gives every row's last audited state, and a row
edited, inserted or removed by another program differs from it. The chain's head (last entry's id
and hash, with an HMAC under a key kept outside the database) is written to a file beside the
database after every entry: a log deleted, cut short or rebuilt no longer ends at it. What this
cannot see (someone holding the database, its head file and the key at once) is in docs/trust.md.

Roles: operators record sessions and register patients; clinicians also edit values, comment, sign
and amend reports and export; engineers calibrate the rig and manage users. Until the first user is
added to a records database roles are not enforced (a new installation), and entries name the
computer account with the role "unregistered".
"""

from __future__ import annotations

import getpass
import hashlib
import hmac
import json
import os
import secrets
import sqlite3
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

from app.auth import proven_user

ROLES = ("operator", "clinician", "engineer")
UNREGISTERED = "unregistered"
GENESIS = "0" * 64

# action -> roles allowed
PERMISSIONS: dict[str, tuple[str, ...]] = {
    "patient registered": ROLES,
    "patient edited": ("operator", "clinician"),
    "session recorded": ROLES,
    "values stored": ROLES,
    "sessions linked": ("clinician",),
    "comment edited": ("clinician",),
    "report signed": ("clinician",),
    "report amended": ("clinician",),
    "calibration saved": ("engineer",),
    "syringe check": ("operator", "engineer"),
    "export": ("clinician",),
    "user added": ("engineer",),
    "password set": ROLES,  # one's own; others' by an engineer (Records.set_password)
    "export identified": ("clinician",),
    "report written": ROLES,  # a PDF; it names the patient only for a clinician (app/report_access.py)
}


class NotPermitted(PermissionError):
    """The acting user's role does not allow the action; the message names both."""


@dataclass(frozen=True)
class Actor:
    name: str
    role: str


@dataclass(frozen=True)
class AuditEntry:
    id: int
    time: str
    user: str
    role: str
    action: str
    target: str
    details: dict
    previous_hash: str
    hash: str


def login_name() -> str:
    """Who acts: the user this process has proven (app/auth.py), else $PHOTOPFT_USER, else the computer account."""
    proven = proven_user()
    if proven:
        return proven
    name = os.environ.get("PHOTOPFT_USER", "").strip()
    if name:
        return name
    try:
        return getpass.getuser()
    except (KeyError, OSError):
        return "unknown"


def entry_hash(previous_hash: str, time: str, user: str, role: str, action: str, target: str,
               details_json: str) -> str:
    payload = json.dumps([previous_hash, time, user, role, action, target, details_json], ensure_ascii=False,
                         separators=(",", ":"))
    return hashlib.sha256(payload.encode("utf-8")).hexdigest()


def actor_of(db: sqlite3.Connection, name: str | None = None) -> Actor:
    """The acting user and their role in this database (UNREGISTERED where no users are registered)."""
    name = name or login_name()
    row = db.execute("SELECT role FROM users WHERE name = ? AND active = 1", (name,)).fetchone()
    return Actor(name, row[0] if row else UNREGISTERED)


def roles_enforced(db: sqlite3.Connection) -> bool:
    return db.execute("SELECT 1 FROM users WHERE active = 1 LIMIT 1").fetchone() is not None


def check_permitted(db: sqlite3.Connection, actor: Actor, action: str) -> None:
    if not roles_enforced(db):
        return
    allowed = PERMISSIONS[action]
    if actor.role not in allowed:
        who = f"{actor.name} is not a registered user" if actor.role == UNREGISTERED else \
            f"{actor.name} is {'an' if actor.role[0] in 'aeiou' else 'a'} {actor.role}"
        raise NotPermitted(f"{action}: {who}; this needs the role {' or '.join(allowed)}")


def append(db: sqlite3.Connection, actor: Actor, action: str, target: str, details: dict | None = None,
           *, checked: bool = False) -> AuditEntry:
    """Check the actor may do `action` (unless `checked` already) and log it. Call inside the
    transaction that does it, so both land or neither."""
    if not checked:
        check_permitted(db, actor, action)
    time = datetime.now(timezone.utc).isoformat(timespec="microseconds")
    details_json = json.dumps(details or {}, sort_keys=True, ensure_ascii=False, separators=(",", ":"))
    row = db.execute("SELECT hash FROM audit_log ORDER BY id DESC LIMIT 1").fetchone()
    previous = row[0] if row else GENESIS
    digest = entry_hash(previous, time, actor.name, actor.role, action, target, details_json)
    cursor = db.execute("INSERT INTO audit_log (time, user, role, action, target, details, previous_hash, hash) "
                        "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                        (time, actor.name, actor.role, action, target, details_json, previous, digest))
    return AuditEntry(int(cursor.lastrowid), time, actor.name, actor.role, action, target, details or {}, previous,
                      digest)


def entries(db: sqlite3.Connection, target: str | None = None, limit: int | None = None) -> list[AuditEntry]:
    """The trail, oldest first (only the entries about `target` if given; the newest `limit`)."""
    where, params = ("WHERE target = ?", [target]) if target is not None else ("", [])
    sql = f"SELECT id, time, user, role, action, target, details, previous_hash, hash FROM audit_log {where} " \
          "ORDER BY id DESC" + (" LIMIT ?" if limit else "")
    rows = db.execute(sql, params + ([limit] if limit else [])).fetchall()
    return [AuditEntry(r[0], r[1], r[2], r[3], r[4], r[5], json.loads(r[6]), r[7], r[8]) for r in reversed(rows)]


def verify_chain(db: sqlite3.Connection) -> str | None:
    """None when the chain is whole; otherwise which entry breaks it and how."""
    previous = GENESIS
    rows = db.execute("SELECT id, time, user, role, action, target, details, previous_hash, hash FROM audit_log "
                      "ORDER BY id").fetchall()
    for r in rows:
        if r[7] != previous:
            return f"audit entry {r[0]} does not follow the entry before it (an entry was removed or inserted)"
        if entry_hash(previous, r[1], r[2], r[3], r[4], r[5], r[6]) != r[8]:
            return f"audit entry {r[0]} ({r[4]}, {r[1]}) was changed after it was written"
        previous = r[8]
    return None


def verify(db: sqlite3.Connection, head_file: Path | None = None, key_file: Path | None = None) -> list[str]:
    """Every way the records depart from their audit trail (empty when they agree): the chain, the
    anchored head (where a head file is given), and every clinical row against its last audited state."""
    broken = verify_chain(db)
    if broken:
        return [broken]
    problems = []
    if head_file is not None and key_file is not None:
        problems += _check_head(db, head_file, key_file)
    problems += [f"{key}: {how}" for key, how in row_differences(db)]
    return problems


# ------------------------------------------------------------------ the clinical rows' states

# (kind, query): the first column names the row, the rest is its content
TRACKED_ROWS = (
    ("patient", "SELECT pseudonym, patient_number, family_name, given_name, sex, birth_date, height_cm, weight_kg, "
                "created FROM patients"),
    ("user", "SELECT name, role, active, created, password_hash FROM users"),
    ("session", "SELECT s.session_path, p.pseudonym, s.results_path, s.recorded, s.operator, s.rig, s.calibration, "
                "s.status, s.summary, q.session_path FROM sessions s LEFT JOIN patients p ON p.id = s.patient_id "
                "LEFT JOIN sessions q ON q.id = s.pre_session_id"),
    ("value", "SELECT s.session_path || ' ' || v.source || ' ' || v.name, v.value FROM session_values v "
              "LEFT JOIN sessions s ON s.id = v.session_id"),
    ("report", "SELECT s.session_path, r.comment, r.signed_by, r.signed_at, r.signed_content FROM reports r "
               "LEFT JOIN sessions s ON s.id = r.session_id"),
    ("amendment", "SELECT a.id, s.session_path, a.time, a.user, a.text FROM report_amendments a "
                  "LEFT JOIN sessions s ON s.id = a.session_id"),
)


def row_states(db: sqlite3.Connection) -> dict[str, str]:
    """'kind name' -> SHA-256 of the row's content, for every clinical row."""
    out = {}
    for kind, query in TRACKED_ROWS:
        for row in db.execute(query):
            content = json.dumps(list(row[1:]), ensure_ascii=False, separators=(",", ":"))
            out[f"{kind} {row[0]}"] = hashlib.sha256(content.encode("utf-8")).hexdigest()
    return out


def audited_states(db: sqlite3.Connection) -> dict[str, str]:
    """Each row's state as the trail last recorded it (rows removed through photopft left out)."""
    states: dict[str, str] = {}
    for (details,) in db.execute("SELECT details FROM audit_log ORDER BY id"):
        for key, digest in json.loads(details).get("rows", {}).items():
            if digest is None:
                states.pop(key, None)
            else:
                states[key] = digest
    return states


def _differing(now: dict[str, str], audited: dict[str, str]) -> dict[str, str | None]:
    changed: dict[str, str | None] = {k: v for k, v in now.items() if audited.get(k) != v}
    changed.update({k: None for k in audited if k not in now})
    return changed


def changed_rows(db: sqlite3.Connection) -> dict[str, str | None]:
    """The rows whose state differs from the trail's ({key: new digest, or None where removed})."""
    return _differing(row_states(db), audited_states(db))


def row_differences(db: sqlite3.Connection) -> list[tuple[str, str]]:
    """changed_rows, each said: added, changed or removed outside photopft."""
    audited = audited_states(db)
    return [(key, "removed outside photopft" if digest is None else
             "added outside photopft (no audited change made it)" if key not in audited else
             "changed outside photopft since its last audited change")
            for key, digest in _differing(row_states(db), audited).items()]


# ------------------------------------------------------------------ the head, anchored outside the database

def _key(key_file: Path) -> bytes:
    """The head's HMAC key, made on first use readable by its owner only."""
    if not key_file.exists():
        key_file.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        try:
            fd = os.open(key_file, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            return key_file.read_bytes()
        with os.fdopen(fd, "wb") as fh:
            fh.write(secrets.token_bytes(32))
    return key_file.read_bytes()


def _head_mac(key: bytes, last_id: int, last_hash: str) -> str:
    return hmac.new(key, f"{last_id}:{last_hash}".encode(), hashlib.sha256).hexdigest()


def write_head(db: sqlite3.Connection, head_file: Path, key_file: Path) -> None:
    """The chain's last entry, with its HMAC, written beside the database (atomically)."""
    row = db.execute("SELECT id, hash FROM audit_log ORDER BY id DESC LIMIT 1").fetchone()
    if row is None:
        return
    text = json.dumps({"last_id": row[0], "hash": row[1], "mac": _head_mac(_key(key_file), row[0], row[1])})
    partial = head_file.with_name(f".{head_file.name}.{os.getpid()}.partial")
    fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(partial, head_file)


def _check_head(db: sqlite3.Connection, head_file: Path, key_file: Path) -> list[str]:
    last = db.execute("SELECT id, hash FROM audit_log ORDER BY id DESC LIMIT 1").fetchone()
    if not head_file.exists():
        return [f"the trail's anchored head {head_file} is missing"] if last is not None else []
    try:
        head = json.loads(head_file.read_text())
        last_id, last_hash, mac = int(head["last_id"]), str(head["hash"]), str(head["mac"])
    except (OSError, ValueError, KeyError, TypeError):
        return [f"the trail's anchored head {head_file} cannot be read"]
    if not key_file.exists() or not hmac.compare_digest(mac, _head_mac(_key(key_file), last_id, last_hash)):
        return [f"the trail's anchored head {head_file} was not written by photopft (its HMAC does not match)"]
    row = db.execute("SELECT hash FROM audit_log WHERE id = ?", (last_id,)).fetchone()
    if row is None or row[0] != last_hash:
        return [f"the trail no longer holds entry {last_id} as it was anchored: the log was deleted, cut short "
                f"or rebuilt"]
    if last is not None and last[0] != last_id:
        return [f"{last[0] - last_id} entr{'y' if last[0] - last_id == 1 else 'ies'} after the anchored head "
                f"(entry {last_id}): written by another program"]
    return []
