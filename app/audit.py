"""The audit trail: who did what when, append-only and hash-chained; and the roles that decide who may do what.

Each entry's hash is SHA-256 over the previous entry's hash and the entry itself (time, user, role,
action, target, details as canonical JSON), so an entry changed, removed or inserted by anything but
this code breaks the chain from that entry on, and `verify` names it. SQLite triggers refuse UPDATE
and DELETE on the table; the chain catches what goes around them (another program editing the file).

Roles: operators record sessions and register patients; clinicians also edit values, comment, sign
and amend reports and export; engineers calibrate the rig and manage users. Until the first user is
added to a records database roles are not enforced (a new installation), and entries name the
computer account with the role "unregistered".
"""

from __future__ import annotations

import getpass
import hashlib
import json
import os
import sqlite3
from dataclasses import dataclass
from datetime import datetime, timezone

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
    """Who acts: $PHOTOPFT_USER, or the computer account."""
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


def append(db: sqlite3.Connection, actor: Actor, action: str, target: str, details: dict | None = None) -> AuditEntry:
    """Check the actor may do `action` and log it. Call inside the transaction that does it, so both
    land or neither."""
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


def verify(db: sqlite3.Connection) -> str | None:
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
