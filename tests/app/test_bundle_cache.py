"""The installed application's numba cache is keyed on each module's place in the bundle, never on
the working folder (the end-to-end check, a second start from another folder, is
installer/smoke-test.sh)."""

from __future__ import annotations

from app.bundle_cache import bundle_relative_dir


def test_a_module_s_cache_folder_is_its_place_in_the_bundle():
    assert bundle_relative_dir("core/sim/render.py", "/opt/photopft/_internal") == "core/sim"
    assert bundle_relative_dir("/opt/photopft/_internal/core/sim/render.py", "/opt/photopft/_internal") == "core/sim"
    assert bundle_relative_dir("./core/../core/volume/maps.py", None) == "core/core/volume"  # never above the cache
    assert bundle_relative_dir("/usr/lib/python3/numba/np/npyfuncs.py", "/opt/photopft/_internal") \
        == "usr/lib/python3/numba/np"
    assert bundle_relative_dir("launcher.py", "/opt/photopft/_internal") == "."


def test_a_cache_folder_that_cannot_be_written_leaves_the_temporary_folder(tmp_path, monkeypatch):
    """A read-only or full home must not stop the application: its kernels go to the temporary folder."""
    import tempfile

    from numba.core import config

    from app.bundle_cache import BundleCacheLocator
    from core.analysis import values

    writable = tmp_path / "cache"
    monkeypatch.setattr(config, "CACHE_DIR", str(writable))
    locator = BundleCacheLocator.from_function(values.least_tidal_l, "core/analysis/values.py")
    assert locator.get_cache_path() == str(writable / "core" / "analysis")
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    monkeypatch.setattr(config, "CACHE_DIR", str(blocked))
    locator = BundleCacheLocator.from_function(values.least_tidal_l, "core/analysis/values.py")
    assert locator.get_cache_path().startswith(tempfile.gettempdir())
    assert locator.get_cache_path().endswith("core/analysis")
