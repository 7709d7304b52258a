"""The rules that refuse or withhold the optical volume of a processed session: where the subject
stands, what hides or cuts off the trunk's sides, a sheen or bent maps, too little trunk; and the
words that say what the volume left out. `process` (core/pipeline/process.py) and the live view's
checks (core/pipeline/live_checks.py) apply them; each returns a Refusal (core/limits.py: its rule's
code, what was measured, what the operator should do), or None.
"""

from __future__ import annotations

import numpy as np

from core.limits import Refusal, past_limit
from core.volume.metric import (MAX_JUMP_SHARE, MAX_MAP_NOISE_L, MAX_SCALE_MISMATCH, MetricVolume,
                                jump_share)
from core.volume.noise import curve_noise_l
from core.volume.sides import MAX_SIDES_TILT
from core.volume.steps import step_spans_s

# what the operator is told to do, rule by rule
HOLD_ARMS_AWAY = "ask the patient to hold the arms away from the body, and record again"
STAND_IN_VIEW = "centre the patient between the heads, wholly in both views, and record again"
SKIN_OR_LIGHTS = ("dry the skin (a towel) or fit crossed polarisers on the LEDs and the lens; if the heads were "
                  "moved, calibrate the lights again")
STAND_STILL = "record again with the patient standing still; if it recurs, calibrate the lights again"

# Outside this a measured distance is a measurement gone wrong, not a subject (docs/reconstruction.md).
WORKING_RANGE_MM = (1500.0, 2600.0)


# The share of the trunk's rows an occluding contour may cross (core/reconstruction/pipeline.py,
# occluded_side_share) in a head's typical map before its sides count as hidden by an arm
MAX_OCCLUDED_SIDE_SHARE = 0.2


# Past this share of a head's maps with an arm hiding the sides, the session is refused (docs/constants.md)
MAX_HIDDEN_MAPS = 0.25


MAX_OUT_OF_VIEW_MAPS = 0.05  # the share of a head's maps that may show the trunk running out of the image


# The least trunk area (m^2) a head's typical map must hold for a volume: a 6-year-old's trunk from
# shoulders to hips is about 0.06 m^2 seen from one side
MIN_TRUNK_AREA_M2 = 0.03


def distance_refusal(distances_mm: dict[str, float]) -> Refusal | None:
    """Why the optical volume cannot be reported from these heads' subject distances, or None."""
    lo, hi = WORKING_RANGE_MM
    for name, distance in distances_mm.items():
        if not np.isfinite(distance):
            return Refusal("no-distance", f"head {name}: no subject distance was measured", STAND_IN_VIEW)
        if not lo <= distance <= hi:
            measured = past_limit(distance, lo if distance < lo else hi)
            return Refusal("working-range",
                           f"head {name}: the subject measured at {measured} mm, outside the rig's working range "
                           f"{lo:.0f}-{hi:.0f} mm (a subject out of place, or skin or lights the calibration does "
                           "not describe)",
                           "place the patient on the marks between the heads and record again; if the patient "
                           "stood there, calibrate the lights again")
    return None


# The most sheen (over the albedo, a head's median) before uncalibrated litres are refused (docs/constants.md)
MAX_SHEEN = 0.04


def reflectance_refusal(sheen_by_head: dict[str, float]) -> Refusal | None:
    """Why the optical volume cannot be reported from heads whose maps show more sheen than
    MAX_SHEEN (the median of their maps' sheen_relative_to_albedo), or None. The sheen, which the
    Lambertian model leaves out, bends the normals and with them the maps: on one body a sheen of
    0.01 put the volume 2.6 % low, one with a broad lobe (exponent 5) of 0.05 3.2 % high. Lights far
    from where the calibration puts them (the drawing's, without their axes and falloff) read as a
    sheen too."""
    for name, sheen in sheen_by_head.items():
        if np.isfinite(sheen) and sheen > MAX_SHEEN:
            return Refusal("sheen", f"head {name}: the shading does not follow the light model: a sheen on the skin "
                           f"{past_limit(sheen, MAX_SHEEN, 2)} of its albedo (at most {MAX_SHEEN:.2f}) bends the maps, "
                           "so the volume would be off by percents (oily or sweaty skin, or lights not where the "
                           "calibration puts them)", SKIN_OR_LIGHTS)
    return None


def coverage_refusal(areas_m2: dict[str, np.ndarray]) -> Refusal | None:
    """Why the optical volume cannot be reported from heads whose maps hold too little of the trunk."""
    for name, area in areas_m2.items():
        area = np.asarray(area, dtype=float)
        typical = float(np.nanmedian(area)) if np.isfinite(area).any() else 0.0
        if typical < MIN_TRUNK_AREA_M2:
            held = past_limit(1e4 * typical, 1e4 * MIN_TRUNK_AREA_M2)
            return Refusal("too-little-trunk",
                           f"head {name}: its maps hold {held} cm^2 of the subject, fewer valid pixels than a trunk "
                           f"({1e4 * MIN_TRUNK_AREA_M2:.0f} cm^2 at least): the subject out of view, covered or unlit",
                           "uncover the trunk and " + STAND_IN_VIEW)
    return None


