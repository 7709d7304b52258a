"""Rendered sessions kept for the population bench (`bench population --renders DIR`): a subject's
sphere sessions and its protocol, keyed by everything that sets them, so that a rerun after a change
to the reconstruction, the volume or the analysis costs calibration and processing only. The light
calibration made from the sphere sessions is kept the same way, keyed by them and by the code that
calibrates (CALIBRATION_SOURCES): a change to the volume or the analysis costs processing only.

A render is one folder DIR/<key>/ holding the session files and `rendered.json` (what was rendered,
by which commit); it is made under a temporary name and renamed when whole, so a run stopped midway
leaves nothing that looks kept. The least recently used renders are removed while the folder holds
more than its budget; only folders with a `rendered.json` are ever removed.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import time
from pathlib import Path
from typing import Callable


MARK = "rendered.json"
# what sets a rendered session besides its arguments: the simulator, the rig and the file it writes
SIMULATOR_SOURCES = ("core/sim", "core/rig.py", "core/io/session.py", "core/io/errors.py", "core/io/outputs.py")


# what sets a light calibration besides its sphere sessions: the calibration, the reconstruction it runs
# on the spheres, and the readers of the session and the rig
CALIBRATION_SOURCES = ("core/calibration", "core/reconstruction", "core/io", "core/rig.py")


@functools.cache


def simulator_digest() -> str:
    """A digest of the simulator's code (SIMULATOR_SOURCES): a render is reused only by the code that made it."""
    return code_digest(SIMULATOR_SOURCES)


@functools.cache


def code_digest(sources: tuple[str, ...]) -> str:
    """A digest of the code in `sources` (folders and files of the checkout, their Python files)."""
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for source in sources:
        path = root / source
        files = sorted(path.rglob("*.py")) if path.is_dir() else [path]
        for file in files:
            digest.update(str(file.relative_to(root)).encode())
            digest.update(file.read_bytes())
    return digest.hexdigest()[:16]


def render_key(what: dict) -> str:
    """The key of a render: its arguments (JSON-able) and the simulator's code."""
    text = json.dumps({**what, "simulator": simulator_digest()}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


class RenderCache:
    def __init__(self, folder: Path, max_bytes: float) -> None:
        self.folder = Path(folder)
        self.max_bytes = max_bytes
        self.folder.mkdir(parents=True, exist_ok=True)

    def rendered(self, what: dict, render: Callable[[Path], None], commit: str) -> tuple[Path, dict]:
        """(the folder holding the render of `what`, its mark): kept, or made now by `render(folder)`
        (which writes the session files into the folder it is given)."""
        key = render_key(what)
        target = self.folder / key
        mark = target / MARK
        if mark.is_file():
            try:
                kept = json.loads(mark.read_text())
            except (OSError, ValueError):
                kept = None
            if kept is not None and kept.get("what") == what:
                os.utime(mark)  # recently used: pruned last
                return target, kept
            shutil.rmtree(target)  # damaged, or another render under the same key: ours to replace
        partial = self.folder / f".{key}.{os.getpid()}.partial"
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir()
        started = time.perf_counter()
        try:
            render(partial)
            made = {"what": what, "commit": commit, "simulator": simulator_digest(),
                    "seconds": time.perf_counter() - started}
            (partial / MARK).write_text(json.dumps(made))
            try:
                partial.rename(target)
            except OSError:  # another worker rendered it meanwhile: theirs is as good
                shutil.rmtree(partial)
                made = json.loads(mark.read_text())
        except BaseException:
            shutil.rmtree(partial, ignore_errors=True)
            raise
        self.prune(keep=target)
        return target, made

    def renders(self) -> list[tuple[float, int, Path]]:
        """(last used, bytes, folder) of every whole render, least recently used first."""
        out = []
        for folder in self.folder.iterdir():
            mark = folder / MARK
            if folder.is_dir() and not folder.name.startswith(".") and mark.is_file():
                size = sum(f.stat().st_size for f in folder.iterdir() if f.is_file())
                out.append((mark.stat().st_mtime, size, folder))
        return sorted(out)

    def prune(self, keep: Path | None = None) -> list[Path]:
        """The least recently used renders removed until the rest fit max_bytes (never `keep`)."""
        renders = self.renders()
        total = sum(size for _, size, _ in renders)
        removed = []
        for _, size, folder in renders:
            if total <= self.max_bytes:
                break
            if folder == keep:
                continue
            shutil.rmtree(folder)
            total -= size
            removed.append(folder)
        return removed
