"""The live volume-time curve of quiet breathing and the slow VC in the patient session, so the
operator sees the breaths and the plateau instead of an empty page (the wizard covers the main
window's curve).

The curves come from engine.blow_trace (seconds from the manoeuvre's mark, litres inhaled positive,
the flow sensor's BTPS with its drift removed, and the optical volume); the slow VC's plateau is
the ATS/ERS criterion: less than 25 mL of change over the last second, once the manoeuvre has moved
the volume by more than PLATEAU_AFTER_L.
"""

from __future__ import annotations

import numpy as np
import pyqtgraph as pg
from PySide6.QtWidgets import QLabel, QVBoxLayout, QWidget

COLOURS = {"flow sensor": "#1f77b4", "optical": "#d62728"}
PLATEAU_WINDOW_S = 1.0
PLATEAU_CHANGE_L = 0.025
PLATEAU_AFTER_L = 0.5  # a pause in quiet breathing is no plateau
SHOWN_S = 30.0  # quiet breathing: the last 30 s


def plateau(t_s: np.ndarray, volume_l: np.ndarray) -> tuple[float | None, float]:
    """(when the slow VC's expiration reached its plateau, s from the mark, or None; the change in
    litres over the last PLATEAU_WINDOW_S). The plateau: a second that changed less than 25 mL at
    the lowest volume so far (within 50 mL), once the manoeuvre moved more than PLATEAU_AFTER_L."""
    t, v = np.asarray(t_s, float), np.asarray(volume_l, float)
    if len(t) < 2 or t[-1] - t[0] < PLATEAU_WINDOW_S:
        return None, float("nan")
    starts = np.searchsorted(t, t - PLATEAU_WINDOW_S)
    lowest, highest = np.minimum.accumulate(v), np.maximum.accumulate(v)
    for i in np.flatnonzero((t - t[0] >= PLATEAU_WINDOW_S) & (highest - lowest > PLATEAU_AFTER_L)
                            & (v <= lowest + 2 * PLATEAU_CHANGE_L)):
        if np.ptp(v[starts[i]:i + 1]) < PLATEAU_CHANGE_L:
            return float(t[i]), float(np.ptp(v[starts[-1]:]))
    return None, float(np.ptp(v[starts[-1]:]))


class VolumeTrace(QWidget):
    """Volume against time per source, and one line of what it says."""

    def __init__(self, parent: QWidget | None = None, window_s: float | None = None) -> None:
        super().__init__(parent)
        self.window_s = window_s
        self.plot = pg.PlotWidget(background="w")
        self.plot.setLabel("left", "volume (L, inhaled up)")
        self.plot.getAxis("left").enableAutoSIPrefix(False)
        self.plot.setLabel("bottom", "s")
        self.plot.addLegend(offset=(10, 10))
        self.plot.setMinimumHeight(160)
        self.curves = {source: self.plot.plot([], [], pen=pg.mkPen(colour, width=2), name=source)
                       for source, colour in COLOURS.items()}
        self.status = QLabel("not started")
        layout = QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.plot, 1)
        layout.addWidget(self.status)

    def show_traces(self, traces: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        for source, curve in self.curves.items():
            t, v = traces.get(source, (np.zeros(0), np.zeros(0)))
            if self.window_s is not None and len(t):
                keep = t >= t[-1] - self.window_s
                t, v = t[keep], v[keep]
            curve.setData(np.asarray(t, float), np.asarray(v, float))

    def main_trace(self, traces) -> tuple[np.ndarray, np.ndarray] | None:
        """The flow sensor's curve where there is one, else the optical one."""
        return traces.get("flow sensor") or traces.get("optical")
