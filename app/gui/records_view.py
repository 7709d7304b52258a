"""The clinician's window on the records: a patient's visits, their trend, the interpretation of a
visit, its comment, sign-off and amendments, its bronchodilator pair; and the audit trail.

Every change goes through app.records, which checks the acting user's role and writes the audit
entry in the same transaction; a refusal is shown as the one line it is.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import pyqtgraph as pg
from PySide6.QtCore import Qt
from PySide6.QtWidgets import (QAbstractItemView, QComboBox, QDialog, QDialogButtonBox, QFileDialog, QGroupBox,
                               QHBoxLayout, QLabel, QLineEdit, QListWidget, QListWidgetItem, QMenu, QPlainTextEdit,
                               QPushButton, QSplitter, QTableWidget, QTableWidgetItem, QVBoxLayout, QWidget)

from app.export import values_csv, volume_csv
from app.fhir_export import write_fhir
from app.gdt_export import write_gdt
from app.gui.errors import show_error
from app.gui.processing import ProcessingPanel
from app.records import Patient, Records, RecordsError, SessionRecord
from app.report_access import log_report, never_ask, report_for
from app.report_data import TREND_VALUES, build_report, source_values, stored_interpretation, trend_points
from app.report_pdf import write_report
from app.session_processing import NOT_A_VISIT
from core.analysis.registry import BY_KEY
from core.io.outputs import OutputError, check_output

TREND_PENS = {"FEV1": pg.mkPen("#1f5fa8", width=2), "FVC": pg.mkPen("#b85c00", width=2, style=Qt.PenStyle.DashLine),
              "FEV1_FVC": pg.mkPen("#333333", width=1.5, style=Qt.PenStyle.DotLine)}
LLN_PEN = pg.mkPen("#aa0000", width=1, style=Qt.PenStyle.DashLine)


def _number(value, digits: int = 2) -> str:
    return f"{value:.{digits}f}" if isinstance(value, (int, float)) else "–"


class TrendPlot(QWidget):
    """FEV1, FVC (litres) and the z-scores of FEV1, FVC, FEV1/FVC over the visits, with the LLN."""

    def __init__(self) -> None:
        super().__init__()
        layout = QHBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        self.litres = pg.PlotWidget(axisItems={"bottom": pg.DateAxisItem()})
        self.z = pg.PlotWidget(axisItems={"bottom": pg.DateAxisItem()})
        for plot, label, corner in ((self.litres, "litres", (10, -10)), (self.z, "z-score", (-10, -10))):
            plot.setBackground("w")
            plot.showGrid(y=True, alpha=0.2)
            plot.setLabel("left", label)
            plot.addLegend(offset=corner)  # bottom corners: the values of healthy visits sit at the top
            plot.setMouseEnabled(x=False, y=False)
            layout.addWidget(plot)

    def show_points(self, points) -> None:
        self.litres.clear()
        self.z.clear()
        times = [datetime.fromisoformat(p.recorded).timestamp() for p in points]
        for name, key in TREND_VALUES:
            if name != "FEV1_FVC":
                xy = [(t, p.values[key]) for t, p in zip(times, points) if key in p.values]
                if xy:
                    self.litres.plot(*zip(*xy), pen=TREND_PENS[name], symbol="o", symbolSize=6, name=name)
            xy = [(t, p.z[name]) for t, p in zip(times, points) if name in p.z]
            if xy:
                self.z.plot(*zip(*xy), pen=TREND_PENS[name], symbol="o", symbolSize=6,
                            name=name.replace("_", "/"))
        self.z.addItem(pg.InfiniteLine(pos=-1.645, angle=0, pen=LLN_PEN, label="LLN", labelOpts={"position": 0.05}))
        # litres from zero and z over at least -3..3: a year's change reads at its true size
        litres = [v for p in points for k, v in p.values.items() if k != "FEV1_FVC"]
        self.litres.setYRange(0.0, max(litres, default=1.0) * 1.15, padding=0)
        zs = [v for p in points for v in p.z.values()]
        self.z.setYRange(min(-3.0, min(zs, default=0.0) - 0.5), max(3.0, max(zs, default=0.0) + 0.5), padding=0)


# The values shown per source for a visit, as the report names them
VISIT_VALUES = tuple(BY_KEY[key] for key in ("FEV1_l", "FVC_l", "FEV1_FVC", "VC_l", "TV_l", "RR_bpm"))
SOURCE_LABELS = {"flow sensor": "flow sensor", "optical": "optical (made before its kind was recorded)"}


def values_by_source_html(summary: dict) -> str:
    """The visit's stored values, one row per source, the optical beside the flow sensor's; an
    optical volume refused says why."""
    rows = []
    for source, values in summary.items():
        if not isinstance(values, dict):
            continue
        if "refused" in values and not any(v.key in values for v in VISIT_VALUES):
            rows.append(f"<tr><td><b>{source}</b></td><td colspan=6>no values: {values['refused']}</td></tr>")
            continue
        label = str(values.get("label") or SOURCE_LABELS.get(source, source))
        cells = "".join(f"<td>{v.label} {float(values[v.key]):.{v.decimals}f}{' ' + v.unit if v.unit else ''}</td>"
                        for v in VISIT_VALUES if isinstance(values.get(v.key), (int, float)))
        rows.append(f"<tr><td><b>{label}</b></td>{cells or '<td>no values</td>'}</tr>")
    if not rows:
        return "No values stored for this visit: process it (Process again)."
    return "<table cellspacing=0 cellpadding=2>" + "".join(rows) + "</table>"


EXPORTS = {"pdf": "Report (PDF)", "fhir": "FHIR bundle (pseudonymous)", "fhir-identified": "FHIR bundle, identified",
           "gdt": "GDT record", "csv": "CSV: values and curves"}


def export_visit(records: Records, visit: SessionRecord, kind: str, output: Path, equations: str) -> str:
    """One visit's export as the command line's `report` and `export` make it: who may, asked and
    logged alike (app/report_access.py; FHIR and CSV a clinician's, identified ones with the password)."""
    source = visit.results_path if visit.results_path and visit.results_path.exists() else visit.session_path
    if kind == "pdf":
        check_output(output, [source, visit.session_path, records.path], force=True)
        data, withheld = report_for(source, records, equations, ask=never_ask)
        written = write_report(data, output)
        log_report(records, source, written, data.patient is not None)
        return f"Report written: {written}" + ("" if withheld is None else " (pseudonymous)")
    action = "export identified" if kind in ("fhir-identified", "gdt") else "export"
    records.check_permitted(action)
    records.require_password(action, never_ask)
    if kind == "csv":
        output.mkdir(parents=True, exist_ok=True)
        data = build_report(source, with_maps=False)
        written = [volume_csv(data, output / "volume.csv"), values_csv(data, output / "values.csv")]
    else:
        check_output(output, [source, visit.session_path, records.path], force=True)
        data = build_report(source, records=records, equations=equations, with_maps=False)
        written = [write_fhir(data, output, identified=kind == "fhir-identified") if kind.startswith("fhir")
                   else write_gdt(data, output)[0]]
    records.log("export", str(source.resolve()), {kind: ", ".join(str(p) for p in written)})
    return f"{EXPORTS[kind]} written: {', '.join(str(p) for p in written)}"


class RecordsWindow(QDialog):
    def __init__(self, parent=None, records: Records | None = None, equations: str = "gli-global",
                 processing=None) -> None:
        """`processing`: the main window's ProcessingPanel, which "Process again" hands a visit to (a
        panel of this window's own where none is given)."""
        super().__init__(parent)
        self.setWindowTitle("Patient records")
        self.records = records or Records()
        self.equations = equations
        actor = self.records.actor
        self.patient: Patient | None = None
        self.visits: list[SessionRecord] = []

        self.search = QLineEdit(placeholderText="Search name, number or pseudonym")
        self.search.textChanged.connect(self._find)
        self.patients = QListWidget()
        self.patients.currentItemChanged.connect(self._choose_patient)
        left = QWidget()
        column = QVBoxLayout(left)
        column.addWidget(self.search)
        column.addWidget(self.patients)

        self.table = QTableWidget(0, 7)
        self.table.setHorizontalHeaderLabels(["Recorded", "Status", "FEV1 (L)", "FVC (L)", "FEV1/FVC", "Grade",
                                              "Report"])
        self.table.setSelectionBehavior(QAbstractItemView.SelectionBehavior.SelectRows)
        self.table.setSelectionMode(QAbstractItemView.SelectionMode.SingleSelection)
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.verticalHeader().hide()
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.itemSelectionChanged.connect(self._choose_visit)
        self.trend = TrendPlot()

        self.interpretation = QLabel(wordWrap=True)
        self.interpretation.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.comment = QPlainTextEdit(placeholderText="The clinician's comment")
        self.comment.setMaximumHeight(70)
        self.save_comment = QPushButton("Save comment", clicked=self._save_comment)
        self.sign = QPushButton("Sign report", clicked=self._sign)
        self.signed = QLabel(wordWrap=True)
        self.amendment = QLineEdit(placeholderText="Amendment to the signed report")
        self.amend = QPushButton("Add amendment", clicked=self._amend)
        self.pre = QComboBox()
        self.link = QPushButton("Link as post-bronchodilator", clicked=self._link)

        self.processing = processing or ProcessingPanel(self)
        self.processing.finished.connect(self._processed)
        self.processing.problem.connect(self._processing_problem)
        self.process_again = QPushButton("Process again", clicked=self._process_again)
        self.export = QPushButton("Export")
        menu = QMenu(self.export)
        for kind, label in EXPORTS.items():
            menu.addAction(label, lambda kind=kind: self._export(kind))
        self.export.setMenu(menu)
        self.values = QLabel(wordWrap=True)
        self.values.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        review = QGroupBox("Review of the selected visit")
        box = QVBoxLayout(review)
        box.addWidget(self.values)
        box.addWidget(self.interpretation)
        box.addWidget(self.comment)
        row = QHBoxLayout()
        for w in (self.save_comment, self.sign):
            row.addWidget(w)
        row.addStretch(1)
        row.addWidget(self.export)
        row.addWidget(self.process_again)
        box.addLayout(row)
        box.addWidget(self.signed)
        row = QHBoxLayout()
        row.addWidget(self.amendment, 1)
        row.addWidget(self.amend)
        box.addLayout(row)
        row = QHBoxLayout()
        row.addWidget(QLabel("Pre-bronchodilator visit:"))
        row.addWidget(self.pre, 1)
        row.addWidget(self.link)
        box.addLayout(row)

        right = QWidget()
        column = QVBoxLayout(right)
        column.addWidget(self.table, 2)
        column.addWidget(QLabel("Trend over the visits (GLI z-scores; the red line is the lower limit of normal)"))
        column.addWidget(self.trend, 3)
        column.addWidget(review)
        splitter = QSplitter()
        splitter.addWidget(left)
        splitter.addWidget(right)
        splitter.setStretchFactor(1, 3)
        self.user = QLabel(f"Acting as {actor.name} ({actor.role})" if self.records.roles_enforced else
                           f"Acting as {actor.name} (roles not enforced: no users registered)")
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Close, rejected=self.reject)
        layout = QVBoxLayout(self)
        layout.addWidget(splitter)
        bottom = QHBoxLayout()
        bottom.addWidget(self.user)
        bottom.addStretch(1)
        if processing is None:
            bottom.addWidget(self.processing)
        bottom.addWidget(buttons)
        layout.addLayout(bottom)
        self.resize(1200, 820)
        self._find("")
        self._choose_visit()

    def _find(self, text: str) -> None:
        self.patients.clear()
        for p in self.records.find_patients(text):
            item = QListWidgetItem(f"{p.display_name}  ({p.patient_number or p.pseudonym})")
            item.setData(Qt.ItemDataRole.UserRole, p.id)
            self.patients.addItem(item)
        if self.patients.count():
            self.patients.setCurrentRow(0)

    def _choose_patient(self, item: QListWidgetItem | None) -> None:
        self.patient = self.records.patient(item.data(Qt.ItemDataRole.UserRole)) if item is not None else None
        self._show_visits()

    def _show_visits(self, keep: int | None = None) -> None:
        self.visits = self.records.history(self.patient.id) if self.patient else []
        self.table.setRowCount(len(self.visits))
        for k, visit in enumerate(self.visits):
            _, values = source_values(visit.summary)
            state = self.records.report_state(visit.id)
            cells = [f"{visit.recorded:%Y-%m-%d %H:%M}", visit.status, _number(values.get("FEV1_l")),
                     _number(values.get("FVC_l")), _number(values.get("FEV1_FVC")), str(values.get("grade", "–")),
                     "signature void: data changed" if state.signature_broken else
                     f"signed by {state.signed_by}" if state.signed else "not signed"]
            for j, text in enumerate(cells):
                self.table.setItem(k, j, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        self.trend.show_points(trend_points(self.records, self.patient, self.equations) if self.patient else [])
        if self.visits:
            self.table.selectRow(keep if keep is not None else len(self.visits) - 1)
        self._choose_visit()

    def _visit(self) -> SessionRecord | None:
        rows = self.table.selectionModel().selectedRows()
        return self.visits[rows[0].row()] if rows and rows[0].row() < len(self.visits) else None

    def _choose_visit(self) -> None:
        visit = self._visit()
        for w in (self.comment, self.save_comment, self.sign, self.amendment, self.amend, self.pre, self.link,
                  self.process_again, self.export):
            w.setEnabled(visit is not None)
        if visit is None:
            self.interpretation.setText("Choose a visit.")
            self.signed.setText("")
            self.values.setText("")
            return
        self.values.setText(values_by_source_html(visit.summary))
        source, values = source_values(visit.summary)
        verdict = stored_interpretation(self.patient, values, visit.recorded, source, self.equations)
        self.interpretation.setText(f"<b>{verdict.summary}</b> (ERS/ATS 2022)<br>" + "<br>".join(verdict.statements))
        state = self.records.report_state(visit.id)
        self.comment.setPlainText(state.comment)
        self.comment.setReadOnly(state.signed)
        self.save_comment.setEnabled(not state.signed)
        self.sign.setEnabled(not state.signed)
        self.amendment.setEnabled(state.signed)
        self.amend.setEnabled(state.signed)
        lines = [f"Signature void: {state.signature_broken}." if state.signature_broken else
                 f"Signed by {state.signed_by} on {state.signed_at:%Y-%m-%d %H:%M} UTC: read-only." if state.signed
                 else "Not signed: a preliminary report."]
        lines += [f"Amendment by {a.user} on {a.time:%Y-%m-%d %H:%M}: {a.text}" for a in state.amendments]
        pre = self.records.pre_bronchodilator(visit.id)
        if pre is not None:
            lines.append(f"Post-bronchodilator visit of {pre.recorded:%Y-%m-%d %H:%M}.")
        self.signed.setText("\n".join(lines))
        self.pre.clear()

        for earlier in self.visits:
            if earlier.recorded < visit.recorded and earlier.status not in NOT_A_VISIT:
                self.pre.addItem(f"{earlier.recorded:%Y-%m-%d %H:%M}", earlier.id)
        self.link.setEnabled(self.pre.count() > 0 and pre is None)

    def _act(self, change) -> None:
        visit = self._visit()
        if visit is None:
            return
        row = self.visits.index(visit)
        try:
            change(visit.id)
        except RecordsError as exc:
            from app.gui.errors import show_error

            show_error(self, "The change was not made.", str(exc))
            return
        self._show_visits(keep=row)

    def _export(self, kind: str) -> None:
        visit = self._visit()
        if visit is None:
            return
        suffix = {"pdf": ".pdf", "fhir": ".json", "fhir-identified": ".json", "gdt": ".gdt", "csv": ""}[kind]
        source = visit.results_path or visit.session_path
        suggested = str(source.with_name(source.stem + ("-csv" if kind == "csv" else "") + suffix))
        if kind == "csv":
            chosen = QFileDialog.getExistingDirectory(self, "CSV into which folder?", str(source.parent))
        else:
            chosen, _ = QFileDialog.getSaveFileName(self, f"{EXPORTS[kind]}: save as", suggested)
        if chosen:
            self.export_to(kind, Path(chosen))

    def export_to(self, kind: str, output: Path) -> str | None:
        """The chosen visit exported (EXPORTS), logged in the audit trail; what was written, in words,
        also shown under the values (None and a dialog where it was refused)."""
        visit = self._visit()
        if visit is None:
            return None
        try:
            said = export_visit(self.records, visit, kind, output, self.equations)
        except (RecordsError, ValueError, OSError, OutputError) as exc:
            show_error(self, "Nothing was exported.", str(exc))
            return None
        self.values.setText(self.values.text() + f"<p>{said}</p>")
        return said

    def _process_again(self) -> None:
        visit = self._visit()
        if visit is not None:
            self.processing.start(visit.id, visit.session_path.name, self.records.path)

    def _processed(self, outcome) -> None:
        visit = self._visit()
        self._show_visits(keep=self.visits.index(visit) if visit in self.visits else None)

    def _processing_problem(self, message: str) -> None:
        self.values.setText(f"<span style='color:#b00020'>{message}</span>")

    def _save_comment(self) -> None:
        self._act(lambda sid: self.records.set_comment(sid, self.comment.toPlainText().strip()))

    def _sign(self) -> None:
        self._act(self.records.sign_report)

    def _amend(self) -> None:
        text = self.amendment.text()
        self._act(lambda sid: self.records.amend_report(sid, text))
        self.amendment.clear()

    def _link(self) -> None:
        pre_id = self.pre.currentData()
        self._act(lambda sid: self.records.link_bronchodilator(pre_id, sid))


class AuditWindow(QDialog):
    """The audit trail, newest first, with the hash chain's verdict."""

    def __init__(self, parent=None, records: Records | None = None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Audit trail")
        self.records = records or Records(read_only=True)
        broken = self.records.verify_audit_trail()
        self.verdict = QLabel(f"<b style='color:#b00000'>The audit trail was tampered with: {broken}</b>" if broken
                              else "The hash chain is whole: no entry was changed, removed or inserted.")
        entries = list(reversed(self.records.audit_trail()))
        self.table = QTableWidget(len(entries), 5)
        self.table.setHorizontalHeaderLabels(["Time (UTC)", "User", "Role", "Action", "About"])
        self.table.setEditTriggers(QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.verticalHeader().hide()
        for k, e in enumerate(entries):
            about = e.target + ("  " + ", ".join(f"{key}: {value}" for key, value in e.details.items()
                                                 if value not in (None, "")) if e.details else "")
            for j, text in enumerate((e.time[:19].replace("T", " "), e.user, e.role, e.action, about)):
                self.table.setItem(k, j, QTableWidgetItem(text))
        self.table.resizeColumnsToContents()
        self.table.horizontalHeader().setStretchLastSection(True)
        layout = QVBoxLayout(self)
        layout.addWidget(self.verdict)
        layout.addWidget(self.table)
        layout.addWidget(QDialogButtonBox(QDialogButtonBox.StandardButton.Close, rejected=self.reject))
        self.resize(1100, 600)
