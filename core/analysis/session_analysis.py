"""The pulmonary function values of a recorded session: from its flow sensor, and from an optical volume
curve when one is given (a results file's /volume). A simulation's truth is not read here
(core/sim/truth.py)."""

from __future__ import annotations

import os
from dataclasses import dataclass, replace

import numpy as np

from core.analysis.optical_labels import calibrated_on_subject
from core.analysis.quiet_breathing import QuietBreathingGain, calibrated_tidal_values
from core.analysis.values import SessionValues, analyse_volume, tidal_windows
from core.volume.flow_sensor import btps_factor, flow_sensor_volume
from core.analysis.reference import Reference, ReferenceUnavailable, reference
from core.io.plausibility import flow_gaps, flow_refusal, frame_gaps_in_manoeuvres, gaps_in_manoeuvres
from core.io.session import SessionError, SessionFile
from core.limits import Refusal
from core.volume.subject_calibration import calibration_segment


@dataclass
class SessionReport:
    flow_sensor: SessionValues | None
    references: dict[str, Reference]
    reference_problem: str | None
    flow_volume: tuple[np.ndarray, np.ndarray] | None  # (seconds from the first frame, litres)
    optical: SessionValues | None = None
    optical_volume: tuple[np.ndarray, np.ndarray] | None = None  # (seconds from the first frame, litres)
    flow_refused: Refusal | None = None  # why none of the flow sensor's values are given (core/io/plausibility.py)
    optical_label: str | None = None  # what the optical litres are (core/analysis/optical_litres.py)
    # where the optical values are read from (s): the end of the subject's calibration for a curve calibrated
    # on it (its own data are the flow sensor's), else the curve's start (-inf)
    optical_from_s: float = float("-inf")
    # the quiet-breathing gain its tidal volumes were read with (core/analysis/quiet_breathing.py), if any
    optical_quiet_gain: QuietBreathingGain | None = None



def without_gapped_manoeuvres(values: SessionValues, gaps) -> SessionValues:
    """The values less those of every kind of manoeuvre whose signal (flow samples, frames) has a gap."""
    if not gaps:
        return values
    kinds = {g.kind for g in gaps}
    problems = [*values.problems] + [f"{_KIND_VALUES[g.kind]} not given: {g.reason}" for g in gaps]
    return replace(values, problems=problems,
                   tidal=None if "tidal" in kinds else values.tidal,
                   vital_capacity=None if "vc" in kinds else values.vital_capacity,
                   vc_manoeuvres=[] if "vc" in kinds else values.vc_manoeuvres,
                   forced=None if "forced" in kinds else values.forced,
                   forced_curves=[] if "forced" in kinds else values.forced_curves)


_KIND_VALUES = {"tidal": "the tidal values", "vc": "VC and its volumes", "forced": "the forced values"}


@dataclass
class SessionFlow:
    """A session's flow-sensor volume: BTPS, drift removed, on seconds from the first frame; or why
    its samples cannot be used (core/io/plausibility.py), in `refused`."""
    t_s: np.ndarray
    volume_l: np.ndarray
    stamps_ns: np.ndarray
    refused: Refusal | None = None


def session_flow_volume(s: SessionFile, events: list[tuple[float, str]] | None = None) -> SessionFlow | None:
    """The flow sensor's volume of an open session, or None without a flow sensor."""
    if s.flow is None:
        return None
    start = s.start_ns()
    events = _events(s, start) if events is None else events
    info = s.flow
    if info.gain_lps is None:
        raise SessionError(f"{s.path}: the flow sensor has no calibration in force (flow_gain_lps)")
    adc, stamps = s.flow_samples()
    refused = flow_refusal(adc, stamps, info.adc_bits, info.sample_rate_hz, info.gain_lps, info.offset_lps,
                           s.frame_span_ns())
    if refused is not None:
        return SessionFlow(np.zeros(0), np.zeros(0), stamps, refused)
    factor = 1.0
    if info.conditions == "ATPS":
        a = info.attrs
        try:
            factor = btps_factor(float(a.get("room_temperature_c", 23.0)), float(a.get("room_pressure_hpa", 1013.0)),
                                 float(a.get("room_humidity_pct", 50.0)))
        except ValueError as exc:
            raise SessionError(f"{s.path}: /flow room conditions: {exc}") from exc
    end_s = (int(stamps[-1]) - start) / 1e9
    volume = flow_sensor_volume(adc, stamps, info.gain_lps, info.offset_lps, factor, tidal_windows(events, end_s))
    return SessionFlow((volume.timestamp_ns - start) / 1e9, volume.volume_l, stamps)


