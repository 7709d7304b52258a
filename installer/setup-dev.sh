#!/usr/bin/env bash
# Set up photopft on Debian 12 from a checkout: system packages, a virtual environment in
# .venv and the Python packages. Safe to run again; run as root (or with sudo rights) for apt.
set -euo pipefail
cd "$(dirname "$0")/.."

# Aravis 0.8 (GigE Vision) through PyGObject, built against Debian 12's GLib; iproute2 for the
# tests' second loopback address; the libraries Qt's xcb and offscreen platforms load; Xvfb for
# screenshots and poppler-utils to look at reports.
SYSTEM_PACKAGES=(python3 python3-venv python3-dev gcc binutils pkg-config git iproute2
                 aravis-tools gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev
                 libegl1 libgl1 libfontconfig1 libdbus-1-3 libxkbcommon0 libxkbcommon-x11-0 libxcb-cursor0
                 libxcb-icccm4 libxcb-keysyms1 libxcb-shape0 libxcb-render-util0 libxcb-image0 libxcb-xinerama0
                 xvfb xauth poppler-utils)

as_root() {
    if [ "$(id -u)" -eq 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else return 1; fi
}

missing=()
for p in "${SYSTEM_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if [ ${#missing[@]} -gt 0 ]; then
    echo "setup: installing system packages: ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    as_root apt-get update -qq && as_root apt-get install -y -qq "${missing[@]}" >/dev/null \
        || { echo "setup: could not install ${missing[*]} (need root); install them and run again" >&2; exit 1; }
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    echo "setup: creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test,bench]'
echo "setup: done; the command is .venv/bin/photopft"
