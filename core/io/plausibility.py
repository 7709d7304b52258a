"""Plausibility of a session's signals before any value is computed from them.

A file can follow the format to the letter and still hold data no instrument produced: ADC samples
past the converter's bit depth, a flow calibration of zero or negative gain, flows no sensor reads,
a flow clock shifted against the cameras', samples missing inside a manoeuvre, a lens of
impossible focal length. Each rule says what it found; the analysis refuses the values the problem
touches (the flow sensor's, or one manoeuvre's) and keeps the rest, and `photopft validate` lists
them (ISO 26782 and ATS/ERS 2019: flow within the sensor's range, gaps flagged). docs/trust.md gives
the limits and why.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from core.limits import Refusal

# Past any human expiration (adult PEF rarely exceeds 16 L/s; ISO 26782 asks a range of 14 L/s).
MAX_FLOW_LPS = 20.0
# A gap in the flow samples longer than this inside a manoeuvre refuses that manoeuvre's values:
# 20 ms is a fifth of the rise to a forced blow's peak flow.
MAX_FLOW_GAP_S = 0.020
# A gap in a head's frames longer than this inside a manoeuvre refuses that manoeuvre's optical values:
# five light cycles, a camera that stalled (docs/trust.md).
MAX_FRAME_GAP_S = 0.250
# The flow sensor's samples lie within the cameras' recording, give or take this.
FLOW_CLOCK_SLACK_S = 1.0
# A camera's horizontal or vertical field of view between these (degrees).
FIELD_OF_VIEW_DEG = (1.0, 170.0)
SENSOR_WIDTH_MM = (1.0, 100.0)  # a phone's sensor to a medium-format camera's
MAX_PIXEL_ASPECT = 2.0

MANOEUVRES = {"tidal-start": "tidal", "vc-start": "vc", "forced-start": "forced"}


def intrinsics_problems(width: int, height: int, fx: float, fy: float, cx: float, cy: float,
                        pixel_size_mm: float) -> list[str]:
    """What makes a head's intrinsics physically impossible (empty when they are plausible)."""
    values = {"fx": fx, "fy": fy, "cx": cx, "cy": cy, "pixel_size_mm": pixel_size_mm}
    bad = [k for k, v in values.items() if not math.isfinite(v)]
    if bad:
        return [f"{', '.join(bad)} not finite"]
    problems = []
    low, high = FIELD_OF_VIEW_DEG
    for name, focal, size in (("fx", fx, width), ("fy", fy, height)):
        if focal <= 0:
            problems.append(f"{name} = {focal:g} px must be positive")
            continue
        fov = math.degrees(2 * math.atan(size / (2 * focal)))
        if not low <= fov <= high:
            problems.append(f"{name} = {focal:g} px gives a field of view of {fov:.3g} deg over {size} px "
                            f"(a lens gives {low:g}-{high:g} deg)")
    if fx > 0 and fy > 0 and not 1 / MAX_PIXEL_ASPECT <= fx / fy <= MAX_PIXEL_ASPECT:
        problems.append(f"fx / fy = {fx / fy:.3g}: pixels that much longer than wide do not exist")
    if not (0 <= cx <= width and 0 <= cy <= height):
        problems.append(f"the principal point ({cx:g}, {cy:g}) px lies outside the {width} x {height} sensor")
    lo, hi = SENSOR_WIDTH_MM
    if not lo <= pixel_size_mm * width <= hi:
        problems.append(f"pixel_size_mm = {pixel_size_mm:g} makes the sensor {pixel_size_mm * width:.3g} mm wide "
                        f"(a camera's is {lo:g}-{hi:g} mm)")
    return problems


def head_intrinsics_problems(head) -> list[str]:
    """`intrinsics_problems` of a core.rig.Head."""
    return intrinsics_problems(head.width, head.height, head.fx, head.fy, head.cx, head.cy, head.pixel_size_mm)


# What the operator or engineer does about a flow refusal
RECALIBRATE_FLOW = "calibrate the flow sensor again (the spirometer wizard) and record the session again"
CHECK_FLOW_SETUP = "check the rig file's flow sensor (its adc_bits) against the device"
CHECK_FLOW_CLOCK = "the flow sensor and the cameras must share one clock: check the rig's wiring and record again"


def adc_range(bits: int) -> tuple[int, int]:
    """The counts a converter of `bits` can give, either convention (signed or not) allowed."""
    return -(2 ** (bits - 1)), 2 ** bits - 1