def optical_read_from_s(optical_label: str | None, flow_end_s: float | None, events: list[tuple[float, str]]) -> float:
    """Where a curve calibrated on the subject begins to be read: the end of its calibration segment
    (flow_end_s: the flow sensor's last sample, None without its values). Its quiet breathing and slow VC
    there are the fit's own data, read by the flow sensor; read optically they would give the fit back,
    not the cameras' litres. -inf for any other curve."""
    if flow_end_s is None or not calibrated_on_subject(optical_label):
        return -np.inf
    segment = calibration_segment(events, flow_end_s)
    return segment[1] if segment is not None else -np.inf


def _events(session: SessionFile, start_ns: int) -> list[tuple[float, str]]:
    return sorted(((t - start_ns) / 1e9, label) for t, label in session.events())


def analyse_session(path: str | os.PathLike, equations: str = "gli-global",
                    optical_volume: tuple[np.ndarray, np.ndarray] | None = None,
                    optical_label: str | None = None,
                    optical_peak_flow: tuple[np.ndarray, np.ndarray] | None = None) -> SessionReport:
    """optical_volume: (timestamp_ns, litres) on the session's clock, e.g. a results file's /volume;
    optical_label: what its litres are (core/analysis/optical_litres.py: calibrated on the subject, or
    an estimate with its uncertainty), kept in the report; optical_peak_flow:
    (timestamp_ns, litres), its volume at every frame through the forced blows' peak flows (/peak_flow_volume),
    which its PEF is read from (analyse_volume). core.io.results.optical_inputs gives all three. A curve
calibrated on the subject has its tidal volumes read with the gain of the subject's quiet breathing
through the flow sensor (core/analysis/quiet_breathing.py)."""
    with SessionFile(path) as s:
        start = s.start_ns()
        events = _events(s, start)
        age = s.subject.age_years if s.subject is not None else None
        flow_values, flow_volume, flow_refused = None, None, None
        flow = session_flow_volume(s, events)
        if flow is not None:
            flow_refused = flow.refused
        if flow is not None and flow.refused is None:
            covered = [(t, label) for t, label in events if t <= flow.t_s[-1]]  # the mouthpiece may come off
            flow_values = without_gapped_manoeuvres(analyse_volume(flow.t_s, flow.volume_l, covered, age),
                                                    gaps_in_manoeuvres(flow_gaps(flow.stamps_ns), s.events(), start))
            flow_volume = (flow.t_s, flow.volume_l)
        optical_values, optical_curve, optical_from_s, quiet_gain = None, None, float("-inf"), None
        if optical_volume is not None:
            t = (np.asarray(optical_volume[0], dtype=np.int64) - start) / 1e9
            volume = np.asarray(optical_volume[1], dtype=float)
            dense = None if optical_peak_flow is None else (
                (np.asarray(optical_peak_flow[0], dtype=np.int64) - start) / 1e9, np.asarray(optical_peak_flow[1], float))
            optical_from_s = optical_read_from_s(optical_label, None if flow_volume is None else float(flow_volume[0][-1]),
                                                 events)
            read = t >= optical_from_s
            optical_values = analyse_volume(t[read], volume[read], events, age, fitted=True, peak_flow_volume=dense)
            optical_values, quiet_gain = calibrated_tidal_values(optical_values, optical_label, flow_volume, (t, volume),
                                                                 events)
            frame_times = {h: s.timestamp_ns(h) for h in s.heads if s.n_frames(h)}
            optical_values = without_gapped_manoeuvres(optical_values,
                                                       frame_gaps_in_manoeuvres(frame_times, s.events(), start))
            optical_curve = (t, volume)
        references: dict[str, Reference] = {}
        problem = None
        if s.subject is not None:
            try:
                for parameter in ("FEV1", "FVC", "FEV1_FVC"):
                    references[parameter] = reference(parameter, s.subject.sex, s.subject.age_years,
                                                      s.subject.height_cm, equations)
                if equations == "gli-2012":
                    references["FEF2575"] = reference("FEF2575", s.subject.sex, s.subject.age_years,
                                                      s.subject.height_cm, equations)
            except ReferenceUnavailable as exc:
                problem = str(exc)
    return SessionReport(flow_values, references, problem, flow_volume, optical_values,
                         optical_curve, flow_refused, optical_label if optical_values is not None else None,
                         optical_from_s, quiet_gain)
