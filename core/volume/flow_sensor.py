"""Flow-sensor volume: ADC counts to litres at BTPS, with the zero drift removed.

flow (L/s) = gain * adc + offset (thesis eq. 5.4, the calibration in force), times the BTPS
factor of the room when the sensor measured at ATPS. Integrating a flow whose zero has drifted
turns an offset into a ramp of volume; the drift is estimated from the end-expiratory levels of
tidal breathing, which are stable over minutes in a resting subject, and removed as a
polynomial in time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import find_peaks

BODY_TEMPERATURE_C = 37.0
WATER_VAPOUR_AT_BODY_KPA = 6.275


def saturated_vapour_pressure_kpa(temperature_c: float) -> float:
    """Magnus formula (Alduchov and Eskridge, 1996), over water."""
    return 0.61094 * float(np.exp(17.625 * temperature_c / (temperature_c + 243.04)))


def btps_factor(temperature_c: float, pressure_hpa: float, humidity_pct: float) -> float:
    """Volume at BTPS over volume at ATPS (ATS/ERS): (310.15 / T) * (PB - PH2O) / (PB - 6.275 kPa)."""
    if not -10 <= temperature_c <= 45:
        raise ValueError(f"room temperature {temperature_c} C is outside -10-45 C")
    if not 500 <= pressure_hpa <= 1100:
        raise ValueError(f"barometric pressure {pressure_hpa} hPa is outside 500-1100 hPa")
    if not 0 <= humidity_pct <= 100:
        raise ValueError(f"relative humidity {humidity_pct} % is outside 0-100 %")
    pb_kpa = pressure_hpa / 10.0
    ph2o = humidity_pct / 100.0 * saturated_vapour_pressure_kpa(temperature_c)
    return (273.15 + BODY_TEMPERATURE_C) / (273.15 + temperature_c) * (pb_kpa - ph2o) / (pb_kpa - WATER_VAPOUR_AT_BODY_KPA)


@dataclass
class FlowVolume:
    timestamp_ns: np.ndarray
    flow_lps: np.ndarray  # BTPS, positive = inspiration
    volume_l: np.ndarray  # BTPS, drift removed, zero at the start
    drift_lps: np.ndarray  # the zero drift that was removed (in flow)
    btps: float


def end_expiratory_points(t_s: np.ndarray, volume_l: np.ndarray, min_breath_s: float = 1.5,
                          min_tidal_l: float = 0.1) -> np.ndarray:
    """Indices of breath minima (end of expiration) of tidal breathing."""
    rate = 1.0 / np.median(np.diff(t_s))
    smooth = np.convolve(volume_l, np.ones(max(1, int(0.1 * rate))) / max(1, int(0.1 * rate)), mode="same")
    minima, _ = find_peaks(-smooth, distance=max(1, int(min_breath_s * rate)), prominence=min_tidal_l)
    return minima


def flow_sensor_volume(adc: np.ndarray, timestamp_ns: np.ndarray, gain_lps: float, offset_lps: float,
                       btps: float = 1.0, tidal_windows_s: list[tuple[float, float]] | None = None,
                       drift_degree: int = 2) -> FlowVolume:
    """Volume from the flow sensor; drift fitted on end-expiratory levels inside the tidal windows
    (seconds from the start; default: the whole recording)."""
    t = (np.asarray(timestamp_ns, dtype=np.int64) - int(timestamp_ns[0])) / 1e9
    flow = (gain_lps * np.asarray(adc, dtype=float) + offset_lps) * btps
    dt = np.diff(t, prepend=t[0])
    raw = np.cumsum(flow * dt)
    minima = end_expiratory_points(t, raw)
    if tidal_windows_s:
        inside = np.zeros(len(minima), dtype=bool)
        for start, end in tidal_windows_s:
            inside |= (t[minima] >= start) & (t[minima] <= end)
        minima = minima[inside]
    drift_volume = np.zeros_like(raw)
    if len(minima) >= 2:
        degree = min(drift_degree, len(minima) - 1)
        coefficients = np.polyfit(t[minima], raw[minima], degree)
        drift_volume = np.polyval(coefficients, t) - np.polyval(coefficients, t[0])
    volume = raw - drift_volume
    drift_flow = np.gradient(drift_volume, t) if len(t) > 1 else np.zeros_like(t)
    return FlowVolume(np.asarray(timestamp_ns, dtype=np.int64), flow - drift_flow, volume - volume[0],
                      drift_flow, btps)
