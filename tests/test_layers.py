"""The layers' import contract (pyproject.toml, [tool.importlinter]): core/ and drivers/ never
import PySide6, pyqtgraph or the application; core/ does not import drivers/; no module of core but the
simulator imports the simulator (the science never sees the truth); no import cycles among the
application's modules; core's stages in layers (io, reconstruction and calibration, volume, analysis,
pipeline) with no cycle among them."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_import_contracts_are_kept():
    command = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or "lint-imports"
    run = subprocess.run([command, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "0 broken" in run.stdout


def test_the_truth_contract_covers_every_module_of_core():
    """The contract lists core's stages (import-linter has no 'all but core.sim'): a new module must
    sit in one of them, or the new stage be added to it."""
    import tomllib

    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    listed = next(c for c in contracts if c.get("forbidden_modules") == ["core.sim"])["source_modules"]
    modules = {".".join(p.relative_to(ROOT).with_suffix("").parts) for p in (ROOT / "core").rglob("*.py")
               if p.parent != ROOT / "core" or p.stem != "__init__"}
    modules = {m.removesuffix(".__init__") for m in modules if not m.startswith("core.sim")}
    uncovered = sorted(m for m in modules if not any(m == s or m.startswith(s + ".") for s in listed))
    assert not uncovered, uncovered


def test_no_science_reads_a_simulation_truth():
    """Only the simulator (core/sim) reads /truth for its values; core/io only reads, checks and
    recovers the file. The analysis, volume, reconstruction, calibration and pipeline never call it."""
    import re

    reading = re.compile(r"\.truth\(\)|\[\"truth\"\]|\btruth_values\b")
    readers = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "core").rglob("*.py")
                     if not p.is_relative_to(ROOT / "core" / "sim") and not p.is_relative_to(ROOT / "core" / "io")
                     and reading.search(p.read_text()))
    assert not readers, readers
