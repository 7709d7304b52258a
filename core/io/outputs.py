"""Writing outputs without losing anything: never over an input or a recording, never half-written.

`check_output` decides whether a command may write a path at all; `atomic_output` gives the
writer a temporary file in the same folder and renames it into place only when the writer has
finished, so an interrupted command (an error, Ctrl-C, SIGTERM) leaves the old file, or none.
"""

from __future__ import annotations

import os
import re
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterable, Iterator

SESSION_FORMAT = "photopft-session"


class OutputError(Exception):
    """An output the command must not write; the message names the file and why."""


_stop_requested: list[BaseException] = []


def request_stop(reason: BaseException) -> None:
    """Called from a signal handler: no output is put in place after this, even where the handler's
    exception was swallowed (a signal that lands in a C callback, as numba's compiler has)."""
    _stop_requested.append(reason)


def stop_if_requested() -> None:
    """Raises the stop a signal asked for, where the handler's own exception was swallowed: long
    loops call this once a step, so a stop never waits for the end of the work."""
    reason = requested_stop()
    if reason is not None:
        raise reason if isinstance(reason, BaseException) else KeyboardInterrupt()


def requested_stop() -> BaseException | None:
    """The stop a signal asked for in this command, or None."""
    return _stop_requested[-1] if _stop_requested else None


def clear_stop() -> None:
    _stop_requested.clear()


def is_session_file(path: str | os.PathLike) -> bool:
    """True for an HDF5 file that says it is a photopft session (a recording: never replaced)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != b"\x89HDF\r\n\x1a\n":
                return False
    except OSError:
        return False
    # here, not at the top: the command line imports this module at start-up, and h5py takes a while
    import h5py

    from core.io.hdf5_probe import probe

    probe(path)
    try:
        with h5py.File(path, "r", locking=False) as f:
            value = f.attrs.get("format", b"")
    except (OSError, RuntimeError, ValueError):
        return True  # an HDF5 file we cannot read may be a recording cut off: treat it as one
    return (value.decode() if isinstance(value, bytes) else str(value)) == SESSION_FORMAT


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def ask_on_terminal(question: str) -> bool:
    """Ask a yes/no question when a person is at a terminal; False when nobody can answer."""
    if not (sys.stdin is not None and sys.stdin.isatty() and sys.stderr.isatty()):
        return False
    print(f"{question} [y/N] ", end="", file=sys.stderr, flush=True)
    try:
        return sys.stdin.readline().strip().lower() in ("y", "yes")
    except (OSError, KeyboardInterrupt):
        return False


def check_output(output: str | os.PathLike, inputs: Iterable[str | os.PathLike] = (), *, force: bool = False,
                 replaceable: bool = True, ask: Callable[[str], bool] = ask_on_terminal) -> Path:
    """Raise OutputError unless `output` may be written.

    Refused always: an output that is one of the inputs, an existing recorded session, a folder,
    a folder that does not exist. An existing file of another kind is replaced only with `force`
    or a yes at the terminal; `replaceable=False` (a new recording) refuses any existing file.
    """
    output = Path(output)
    resolved = output.resolve()
    for source in inputs:
        source = Path(source)
        if resolved == source.resolve() or _same_file(output, source):
            raise OutputError(f"{output} is also an input of this command: refusing to write over it")
    if not resolved.parent.is_dir():
        raise OutputError(f"cannot write {output}: the folder {output.parent} does not exist")
    if output.is_dir():
        raise OutputError(f"cannot write {output}: it is a folder")
    if output.exists() or output.is_symlink():
        if is_session_file(output):
            raise OutputError(f"{output} is a recorded session and is never replaced: choose another name")
        if not replaceable:
            raise OutputError(f"{output} exists: choose another name (this command never replaces a file)")
        if not force and not ask(f"{output} exists: replace it?"):
            raise OutputError(f"{output} exists: use --force to replace it")
    return output


def next_free_path(path: str | os.PathLike) -> Path:
    """`path` if nothing is there, else NAME-2.EXT, NAME-3.EXT, ...: a new file never takes an old one's name."""
    path = Path(path)
    candidate, k = path, 2
    while candidate.exists() or candidate.is_symlink():
        candidate = path.with_name(f"{path.stem}-{k}{path.suffix}")
        k += 1
    return candidate


def partial_path(output: str | os.PathLike) -> Path:
    """The temporary name an output is written under until it is complete (same folder, hidden)."""
    output = Path(output)
    return output.with_name(f".{output.stem}.{os.getpid()}.partial{output.suffix}")


_PARTIAL = re.compile(r"\.(?P<stem>.+)\.(?P<pid>[0-9]+)\.partial(?P<suffix>\.[^.]*)?")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # another user's process
    return True


def remove_dead_partials(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary outputs (`partial_path`) that a process now dead left in `folder` (a
    command killed with SIGKILL, a machine that lost power); those of live processes are kept.
    Called before each new output, so the next run of a verb cleans up after the one that died."""
    removed = []
    try:
        names = os.listdir(folder)
    except OSError:
        return removed
    for name in names:
        match = _PARTIAL.fullmatch(name)
        if match is None or int(match["pid"]) == os.getpid() or _alive(int(match["pid"])):
            continue
        path = Path(folder) / name
        try:
            if path.is_file() and not path.is_symlink():
                path.unlink()
                removed.append(path)
        except OSError:
            pass
    return removed


@contextmanager
def atomic_output(output: str | os.PathLike, *, replace_session: bool = False,
                  private: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside `output`; rename it onto `output` when the block ends without
    an exception, remove it otherwise (KeyboardInterrupt and SystemExit included). A recorded
    session at `output` is refused unless `replace_session` (a recovery, which keeps it aside).
    `private`: the file is readable and writable by its owner only (0600; identified data), from
    before its first byte to its place."""
    output = Path(output)
    if not replace_session and is_session_file(output):
        raise OutputError(f"{output} is a recorded session and is never replaced: choose another name")
    remove_dead_partials(output.parent)
    partial = partial_path(output)
    if private:
        os.close(os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600))
        os.chmod(partial, 0o600)
    try:
        yield partial
        if _stop_requested:
            raise _stop_requested[0]
        if not partial.exists():
            raise OutputError(f"{output} was not written")
        if private:
            os.chmod(partial, 0o600)  # a writer that made the file anew gets the umask's mode
        os.replace(partial, output)
    finally:
        try:
            partial.unlink()
        except FileNotFoundError:
            pass


def write_text_atomic(output: str | os.PathLike, text: str) -> Path:
    """Write a whole text file (a profile, a CSV) through `atomic_output`."""
    with atomic_output(output) as partial:
        partial.write_text(text, encoding="utf-8")
    return Path(output)
