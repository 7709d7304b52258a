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
