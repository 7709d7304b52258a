"""The forced-blow screen: during each blow the flow-volume loop and the volume-time curve as they
happen (flow sensor and optical side by side), the back-extrapolated volume, time since time zero
and the end-of-test plateau; all blows overlaid with accept/reject and the best marked; the
repeatability against the ATS/ERS 2019 tolerance; the predicted FVC on the loop; for a child, a
bar to fill."""

from __future__ import annotations

from datetime import datetime, timezone

import numpy as np
import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import QGridLayout, QLabel, QProgressBar, QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget

from app.report_data import references_on
from core.analysis.blow_monitor import LiveBlow, best_blow, live_blow
from core.analysis.spirometry import ForcedValues, SessionGrade, repeatability_tolerance_l
from core.analysis.values import pef_not_given

SOURCES = {"flow sensor": (31, 119, 180), "optical": (230, 120, 20)}
CHILD_AGE_YEARS = 12  # younger patients get the incentive bar


def _plot(title: str, x: str, x_unit: str, y: str, y_unit: str) -> pg.PlotWidget:
    plot = pg.PlotWidget(background="w", title=title)
    plot.setLabel("bottom", x, units=x_unit)
    plot.setLabel("left", y, units=y_unit)
    for axis in ("bottom", "left"):
        plot.getAxis(axis).enableAutoSIPrefix(False)
    plot.showGrid(x=True, y=True, alpha=0.2)
    return plot


