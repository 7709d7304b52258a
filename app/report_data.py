"""What a report shows, gathered from a session (and its results file) by the same processing as
`photopft process` and the live view: core.analysis.session_analysis for the values, core.pipeline.head_maps.maps_at
for the height maps. The PDF (app.report_pdf) and the CSV export (app.export) only lay it out.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from app.records import Patient, Records, ReportState
from core.analysis import registry
from core.analysis.interpretation import (BronchodilatorChange, Interpretation, bronchodilator_response,
                                          bronchodilator_statement, interpret)
from core.analysis.reference import Reference, ReferenceUnavailable, reference
from core.analysis.session_analysis import analyse_session
from core.analysis.values import ANALYSIS_RATE_HZ, SessionValues, tidal_breaths, tidal_stretches
from core.io.hdf5_probe import probe
from core.io.results import (READ_ERRORS, RESULTS_FORMAT, ResultsFile, check_results, optical_inputs, optical_refusal,
                             processed_distance_mm, processed_light_gains, session_of_results)
from core.io.session import SessionError, SessionFile
from core.pipeline.head_maps import maps_at
from core.reconstruction.pipeline import ReconstructionSettings
from core.volume.maps import body_aligned_displacement, normalised_gradient_volume, torso_rows, trunk_regions

OPTICAL = "optical"
FLOW_SENSOR = "flow sensor"

# The report's two tables (core/analysis/registry.py): the main values, with predicted values, and the tidal ones
def main_table_rows() -> tuple[registry.SpirometricValue, ...]:
    """The registry's values of the report's main table (with predicted values), in order."""
    return tuple(v for v in registry.VALUES if v.table == "main")


def tidal_table_rows() -> tuple[registry.SpirometricValue, ...]:
    """The registry's values of the report's table of tidal and further values."""
    return tuple(v for v in registry.VALUES if v.table == "tidal")


@dataclass
class ValueRow:
    key: str
    label: str
    unit: str
    values: dict[str, float]  # by source
    reference: Reference | None
    decimals: int | None = None  # as the registry gives them; None: by the unit (app/report_pdf.py, fmt)

    def z(self, source: str) -> float | None:
        value = self.values.get(source)
        return self.reference.zscore(value) if self.reference is not None and value is not None else None

    def percent(self, source: str) -> float | None:
        value = self.values.get(source)
        return self.reference.percent(value) if self.reference is not None and value is not None else None


@dataclass
class Manoeuvre:
    number: int  # 1-based, in the order blown
    time_s: np.ndarray  # from back-extrapolated time zero
    volume_l: np.ndarray  # exhaled
    flow_lps: np.ndarray
    fev1_l: float
    fvc_l: float
    acceptable: bool
    problems: list[str]


@dataclass
class HeadMaps:
    head: str
    inspiration_mm: np.ndarray  # height above the subject's mean surface at end inspiration (NaN off)
    expiration_mm: np.ndarray
    displacement_mm: np.ndarray  # towards the camera from end expiration to end inspiration
    regions: dict[str, float]  # share of the displacement volume, per region (0..1)
    distance_mm: float  # the subject's distance the maps were made at
    distance_from: str  # where that distance comes from (DISTANCE_FROM_PROCESS, _FROM_FIT, _NOT_STORED, _REFUSED)


@dataclass
class Comparison:
    """The optical method against the flow sensor."""
    curve_r: float | None  # volume curves (litres) on a common time base
    tidal_pairs: list[tuple[float, float]]  # per breath (optical VT, flow-sensor VT), for Bland-Altman
    gradient_r: dict[str, float]  # normalised gradient volume (thesis eq. 3.27) per head and combined
    note: str = ""

    def bland_altman(self) -> tuple[float, float, float] | None:
        """(mean difference, lower and upper limits of agreement) of optical minus flow sensor."""
        if len(self.tidal_pairs) < 3:
            return None
        diff = np.array([a - b for a, b in self.tidal_pairs])
        bias, sd = float(diff.mean()), float(diff.std(ddof=1))
        return bias, bias - 1.96 * sd, bias + 1.96 * sd


@dataclass
class Bronchodilator:
    """This session as the post-bronchodilator one of `pre_path`."""
    pre_path: Path
    pre_recorded: str
    changes: list[BronchodilatorChange]
    statement: str
    pre_best: Manoeuvre | None  # the pre session's best blow, to overlay


@dataclass
class TrendPoint:
    recorded: str  # ISO date and time of the visit
    session_name: str
    values: dict[str, float]  # FEV1_l, FVC_l, FEV1_FVC where stored
    z: dict[str, float]  # FEV1, FVC, FEV1_FVC where a reference applies
    post_bronchodilator: bool = False  # kept out of the trend's lines, which follow the baseline


TREND_VALUES = (("FEV1", "FEV1_l"), ("FVC", "FVC_l"), ("FEV1_FVC", "FEV1_FVC"))


@dataclass
class ReportData:
    session_path: Path
    results_path: Path | None
    kind: str
    recorded: str
    operator: str
    rig: str
    calibration: list[str]
    subject: dict[str, str | float] | None
    patient: Patient | None
    equations: str
    sources: dict[str, SessionValues]
    curves: dict[str, tuple[np.ndarray, np.ndarray]]  # seconds from the first frame, litres
    main_source: str | None
    rows: list[ValueRow]
    tidal_rows: list[ValueRow]
    manoeuvres: list[Manoeuvre]
    comparison: Comparison | None
    maps: list[HeadMaps]
    breath_times_s: tuple[float, float] | None  # end inspiration, end expiration of the mapped breath
    notes: list[str] = field(default_factory=list)
    interpretation: Interpretation | None = None
    optical_manoeuvres: list[Manoeuvre] = field(default_factory=list)  # beside the flow sensor's
    review: ReportState | None = None  # the clinician's comment and sign-off, where the session is on record
    bronchodilator: Bronchodilator | None = None
    post_bronchodilator_session: Path | None = None  # where this is the pre-bronchodilator session of a pair
    trend: list[TrendPoint] = field(default_factory=list)
    # what the optical litres are: calibrated on the subject (residual) or an estimate (uncertainty)
    optical_label: str | None = None

    def parameters(self, source: str) -> dict[str, float | str | int]:
        return self.sources[source].parameters() if source in self.sources else {}


def open_inputs(path: str | os.PathLike) -> tuple[Path, Path | None]:
    """(session, results or None) for a session file or a results file."""
    path = Path(path)
    probe(path)
    try:
        with h5py.File(path, "r") as f:
            is_results = str(f.attrs.get("format", "")) == RESULTS_FORMAT
    except READ_ERRORS as exc:
        raise SessionError(f"cannot open {path}: {str(exc).splitlines()[0] if str(exc) else exc!r}") from exc
    if not is_results:
        return path, None
    check_results(path)
    return session_of_results(path), path


def _gradient_correlation(results: Path, start_ns: int, t_flow: np.ndarray, v_flow: np.ndarray) -> dict[str, float]:
    out: dict[str, float] = {}
    with ResultsFile(results) as r:
        heads = r.heads
        series = {h: ((r.series(h, "timestamp_ns") - start_ns) / 1e9, r.series(h, "gradient_volume")) for h in heads}
    if not heads:
        return out
    t = series[heads[0]][0]
    flow = np.interp(t, t_flow, v_flow)
    normalised = {h: normalised_gradient_volume(np.interp(t, *series[h])) for h in heads}
    with np.errstate(invalid="ignore", divide="ignore"):  # a flat series has no correlation: NaN, said as such
        for h, values in normalised.items():
            out[h] = float(np.corrcoef(values, flow)[0, 1])
        if len(heads) > 1:
            out["combined"] = float(np.corrcoef(sum(normalised.values()), flow)[0, 1])
    return out


def _compare(curves: dict[str, tuple[np.ndarray, np.ndarray]], events: list[tuple[float, str]],
             results: Path | None, start_ns: int, optical: SessionValues | None = None,
             quiet_gain: float = 1.0) -> Comparison | None:
    """optical: the optical values as given; where they have no tidal volume its breaths are not paired
    with the flow sensor's either. quiet_gain: the factor its tidal volumes were read with
    (core/analysis/quiet_breathing.py), on each optical breath too."""
    if FLOW_SENSOR not in curves:
        return None
    t_flow, v_flow = curves[FLOW_SENSOR]
    gradient = _gradient_correlation(results, start_ns, t_flow, v_flow) if results is not None else {}
    if OPTICAL not in curves:
        refused = optical_refusal(results) if results is not None else None
        note = (f"optical values refused: {refused}" if refused else
                "no optical volume in litres in this results file (it needs a volume calibration profile); the "
                "normalised gradient volume is compared instead") if results is not None else \
            "the session has not been processed: run `photopft process` to compare the optical method"
        return Comparison(None, [], gradient, note)
    t_opt, v_opt = curves[OPTICAL]
    lo, hi = max(t_opt[0], t_flow[0]), min(t_opt[-1], t_flow[-1])
    grid = np.arange(lo, hi, 0.05)
    on_grid = np.interp(grid, t_opt, v_opt)
    measured = np.isfinite(on_grid)  # not in a gap of maps left out (an arm against the trunk)
    r = float(np.corrcoef(on_grid[measured], np.interp(grid[measured], t_flow, v_flow))[0, 1])
    withheld = "" if optical is None or optical.tidal is not None else "tidal values not given"
    breaths = [] if withheld else tidal_breaths(tidal_stretches(t_opt, v_opt, events))
    flow = tidal_breaths(tidal_stretches(t_flow, v_flow, events))
    pairs = []
    for b in breaths:
        match = min(flow, key=lambda f: abs(f[6] - b[6]), default=None)
        if match is not None and abs(match[6] - b[6]) < 1.0:
            pairs.append((quiet_gain * float(b[0]), float(match[0])))
    return Comparison(r, pairs, gradient, f"optical {withheld}" if withheld else "")


def _manoeuvres(values: SessionValues) -> list[Manoeuvre]:
    if values.forced is None:
        return []
    out = []
    for k, (m, curve) in enumerate(zip(values.forced.manoeuvres, values.forced_curves), start=1):
        t = np.arange(len(curve)) / ANALYSIS_RATE_HZ - m.time_zero_s
        flow = np.gradient(curve, 1.0 / ANALYSIS_RATE_HZ)
        out.append(Manoeuvre(k, t, curve, flow, m.fev1_l, m.fvc_l, m.fvc_acceptable, list(m.problems)))
    return out


def best_manoeuvres(manoeuvres: list[Manoeuvre], count: int = 3) -> list[Manoeuvre]:
    """The blows with the largest FEV1 + FVC, acceptable ones first."""
    return sorted(manoeuvres, key=lambda m: (not m.acceptable, -(m.fev1_l + m.fvc_l)))[:count]


def _regions(head: str, displacement: np.ndarray, depth: np.ndarray, fx: float, fy: float) -> dict[str, float]:
    """Share of the displacement volume by quadrant of the trunk (upper/lower half of the trunk
    rows, split at the subject's midline). The front head sees the patient's left on the image's
    right; the back head their right."""
    mask = np.isfinite(displacement) & np.isfinite(depth)
    parts = trunk_regions(mask, head)
    if not parts:
        return {}
    footprint = (depth / fx) * (depth / fy)  # mm^2 per pixel
    volume = np.where(mask, displacement * footprint, 0.0)
    sums = {name: float(volume[region].sum()) for name, region in parts.items()}
    total = sum(sums.values())
    if not np.isfinite(total) or total <= 0.0:  # no net outward movement: within the alignment's error
        return {}
    return {name: value / total for name, value in sums.items()}


DISTANCE_FROM_PROCESS = "as processed"
DISTANCE_FROM_FIT = "photometric fit, not processed"
DISTANCE_NOT_STORED = "photometric fit, the results file holds no distance"
# `process` refused the optical values: the distance its geometry gave (the trunk's widths) is then
# not vouched for either (an arm against the trunk puts it hundreds of millimetres off)
DISTANCE_REFUSED = "not given: the optical values were refused"


def _head_maps(session_path: Path, session: SessionFile, times_s: tuple[float, float], start_ns: int,
               settings: ReconstructionSettings, results_path: Path | None) -> list[HeadMaps]:
    """Each head's maps at end inspiration and end expiration, made at the distance `process` measured
    (the two heads' geometry) when there are results: the photometric fit alone is tens to hundreds
    of millimetres off with glossy skin or lights a few millimetres from their calibration."""
    out = []
    refused = optical_refusal(results_path) if results_path is not None else None
    for name in session.heads:
        stamps = (session.timestamp_ns(name) - start_ns) / 1e9
        frames = [int(np.clip(np.searchsorted(stamps, t), 0, len(stamps) - 1)) for t in times_s]
        known = processed_distance_mm(results_path, name, frames) if results_path is not None else None
        gains = (processed_light_gains(results_path, name, session.timestamp_ns(name)[frames])
                 if results_path is not None else None)
        inspiration, expiration = maps_at(session_path, name, frames, settings=settings, distances_mm=known,
                                          light_gains=gains)
        head = session.rig.heads[name]
        depth_in = np.where(inspiration.mask, inspiration.depth_mm, np.nan)
        depth_ex = np.where(expiration.mask, expiration.depth_mm, np.nan)
        displacement = body_aligned_displacement(inspiration.depth_mm, inspiration.mask, expiration.depth_mm,
                                                 expiration.mask, head)
        trunk = np.zeros(displacement.shape, bool)
        trunk[torso_rows(expiration.mask)] = True
        displacement[~trunk] = np.nan  # the neck and head are not the trunk
        # heights above each map's own mean surface: sway does not show as an offset
        out.append(HeadMaps(name, np.nanmean(depth_in) - depth_in, np.nanmean(depth_ex) - depth_ex, displacement,
                            _regions(name, displacement, depth_ex, head.fx, head.fy), inspiration.distance_mm,
                            DISTANCE_REFUSED if refused else DISTANCE_FROM_FIT if known is None else
                            DISTANCE_FROM_PROCESS if np.isfinite(known[0]) else DISTANCE_NOT_STORED))
    return out


def _interpretation(main: str | None, sources: dict[str, SessionValues],
                    references: dict[str, Reference]) -> Interpretation | None:
    if main is None:
        return None
    p = sources[main].parameters()
    grade = p.get("grade")
    return interpret({k: float(v) for k, v in p.items() if k in ("FEV1_l", "FVC_l", "FEV1_FVC")}, references,
                     str(grade) if grade is not None else None, main)


def references_on(patient: Patient, day, equations: str) -> dict[str, Reference]:
    """FEV1, FVC and FEV1/FVC references of a patient on a day (their age then, their height on record)."""
    out = {}
    for name, _ in TREND_VALUES:
        try:
            out[name] = reference(name, patient.sex, patient.age_years(day), patient.height_cm, equations)
        except ReferenceUnavailable:
            continue
    return out


def stored_interpretation(patient: Patient, values: dict, recorded, source: str,
                          equations: str = "gli-global") -> Interpretation:
    """The interpretation of values kept in the records (a session's summary), with the references
    at the patient's age on the day it was recorded."""
    references = references_on(patient, recorded, equations)
    grade = values.get("grade")
    numbers = {k: float(v) for k, v in values.items()
               if k in ("FEV1_l", "FVC_l", "FEV1_FVC") and isinstance(v, (int, float))}
    return interpret(numbers, references, str(grade) if grade is not None else None, source)


def main_source(sources: dict[str, SessionValues]) -> str | None:
    """The source the predicted values, the grade and the interpretation are read from: the flow sensor
    where it recorded the forced blows (the reference instrument; the optical values stand beside it),
    else the optical values where they hold them (the mouthpiece came off after the subject's
    calibration), else whichever there is."""
    for source in (FLOW_SENSOR, OPTICAL):
        if source in sources and sources[source].forced is not None:
            return source
    return FLOW_SENSOR if FLOW_SENSOR in sources else (OPTICAL if OPTICAL in sources else None)


def source_values(summary: dict) -> tuple[str, dict]:
    """(source, values) of a stored session: the flow sensor's where it has the forced values, else the
    optical ones where they have them (the mouthpiece came off after the subject's calibration), else the
    flow sensor's, else the optical ones."""
    for source in (FLOW_SENSOR, OPTICAL):
        if isinstance(summary.get(source), dict) and "FEV1_l" in summary[source]:
            return source, summary[source]
    if summary.get(FLOW_SENSOR):
        return FLOW_SENSOR, summary[FLOW_SENSOR]
    return OPTICAL, summary.get(OPTICAL) or {}


def trend_points(records: Records, patient: Patient, equations: str) -> list[TrendPoint]:
    out = []
    for record in records.history(patient.id):
        values = {key: float(v) for _, key in TREND_VALUES
                  if isinstance(v := source_values(record.summary)[1].get(key), (int, float))}
        if not values:
            continue
        references = references_on(patient, record.recorded, equations)
        z = {name: references[name].zscore(values[key]) for name, key in TREND_VALUES
             if key in values and name in references}
        out.append(TrendPoint(record.recorded.isoformat(), record.session_path.name, values, z,
                              records.pre_bronchodilator(record.id) is not None))
    return out


def _bronchodilator(records: Records, session_id: int, post: dict[str, float], references: dict[str, Reference],
                    equations: str) -> Bronchodilator | None:
    pre = records.pre_bronchodilator(session_id)
    if pre is None:
        return None
    pre_values = source_values(pre.summary)[1]
    changes = bronchodilator_response(pre_values, post, references)
    best = None
    if pre.session_path.is_file():
        try:
            pre_data = build_report(pre.results_path or pre.session_path, equations=equations, with_maps=False)
        except SessionError:
            pre_data = None
        chosen = best_manoeuvres(pre_data.manoeuvres, 1) if pre_data is not None else []
        best = chosen[0] if chosen else None
    return Bronchodilator(pre.session_path, pre.recorded.isoformat(), changes, bronchodilator_statement(changes), best)


def _on_record(data: ReportData, records: Records | None, references: dict[str, Reference]) -> None:
    """What the records database adds: the clinician's review, the bronchodilator pair, the trend."""
    if records is None:
        return
    record = records.session_by_path(data.session_path)
    if record is not None:
        data.operator = data.operator or record.operator
        data.review = records.report_state(record.id)
        post = {k: float(v) for k, v in data.parameters(data.main_source).items()
                if k in ("FEV1_l", "FVC_l")} if data.main_source else {}
        data.bronchodilator = _bronchodilator(records, record.id, post, references, data.equations)
        follow_up = records.post_bronchodilator(record.id)
        data.post_bronchodilator_session = follow_up.session_path if follow_up is not None else None
    if data.patient is not None:
        data.trend = trend_points(records, data.patient, data.equations)


def _patient(records: Records | None, subject) -> Patient | None:
    if records is None or subject is None:
        return None
    return records.patient_by_pseudonym(subject.id)


def _read_back(results_path: Path, parameters: dict[str, dict]) -> list[str]:
    """The values stored by `process` go in the table (so the report says what the results file
    says); where this version's analysis of the same curves gives another number, a note says which
    and that processing the session again brings the file up to date."""
    with ResultsFile(results_path) as r:
        stored = r.stored_values()
    differ = []
    for src, values in parameters.items():
        for key, value in stored.get(src, {}).items():
            now = values.get(key)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.number)):
                continue
            if isinstance(now, (int, float, np.number)) and abs(float(now) - float(value)) > 1e-6 * max(1.0, abs(float(value))):
                differ.append(f"{src} {key} {float(value):.3f} stored, {float(now):.3f} now")
            values[key] = value.item() if isinstance(value, np.generic) else value
    if not differ:
        return []
    return [f"The values are those stored when the session was processed; this version analyses the same curves "
            f"differently ({'; '.join(differ[:4])}{' ...' if len(differ) > 4 else ''}): process the session again "
            "to bring the results file up to date."]


def build_report(path: str | os.PathLike, *, records: Records | None = None, equations: str = "gli-global",
                 with_maps: bool = True, settings: ReconstructionSettings | None = None) -> ReportData:
    """Everything the report shows, for a session file or a results file."""
    session_path, results_path = open_inputs(path)
    analysed = analyse_session(session_path, equations, **optical_inputs(results_path))
    notes: list[str] = []
    with SessionFile(session_path) as s:
        start = s.start_ns()
        events = sorted(((t - start) / 1e9, label) for t, label in s.events())
        subject = s.subject
        sources: dict[str, SessionValues] = {}
        curves: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if analysed.optical is not None:
            curves[OPTICAL] = analysed.optical_volume
            sources[OPTICAL] = analysed.optical
        elif results_path is not None and (refused := optical_refusal(results_path)):
            if analysed.flow_sensor is None:  # with one, the comparison with it says why (_compare), once
                notes.append(f"Optical volume in litres: refused when the session was processed: {refused}.")
        else:
            notes.append("Optical volume in litres: not available for this session (no volume calibration "
                         "profile was applied when it was processed)." if results_path is not None else
                         "Optical volume in litres: the session has not been processed.")
        if analysed.flow_sensor is not None:
            sources[FLOW_SENSOR] = analysed.flow_sensor
            curves[FLOW_SENSOR] = analysed.flow_volume
        elif analysed.flow_refused:
            notes.append(f"Flow sensor: no values, its signal is impossible: {analysed.flow_refused}.")
        else:
            notes.append("No flow sensor was recorded in this session.")
        main = main_source(sources)
        if main is None:
            notes.append("No volume curve in litres: no pulmonary function values can be reported.")
        if subject is None:
            notes.append("The session has no subject data: no predicted values.")
        elif analysed.reference_problem:
            notes.append(f"No predicted values: {analysed.reference_problem}")
        parameters = {src: v.parameters() for src, v in sources.items()}
        if results_path is not None:
            notes += _read_back(results_path, parameters)

        def by_source(key: str) -> dict[str, float]:
            return {src: float(p[key]) for src, p in parameters.items() if key in p}

        rows = [ValueRow(v.key, v.name, v.unit, by_source(v.key),
                         analysed.references.get(v.reference) if v.reference else None, v.decimals)
                for v in main_table_rows()]
        tidal_rows = [ValueRow(v.key, v.name, v.unit, by_source(v.key), None, v.decimals) for v in tidal_table_rows()]
        for src, values in sources.items():
            notes += [f"{src}: {problem}" for problem in values.problems]
        manoeuvres = _manoeuvres(sources[main]) if main is not None else []
        if main is not None and sources[main].forced is None:
            notes.append(f"{main}: no forced expiration was recorded or analysable.")
        breath = None
        maps: list[HeadMaps] = []
        timing = FLOW_SENSOR if FLOW_SENSOR in curves else main  # the reference curve places the breath best
        if timing is not None:
            breaths = tidal_breaths(tidal_stretches(*curves[timing], events))
            if breaths:
                chosen = sorted(breaths, key=lambda b: b[0])[len(breaths) // 2]  # the median tidal breath
                breath = (float(chosen[6]), float(chosen[7]))
        if with_maps and breath is not None:
            maps = _head_maps(session_path, s, breath, start, settings or ReconstructionSettings(), results_path)
        elif with_maps:
            notes.append("Height maps: no tidal breath found to place end inspiration and end expiration.")
        calibration = [f"lights of the {h} head calibrated {s.rig.heads[h].calibrated}" if s.rig.heads[h].calibrated
                       else f"lights of the {h} head not calibrated (as built or drawn)" for h in s.heads]
        if s.flow is not None and s.flow.gain_lps is not None:
            calibration.append(f"flow sensor: {s.flow.gain_lps:.6g} L/s per count, offset "
                               f"{s.flow.offset_lps:+.4g} L/s ({s.flow.conditions})")
        if results_path is not None:
            with ResultsFile(results_path) as r:
                created = r.volume_attrs().get("calibration_created")
            if created is not None:
                calibration.append(f"volume calibration of {created}")
        data = ReportData(
            session_path=session_path, results_path=results_path, kind=s.kind, recorded=s.created,
            operator=str(s.attrs.get("operator", "")), rig=s.rig.name, calibration=calibration,
            subject=None if subject is None else {"id": subject.id, "sex": subject.sex, "age_years": subject.age_years,
                                                  "height_cm": subject.height_cm, "weight_kg": subject.weight_kg},
            patient=_patient(records, subject), equations=equations, sources=sources, curves=curves,
            main_source=main, rows=rows, tidal_rows=tidal_rows, manoeuvres=manoeuvres,
            comparison=_compare(curves, events, results_path, start, sources.get(OPTICAL),
                                analysed.optical_quiet_gain.factor if analysed.optical_quiet_gain else 1.0),
            maps=maps,
            breath_times_s=breath, notes=notes,
            interpretation=_interpretation(main, sources, analysed.references),
            optical_manoeuvres=_manoeuvres(sources[OPTICAL]) if OPTICAL in sources and main != OPTICAL else [],
            optical_label=analysed.optical_label)
    _on_record(data, records, analysed.references)
    return data
