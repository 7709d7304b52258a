#!/usr/bin/env bash
# Smoke test of the built application: install the tarball into a scratch prefix, start it
# offscreen with --smoke-test (record a simulated session in the real window, process it, write its
# report) and check it exits 0. Usage: bash installer/smoke-test.sh [dist/photopft-*.tar.gz]
set -euo pipefail
cd "$(dirname "$0")/.."
tarball=${1:-$(ls -t dist/photopft-*-linux-*.tar.gz | head -1)}
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
tar -C "$scratch" -xzf "$tarball"
app=$(ls -d "$scratch"/photopft-*/photopft)/photopft
export HOME="$scratch/home" TMPDIR="$scratch" QT_QPA_PLATFORM=offscreen
mkdir -p "$HOME"
"$app" --version
started=$(date +%s)
"$app" gui --smoke-test "${SMOKE_SECONDS:-10}"
echo "smoke test passed in $(( $(date +%s) - started )) s"
# started again from another folder, it finds the kernels it compiled (app/bundle_cache.py)
cache="$HOME/.cache/photopft/numba"
compiled=$(find "$cache" -name '*.nbc' 2>/dev/null | wc -l)
[ "$compiled" -gt 0 ] || { echo "no compiled kernels in $cache"; exit 1; }
mkdir -p "$scratch/elsewhere"
(cd "$scratch/elsewhere" && "$app" gui --smoke-test "${SMOKE_AGAIN_SECONDS:-5}")
again=$(find "$HOME/.cache" -name '*.nbc' | wc -l)
[ "$again" -eq "$compiled" ] || {
    echo "started from another folder, it compiled again ($compiled kernels, then $again)"; exit 1; }
echo "second start from another folder: the $compiled compiled kernels found again"