class BlowScreen(QWidget):
    def __init__(self, age_years: float | None = None, predicted_fvc_l: float | None = None, parent=None) -> None:
        super().__init__(parent)
        self.age_years = age_years
        self.loop = _plot("Flow-volume", "volume exhaled", "L", "flow", "L/s")
        self.volume_time = _plot("Volume-time", "time from time zero", "s", "volume exhaled", "L")
        # a curve is named in the legend once it is drawn: after the mouthpiece comes off there is no
        # flow sensor's blow to name
        self.legend = self.loop.addLegend(offset=(-10, 10))
        self.named: set[str] = set()
        self.live = {}
        for source, colour in SOURCES.items():
            pen = pg.mkPen(colour, width=3, style=Qt.PenStyle.SolidLine if source == "flow sensor"
                           else Qt.PenStyle.DashLine)
            self.live[source] = (self.loop.plot([], [], pen=pen), self.volume_time.plot([], [], pen=pen))
            for item in self.live[source]:
                item.setZValue(10)  # this blow over the earlier ones
        self.earlier: list[tuple[pg.PlotDataItem, pg.PlotDataItem]] = []
        self.curves: list[LiveBlow] = []  # the flow sensor's curve of each finished blow
        self.predicted_fvc_l = predicted_fvc_l
        if predicted_fvc_l:
            line = pg.InfiniteLine(predicted_fvc_l, angle=90, pen=pg.mkPen((120, 120, 120), width=1,
                                                                          style=Qt.PenStyle.DotLine),
                                   label=f"predicted FVC {predicted_fvc_l:.2f} L", labelOpts={"position": 0.5})
            self.loop.addItem(line)
        self.loop.setXRange(0, max(predicted_fvc_l or 0.0, 3.0) * 1.15)
        self.volume_time.setXRange(-0.5, 8.0)
        self.status = QLabel("Press Start blow, then the patient blows.")
        self.status.setWordWrap(True)
        self.status.setStyleSheet("font-size: 14px")
        self.end_of_test = QLabel("end of test: not yet")
        self.repeatability = QLabel("repeatability: after two acceptable blows")
        self.repeatability.setWordWrap(True)
        self.pef_note = QLabel("no predicted PEF is drawn: the GLI equations have none")
        self.pef_note.setStyleSheet("color: #666")
        self.table = QTableWidget(0, 8)
        self.table.setHorizontalHeaderLabels(["blow", "FVC (L)", "FEV1 (L)", "PEF (L/s)", "FET (s)", "BEV (mL)",
                                              "verdict", "best"])
        self.table.setMaximumHeight(170)
        self.table.verticalHeader().setVisible(False)
        self.incentive = QProgressBar()
        self.incentive.setRange(0, 100)
        self.incentive.setFormat("blow the bar full! %p %")
        self.incentive.setVisible(age_years is not None and age_years < CHILD_AGE_YEARS and bool(predicted_fvc_l))
        grid = QGridLayout()
        grid.addWidget(self.loop, 0, 0)
        grid.addWidget(self.volume_time, 0, 1)
        layout = QVBoxLayout(self)
        layout.addLayout(grid, 3)
        layout.addWidget(self.incentive)
        layout.addWidget(self.status)
        layout.addWidget(self.end_of_test)
        layout.addWidget(self.repeatability)
        layout.addWidget(self.pef_note)
        layout.addWidget(self.table, 1)
        self.current: dict[str, LiveBlow] = {}

    def show_live(self, traces: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
        """The blow so far, from engine.blow_trace: (s from the mark, L positive inhaled) per source."""
        self.current = {s: live_blow(t, v, 0.0) for s, (t, v) in traces.items() if s in SOURCES}
        for source, (loop, volume_time) in self.live.items():
            blow = self.current.get(source)
            if blow is None or not len(blow.t_s):
                loop.setData([], [])
                volume_time.setData([], [])
                continue
            loop.setData(blow.exhaled_l, blow.flow_lps)
            volume_time.setData(blow.t_s, blow.exhaled_l)
            self._name(source, loop, f"{source}, this blow")
            self._fit_axes(blow)
        main = self.current.get("flow sensor") or self.current.get("optical")
        if main is None:
            self.status.setText("no volume yet")
            return
        optical = self.current.get("optical")
        extra = (f"; optical {optical.values.fvc_l:.2f} L" if optical is not None and optical.values is not None
                 and main is not optical else "")
        self.status.setText(main.status() + extra)
        self._show_end(main)
        if self.incentive.isVisible() and main.values is not None:
            self.incentive.setValue(int(min(100.0, 100.0 * main.values.fvc_l / self.predicted_fvc_l)))

    def _name(self, key: str, item: pg.PlotDataItem, name: str) -> None:
        if key not in self.named:
            self.named.add(key)
            self.legend.addItem(item, name)

    def _fit_axes(self, blow: LiveBlow) -> None:
        """Widen the axes when a blow goes past them (never narrowed during a session)."""
        if len(blow.exhaled_l) and blow.exhaled_l[-1] * 1.08 > self.loop.viewRange()[0][1]:
            self.loop.setXRange(0, blow.exhaled_l[-1] * 1.15)
        if len(blow.t_s) and blow.t_s[-1] + 0.5 > self.volume_time.viewRange()[0][1]:
            self.volume_time.setXRange(-0.5, blow.t_s[-1] + 2.0)

    def _show_end(self, blow: LiveBlow) -> None:
        if blow.end_of_test:
            self.end_of_test.setText(f"END OF TEST reached (plateau, FET {blow.values.fet_s:.1f} s): "
                                     "the patient may breathe in")
            self.end_of_test.setStyleSheet("color: white; background: #1b7f3b; font-weight: bold; padding: 3px")
        elif blow.started:
            self.end_of_test.setText(f"end of test: not yet (FET {blow.values.fet_s:.1f} s) — keep blowing")
            self.end_of_test.setStyleSheet("color: black; background: #ffd54f; padding: 3px")
        else:
            self.end_of_test.setText("end of test: not started")
            self.end_of_test.setStyleSheet("")

    def finish_blow(self, grade: SessionGrade | None) -> None:
        """The blow just ended: its curve joins the earlier ones; every blow's verdict and the best
        as the session's grade has them (acceptability depends on the other blows)."""
        blow = self.current.get("flow sensor") or self.current.get("optical")
        if blow is not None and len(blow.t_s):
            self.curves.append(blow)
            grey = pg.mkPen((150, 150, 150), width=1)
            self.earlier.append((self.loop.plot(blow.exhaled_l, blow.flow_lps, pen=grey),
                                 self.volume_time.plot(blow.t_s, blow.exhaled_l, pen=grey)))
        for loop, volume_time in self.live.values():
            loop.setData([], [])
            volume_time.setData([], [])
        self.current = {}
        if grade is not None:
            self.show_grade(grade)

    def reject_last(self) -> None:
        """The operator rejected the last blow: its curve goes."""
        if self.earlier:
            for item, plot in zip(self.earlier.pop(), (self.loop, self.volume_time)):
                plot.removeItem(item)
            self.curves.pop()
        self.table.setRowCount(len(self.earlier))

    def show_grade(self, grade: SessionGrade) -> None:
        blows = grade.manoeuvres
        best = best_blow(blows)
        self.table.setRowCount(len(blows))
        for row, b in enumerate(blows):
            why_no_pef = pef_not_given(b)
            cells = (f"{row + 1}", f"{b.fvc_l:.2f}", f"{b.fev1_l:.2f}", f"{b.pef_lps:.1f}" if why_no_pef is None else "—",
                     f"{b.fet_s:.1f}", f"{1000 * b.bev_l:.0f}" if b.bev_judged else "—", blow_verdict(b),
                     "★ best" if row == best else "")
            for column, text in enumerate(cells):
                item = QTableWidgetItem(text)
                item.setFlags(item.flags() & ~Qt.ItemFlag.ItemIsEditable)
                if column == 6:
                    item.setForeground(pg.mkColor("#1b7f3b" if b.fvc_acceptable else
                                                  "#b26a00" if b.fev1_acceptable else "#b00020"))
                    item.setToolTip("; ".join(b.problems))
                if column == 3 and why_no_pef is not None:
                    item.setToolTip(f"PEF not given: {why_no_pef}")
                if column == 5 and not b.bev_judged:
                    item.setToolTip(next(p for p in b.problems if p.startswith("start not judged")))
                self.table.setItem(row, column, item)
        self.table.resizeColumnsToContents()
        if best is not None:
            self._name("best", pg.PlotDataItem(pen=pg.mkPen((27, 127, 59), width=3)), "best blow so far")
        for k, (loop, volume_time) in enumerate(self.earlier):
            pen = (pg.mkPen((27, 127, 59), width=3) if k == best else
                   pg.mkPen((150, 150, 150), width=1) if k < len(blows) and blows[k].fvc_usable else
                   pg.mkPen((200, 120, 120), width=1, style=Qt.PenStyle.DotLine))
            loop.setPen(pen)
            volume_time.setPen(pen)
        self.repeatability.setText(repeatability_text(grade, self.age_years))


def blow_verdict(blow: ForcedValues) -> str:
    """The blow table's verdict in a few words; the problems in full are its tooltip and the feedback
    under the table (a 1366 px screen showed a tenth of them)."""
    unjudged = [] if blow.bev_judged else ["start not judged"]
    if blow.fvc_acceptable:
        return "acceptable" + (f" ({unjudged[0]})" if unjudged else "")
    failed = [reason for reason, fails in (("hesitant start", not blow.bev_ok), ("cough", blow.cough_in_first_second),
                                           ("no plateau", not blow.eofe)) if fails]
    return ("FEV1 acceptable" if blow.fev1_acceptable else "rejected") + f" ({', '.join(failed + unjudged)})"


def repeatability_text(grade: SessionGrade, age_years: float | None) -> str:
    """The two largest FVC and FEV1 of the acceptable blows against the ATS/ERS 2019 tolerance."""
    parts = []
    for name, spread, largest, count in (("FVC", grade.fvc_repeatability_l, grade.fvc_l, grade.acceptable_fvc),
                                         ("FEV1", grade.fev1_repeatability_l, grade.fev1_l, grade.acceptable_fev1)):
        tolerance = repeatability_tolerance_l(largest, age_years)
        if count < 2 or not np.isfinite(spread):
            parts.append(f"{name}: {count} acceptable, two needed")
        else:
            parts.append(f"{name} within {1000 * spread:.0f} mL of each other "
                         f"({'met' if spread <= tolerance else 'NOT met'}: tolerance {1000 * tolerance:.0f} mL)")
    return f"Repeatability (grade {grade.grade}): " + "; ".join(parts)


def predicted_fvc_l(patient, day=None) -> float | None:
    """The patient's predicted FVC (GLI) for the loop, None where there is no equation for them."""
    if patient is None:
        return None
    reference = references_on(patient, day or datetime.now(timezone.utc), "gli-global").get("FVC")
    return float(reference.predicted) if reference is not None else None

