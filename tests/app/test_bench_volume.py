"""photopft bench volume: its pass/fail limit."""

from __future__ import annotations

from benchmarks.volume import within_limit


def test_volume_bench_limit_is_three_percent_or_50_ml():
    assert within_limit(0.545, 0.500) and not within_limit(0.551, 0.500)  # 50 mL governs small volumes
    assert within_limit(5.14, 5.00) and not within_limit(5.16, 5.00)  # 3 % governs large ones
