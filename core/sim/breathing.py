"""Simulated breathing: a subject, manoeuvres and the protocol that strings them together.

The lung volume signal (litres above the end-tidal level at the start, positive = inhaled)
drives the torso's displacement modes; the volume a reader must recover is measured from the
displaced surfaces (core/sim/scene.py), not taken from this signal.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq

from core.analysis.protocol_feedback import MIN_TIDAL_BREATHS
from core.volume.subject_calibration import MOUTHPIECE_OFF

RATE_HZ = 1000.0  # sampling of the generated waveforms


@dataclass(frozen=True)
class Subject:
    """A simulated subject. Lung volumes default to the ECSC 1993 predicted values (Quanjer et al.)."""

    id: str = "SIM-0001"
    sex: str = "male"
    age_years: float = 30.0
    height_cm: float = 175.0
    weight_kg: float = 75.0
    fvc_l: float | None = None
    fev1_l: float | None = None
    pef_lps: float | None = None
    tidal_volume_l: float | None = None
    respiratory_rate_bpm: float = 14.0
    ie_ratio: float = 1.5  # expiratory over inspiratory time
    chest_share: float = 0.62  # of each breath; the abdomen has the rest
    left_share: float = 0.5  # of the chest's share
    abdomen_lag_s: float = 0.08  # abdomen after chest (thoraco-abdominal phase)
    rate_variability: float = 0.06  # breath-to-breath spread of the period (and of the tidal volume, 4/3 of it)
    sigh_every: int = 0  # a sigh (2-3 tidal volumes) about every this many breaths; 0: none

    def __post_init__(self) -> None:
        if self.sex not in ("male", "female"):
            raise ValueError(f"sex must be 'male' or 'female', got {self.sex!r}")
        if not 3 <= self.age_years <= 100:
            raise ValueError(f"age_years {self.age_years} outside 3-100")
        if not 90 <= self.height_cm <= 230:
            raise ValueError(f"height_cm {self.height_cm} outside 90-230")

    @property
    def _h(self) -> float:
        return self.height_cm / 100.0

    @property
    def predicted(self) -> dict[str, float]:
        """ECSC 1993 for adults; under 18, Polgar and Promadhat (1971) for FVC, FEV1 and PEF, with
        TLC = FVC / 0.8, RV the rest and FRC 45 % of TLC (children's usual ratios)."""
        h, a = self._h, self.age_years
        if a < 18:
            fvc = 4.4e-6 * self.height_cm**2.67
            tlc = fvc / 0.8
            return {"FVC": fvc, "FEV1": 2.1e-6 * self.height_cm**2.80, "PEF": (5.175 * self.height_cm - 407) / 60,
                    "TLC": tlc, "FRC": 0.45 * tlc, "RV": tlc - fvc}
        if self.sex == "male":
            return {"FVC": 5.76 * h - 0.026 * a - 4.34, "FEV1": 4.30 * h - 0.029 * a - 2.49,
                    "PEF": 6.14 * h - 0.043 * a + 0.15, "TLC": 7.99 * h - 7.08,
                    "FRC": 2.34 * h + 0.009 * a - 1.09, "RV": 1.31 * h + 0.022 * a - 1.23}
        return {"FVC": 4.43 * h - 0.026 * a - 2.89, "FEV1": 3.95 * h - 0.025 * a - 2.60,
                "PEF": 5.50 * h - 0.030 * a - 1.11, "TLC": 6.60 * h - 5.79,
                "FRC": 2.24 * h + 0.001 * a - 1.00, "RV": 1.81 * h + 0.016 * a - 2.00}

    @property
    def fvc(self) -> float:
        return self.fvc_l if self.fvc_l is not None else self.predicted["FVC"]

    @property
    def fev1(self) -> float:
        return self.fev1_l if self.fev1_l is not None else self.predicted["FEV1"]

    @property
    def pef(self) -> float:
        return self.pef_lps if self.pef_lps is not None else self.predicted["PEF"]

    @property
    def tidal_volume(self) -> float:
        return self.tidal_volume_l if self.tidal_volume_l is not None else 0.007 * self.weight_kg

    @property
    def inspiratory_capacity(self) -> float:
        p = self.predicted
        return (p["TLC"] - p["FRC"]) * self.fvc / p["FVC"]

    @property
    def expiratory_reserve(self) -> float:
        p = self.predicted
        return (p["FRC"] - p["RV"]) * self.fvc / p["FVC"]

    def compartment_shares(self) -> dict[str, float]:
        chest = self.chest_share
        return {"chest_left": chest * self.left_share, "chest_right": chest * (1 - self.left_share),
                "abdomen": 1.0 - chest}


@dataclass(frozen=True)
class ForcedBlow:
    """One forced expiration; the defaults are a good blow."""

    rise_time_s: float = 0.06  # slow start: 0.3 s or more
    stop_after_s: float | None = None  # early stop: expiration ends here
    cough_at_s: float | None = None  # a cough: flow stops for 80 ms at this time
    effort: float = 1.0  # scales PEF (and FEV1 a little)
    # a standard volume-time waveform (exhaled L at RATE_HZ, core/sim/breathing.standard_curve) that the blow
    # follows, scaled to the subject's FVC; None: the two-exponential model
    standard: np.ndarray | None = field(default=None, compare=False)


@dataclass
class Waveform:
    """Lung volume at RATE_HZ from t = 0, with protocol events."""

    volume_l: np.ndarray
    events: list[tuple[float, str]] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        return len(self.volume_l) / RATE_HZ

    def __post_init__(self) -> None:
        self._set(np.asarray(self.volume_l, dtype=float))

    def _set(self, volume_l: np.ndarray) -> None:
        """Replace the curve in one step (readers on other threads see the old or the new one)."""
        self._curves = (np.arange(len(volume_l)) / RATE_HZ, volume_l, np.gradient(volume_l) * RATE_HZ)
        self.volume_l = volume_l

    def at(self, t_s: np.ndarray | float) -> np.ndarray:
        grid, volume, _ = self._curves
        return np.interp(np.asarray(t_s, dtype=float), grid, volume)

    def flow_at(self, t_s: np.ndarray | float) -> np.ndarray:
        grid, _, flow = self._curves
        return np.interp(np.asarray(t_s, dtype=float), grid, flow)

    def splice(self, t_s: float, samples: np.ndarray, after: np.ndarray) -> None:
        """From `t_s` on: `samples` (a manoeuvre from the tidal level), eased from the volume at
        `t_s` over half a second, then `after`; for a simulated subject that follows prompts."""
        i = int(round(t_s * RATE_HZ))
        start = float(self.at(t_s))
        ease = (start - samples[0]) * np.exp(-np.arange(len(samples)) / (0.5 * RATE_HZ))
        self._set(np.concatenate([self.volume_l[:i], samples + ease, after]))


def _samples(duration_s: float) -> np.ndarray:
    return np.arange(int(round(duration_s * RATE_HZ))) / RATE_HZ


def _ramp(level_from: float, level_to: float, duration_s: float) -> np.ndarray:
    """A smooth (raised-cosine) change of level."""
    t = _samples(duration_s)
    return level_from + (level_to - level_from) * 0.5 * (1 - np.cos(np.pi * t / duration_s))


def _ease_out(level_from: float, level_to: float, duration_s: float) -> np.ndarray:
    """A change of level that starts briskly and levels off (cubic ease-out): a slow exhalation
    to residual volume, which ends on a plateau."""
    t = _samples(duration_s)
    return level_from + (level_to - level_from) * (1 - (1 - t / duration_s) ** 3)


def _breath(subject: Subject, rng: np.random.Generator, level_l: float) -> np.ndarray:
    """One tidal breath from the end-expiratory level back to it: raised-cosine inspiration,
    passive (exponential) expiration, breath-to-breath variability, now and then a sigh."""
    spread = subject.rate_variability
    period = 60.0 / subject.respiratory_rate_bpm * float(np.clip(1 + spread * rng.standard_normal(), 0.5, 1.8))
    vt = subject.tidal_volume * float(np.clip(1 + 4 / 3 * spread * rng.standard_normal(), 0.4, 2.0))
    if subject.sigh_every and rng.random() < 1.0 / subject.sigh_every:
        vt *= rng.uniform(2.0, 3.0)
        period *= 1.6
    ti = period / (1 + subject.ie_ratio)
    te = period - ti
    inspiration = level_l + vt * 0.5 * (1 - np.cos(np.pi * _samples(ti) / ti))
    tau = te / 4.0
    t = _samples(te)
    expiration = level_l + vt * (np.exp(-t / tau) - np.exp(-te / tau)) / (1 - np.exp(-te / tau))
    return np.concatenate([inspiration, expiration])


def tidal(subject: Subject, duration_s: float, rng: np.random.Generator, level_l: float = 0.0) -> np.ndarray:
    """Whole tidal breaths covering at least `duration_s`: the last one is finished, so the volume
    ends at the end-expiratory level and what follows starts from it without a jump."""
    parts: list[np.ndarray] = [np.zeros(0)]
    total = int(round(duration_s * RATE_HZ))
    while sum(len(p) for p in parts) < total:
        parts.append(_breath(subject, rng, level_l))
    return np.concatenate(parts)


def lead_breaths(subject: Subject, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` whole tidal breaths before a manoeuvre."""
    return np.concatenate([np.zeros(0)] + [_breath(subject, rng, 0.0) for _ in range(count)])


def slow_vc(subject: Subject, rng: np.random.Generator,
            lead_count: int = 0) -> tuple[np.ndarray, list[tuple[float, str]]]:
    """Tidal breaths, a slow full inspiration to TLC, a slow full expiration to RV, back to FRC."""
    ic, erv = subject.inspiratory_capacity, subject.expiratory_reserve
    lead = lead_breaths(subject, lead_count, rng)
    parts = [lead, _ramp(0.0, ic, 3.0), np.full(int(0.5 * RATE_HZ), ic), _ease_out(ic, -erv, 7.0),
             np.full(int(0.4 * RATE_HZ), -erv), _ramp(-erv, 0.0, 2.0)]
    start = len(lead) / RATE_HZ
    end = sum(len(p) for p in parts) / RATE_HZ
    return np.concatenate(parts), [(start, "vc-start"), (end, "maneuver-end")]


def forced_expiration_curve(fvc: float, fev1: float, pef: float, blow: ForcedBlow,
                            duration_s: float = 6.0) -> np.ndarray:
    """Exhaled volume (L) against time for one forced expiration at RATE_HZ.

    Flow rises to PEF as sin^2 over the rise time; the volume still to exhale then falls as
    two exponentials, a fast (large airways) and a slow (small airways) part,
    w(t) = w_peak * (a * exp(-t / tau_fast) + (1 - a) * exp(-t / tau_slow)), with tau_slow a fifth
    of the blow (a plateau by its end), and a, tau_fast fixed by PEF (the initial slope) and
    FEV1 at back-extrapolated time zero. Obstructed curves have a large slow part.
    """
    pef = pef * blow.effort
    fev1 = fev1 * (0.85 + 0.15 * blow.effort)
    t = _samples(duration_s)
    tr = blow.rise_time_s
    v_peak = pef * tr / 2.0
    w_peak = fvc - v_peak
    if v_peak >= 0.5 * fvc or fev1 >= fvc:
        raise ValueError(f"no forced expiration fits FVC {fvc:.2f} L, FEV1 {fev1:.2f} L, PEF {pef:.2f} L/s, "
                         f"rise {tr:.2f} s")
    tau_slow = (duration_s - tr) / 5.0
    t0 = tr / 2.0  # back-extrapolated time zero of a sin^2 rise (tangent at peak flow)

    def tau_fast(a: float) -> float:
        return a / (pef / w_peak - (1 - a) / tau_slow)

    def remaining(a: float, ts: np.ndarray) -> np.ndarray:
        return w_peak * (a * np.exp(-ts / tau_fast(a)) + (1 - a) * np.exp(-ts / tau_slow))

    def fev1_error(a: float) -> float:
        return float(fvc - remaining(a, np.array(t0 + 1.0 - tr))) - fev1

    a_min = max(1e-6, 1.0 - pef * tau_slow / w_peak + 1e-6)  # tau_fast must stay positive
    if fev1_error(a_min) * fev1_error(1.0 - 1e-9) > 0:
        raise ValueError(f"FEV1 {fev1:.2f} L cannot follow from PEF {pef:.2f} L/s and FVC {fvc:.2f} L "
                         f"in a {duration_s:.0f} s blow")
    a = brentq(fev1_error, a_min, 1.0 - 1e-9, xtol=1e-9)
    rise = pef * (t / 2.0 - tr / (2 * np.pi) * np.sin(np.pi * np.clip(t, 0, tr) / tr))
    volume = np.where(t < tr, rise, fvc - remaining(a, np.clip(t - tr, 0.0, None)))
    if blow.cough_at_s is not None:
        i = int(blow.cough_at_s * RATE_HZ)
        n = int(0.08 * RATE_HZ)
        volume = np.concatenate([volume[:i], np.full(n, volume[i]), volume[i:-n]])
    if blow.stop_after_s is not None:
        i = int(blow.stop_after_s * RATE_HZ)
        volume[i:] = volume[i]
    return volume


def forced(subject: Subject, blow: ForcedBlow, rng: np.random.Generator, blow_s: float | None = None,
           lead_count: int = 1) -> tuple[np.ndarray, list[tuple[float, str]]]:
    """Tidal breaths, a full inspiration to TLC, a short hold, the blow, back to the tidal level.

    The blow lasts 6 s, or 10 s when FEV1/FVC < 0.7 (obstructed lungs empty slowly).
    """
    ic = subject.inspiratory_capacity
    if blow_s is None:
        blow_s = 6.0 if subject.fev1 / subject.fvc >= 0.7 else 10.0
    lead = lead_breaths(subject, lead_count, rng)
    inhale = _ramp(0.0, ic, 1.6)
    hold = np.full(int(0.4 * RATE_HZ), ic)
    if blow.standard is not None:
        # a weaker blow of a standard shape empties a little less (1.5 % at 97 % effort)
        exhaled = blow.standard * (subject.fvc * (1.0 - 0.5 * (1.0 - blow.effort)) / float(blow.standard[-1]))
    else:
        exhaled = forced_expiration_curve(subject.fvc, subject.fev1, subject.pef, blow, blow_s)
    blow_part = ic - exhaled
    recover = _ramp(blow_part[-1], 0.0, 1.5)
    start = (len(lead) + len(inhale) + len(hold)) / RATE_HZ
    end = start + len(blow_part) / RATE_HZ
    parts = [lead, inhale, hold, blow_part, recover]
    return np.concatenate(parts), [(start, "forced-start"), (end, "maneuver-end")]


def standard_curve(volume_l: np.ndarray, rate_hz: float) -> np.ndarray:
    """A standard test waveform's exhaled volume (ATS-24, ISO 26782) at RATE_HZ: from its start to
    one second after it comes within 1 mL of its final volume (the files pad with a long plateau),
    held to at least 6 s; shape-preserving (PCHIP) between its samples."""
    volume = np.asarray(volume_l, dtype=float)
    volume = volume - volume[0]
    end = int(np.argmax(volume >= volume[-1] - 0.001)) + int(round(rate_hz))
    volume = volume[: min(end, len(volume) - 1) + 1]
    t = np.arange(len(volume)) / rate_hz
    out = PchipInterpolator(t, volume)(np.arange(int(t[-1] * RATE_HZ) + 1) / RATE_HZ)
    out = np.maximum.accumulate(np.clip(out, 0.0, None))
    return np.concatenate([out, np.full(max(0, int(6 * RATE_HZ) - len(out)), out[-1])])


PROTOCOLS = ("tidal", "vc", "forced", "full", "short", "clinical", "static")
TIDAL_SECONDS = {"full": 8.0, "short": 20.0, "clinical": 20.0}  # the tidal part that opens a whole protocol
# the clinical protocol's quiet breathing once the mouthpiece is off: at least this long, and as many
# breaths as the guided session asks for there (core/analysis/protocol_feedback.py MIN_TIDAL_BREATHS) and one
CLINICAL_TIDAL_AFTER_S = 10.0
CLINICAL_OFF_AFTER_S = 3.0  # and before, from the calibration's slow VC to the mouthpiece's removal


def clinical_tidal_after_s(subject: Subject) -> float:
    """The clinical protocol's quiet breathing without the mouthpiece: the guided session extends it
    until MIN_TIDAL_BREATHS breaths are read (the tidal page), so the protocol breathes that many and
    one more (10 s alone held 2-3 breaths at 12-18 /min, and a test subject's none to read)."""
    return max(CLINICAL_TIDAL_AFTER_S, (MIN_TIDAL_BREATHS + 1) * 60.0 / subject.respiratory_rate_bpm)


def protocol_waveform(subject: Subject, protocol: str, seconds: float | None, seed: int,
                      blows: list[ForcedBlow] | None = None) -> Waveform:
    """The lung volume of a whole protocol; `seconds` trims or pads (with tidal breathing) the end.

    full (57 s): 8 s tidal breathing, a slow VC, then forced expirations (three good blows by default).
    short (about 55 s): 20 s tidal breathing, a slow VC, the first two blows.
    clinical (about 115 s, the population benchmark's): the subject's calibration through the flow sensor
    (20 s tidal breathing, a slow VC), `mouthpiece-off`, then tidal breathing (clinical_tidal_after_s),
    a slow VC and the forced expirations, seen by the cameras alone.
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}: one of {', '.join(PROTOCOLS)}")
    rng = np.random.default_rng(seed + 17)
    blows = blows if blows is not None else [ForcedBlow(), ForcedBlow(effort=0.97), ForcedBlow(effort=1.02)]
    parts: list[np.ndarray] = []
    events: list[tuple[float, str]] = []

    def add(samples: np.ndarray, part_events: list[tuple[float, str]] = ()) -> None:
        offset = sum(len(p) for p in parts) / RATE_HZ
        events.extend((offset + t, label) for t, label in part_events)
        parts.append(samples)

    if protocol == "static":
        add(np.zeros(int(round((seconds or 5.0) * RATE_HZ))))
        return Waveform(np.concatenate(parts), events)
    whole = protocol in TIDAL_SECONDS
    if protocol == "tidal" or whole:
        tidal_s = TIDAL_SECONDS.get(protocol, seconds or 30.0)
        add(tidal(subject, tidal_s, rng), [(0.0, "tidal-start")])
        if whole:
            events.append((len(parts[-1]) / RATE_HZ, "maneuver-end"))
    if protocol == "vc" or whole:
        add(*slow_vc(subject, rng, lead_count=0 if whole else 1))
    if protocol == "clinical":  # a few quiet breaths through the mouthpiece still, while the operator
        add(tidal(subject, CLINICAL_OFF_AFTER_S, rng))  # sees the calibration's fit, then it comes off
        events.append((sum(len(p) for p in parts) / RATE_HZ, MOUTHPIECE_OFF))
        add(tidal(subject, clinical_tidal_after_s(subject), rng), [(0.0, "tidal-start")])
        events.append((sum(len(p) for p in parts) / RATE_HZ, "maneuver-end"))
        add(*slow_vc(subject, rng, lead_count=0))
    if protocol == "forced" or whole:
        for k, blow in enumerate(blows[:2] if protocol == "short" else blows):
            add(*forced(subject, blow, rng, lead_count=0 if k == 0 and whole else 1))
    volume = np.concatenate(parts)
    if seconds is not None:
        n = int(round(seconds * RATE_HZ))
        if n > len(volume):
            volume = np.concatenate([volume, tidal(subject, (n - len(volume)) / RATE_HZ, rng)])
        volume = volume[:n]
        events = [(t, label) for t, label in events if t < seconds]
    return Waveform(volume, events)


def natural_duration_s(subject: Subject, protocol: str, seed: int) -> float:
    return protocol_waveform(subject, protocol, None, seed).duration_s


@dataclass(frozen=True)
class Sway:
    """Postural sway: smooth random rigid shifts of the whole subject (mm), peak amplitudes given."""

    axial_mm: float = 50.0
    lateral_mm: float = 15.0
    vertical_mm: float = 3.0
    seed: int = 0
    steps: int = 0  # steps of 20-50 mm, each within 0.5 s, at random times
    steps_span_s: float = 60.0  # the steps fall within this time from the start

    def at(self, t_s: np.ndarray | float) -> np.ndarray:
        """(..., 3) shift in the front camera frame: x lateral, y vertical, z along the axis."""
        t = np.asarray(t_s, dtype=float)
        rng = np.random.default_rng(self.seed + 23)
        out = []
        for amplitude in (self.lateral_mm, self.vertical_mm, self.axial_mm):
            freqs = rng.uniform(0.03, 0.25, 4)
            phases = rng.uniform(0, 2 * np.pi, 4)
            weights = rng.uniform(0.5, 1.0, 4)
            s = sum(w * np.sin(2 * np.pi * f * t + p) for w, f, p in zip(weights, freqs, phases))
            out.append(amplitude * s / weights.sum())
        shift = np.stack(out, axis=-1)
        for k in range(self.steps):
            start = rng.uniform(0.1, 0.9) * self.steps_span_s
            angle = rng.uniform(0, 2 * np.pi)
            size = rng.uniform(20.0, 50.0)
            progress = np.clip((t - start) / 0.5, 0.0, 1.0)
            progress = progress * progress * (3.0 - 2.0 * progress)
            shift = shift + size * progress[..., None] * np.array([np.sin(angle), 0.0, np.cos(angle)])
        return shift
