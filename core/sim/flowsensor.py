"""The simulated pneumotachometer: a 12-bit ADC at 1000 samples/s behind an affine transfer.

    flow (L/s) = gain * adc + offset        (thesis eq. 5.4: gain 0.002085, offset -4.007)

The sensor sees gas at room conditions (ATPS): the lungs' (BTPS) flow divided by the BTPS
factor of the room. Noise (counts) and a slow zero drift are added before rounding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from core.volume.flow_sensor import btps_factor

@dataclass(frozen=True)
class FlowSensorModel:
    gain_lps: float = 0.0075  # L/s per count: +-15.4 L/s over 12 bits, room for a forced expiration
    offset_lps: float = -15.36
    adc_bits: int = 12
    sample_rate_hz: float = 1000.0
    noise_counts: float = 1.2
    drift_counts_per_min: float = 2.0
    room_temperature_c: float = 23.0
    room_pressure_hpa: float = 1013.0
    room_humidity_pct: float = 45.0
    sensor: str = "simulated pneumotachometer (12-bit ADC)"

    @property
    def btps(self) -> float:
        return btps_factor(self.room_temperature_c, self.room_pressure_hpa, self.room_humidity_pct)

    def adc_counts(self, flow_btps_lps: np.ndarray, t_s: np.ndarray, seed: int) -> np.ndarray:
        """ADC counts (int32) for the lungs' flow (L/s, positive = inspiration) at times t_s."""
        rng = np.random.default_rng(seed + 31)
        flow_atps = np.asarray(flow_btps_lps, dtype=float) / self.btps
        counts = (flow_atps - self.offset_lps) / self.gain_lps
        counts = counts + self.noise_counts * rng.standard_normal(len(counts))
        counts = counts + self.drift_counts_per_min * np.asarray(t_s) / 60.0
        full_scale = (1 << self.adc_bits) - 1
        return np.clip(np.round(counts), 0, full_scale).astype(np.int32)

    def file_attrs(self) -> dict[str, object]:
        return {"positive": "inspiration", "room_temperature_c": self.room_temperature_c,
                "room_pressure_hpa": self.room_pressure_hpa, "room_humidity_pct": self.room_humidity_pct}
