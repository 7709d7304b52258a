"""Where the installed application (the PyInstaller bundle) keeps numba's compiled kernels.

numba keys its cache folder on each module's file name. In the bundle those names are relative
(`core/sim/render.py`), so numba's own user-wide locator put them under the working folder's hash:
started from another folder, the application compiled every kernel again (75 s before the first
height maps, measured 2026-11-27) and left one more copy in the user's cache. This locator keys
them on the module's place inside the bundle instead, under the user's cache folder
(NUMBA_CACHE_DIR), or the temporary folder where that cannot be written. installer/launcher.py names
it to numba (NUMBA_CACHE_LOCATOR_CLASSES), with numba's user-wide locator after it. numba's own stamp
stays: in a bundle it is the executable's hash, so a new build compiles afresh.
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import PurePosixPath

from numba.core import config
from numba.core.caching import _CacheLocator, _SourceFileBackedLocatorMixin

def bundle_relative_dir(py_file: str, bundle: str | None) -> str:
    """The folder of a module's file inside the bundle, as a relative POSIX path: relative names as
    they are, absolute ones inside the bundle from its root, any other absolute one whole (its root
    dropped), so that it never depends on the working folder."""
    path = PurePosixPath(py_file.replace(os.sep, "/"))
    if path.is_absolute():
        if bundle:
            try:
                path = path.relative_to(PurePosixPath(bundle.replace(os.sep, "/")))
            except ValueError:
                path = path.relative_to(path.anchor)
        else:
            path = path.relative_to(path.anchor)
    parts = [p for p in path.parent.parts if p not in ("", ".", "..")]
    return "/".join(parts) or "."


class BundleCacheLocator(_SourceFileBackedLocatorMixin, _CacheLocator):
    """numba's cache of one function at NUMBA_CACHE_DIR / (its module's folder inside the bundle)."""

    def __init__(self, py_func, py_file, root: str):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        relative = bundle_relative_dir(py_file, getattr(sys, "_MEIPASS", None))
        self._cache_path = os.path.join(root, *relative.split("/"))

    def get_cache_path(self):
        return self._cache_path

    @classmethod
    def from_function(cls, py_func, py_file):
        """In the user's cache folder; where that cannot be written (a read-only or full home), in the
        temporary folder, compiled again at each start but running; None where neither can be."""
        roots = [config.CACHE_DIR] if config.CACHE_DIR else []
        roots.append(os.path.join(tempfile.gettempdir(), f"photopft-numba-{os.getuid()}"))
        for root in roots:
            locator = cls(py_func, py_file, root)
            try:
                locator.ensure_cache_path()
            except OSError:
                continue
            return locator
        return None
