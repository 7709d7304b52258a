"""Entry point of the installed application (PyInstaller): the `photopft` command line."""

import multiprocessing
import os
import sys
from pathlib import Path

if getattr(sys, "frozen", False):
    # numba keeps its compiled functions in the user's cache folder (the bundle is read-only), keyed
    # on each module's place in the bundle whatever the working folder (app/bundle_cache.py)
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "photopft" / "numba"
    os.environ.setdefault("NUMBA_CACHE_DIR", str(cache))
    os.environ.setdefault("NUMBA_CACHE_LOCATOR_CLASSES", "app.bundle_cache.BundleCacheLocator,UserWideCacheLocator")
    # Aravis' typelib and libraries travel in the bundle
    bundle = Path(sys._MEIPASS)
    os.environ["GI_TYPELIB_PATH"] = os.pathsep.join(
        p for p in (str(bundle / "gi_typelibs"), os.environ.get("GI_TYPELIB_PATH", "")) if p)

# the live engine runs in a spawned process of this same executable (app/engine/process.py)
multiprocessing.freeze_support()

from app.cli import main  # noqa: E402

sys.exit(main())
