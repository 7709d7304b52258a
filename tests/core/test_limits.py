"""A refusal never writes the refused value as its own limit."""

import numpy as np

from core.limits import past_limit
from core.pipeline.quality import MAX_HIDDEN_MAPS, WORKING_RANGE_MM, distance_refusal, occlusion_refusal, reflectance_refusal


def test_a_value_past_its_limit_gets_the_decimals_that_tell_them_apart():
    assert past_limit(116.2, 115.0) == "116"
    assert past_limit(115.04, 115.0) == "115.04"
    assert past_limit(5.3, 5.0) == "5.3"
    assert past_limit(0.0404, 0.04, 2) == "0.0404"
    assert past_limit(-3.0, 0.0) == "-3"


def test_refusals_just_past_their_limits_read_past_them():
    """A subject with an arm against the trunk in 5.3 % of its maps read "in 5 % of the maps"."""
    hidden = np.zeros(1000)
    hidden[: int(1000 * MAX_HIDDEN_MAPS) + 3] = 0.5
    arm = occlusion_refusal({"front": hidden})
    assert f"in {100 * (MAX_HIDDEN_MAPS + 0.003):.1f} % of the maps" in arm.reason
    far = distance_refusal({"front": WORKING_RANGE_MM[1] + 0.3})
    assert f"{WORKING_RANGE_MM[1] + 0.3:.1f} mm" in far.reason
    assert "0.0404 of its albedo" in reflectance_refusal({"back": 0.0404}).reason
