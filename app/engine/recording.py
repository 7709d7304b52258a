"""A live session's recording as the engine keeps it for the operator: the flow sensor's samples and
the protocol's events, the subject's calibration through the flow sensor once it is made, and the
calibrated optical volume after the mouthpiece came off; the values and blow traces after each
manoeuvre come from them by the same analysis as the report."""

from __future__ import annotations

import threading

import numpy as np

from app.engine.flow_record import FlowRecord
from core.analysis.quiet_breathing import QuietBreathingGain, quiet_breathing_gain, with_quiet_breathing_gain
from core.analysis.values import analyse_volume, tidal_windows
from core.volume.flow_sensor import flow_sensor_volume
from core.volume.subject_calibration import MOUTHPIECE_OFF, SubjectCalibration, fit_subject_calibration
from drivers.flowsensor import FlowBlock
from drivers.recorder import Recorder

NO_LIMIT_NS = 2**63 - 1


class SubjectRecording:
    """One recording's data beside its Recorder (which writes the file). `flow_calibration` (gain,
    offset) of the flow sensor in force, None without one; `btps` its volume's factor to BTPS;
    `has_flow` whether the rig has a flow sensor at all."""

    def __init__(self, recorder: Recorder, flow_calibration: tuple[float, float] | None, btps: float,
                 has_flow: bool) -> None:
        self.recorder = recorder
        self._flow_calibration = flow_calibration
        self._btps = btps
        self._has_flow = has_flow
        self._lock = threading.Lock()
        self._flow = FlowRecord()
        self._events: list[tuple[int, str]] = []
        self.calibration: SubjectCalibration | None = None  # the subject's, once made and not refused
        self.quiet_gain: QuietBreathingGain | None = None  # its quiet breathing's (core/analysis/quiet_breathing.py)
        self._mouthpiece_off_ns: int | None = None
        self._optical: list[tuple[int, float]] = []  # (stamp, calibrated litres) after mouthpiece-off
        self._blow_drift: tuple[int, float] | None = None  # (a blow's mark, the flow sensor's drift there, L/s)

    @property
    def mouthpiece_off(self) -> bool:
        return self._mouthpiece_off_ns is not None

    def mark(self, stamp: int, label: str) -> None:
        self.recorder.submit_event(stamp, label)
        with self._lock:
            self._events.append((stamp, label))
            if label == MOUTHPIECE_OFF:  # the flow sensor's samples end here
                self._mouthpiece_off_ns = stamp

    def take_flow(self, block: FlowBlock) -> None:
        """A flow sensor block recorded: what came before the mouthpiece came off."""
        off_ns = self._mouthpiece_off_ns
        if off_ns is not None:
            before = block.timestamp_ns <= off_ns
            block = FlowBlock(block.adc[before], block.counter[before], block.timestamp_ns[before],
                              block.lost if before.any() else 0)
        if len(block.adc):
            self.recorder.submit_flow(block)
            with self._lock:
                self._flow.append(block)

    def take_optical(self, stamp: int, litres: float) -> None:
        """A calibrated optical volume sample (the values after mouthpiece-off come from these)."""
        with self._lock:
            self._optical.append((stamp, litres))

    def flow_until_ns(self) -> int:
        """How far the volume the recording's values come from reaches: the flow sensor's samples, or
        after `mouthpiece-off` the calibrated optical volume's maps (which lag the frames that stamp
        the events by their reconstruction)."""
        with self._lock:
            if self.mouthpiece_off and self.calibration is not None:
                return int(self._optical[-1][0]) if self._optical else 0
            if not self._has_flow or self.mouthpiece_off:
                return NO_LIMIT_NS
            return self._flow.last_ns

    def calibrate(self, start_ns: int, curve: list[tuple[float, dict]], t0_ns: int | None) -> SubjectCalibration:
        """The subject's calibration (core/volume/subject_calibration.py) on the flow sensor's volume and
        the live regional signals `curve` ((s from t0_ns, {region: signal}) per map) from `start_ns` (a
        mark) to now; kept for the live volume when it is not refused."""
        recorded = self.flow_volume()
        if recorded is None or t0_ns is None or not curve:
            return SubjectCalibration.refused_for("calibration-no-signal", "no flow sensor volume or no optical "
                                                  "signal recorded to calibrate on")
        volume, start, marks = recorded
        map_t = (t0_ns + np.array([t for t, _ in curve]) * 1e9 - start) / 1e9
        names = list(curve[-1][1])
        signals = {n: np.array([sig.get(n, np.nan) for _, sig in curve], dtype=float) for n in names}
        flow_t = (volume.timestamp_ns - start) / 1e9
        calibration = fit_subject_calibration(map_t, signals, flow_t, volume.volume_l,
                                              ((start_ns - start) / 1e9, float(flow_t[-1])))
        if "fit_t_s" in calibration.extra:  # the fitted curve on seconds from the mark, as blow_trace has them
            calibration.extra["fit_t_s"] = calibration.extra["fit_t_s"] - (start_ns - start) / 1e9
        if calibration.refused is None:
            gain = quiet_breathing_gain(flow_t, volume.volume_l, map_t, calibration.volume_l(signals), marks,
                                        ((start_ns - start) / 1e9, float(flow_t[-1])))
            with self._lock:
                self.calibration = calibration
                self.quiet_gain = gain
        return calibration

    def values(self, age_years: float | None = None):
        """The pulmonary function values so far, by the report's analysis (core.analysis.values): from
        the flow sensor, or after mouthpiece-off from the calibrated optical volume. None without
        a volume to read them from."""
        if self.mouthpiece_off:  # the cameras alone, through the subject's calibration
            with self._lock:
                optical = np.array(self._optical, dtype=float).reshape(-1, 2)
                events = list(self._events)
            if len(optical) < 10:
                return None
            start = int(optical[0, 0])
            marks = sorted(((t - start) / 1e9, label) for t, label in events)
            return with_quiet_breathing_gain(
                analyse_volume((optical[:, 0] - start) / 1e9, optical[:, 1], marks, age_years, fitted=True),
                self.quiet_gain)
        recorded = self.flow_volume()
        if recorded is None:
            return None
        volume, start, marks = recorded
        return analyse_volume((volume.timestamp_ns - start) / 1e9, volume.volume_l, marks, age_years)

    def flow_volume(self):
        """(the flow sensor's volume so far, its first stamp, the events in s from it), with the drift
        removed as the report removes it; None without a calibrated flow sensor."""
        if self._flow_calibration is None:
            return None
        with self._lock:
            adc, stamps = self._flow.samples()
            events = list(self._events)
        if len(adc) < 2:
            return None
        start = int(stamps[0])
        end_s = (int(stamps[-1]) - start) / 1e9
        # the flow sensor's newest samples arrive a little after the frames that stamp the events
        marks = sorted((min((t - start) / 1e9, end_s) if (t - start) / 1e9 - end_s < 0.5 else (t - start) / 1e9,
                        label) for t, label in events)
        gain, offset = self._flow_calibration
        return flow_sensor_volume(adc, stamps, gain, offset, self._btps, tidal_windows(marks, end_s)), start, marks

    def flow_trace(self, mark_ns: int, before_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The flow sensor's volume (s from the mark, L, BTPS, about 100 samples a second) since `before_s`
        before a manoeuvre's mark, its drift as the report will remove it, taken once from the recording
        up to the mark; None without enough samples or a calibration."""
        if self._flow_calibration is None:
            return None
        if self._blow_drift is None or self._blow_drift[0] != mark_ns:
            recorded = self.flow_volume()
            self._blow_drift = (mark_ns, float(recorded[0].drift_lps[-1]) if recorded is not None else 0.0)
        with self._lock:
            adc, stamps = self._flow.samples()
        keep = stamps >= mark_ns - int(before_s * 1e9)
        adc, stamps = adc[keep], stamps[keep]
        if len(stamps) <= 20:
            return None
        gain, offset = self._flow_calibration
        drift = self._blow_drift[1]
        volume = flow_sensor_volume(adc, stamps, gain, offset - drift / self._btps, self._btps, drift_degree=0)
        step = max(1, len(stamps) // max(1, int((stamps[-1] - stamps[0]) / 1e7)))  # about 100 per second
        return (volume.timestamp_ns[::step] - mark_ns) / 1e9, volume.volume_l[::step]
