"""Where the installed application (the PyInstaller bundle) keeps numba's compiled kernels.

numba keys its cache folder on each module's file name. In the bundle those names are relative
(`core/sim/render.py`), so numba's own user-wide locator put them under the working folder's hash:
started from another folder, the application compiled every kernel again (75 s before the first
height maps, measured 2026-11-27) and left one more copy in the user's cache. This locator keys
them on the module's place inside the bundle instead, under the user's cache folder
(NUMBA_CACHE_DIR), or a temporary folder of the process's own where that cannot be written.
installer/launcher.py names it to numba (NUMBA_CACHE_LOCATOR_CLASSES), with numba's user-wide
locator after it. numba's own stamp stays: in a bundle it is the executable's hash, so a new build
compiles afresh.
"""

from __future__ import annotations

import atexit
import functools
import os
import shutil
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
        root = PurePosixPath(bundle.replace(os.sep, "/")) if bundle else None
        path = path.relative_to(root if root is not None and path.is_relative_to(root) else path.anchor)
    parts = [p for p in path.parent.parts if p not in ("", ".", "..")]
    return "/".join(parts) or "."


@functools.cache
def _private_temporary_root() -> str:
    """A folder of this process's own (mode 0700, removed at exit): compiled kernels are loaded as
    pickles, so never from a shared temporary path another user could have made first."""
    root = tempfile.mkdtemp(prefix="photopft-numba-")
    atexit.register(shutil.rmtree, root, True)
    return root


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
        """In the user's cache folder; where that cannot be written (a read-only or full home), in a
        temporary folder of the process's own, compiled again at each start but running; None where
        neither can be."""
        for root in ([config.CACHE_DIR] if config.CACHE_DIR else []) + [None]:
            try:
                locator = cls(py_func, py_file, root if root is not None else _private_temporary_root())
                locator.ensure_cache_path()
            except OSError:
                continue
            return locator
        return None