def flow_refusal(adc: np.ndarray, timestamp_ns: np.ndarray, adc_bits: int, sample_rate_hz: float,
                 gain_lps: float | None, offset_lps: float | None,
                 frame_span_ns: tuple[int, int] | None) -> Refusal | None:
    """Why none of the flow sensor's values may be given (None when its signal is plausible)."""
    if gain_lps is not None:
        if not (math.isfinite(gain_lps) and gain_lps > 0):
            return Refusal("flow-gain", f"the flow calibration's gain is {gain_lps:g} L/s per count: it must be "
                           "positive", RECALIBRATE_FLOW)
        if offset_lps is None or not math.isfinite(offset_lps):
            return Refusal("flow-offset", f"the flow calibration's offset is {offset_lps}: it must be a finite number",
                           RECALIBRATE_FLOW)
    if not 1 <= adc_bits <= 31:
        return Refusal("flow-adc-bits", f"adc_bits = {adc_bits}: a converter has 1 to 31 bits", CHECK_FLOW_SETUP)
    if len(adc) == 0:
        return None
    low, high = adc_range(adc_bits)
    outside = np.flatnonzero((adc < low) | (adc > high))
    if len(outside):
        k = int(outside[0])
        return Refusal("flow-adc-range", f"{len(outside)} sample(s) outside what a {adc_bits}-bit converter gives "
                       f"({low} to {high}), the first {int(adc[k])} at sample {k}", CHECK_FLOW_SETUP)
    if gain_lps is not None:
        flow = gain_lps * adc.astype(float) + offset_lps
        peak = float(np.max(np.abs(flow)))
        if peak > MAX_FLOW_LPS:
            return Refusal("flow-past-breath", f"the flow reaches {peak:.1f} L/s, past any breath "
                           f"({MAX_FLOW_LPS:g} L/s)", RECALIBRATE_FLOW)
    if len(timestamp_ns) > 1 and np.any(np.diff(timestamp_ns) <= 0):
        return Refusal("flow-timestamps", "its timestamps do not increase", CHECK_FLOW_CLOCK)
    if frame_span_ns is not None:
        slack = FLOW_CLOCK_SLACK_S * 1e9
        first, last = int(timestamp_ns[0]), int(timestamp_ns[-1])
        if first < frame_span_ns[0] - slack or last > frame_span_ns[1] + slack:
            return Refusal("flow-clock", f"its samples run from {(first - frame_span_ns[0]) / 1e9:+.2f} s to "
                           f"{(last - frame_span_ns[1]) / 1e9:+.2f} s of the cameras' first and last frames "
                           f"(at most {FLOW_CLOCK_SLACK_S:g} s outside): its clock is not the cameras'",
                           CHECK_FLOW_CLOCK)
    return None


def flow_gaps(timestamp_ns: np.ndarray, limit_s: float = MAX_FLOW_GAP_S) -> list[tuple[int, int]]:
    """(last sample before, first sample after) of every gap longer than `limit_s`."""
    t = np.asarray(timestamp_ns, dtype=np.int64)
    if len(t) < 2:
        return []
    at = np.flatnonzero(np.diff(t) > limit_s * 1e9)
    return [(int(t[k]), int(t[k + 1])) for k in at]


@dataclass(frozen=True)
class ManoeuvreGap:
    kind: str  # tidal, vc or forced
    start_s: float  # the manoeuvre's start, seconds from the session's start
    gap_s: float
    what: str = "flow samples"
    limit_s: float = MAX_FLOW_GAP_S
    count: int = 1  # the manoeuvre's gaps over limit_s; gap_s is the longest

    @property
    def reason(self) -> str:
        longest = f"the longest of {self.count} gaps; " if self.count > 1 else ""
        return (f"{self.gap_s * 1000:.0f} ms of {self.what} missing inside the {self.kind} manoeuvre at "
                f"{self.start_s:.1f} s ({longest}at most {self.limit_s * 1000:.0f} ms)")


def gaps_in_manoeuvres(gaps: list[tuple[int, int]], events: list[tuple[int, str]], start_ns: int,
                       what: str = "flow samples", limit_s: float = MAX_FLOW_GAP_S) -> list[ManoeuvreGap]:
    """The gaps that fall inside a manoeuvre, one ManoeuvreGap for each manoeuvre that has any (its
    longest): from its start event to the next `maneuver-end`, the next manoeuvre's start, or the end
    of the recording."""
    spans, opened = [], None
    for t, label in sorted(events):
        if (label in MANOEUVRES or label == "maneuver-end") and opened is not None:
            spans.append((opened[0], t, opened[1]))
            opened = None
        if label in MANOEUVRES:
            opened = (t, MANOEUVRES[label])
    if opened is not None:
        spans.append((opened[0], np.iinfo(np.int64).max, opened[1]))
    out = []
    for begin, end, kind in spans:
        inside = [(after - before) / 1e9 for before, after in gaps if before < end and after > begin]
        if inside:
            out.append(ManoeuvreGap(kind, (begin - start_ns) / 1e9, max(inside), what, limit_s, len(inside)))
    return out


def frame_gaps_in_manoeuvres(frame_times: dict[str, np.ndarray], events: list[tuple[int, str]],
                             start_ns: int) -> list[ManoeuvreGap]:
    """Each head's gaps over MAX_FRAME_GAP_S inside a manoeuvre (a camera that stalled, frames lost)."""
    out = []
    for head, times in frame_times.items():
        out += gaps_in_manoeuvres(flow_gaps(times, MAX_FRAME_GAP_S), events, start_ns, f"the {head} head's frames",
                                  MAX_FRAME_GAP_S)
    return out