def session_refusal(distances_mm: dict[str, float], areas_m2: dict[str, np.ndarray],
                    occluded_share: dict[str, np.ndarray], out_of_view_share: dict[str, np.ndarray]) -> Refusal | None:
    """The first reason the session's optical signal itself is lost, or None. An arm against the
    trunk comes first: with two heads it also moves both distances, by hundreds of mm (population
    subject 2 of seed 1 was refused as 2658 mm away, out of the working range, at 2255 mm with its
    arms close; docs/volume.md), and the trunk's area with them."""
    return (occlusion_refusal(occluded_share, out_of_view_share) or distance_refusal(distances_mm)
            or coverage_refusal(areas_m2))


def shading_refusal(sheen_by_head: dict[str, float], tilts: np.ndarray) -> Refusal | None:
    """Why maps bent by a sheen on the skin or against each other cannot give litres without the subject's
    calibration, or None: the bend changes the volume's scale, which a calibration on the subject takes
    and a population's gain does not."""
    return reflectance_refusal(sheen_by_head) or bend_refusal(tilts)


def _first_hidden(shares_by_head: dict[str, np.ndarray], limit: float) -> tuple[str, float] | None:
    """(head, share of its maps) of the first head whose maps show more than MAX_OCCLUDED_SIDE_SHARE of
    the trunk's rows hidden in more than `limit` of them, or None."""
    for name, shares in shares_by_head.items():
        shares = np.asarray(shares, dtype=float)
        hidden = float(np.mean(~sides_shown(shares))) if len(shares) else 0.0
        if hidden > limit:
            return name, hidden
    return None


def sides_shown(hidden_share: np.ndarray) -> np.ndarray:
    """Per map (or for one), whether the trunk's sides are seen: at most MAX_OCCLUDED_SIDE_SHARE of its
    rows hidden (by an arm, `occluded_side_share`; or cut off by the image, `side_out_of_view_share`).
    A map without the share measured counts as shown."""
    return ~(np.asarray(hidden_share, dtype=float) > MAX_OCCLUDED_SIDE_SHARE)


def maps_left_out_words(displacements: dict, sides: dict[str, np.ndarray], in_step: dict[str, np.ndarray],
                        arm_in_outline: dict[str, np.ndarray]) -> str:
    """What the volume left out and why, for /@maps_left_out: the maps an arm hid the sides of, the
    maps whose trunk outline took in an arm (core/volume/metric.py, arm_in_outline) and the maps in a
    step (core/volume/steps.py), each head's share; "" when none."""
    def shares(masks: dict[str, np.ndarray]) -> str:
        return ", ".join(f"head {n} {100 * float(np.mean(m)):.1f} % of its maps" for n, m in masks.items())

    parts = []
    if any((~m).any() for m in sides.values()):
        parts.append("an arm against the trunk hid its sides: " + shares({n: ~m for n, m in sides.items()}))
    if any(m.any() for m in arm_in_outline.values()):
        parts.append("an arm was taken into the trunk's outline: " + shares(arm_in_outline))
    if any(m.any() for m in in_step.values()):
        first = next(iter(displacements))
        spans = step_spans_s(displacements[first].timestamp_ns, in_step[first]) or [
            span for n in in_step for span in step_spans_s(displacements[n].timestamp_ns, in_step[n])]
        at = ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in spans)
        parts.append(f"the subject stepped ({at}): " + shares(in_step))
    return "; ".join(parts)


def _share_of_maps(hidden: float, limit: float) -> str:
    """A share of maps past `limit`, in percent, as a refusal writes it."""
    return past_limit(100 * hidden, 100 * limit)


def occlusion_refusal(occluded_share: dict[str, np.ndarray], out_of_view_share: dict[str, np.ndarray] | None = None,
                      ) -> Refusal | None:
    """Why the optical volume cannot be reported from heads whose trunk's sides an arm hides or the
    image cuts off in more than MAX_HIDDEN_MAPS (MAX_OUT_OF_VIEW_MAPS) of their maps, or None. The shares are per map
    (core/reconstruction/pipeline.py): an arm that swings against the trunk now and then changes the trunk's
    outline from map to map, and the volume with it."""
    if (arm := _first_hidden(occluded_share, MAX_HIDDEN_MAPS)) is not None:
        name, hidden = arm
        return Refusal("arm-against-trunk", f"head {name}: an arm lies against the trunk (along more than "
                       f"{100 * MAX_OCCLUDED_SIDE_SHARE:.0f} % of its height) in "
                       f"{_share_of_maps(hidden, MAX_HIDDEN_MAPS)} % of the maps and hides the sides the volume is "
                       "referred to", HOLD_ARMS_AWAY)
    if (edge := _first_hidden(out_of_view_share or {}, MAX_OUT_OF_VIEW_MAPS)) is not None:
        name, hidden = edge
        return Refusal("trunk-out-of-view", f"head {name}: the trunk runs out of the image at the side in "
                       f"{_share_of_maps(hidden, MAX_OUT_OF_VIEW_MAPS)} % of the maps (the patient off centre or too "
                       "near): the sides the volume is referred to are not seen", STAND_IN_VIEW)
    return None


