"""photopft bench integration: both integrators' errors on the real bear; a wrong folder named."""

from __future__ import annotations

import re

import pytest

from benchmarks.integration import run_integration


def test_integration_bench_reports_both_integrators_on_real_data(shared_data):
    text = run_integration(shared_data / "diligent-integration" / "bear", write=False, repeat=1)
    errors = [float(e) for e in re.findall(r"\| ([0-9.]+) \| [0-9.]+ % \|", text)]
    assert len(errors) == 2
    assert errors[0] <= 0.1 and 2.0 <= errors[1] <= 3.6  # accurate 0.058 mm; the plain DCT 3.3-3.5 mm


def test_integration_bench_names_a_folder_without_the_data(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing normal_map.png"):
        run_integration(tmp_path, write=False)
