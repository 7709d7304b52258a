#!/usr/bin/env bash
# Remove the installed program. Each user's patient records, sessions, settings, calibration
# profiles and logs stay in ~/.local/share/photopft, ~/.config/photopft and ~/.local/state/photopft.
set -euo pipefail
prefix=${PREFIX:-/opt/photopft}
rm -rf "$prefix"
rm -f /usr/local/bin/photopft /usr/share/applications/photopft.desktop \
      /usr/share/icons/hicolor/scalable/apps/photopft.svg
echo "removed photopft from $prefix (user data kept)"
