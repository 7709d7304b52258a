"""The rules that refuse or withhold the optical volume of a processed session: where the subject
stands, what hides or cuts off the trunk's sides, a sheen or bent maps, too little trunk; and the
words that say what the volume left out. `process` (core/pipeline/process.py) and the live view's
checks (core/pipeline/live_checks.py) apply them; each returns its reason, or None.
"""

from __future__ import annotations

import numpy as np

from core.limits import past_limit
from core.volume.sides import bend_refusal
from core.volume.steps import step_spans_s

# Outside this a measured distance is a measurement gone wrong, not a subject (docs/reconstruction.md).
WORKING_RANGE_MM = (1500.0, 2600.0)


# The share of the trunk's rows an occluding contour may cross (core/reconstruction/pipeline.py,
# occluded_side_share) in a head's typical map before its sides count as hidden by an arm
MAX_OCCLUDED_SIDE_SHARE = 0.2


# A map whose sides an arm hides is left out of the distance and the volume (the volume is NaN there,
# and the analysis leaves out what it would have needed: core/analysis/values.py); past this share of a
# head's maps the arms are held against the trunk and the session is refused. It was 5 % of the maps
# with the whole session refused past it: population subjects 12, 14 and 20 of seed 1, arms held away
# and swung against the trunk now and then (6-9 % of their maps), gave no optical value at all.
MAX_HIDDEN_MAPS = 0.25


MAX_OUT_OF_VIEW_MAPS = 0.05  # the share of a head's maps that may show the trunk running out of the image


# The least trunk area (m^2) a head's typical map must hold for a volume: a 6-year-old's trunk from
# shoulders to hips is about 0.06 m^2 seen from one side
MIN_TRUNK_AREA_M2 = 0.03


def distance_refusal(distances_mm: dict[str, float]) -> str | None:
    """Why the optical volume cannot be reported from these heads' subject distances, or None."""
    lo, hi = WORKING_RANGE_MM
    for name, distance in distances_mm.items():
        if not np.isfinite(distance):
            return f"head {name}: no subject distance was measured"
        if not lo <= distance <= hi:
            measured = past_limit(distance, lo if distance < lo else hi)
            return (f"head {name}: the subject measured at {measured} mm, outside the rig's working range "
                    f"{lo:.0f}-{hi:.0f} mm (a subject out of place, or skin or lights the calibration does not "
                    "describe)")
    return None


# The most sheen a head's maps may show (core/reconstruction/reflectance.py: the lobe's weight over the
# albedo, the median of the session's maps) before the volume is refused (docs/history/volume-log.md, "A sheen,
# measured"): on random body 1004's slow VC in the clinic world (true lights) matte skin read 0.001-0.003
# and nine matte bodies -0.004-+0.003; a sheen of 0.01 read 0.05 / 0.08 (front / back) and its volume
# 2.6 % low, 0.02 read 0.11 / 0.16 and 4.8 % low, 0.05 0.24 / 0.32 and 11 % low
MAX_SHEEN = 0.04


def reflectance_refusal(sheen_by_head: dict[str, float]) -> str | None:
    """Why the optical volume cannot be reported from heads whose maps show more sheen than
    MAX_SHEEN (the median of their maps' sheen_relative_to_albedo), or None. The sheen, which the
    Lambertian model leaves out, bends the normals and with them the maps: on one body a sheen of
    0.01 put the volume 2.6 % low, one with a broad lobe (exponent 5) of 0.05 3.2 % high. Lights far
    from where the calibration puts them (the drawing's, without their axes and falloff) read as a
    sheen too."""
    for name, sheen in sheen_by_head.items():
        if np.isfinite(sheen) and sheen > MAX_SHEEN:
            return (f"head {name}: the shading does not follow the light model: a sheen on the skin "
                    f"{past_limit(sheen, MAX_SHEEN, 2)} of its albedo (at most {MAX_SHEEN:.2f}) bends the maps, so the "
                    "volume would be off by percents (oily or sweaty skin: crossed polarisers on the LEDs and the lens "
                    "remove it, or a towel; or lights not where the calibration puts them)")
    return None


