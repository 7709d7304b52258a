"""`photopft review`, `photopft users` and `photopft audit`: the clinician's sign-off, who may do what,
and who did what."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from app.errors import UserError

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--records", type=Path, help="patient records database (default: the site's, else the user's "
                                                  "data folder)")
    p.add_argument("--user", help="who acts (default: $PHOTOPFT_USER or the computer account); once users are "
                                  "registered, a role-bound action asks their password (at the terminal, or the "
                                  "first line of standard input)")


def add_review_verbs(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("review", help="a session's clinician comment, sign-off, amendments, bronchodilator pair",
                       description="Without options: the session's review state. A signed report is read-only; "
                                   "what changes after signing is an amendment.")
    r.add_argument("session", type=Path, help="a session file on record (photopft patients register)")
    r.add_argument("--comment", help="set the clinician's comment (until the report is signed)")
    r.add_argument("--sign", action="store_true", help="sign the report as the acting clinician")
    r.add_argument("--amend", metavar="TEXT", help="add an amendment to a signed report")
    r.add_argument("--post-bronchodilator-of", type=Path, metavar="PRE.h5",
                   help="this session is the post-bronchodilator session of PRE.h5")
    _common(r)
    r.set_defaults(run=run_review)

    u = sub.add_parser("users", help="users and their roles (operator, clinician, engineer)",
                       description="Roles are enforced from the first user on; the first user is an engineer.")
    verbs = u.add_subparsers(dest="users_verb", metavar="ACTION", required=True)
    add = verbs.add_parser("add", help="a user with a role; asks the new user's password (twice at a terminal, "
                                       "else the next line of standard input)")
    add.add_argument("name")
    add.add_argument("--role", choices=("operator", "clinician", "engineer"), required=True)
    password = verbs.add_parser("password", help="set a user's password (one's own, or anyone's by an engineer)")
    password.add_argument("name")
    verbs.add_parser("list", help="the users and their roles")
    _common(u)  # before the action, as for `photopft patients`
    u.set_defaults(run=run_users)

    a = sub.add_parser("audit", help="the audit trail: who did what when; --verify checks its hash chain")
    a.add_argument("--session", type=Path, help="only the entries about this session")
    a.add_argument("--limit", type=int, default=50, help="the newest N entries (default 50; 0: all)")
    a.add_argument("--verify", action="store_true", help="check the hash chain; exit 1 when it is broken")
    _common(a)
    a.set_defaults(run=run_audit)


def _records(args: argparse.Namespace, read_only: bool = False):
    from app.records import Records, RecordsError, default_path

    path = args.records or default_path()
    if not path.exists():
        raise UserError(f"{path}: no records database there (`photopft patients add` starts one)")
    try:
        return Records(path, read_only=read_only, user=args.user)
    except RecordsError as exc:
        raise UserError(str(exc)) from exc


def _session_id(records, path: Path) -> int:
    record = records.session_by_path(path)
    if record is None:
        raise UserError(f"{path}: not on record (`photopft patients register` puts it there)")
    return record.id


def run_review(args: argparse.Namespace) -> int:
    from app.records import RecordsError

    changes = args.comment is not None or args.sign or args.amend or args.post_bronchodilator_of
    with _records(args, read_only=not changes) as records:
        try:
            sid = _session_id(records, args.session)
            for wanted, action in ((args.comment is not None, "comment edited"), (args.sign, "report signed"),
                                   (args.amend, "report amended")):
                if wanted:
                    records.check_permitted(action)
                    records.require_password(action)
            if args.post_bronchodilator_of is not None:
                records.link_bronchodilator(_session_id(records, args.post_bronchodilator_of), sid)
            if args.comment is not None:
                records.set_comment(sid, args.comment)
            if args.sign:
                records.sign_report(sid)
            if args.amend:
                records.amend_report(sid, args.amend)
            state = records.report_state(sid)
            pre = records.pre_bronchodilator(sid)
        except RecordsError as exc:
            raise UserError(str(exc)) from exc
    print(f"{state.session_path.name}: " + (state.signature_broken if state.signature_broken else
                                           f"signed by {state.signed_by} on {state.signed_at:%Y-%m-%d %H:%M} UTC"
                                           if state.signed else "not signed"))
    print(f"  comment: {state.comment or 'none'}")
    for a in state.amendments:
        print(f"  amendment by {a.user} on {a.time:%Y-%m-%d %H:%M}: {a.text}")
    if pre is not None:
        print(f"  post-bronchodilator session of {pre.session_path.name}")
    return 0


def _new_password(name: str) -> str:
    """The new password, typed twice at a terminal; else the next line of standard input."""
    from app.auth import AuthenticationError, ask_password

    try:
        first = ask_password(name, f"new password of {name}: ")
        if sys.stdin is not None and sys.stdin.isatty() and ask_password(name, "again: ") != first:
            raise UserError(f"the two passwords for {name} differ: nothing was changed")
    except AuthenticationError as exc:
        raise UserError(f"{name}: a new password is needed ({exc})") from exc
    return first


def run_users(args: argparse.Namespace) -> int:
    from app.records import RecordsError

    with _records(args, read_only=args.users_verb == "list") as records:
        try:
            if args.users_verb == "add":
                if records.roles_enforced:
                    records.check_permitted("user added")
                    records.require_password("user added")
                records.add_user(args.name, args.role, _new_password(args.name))
                print(f"added {args.name} ({args.role})")
                return 0
            if args.users_verb == "password":
                if args.name not in dict(records.users()):
                    raise UserError(f"no active user {args.name}: nothing was changed")
                records.require_password("password set")
                records.set_password(args.name, _new_password(args.name))
                print(f"password of {args.name} set")
                return 0
            users = records.users()
        except RecordsError as exc:
            raise UserError(str(exc)) from exc
    if not users:
        print("no users: roles are not enforced (`photopft users add NAME --role engineer` starts them)")
    for name, role in users:
        print(f"{name}  {role}")
    return 0


def run_audit(args: argparse.Namespace) -> int:
    with _records(args, read_only=True) as records:
        target = str(args.session.resolve()) if args.session is not None else None
        entries = records.audit_trail(target, args.limit or None)
        problems = records.audit_problems() if args.verify else []
    for e in entries:
        details = ", ".join(f"{k}={v}" for k, v in e.details.items() if v not in (None, "") and k != "rows")
        print(f"{e.time[:19].replace('T', ' ')}  {e.user} ({e.role})  {e.action}  {e.target}"
              + (f"  [{details}]" if details else ""))
    if args.verify:
        for problem in problems:
            print(f"audit trail: {problem}")
        if not problems:
            print("audit trail: the hash chain is whole, ends at its anchored head, and every record matches "
                  "its last audited state")
        return 1 if problems else 0
    return 0