def outline_refusal(arm_in_outline: dict[str, np.ndarray]) -> Refusal | None:
    """Why the optical volume cannot be reported from heads whose trunk outline took in an arm
    (core/volume/metric.py, arm_in_outline) in more than MAX_HIDDEN_MAPS of their maps, or None: such
    maps are left out, and a volume of the few left would be mostly gaps."""
    for name, arm in arm_in_outline.items():
        share = float(np.mean(arm)) if len(arm) else 0.0
        if share > MAX_HIDDEN_MAPS:
            return Refusal("arm-in-outline", f"head {name}: an arm was taken into the trunk's outline in "
                           f"{_share_of_maps(share, MAX_HIDDEN_MAPS)} % of the maps (at most "
                           f"{100 * MAX_HIDDEN_MAPS:.0f} %), and the trunk's sides with it", HOLD_ARMS_AWAY)
    return None


def geometric_distance_refusal(occluded_share: dict[str, np.ndarray]) -> Refusal | None:
    """Why the two heads' geometry cannot give the subject's distance, or None: it is measured
    between the trunk's sides, and an arm against the trunk in one head's view hides them from both.
    The front head of population subject 2 (seed 1) kept the arms in its trunk and the back head cut
    them off at the crease beside them: 1845 and 2586 mm for a true 2195 and 2139 (docs/history/volume-log.md,
    "An arm against the trunk moves the two heads' distances")."""
    if (arm := _first_hidden(occluded_share, MAX_HIDDEN_MAPS)) is None:
        return None
    name, hidden = arm
    return Refusal("arm-hides-distance", f"an arm lies against the trunk in head {name}'s view in "
                   f"{_share_of_maps(hidden, MAX_HIDDEN_MAPS)} % of the maps: the two heads' distances are measured "
                   "between the trunk's sides, which it hides", HOLD_ARMS_AWAY)


def bend_refusal(tilts: np.ndarray) -> Refusal | None:
    """Why the optical volume cannot be reported from maps whose sides the two heads place at
    depths that drift apart along the trunk's height by more than MAX_SIDES_TILT (the median over
    the pairs of maps compared, core/volume/sides.py paired_tilts), or None."""
    tilts = np.asarray(tilts, dtype=float)
    tilts = tilts[np.isfinite(tilts)]
    if not len(tilts):
        return None
    tilt = float(np.median(tilts))
    if abs(tilt) <= MAX_SIDES_TILT:
        return None
    apart = past_limit(100 * abs(tilt), 100 * MAX_SIDES_TILT)
    return Refusal("bent-maps", f"the front and back maps disagree on the depth of the trunk's sides by {apart} mm "
                   f"more for every 100 mm of its height (at most {100 * MAX_SIDES_TILT:.0f} mm): the maps are bent "
                   "(a sheen on the skin, lights the calibration does not describe), and their volume would not be "
                   "the breathing's", SKIN_OR_LIGHTS)


def volume_refusal(metric: MetricVolume) -> Refusal | None:
    """Why this optical volume cannot be reported, or None: a curve noisier from map to map than
    MAX_MAP_NOISE_L, one that jumps away and back in more than MAX_JUMP_SHARE of its maps (jump_share),
    or a head whose maps had to be rescaled by more than MAX_SCALE_MISMATCH to put their sides where the
    two heads' trunk widths put them."""
    noise = curve_noise_l(metric.volume_l)
    if noise > MAX_MAP_NOISE_L:
        noisy = past_limit(1000 * noise, 1000 * MAX_MAP_NOISE_L)
        return Refusal("noisy-volume", f"the optical volume's noise from map to map is {noisy} mL (at most "
                       f"{1000 * MAX_MAP_NOISE_L:.0f} mL for values within tolerance): its values would be the "
                       "noise's", STAND_STILL)
    share, largest = jump_share(metric.timestamp_ns, metric.volume_l)
    if share > MAX_JUMP_SHARE:
        return Refusal("jumping-volume", f"the optical volume jumps away and back (up to {1000 * largest:.0f} mL) "
                       f"in {past_limit(100 * share, 100 * MAX_JUMP_SHARE, 1)} % of its maps (at most "
                       f"{100 * MAX_JUMP_SHARE:.0f} %): its tidal volume, rate and peak flow would be the jumps'",
                       STAND_STILL)
    for name, mismatch in metric.scale_mismatch.items():
        if mismatch > MAX_SCALE_MISMATCH:
            return Refusal("scale-mismatch", f"head {name}: the trunk's width in the two heads' views and its depth "
                           f"in this head's maps disagree by {100 * mismatch:.0f} % (arms against the trunk's sides, "
                           "or the trunk not wholly in view)", HOLD_ARMS_AWAY + "; " + STAND_IN_VIEW)
    return None
