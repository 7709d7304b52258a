"""PyInstaller hook: Aravis 0.8 (GigE Vision) through GObject introspection, its typelib and
shared library, and the GObject, Gio and GLib typelibs it depends on."""

from PyInstaller.utils.hooks.gi import GiModuleInfo

module_info = GiModuleInfo("Aravis", "0.8")
if module_info.available:
    binaries, datas, hiddenimports = module_info.collect_typelib_data()
    hiddenimports += ["gi.repository.GObject", "gi.repository.Gio", "gi.repository.GLib"]