def coverage_refusal(areas_m2: dict[str, np.ndarray]) -> str | None:
    """Why the optical volume cannot be reported from heads whose maps hold too little of the trunk."""
    for name, area in areas_m2.items():
        area = np.asarray(area, dtype=float)
        typical = float(np.nanmedian(area)) if np.isfinite(area).any() else 0.0
        if typical < MIN_TRUNK_AREA_M2:
            held = past_limit(1e4 * typical, 1e4 * MIN_TRUNK_AREA_M2)
            return (f"head {name}: its maps hold {held} cm^2 of the subject, fewer valid pixels than a trunk "
                    f"({1e4 * MIN_TRUNK_AREA_M2:.0f} cm^2 at least): the subject out of view, covered or unlit")
    return None


def session_refusal(distances_mm: dict[str, float], areas_m2: dict[str, np.ndarray],
                    occluded_share: dict[str, np.ndarray], out_of_view_share: dict[str, np.ndarray]) -> str | None:
    """The first reason the session's optical signal itself is lost, or None. An arm against the
    trunk comes first: with two heads it also moves both distances, by hundreds of mm (population
    subject 2 of seed 1 was refused as 2658 mm away, out of the working range, at 2255 mm with its
    arms close; docs/volume.md), and the trunk's area with them."""
    return (occlusion_refusal(occluded_share, out_of_view_share) or distance_refusal(distances_mm)
            or coverage_refusal(areas_m2))


def shading_refusal(sheen_by_head: dict[str, float], tilts: np.ndarray) -> str | None:
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


def maps_left_out_words(displacements: dict, sides: dict[str, np.ndarray], in_step: dict[str, np.ndarray]) -> str:
    """What the volume left out and why, for /@maps_left_out: the maps an arm hid the sides of and
    the maps in a step (core/volume/steps.py), each head's share; "" when none."""
    def shares(masks: dict[str, np.ndarray]) -> str:
        return ", ".join(f"head {n} {100 * float(np.mean(m)):.1f} % of its maps" for n, m in masks.items())

    parts = []
    if any((~m).any() for m in sides.values()):
        parts.append("an arm against the trunk hid its sides: " + shares({n: ~m for n, m in sides.items()}))
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
                      ) -> str | None:
    """Why the optical volume cannot be reported from heads whose trunk's sides an arm hides or the
    image cuts off in more than MAX_HIDDEN_MAPS (MAX_OUT_OF_VIEW_MAPS) of their maps, or None. The shares are per map
    (core/reconstruction/pipeline.py): an arm that swings against the trunk now and then changes the trunk's
    outline from map to map, and the volume with it."""
    if (arm := _first_hidden(occluded_share, MAX_HIDDEN_MAPS)) is not None:
        name, hidden = arm
        return (f"head {name}: an arm lies against the trunk (along more than "
                f"{100 * MAX_OCCLUDED_SIDE_SHARE:.0f} % of its height) in {_share_of_maps(hidden, MAX_HIDDEN_MAPS)} "
                "% of the maps and "
                "hides the sides the volume is referred to (the patient should hold the arms away from the body)")
    if (edge := _first_hidden(out_of_view_share or {}, MAX_OUT_OF_VIEW_MAPS)) is not None:
        name, hidden = edge
        return (f"head {name}: the trunk runs out of the image at the side in "
                f"{_share_of_maps(hidden, MAX_OUT_OF_VIEW_MAPS)} % of the "
                "maps (the patient off centre or too near): the sides the volume is referred to are not seen")
    return None


def geometric_distance_refusal(occluded_share: dict[str, np.ndarray]) -> str | None:
    """Why the two heads' geometry cannot give the subject's distance, or None: it is measured
    between the trunk's sides, and an arm against the trunk in one head's view hides them from both.
    The front head of population subject 2 (seed 1) kept the arms in its trunk and the back head cut
    them off at the crease beside them: 1845 and 2586 mm for a true 2195 and 2139 (docs/history/volume-log.md,
    "An arm against the trunk moves the two heads' distances")."""
    if (arm := _first_hidden(occluded_share, MAX_HIDDEN_MAPS)) is None:
        return None
    name, hidden = arm
    return (f"an arm lies against the trunk in head {name}'s view in {_share_of_maps(hidden, MAX_HIDDEN_MAPS)} % of "
            "the maps: the two "
            "heads' distances are measured between the trunk's sides, which it hides")
