#!/usr/bin/env bash
# Install (or upgrade) photopft under /opt/photopft with a launcher and a menu entry. Run as root
# from the unpacked tarball. Patient records, sessions, settings and calibration profiles live in
# each user's XDG folders and are not touched by an upgrade.
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
prefix=${PREFIX:-/opt/photopft}
if [ -d "$prefix" ]; then
    rm -rf "$prefix.previous"
    mv "$prefix" "$prefix.previous"
fi
mkdir -p "$prefix"
cp -a "$here/photopft/." "$prefix/"
install -Dm644 "$here/photopft.svg" /usr/share/icons/hicolor/scalable/apps/photopft.svg
install -Dm644 "$here/photopft.desktop" /usr/share/applications/photopft.desktop
ln -sf "$prefix/photopft" /usr/local/bin/photopft
rm -rf "$prefix.previous"
echo "installed photopft in $prefix; start it from the menu or with: photopft gui"
