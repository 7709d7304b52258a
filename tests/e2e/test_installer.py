"""The installable application: installer/build.sh builds the PyInstaller bundle and tarball,
installer/smoke-test.sh unpacks it into a scratch folder and runs `photopft gui --smoke-test`
offscreen (record a simulated session in the real window, process it, report it)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow


def test_build_install_and_smoke_test():
    build = subprocess.run(["bash", "installer/build.sh"], cwd=ROOT, capture_output=True, text=True, timeout=1800)
    assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-4000:]
    assert "built dist/photopft-" in build.stdout
    tarball = sorted(ROOT.glob("dist/photopft-*-linux-*.tar.gz"))[-1]
    smoke = subprocess.run(["bash", "installer/smoke-test.sh", str(tarball)], cwd=ROOT, capture_output=True,
                           text=True, timeout=900, env={**os.environ, "SMOKE_SECONDS": "5", "SMOKE_AGAIN_SECONDS": "2"})
    assert smoke.returncode == 0, smoke.stdout[-3000:] + smoke.stderr[-3000:]
    assert "smoke test passed" in smoke.stdout and "report" in smoke.stdout
    assert "compiled kernels found again" in smoke.stdout
