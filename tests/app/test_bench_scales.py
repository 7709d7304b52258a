"""photopft bench scales: a body's slopes set side by side, and what it says of a scale that gave none."""

from __future__ import annotations

import math

import pytest

from benchmarks.scales import ScaleRow, named_body, scales_table, slope_spread


def test_the_spread_is_the_largest_slope_over_the_smallest():
    assert slope_spread([1.00, 1.02, 1.01]) == pytest.approx(0.02)
    assert slope_spread([0.95, float("nan"), 0.96]) == pytest.approx(0.96 / 0.95 - 1)  # a refused scale left out
    assert math.isnan(slope_spread([1.0, float("nan")]))  # one slope: nothing to compare


def test_the_table_gives_each_body_its_spread_and_each_refusal_its_reason():
    rows = [ScaleRow("torso", 0.25, 100, 1.010, 0.999, 0.02), ScaleRow("torso", 0.5, 100, 1.015, 0.999, 0.02),
            ScaleRow("random-1004", 0.25, 100, 0.95, 0.99, 0.04), ScaleRow("random-1004", 0.5, 100, 0.97, 0.99, 0.04),
            ScaleRow("child", 0.25, 80, refused="an arm lies against the trunk"), ScaleRow("child", 0.5, 80, 1.0)]
    text = scales_table(rows, "vc", None, 1, 10.0)
    assert "| torso | 0.5 | 700 x 512 | 100 | 1.0150 |" in text
    assert "- torso: slopes spread by 0.50 % (within the 1 %)" in text
    assert "- random-1004: slopes spread by 2.11 % (outside the 1 %)" in text
    assert "an arm lies against the trunk |" in text
    assert "- child: slopes spread by not measured: fewer than two scales give a volume" in text


def test_population_bodies_are_named_by_their_seed():
    assert named_body("random-1004", 1).name == "random-1004"
    assert named_body("average-man", 1).name == "average-man"
    with pytest.raises(ValueError, match="unknown body"):
        named_body("random-x", 1)


def test_a_wrong_scale_or_body_gets_one_line_before_any_rendering(capsys):
    from app.cli import main

    assert main(["bench", "scales", "--scales", "0.5,0", "--no-write"]) == 2
    assert capsys.readouterr().err.strip().endswith("must be a positive finite number, got 0")
    assert main(["bench", "scales", "--bodies", "torso,nobody", "--no-write"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("photopft bench: error: --scales 0.25,0.5,1 --bodies torso,nobody: unknown body 'nobody'")
    assert "\n" not in err
