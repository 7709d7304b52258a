"""The error a session file that cannot be read or written raises: here, below both the session's
reader and writer (core/io/session.py) and the probe that opens a file first (core/io/hdf5_probe.py)."""

from __future__ import annotations


class SessionError(Exception):
    """A session file that cannot be read or written as the spec says; the message names the item."""
