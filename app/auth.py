"""Who acts, proven: each user's password, kept as a scrypt hash, asked before a role-bound action.

`--user` and $PHOTOPFT_USER name who acts; a name proves nothing. Once users are registered in the
records, the actions in NEEDS_PASSWORD (signing, amending, calibrating, managing users, exporting
identified data) are done only after that user's password is given: at the terminal (hidden), or
as the first line of standard input for a script. The GUI asks at start-up and again after
its idle timeout. A wrong password is refused and written to the audit trail.

scrypt is Python's own (hashlib, OpenSSL's implementation): a memory-hard function, so no further
dependency is needed; the parameters (N = 2^15, r = 8, p = 1: 32 MiB, about 0.1 s here) are OWASP's
recommendation for scrypt.
"""

from __future__ import annotations

import base64
import getpass
import hashlib
import hmac
import secrets
import sys

SCRYPT_N, SCRYPT_R, SCRYPT_P = 2 ** 15, 8, 1
KEY_BYTES = 32
MIN_LENGTH = 8

NEEDS_PASSWORD = frozenset({"report signed", "report amended", "comment edited", "calibration saved", "user added",
                            "password set", "export identified"})


class AuthenticationError(PermissionError):
    """The password was not given or not right; the message says which and what to do."""


def _scrypt(password: str, salt: bytes, n: int, r: int, p: int) -> bytes:
    return hashlib.scrypt(password.encode("utf-8"), salt=salt, n=n, r=r, p=p, dklen=KEY_BYTES,
                          maxmem=2 * 128 * r * n)


def hash_password(password: str) -> str:
    """The stored form: scrypt$N$r$p$salt$key (base64)."""
    if len(password) < MIN_LENGTH:
        raise ValueError(f"a password needs at least {MIN_LENGTH} characters")
    salt = secrets.token_bytes(16)
    key = _scrypt(password, salt, SCRYPT_N, SCRYPT_R, SCRYPT_P)
    return "$".join(["scrypt", str(SCRYPT_N), str(SCRYPT_R), str(SCRYPT_P), base64.b64encode(salt).decode(),
                     base64.b64encode(key).decode()])


def password_matches(password: str, stored: str | None) -> bool:
    if not stored:
        return False
    try:
        kind, n, r, p, salt, key = stored.split("$")
        if kind != "scrypt":
            return False
        expected = base64.b64decode(key)
        actual = _scrypt(password, base64.b64decode(salt), int(n), int(r), int(p))
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(actual, expected)


def ask_password(user: str, prompt: str | None = None) -> str:
    """The password, hidden at a terminal; otherwise the first line of standard input."""
    prompt = prompt or f"password of {user}: "
    if sys.stdin is not None and sys.stdin.isatty():
        try:
            return getpass.getpass(prompt)
        except (EOFError, KeyboardInterrupt) as exc:
            raise AuthenticationError(f"no password given for {user}") from exc
    line = sys.stdin.readline() if sys.stdin is not None else ""
    if not line.strip():
        raise AuthenticationError(f"this needs the password of {user}: run it at a terminal, or give the password "
                                  "as the first line of standard input")
    return line.rstrip("\r\n")


# How this process asks for a password: the terminal's ask_password, or the application's dialog.
_asker = [ask_password]


def use_asker(asker) -> None:
    """The application asks in a dialog (never on a terminal nobody watches)."""
    _asker[0] = asker


def asker():
    return _asker[0]


# The user this process has proven (the GUI's login, a command's password), with when.
_proven: dict[str, float] = {}


def prove(user: str, at: float) -> None:
    _proven.clear()
    _proven[user] = at


def forget() -> None:
    """The login ends (the GUI's timeout, a logout): the next role-bound action asks again."""
    _proven.clear()


def proven_user() -> str | None:
    return next(iter(_proven), None)
