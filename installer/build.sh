#!/usr/bin/env bash
# Build the installable application: a PyInstaller one-folder bundle and a tarball that installs
# it under /opt/photopft. Run from a checkout after installer/setup-dev.sh:
#   bash installer/build.sh            -> dist/photopft-VERSION-linux-ARCH.tar.gz
set -euo pipefail
cd "$(dirname "$0")/.."
[ -x .venv/bin/python ] || bash installer/setup-dev.sh
.venv/bin/python -m pip install -q "pyinstaller>=6.10"
version=$(.venv/bin/python -c "from core import __version__; print(__version__)")
arch=$(uname -m)
started=$(date +%s)
rm -rf build/pyinstaller dist/photopft dist/stage
.venv/bin/pyinstaller --noconfirm --clean --log-level WARN --distpath dist --workpath build/pyinstaller \
    installer/photopft.spec
# hdf5plugin's filters come with their debug information (185 MB, libh5sz3 alone 95 MB): stripped of it
# (22 MB; the bundle 967 -> 804 MB), each checked to load still, else kept as it came. Not the other
# libraries: many were rewritten by patchelf, which binutils' strip breaks ("ELF load command
# address/offset not page-aligned": numba's OpenMP pool failed to load, and the layer numba fell back to
# aborted the live view's concurrent kernels)
shopt -s nullglob
for library in dist/photopft/_internal/hdf5plugin/plugins/*.so; do
    cp -p "$library" "$library.orig"
    strip --strip-debug "$library"
    if .venv/bin/python -c 'import ctypes, sys; ctypes.CDLL(sys.argv[1])' "$library"; then
        rm "$library.orig"
    else
        mv "$library.orig" "$library"
    fi
done
shopt -u nullglob
stage="dist/stage/photopft-$version"
mkdir -p "$stage"
cp -a dist/photopft "$stage/photopft"
cp installer/install.sh installer/uninstall.sh installer/photopft.desktop "$stage/"
cp resources/icons/photopft.svg "$stage/photopft.svg"
tarball="dist/photopft-$version-linux-$arch.tar.gz"
# gzip -1: 14 s against 34 s at the default level for the 967 MB bundle, the tarball 381 MB against 344 MB
tar -C dist/stage -I "gzip -1" -cf "$tarball" "photopft-$version"
rm -rf dist/stage
echo "built $tarball ($(du -sh dist/photopft | cut -f1) unpacked, $(du -h "$tarball" | cut -f1) packed) in $(( $(date +%s) - started )) s"
