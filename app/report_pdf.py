"""The PDF report (reportlab): page 1 for the clinician's values and curves, page 2 for the
height maps, regional contributions and tidal indices. Curves are vector graphics; maps are
images in a colour map whose lightness rises monotonically (viridis), so they read in grey too.
Fonts are embedded (DejaVu Sans) so any Latin, Greek or Cyrillic name prints.
"""

from __future__ import annotations

import io
import math
import os
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np
from reportlab import rl_config
from reportlab.graphics.charts.lineplots import LinePlot
from reportlab.graphics import shapes
from reportlab.graphics.shapes import Drawing, Group, Line, Rect, String
from reportlab.graphics.widgets.markers import makeMarker
from reportlab.lib import colors
from reportlab.lib.pagesizes import A4, letter
from reportlab.lib.styles import ParagraphStyle
from reportlab.lib.units import mm
from reportlab.pdfbase import pdfmetrics
from reportlab.pdfbase.ttfonts import TTFont
from reportlab.platypus import (Image, KeepTogether, PageBreak, Paragraph, SimpleDocTemplate, Spacer, Table,
                                TableStyle)

from app.paths import resources_dir
from app.report_data import DISTANCE_REFUSED, FLOW_SENSOR, OPTICAL, HeadMaps, ReportData, best_manoeuvres
from core import __version__
from core.analysis.values import grade_caveat
from core.io.outputs import atomic_output

PAGE_SIZES = {"a4": A4, "letter": letter}
FONT, BOLD = "DejaVuSans", "DejaVuSans-Bold"
DASHES = (None, (4, 2), (1, 2))  # the best manoeuvre solid, then dashed, then dotted
GREYS = (colors.black, colors.Color(0.3, 0.3, 0.3), colors.Color(0.45, 0.45, 0.45))


def _register_fonts() -> None:
    if FONT in pdfmetrics.getRegisteredFontNames():
        return
    fonts = resources_dir() / "fonts"
    pdfmetrics.registerFont(TTFont(FONT, str(fonts / "DejaVuSans.ttf")))
    pdfmetrics.registerFont(TTFont(BOLD, str(fonts / "DejaVuSans-Bold.ttf")))
    pdfmetrics.registerFontFamily(FONT, normal=FONT, bold=BOLD, italic=FONT, boldItalic=BOLD)
    rl_config.canvas_basefontname = FONT  # pages and drawings start in it: no font but the embedded ones
    shapes.STATE_DEFAULTS["fontName"] = FONT


def _styles() -> dict[str, ParagraphStyle]:
    body = ParagraphStyle("body", fontName=FONT, fontSize=8.5, leading=11)
    return {"body": body,
            "small": ParagraphStyle("small", parent=body, fontSize=7.5, leading=9.5),
            "title": ParagraphStyle("title", parent=body, fontName=BOLD, fontSize=14, leading=18),
            "h2": ParagraphStyle("h2", parent=body, fontName=BOLD, fontSize=10, leading=13, spaceBefore=6,
                                 spaceAfter=3)}


def fmt(value: float | None, unit: str = "", digits: int | None = None) -> str:
    """A value as the report prints it (and the tests read it back)."""
    if value is None or not math.isfinite(value):
        return "–"
    if digits is None:
        digits = 0 if unit in ("%", "/min") else (1 if unit in ("L/min", "s") else 2)
    return f"{value:.{digits}f}"


def _grid(data, widths, header_rows=1, align_from=1) -> Table:
    table = Table(data, colWidths=widths, repeatRows=header_rows)
    table.setStyle(TableStyle([
        ("FONT", (0, 0), (-1, -1), FONT, 8),
        ("FONT", (0, 0), (-1, header_rows - 1), BOLD, 8),
        ("ALIGN", (align_from, 0), (-1, -1), "RIGHT"),
        ("LINEBELOW", (0, header_rows - 1), (-1, header_rows - 1), 0.6, colors.black),
        ("LINEBELOW", (0, -1), (-1, -1), 0.3, colors.grey),
        ("ROWBACKGROUNDS", (0, header_rows), (-1, -1), [colors.white, colors.Color(0.93, 0.93, 0.93)]),
        ("TOPPADDING", (0, 0), (-1, -1), 1.5), ("BOTTOMPADDING", (0, 0), (-1, -1), 1.5),
    ]))
    return table


def _patient_block(data: ReportData, styles) -> Table:
    subject = data.subject or {}
    patient = data.patient
    name = patient.display_name if patient else "not on record here (pseudonymous session)"
    recorded = data.recorded
    try:
        recorded = datetime.fromisoformat(data.recorded).strftime("%Y-%m-%d %H:%M %Z").strip()
    except ValueError:
        pass
    left = [("Patient", name),
            ("Patient number", patient.patient_number or "–" if patient else "–"),
            ("Pseudonym", str(subject.get("id", "–"))),
            ("Sex", str(subject.get("sex", "–"))),
            ("Age", f"{subject['age_years']:.1f} years" if "age_years" in subject else "–"),
            ("Height / weight", f"{subject['height_cm']:.0f} cm / {subject['weight_kg']:.1f} kg"
             if "height_cm" in subject else "–")]
    if patient is not None:
        left.insert(2, ("Date of birth", patient.birth_date.isoformat()))
    right = [("Recorded", recorded), ("Operator", data.operator or "not recorded"), ("Rig", data.rig),
             ("Reference equations", {"gli-global": "GLI Global 2022", "gli-2012": "GLI-2012"}[data.equations]),
             ("Session file", data.session_path.name)]
    rows = []
    for k in range(max(len(left), len(right))):
        a = left[k] if k < len(left) else ("", "")
        b = right[k] if k < len(right) else ("", "")
        rows.append([Paragraph(f"<b>{a[0]}</b>", styles["small"]), Paragraph(_escape(a[1]), styles["small"]),
                     Paragraph(f"<b>{b[0]}</b>", styles["small"]), Paragraph(_escape(b[1]), styles["small"])])
    table = Table(rows, colWidths=[28 * mm, 55 * mm, 32 * mm, 60 * mm])
    table.setStyle(TableStyle([("FONT", (0, 0), (-1, -1), FONT, 8), ("VALIGN", (0, 0), (-1, -1), "TOP"),
                               ("TOPPADDING", (0, 0), (-1, -1), 0.5),
                               ("BOTTOMPADDING", (0, 0), (-1, -1), 0.5),
                               ("BOX", (0, 0), (-1, -1), 0.5, colors.black)]))
    return table


def _escape(text: str) -> str:
    return str(text).replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def _sources(data: ReportData) -> list[str]:
    return [s for s in (OPTICAL, FLOW_SENSOR) if s in data.sources]


def _values_table(data: ReportData) -> Table:
    sources = _sources(data)
    main = data.main_source
    header = ["Parameter", "Unit"] + [s.capitalize() for s in sources] + ["Predicted", "LLN", f"z-score\n{main}",
                                                                          f"% predicted\n{main}"]
    body = []
    for row in data.rows:
        if not row.values and row.reference is None:
            body.append([row.label, row.unit] + ["–"] * (len(sources) + 4))
            continue
        cells = [fmt(row.values.get(s), row.unit, row.decimals) for s in sources]
        ref = row.reference
        pred = [fmt(ref.predicted, row.unit, row.decimals), fmt(ref.lln, row.unit, row.decimals)] if ref else ["–", "–"]
        z = fmt(row.z(main), digits=2) if main else "–"
        pct = fmt(row.percent(main), digits=0) if main else "–"
        body.append([row.label, row.unit] + cells + pred + [z, pct])
    widths = [34 * mm, 13 * mm] + [22 * mm] * len(sources) + [19 * mm, 16 * mm, 20 * mm, 22 * mm]
    return _grid([header] + body, widths, align_from=2)


def _quality_lines(data: ReportData) -> list[str]:
    lines = []
    for source in _sources(data):
        p = data.parameters(source)
        if "grade" in p:
            caveat = grade_caveat(p)
            lines.append(f"<b>{source.capitalize()}</b>: ATS/ERS 2019 grade <b>{p['grade']}</b> (FEV1 "
                         f"{p['grade_FEV1']}, FVC {p['grade_FVC']}); acceptable manoeuvres: {p['acceptable_FEV1']} "
                         f"for FEV1 and {p['acceptable_FVC']} for FVC, of {p['manoeuvres']}"
                         + (f"; {caveat}" if caveat else "") + ".")
        else:
            lines.append(f"<b>{source.capitalize()}</b>: no forced expiration graded.")
    if OPTICAL in data.sources:
        lines.append(optical_kind(data.optical_label))
    return lines


def optical_kind(label: str | None) -> str:
    """The line that says what the optical litres are (core/analysis/optical_litres.py)."""
    return f"<b>Optical</b> litres: {_escape(label or 'made before their kind was recorded: process the session again')}."


def _plot(width: float, height: float, series: list[list[tuple[float, float]]], x_label: str, y_label: str,
          x_range: tuple[float, float] | None = None, y_range: tuple[float, float] | None = None,
          points_first: bool = False) -> Drawing:
    """Lines in black, grey, dashed and dotted; `points_first`: the first series as points only."""
    drawing = Drawing(width, height)
    plot = LinePlot()
    plot.x, plot.y = 34, 26
    plot.width, plot.height = width - 44, height - 36
    plot.data = series
    for k in range(len(series)):
        line = plot.lines[k]
        line.strokeColor = GREYS[k % len(GREYS)]
        line.strokeWidth = 1.2 if k == 0 else 0.8
        if DASHES[k % len(DASHES)] is not None:
            line.strokeDashArray = DASHES[k % len(DASHES)]
    if points_first:
        plot.lines[0].symbol = makeMarker("Circle", size=3)
        plot.lines[0].strokeWidth = 0
        plot.lines[0].strokeColor = None
    for axis in (plot.xValueAxis, plot.yValueAxis):
        axis.labels.fontName = FONT
        axis.labels.fontSize = 6.5
        axis.strokeWidth = 0.5
    if x_range:
        plot.xValueAxis.valueMin, plot.xValueAxis.valueMax = x_range
    if y_range:
        plot.yValueAxis.valueMin, plot.yValueAxis.valueMax = y_range
    plot.yValueAxis.visibleGrid = True
    plot.yValueAxis.gridStrokeColor = colors.Color(0.85, 0.85, 0.85)
    plot.yValueAxis.gridStrokeWidth = 0.3
    drawing.add(plot)
    drawing.add(String(plot.x + plot.width / 2, 4, x_label, fontName=FONT, fontSize=7, textAnchor="middle"))
    label = String(0, 0, y_label, fontName=FONT, fontSize=7, textAnchor="middle")
    rotated = Group(label)
    rotated.transform = (0, 1, -1, 0, 8, plot.y + plot.height / 2)
    drawing.add(rotated)
    return drawing


def _decimate(x: np.ndarray, y: np.ndarray, x_range: tuple[float, float], y_range: tuple[float, float],
              points: int = 300) -> list[tuple[float, float]]:
    """At most `points` points, inside the axes (a plot does not clip what lies outside)."""
    inside = (x >= x_range[0]) & (x <= x_range[1]) & np.isfinite(x) & np.isfinite(y)
    x, y = x[inside], np.clip(y[inside], *y_range)
    step = max(1, len(x) // points)
    return [(float(a), float(b)) for a, b in zip(x[::step], y[::step])]


def _blows_drawing(blows: list, width: float, height: float) -> Drawing:
    """Volume-time and flow-volume of blows side by side, on axes that hold them all."""
    half = width / 2 - 4
    t_range = (-0.5, max(6.0, min(15.0, max(float(m.time_s[-1]) for m in blows))))
    v_range = (0.0, max(float(np.max(m.volume_l)) for m in blows) * 1.1)
    f_max = max(float(np.percentile(m.flow_lps, 99.5)) for m in blows) * 1.15
    f_range = (-0.05 * f_max, f_max)
    volume_time = _plot(half, height, [_decimate(m.time_s, m.volume_l, t_range, v_range) for m in blows],
                        "time from time zero (s)", "exhaled volume (L)", t_range, v_range)
    flow_volume = _plot(half, height, [_decimate(m.volume_l, m.flow_lps, v_range, f_range) for m in blows],
                        "exhaled volume (L)", "expiratory flow (L/s)", v_range, f_range)
    drawing = Drawing(width, height)
    drawing.add(volume_time)
    flow_volume.translate(half + 8, 0)
    drawing.add(flow_volume)
    return drawing


def _curves(data: ReportData, width: float) -> tuple[Drawing, str] | None:
    """Volume-time and flow-volume of the best blows, and the key to their line styles."""
    best = best_manoeuvres(data.manoeuvres)
    if not best:
        return None
    styles = ("solid", "dashed", "dotted")
    key = "; ".join(f"{styles[k]}: blow {m.number} (FEV1 {m.fev1_l:.2f} L, FVC {m.fvc_l:.2f} L, "
                    f"{'acceptable' if m.acceptable else 'not acceptable'})" for k, m in enumerate(best))
    return _blows_drawing(best, width, 150), key


def _interpretation(data: ReportData, styles) -> list:
    out: list = [Paragraph("Interpretation (ERS/ATS 2022, z-scores)", styles["h2"])]
    i = data.interpretation
    if i is None:
        out.append(Paragraph("No values to interpret.", styles["body"]))
        return out
    out.append(Paragraph(f"<b>{_escape(i.summary)}</b>", styles["body"]))
    out += [Paragraph(_escape(line), styles["small"]) for line in i.statements]
    out.append(Paragraph("Lower limit of normal at z = −1.645; severity by the FEV1 z-score (mild −1.65 to −2.5, "
                         "moderate −2.5 to −4, severe below −4). No predicted value exists for PEF in the GLI "
                         "equations.", styles["small"]))
    return out


def _blows(data: ReportData, styles) -> list:
    if not data.manoeuvres:
        return []
    rows = [["Blow", "FEV1 (L)", "FVC (L)", "Acceptable", "Problems"]]
    for m in data.manoeuvres:
        rows.append([str(m.number), fmt(m.fev1_l, "L"), fmt(m.fvc_l, "L"), "yes" if m.acceptable else "no",
                     Paragraph(_escape("; ".join(m.problems) or "none"), styles["small"])])
    table = _grid(rows, [12 * mm, 18 * mm, 18 * mm, 20 * mm, 110 * mm], align_from=1)
    table.setStyle(TableStyle([("ALIGN", (4, 0), (4, -1), "LEFT"), ("ALIGN", (3, 0), (3, -1), "CENTER")]))
    return [Paragraph(f"Every blow ({data.main_source}), with the ATS/ERS 2019 acceptability", styles["small"]),
            table]


def _loops(data: ReportData, styles, width: float) -> list:
    """The optical flow-volume loops beside the flow sensor's, on the same axes."""
    optical, sensor = best_manoeuvres(data.optical_manoeuvres), best_manoeuvres(data.manoeuvres)
    if not optical or not sensor:
        return []
    both = optical + sensor
    v_range = (0.0, max(float(np.max(m.volume_l)) for m in both) * 1.1)
    f_range = (0.0, max(float(np.percentile(m.flow_lps, 99.5)) for m in both) * 1.15)
    half = width / 2 - 4
    drawing = Drawing(width, 140)
    for k, (name, blows) in enumerate(((FLOW_SENSOR, sensor), (OPTICAL, optical))):
        plot = _plot(half, 140, [_decimate(m.volume_l, m.flow_lps, v_range, f_range) for m in blows],
                     f"exhaled volume (L), {name}", "expiratory flow (L/s)", v_range, f_range)
        plot.translate(k * (half + 8), 0)
        drawing.add(plot)
    # the caption stays with its loops (it fell at a page's foot with the loops over the page)
    return [KeepTogether([Paragraph("Flow-volume loops: flow sensor (left) and optical method (right), best blows, "
                                    "same axes", styles["small"]), drawing])]


def _bronchodilator(data: ReportData, styles, width: float) -> list:
    b = data.bronchodilator
    if b is None:
        return []
    out: list = [Paragraph("Bronchodilator response", styles["h2"]),
                 Paragraph(f"This session is the post-bronchodilator session of {_escape(b.pre_path.name)} "
                           f"(recorded {_escape(b.pre_recorded[:16].replace('T', ' '))}).", styles["small"]),
                 Paragraph(_escape(b.statement), styles["body"])]
    if b.changes:
        rows = [["", "Pre (L)", "Post (L)", "Change (mL)", "% of predicted", "Response"]]
        rows += [[c.parameter, fmt(c.pre_l, "L"), fmt(c.post_l, "L"), f"{c.change_ml:+.0f}",
                  f"{c.change_percent_predicted:+.1f}", "yes" if c.response else "no"] for c in b.changes]
        out.append(_grid(rows, [20 * mm, 20 * mm, 20 * mm, 24 * mm, 26 * mm, 20 * mm]))
    post = best_manoeuvres(data.manoeuvres, 1)
    if b.pre_best is not None and post:
        drawing = _blows_drawing([post[0], b.pre_best], width, 130)
        out += [drawing, Paragraph("Solid: best blow after the bronchodilator; dashed: best blow before.",
                                   styles["small"])]
    return out


def _decimal_year(iso: str) -> float:
    moment = datetime.fromisoformat(iso)
    start = datetime(moment.year, 1, 1, tzinfo=moment.tzinfo)
    return moment.year + (moment - start).total_seconds() / (365.25 * 86400)


def _year_month(year: float) -> str:
    whole = int(math.floor(year))
    return f"{whole}-{min(12, int((year - whole) * 12) + 1):02d}"


def _trend(data: ReportData, styles, width: float) -> list:
    out: list = [Paragraph("Trend over the patient's visits", styles["h2"])]
    baseline = [p for p in data.trend if not p.post_bronchodilator]
    if len(data.trend) < 2:
        out.append(Paragraph("First visit on record: no trend yet." if data.trend else
                             "No earlier visits on record.", styles["small"]))
        return out
    rows = [["Visit", "", "FEV1 (L)", "z", "FVC (L)", "z", "FEV1/FVC", "z"]]
    for point in data.trend:
        cells = [point.recorded[:10], "post-BD" if point.post_bronchodilator else ""]
        for name, key in (("FEV1", "FEV1_l"), ("FVC", "FVC_l"), ("FEV1_FVC", "FEV1_FVC")):
            cells += [fmt(point.values.get(key), "", 2), fmt(point.z.get(name), "", 2)]
        rows.append(cells)
    out.append(_grid(rows, [24 * mm, 16 * mm] + [18 * mm] * 6))
    if len(baseline) >= 2:
        years = [_decimal_year(p.recorded) for p in baseline]
        span = max(years) - min(years)
        x_range = (min(years) - 0.05 * span - 0.02, max(years) + 0.05 * span + 0.02)
        half = width / 2 - 4
        litres = [[(x, p.values[key]) for x, p in zip(years, baseline) if key in p.values]
                  for key in ("FEV1_l", "FVC_l")]
        zs = [[(x, p.z[name]) for x, p in zip(years, baseline) if name in p.z] for name in ("FEV1", "FVC", "FEV1_FVC")]
        drawing = Drawing(width, 120)
        for k, (series, label, y_range) in enumerate((
                (litres, "litres", (0.0, max((v for s in litres for _, v in s), default=1.0) * 1.15)),
                (zs, "z-score", (min(-3.0, min((v for s in zs for _, v in s), default=0.0) - 0.5), 3.0)))):
            if not all(series):
                continue
            lln = [[(x_range[0], -1.645), (x_range[1], -1.645)]] if label == "z-score" else []
            plot = _plot(half, 120, series + lln, "visit", label, x_range, y_range)
            line_plot = plot.contents[0]
            line_plot.xValueAxis.labelTextFormat = _year_month
            for j in range(len(series)):
                line_plot.lines[j].symbol = makeMarker("Circle", size=3)
            if lln:
                line_plot.lines[len(series)].strokeColor = colors.Color(0.6, 0.6, 0.6)
                line_plot.lines[len(series)].strokeWidth = 0.6
                line_plot.lines[len(series)].strokeDashArray = (1, 1)
            plot.translate(k * (half + 8), 0)
            drawing.add(plot)
        out += [drawing, Paragraph("Baseline visits (post-bronchodilator sessions are in the table only). Left: "
                                   "FEV1 (solid) and FVC (dashed) in litres. Right: z-scores of FEV1 (solid), FVC "
                                   "(dashed) and FEV1/FVC (dotted); the grey line is the lower limit of normal "
                                   "(z = −1.645).", styles["small"])]
    return out


def _review(data: ReportData, styles) -> list:
    out: list = [Paragraph("Clinician's review", styles["h2"])]
    r = data.review
    if r is None:
        out.append(Paragraph("The session is not on record in the records database: no comment or sign-off.",
                             styles["small"]))
        return out
    out.append(Paragraph("Comment: " + (_escape(r.comment) if r.comment else "none"), styles["body"]))
    if r.signature_broken:
        out.append(Paragraph(f"<b>Signature void</b>: {_escape(r.signature_broken)}.", styles["body"]))
    elif r.signed:
        out.append(Paragraph(f"<b>Signed</b> by {_escape(r.signed_by)} on {r.signed_at:%Y-%m-%d %H:%M} UTC; the "
                             "report is read-only since.", styles["body"]))
    else:
        out.append(Paragraph("<b>Not signed</b>: a preliminary report.", styles["body"]))
    for a in r.amendments:
        out.append(Paragraph(f"Amendment by {_escape(a.user)} on {a.time:%Y-%m-%d %H:%M} UTC: {_escape(a.text)}",
                             styles["small"]))
    return out


def _comparison(data: ReportData, styles, width: float) -> list:
    c = data.comparison
    out: list = [Paragraph("Optical method and flow sensor", styles["h2"])]
    if c is None:
        out.append(Paragraph("No flow sensor was recorded: no comparison.", styles["body"]))
        return out
    lines = []
    if c.curve_r is not None:
        lines.append(f"Volume curves (litres): r = {c.curve_r:.3f}.")
    ba = c.bland_altman()
    if ba is not None:
        lines.append(f"Tidal volume per breath, optical minus flow sensor ({len(c.tidal_pairs)} breaths): mean "
                     f"difference {ba[0]:+.3f} L, limits of agreement {ba[1]:+.3f} to {ba[2]:+.3f} L.")
    elif c.curve_r is not None:
        lines.append(f"Only {len(c.tidal_pairs)} tidal breaths paired: too few for limits of agreement.")
    if c.gradient_r:
        lines.append("Normalised gradient volume (thesis eq. 3.27) against the flow-sensor volume: "
                     + ", ".join(f"{head} r = {r:.3f}" for head, r in c.gradient_r.items()) + ".")
    if c.note:
        lines.append(c.note[0].upper() + c.note[1:] + ".")
    out += [Paragraph(line, styles["body"]) for line in lines]
    if ba is not None:
        means = [(a + b) / 2 for a, b in c.tidal_pairs]
        diffs = [a - b for a, b in c.tidal_pairs]
        lo, hi = min(means) - 0.05, max(means) + 0.05
        span = max(abs(ba[1]), abs(ba[2]), max(abs(d) for d in diffs)) * 1.3
        series = [list(zip(means, diffs)), [(lo, ba[0]), (hi, ba[0])], [(lo, ba[1]), (hi, ba[1])],
                  [(lo, ba[2]), (hi, ba[2])]]
        plot = _plot(width * 0.55, 120, series, "mean of the two tidal volumes (L)",
                     "optical − flow sensor (L)", (lo, hi), (-span, span), points_first=True)
        scatter = plot.contents[0]
        for k in (1, 2, 3):
            scatter.lines[k].strokeColor = colors.black
            scatter.lines[k].strokeWidth = 0.6
            scatter.lines[k].strokeDashArray = None if k == 1 else (3, 2)
        out.append(plot)
    return out


def _colour_image(values: np.ndarray, lo: float, hi: float, width_pt: float) -> Image:
    scaled = np.clip((values - lo) / (hi - lo) if hi > lo else np.zeros_like(values), 0.0, 1.0)
    grey = np.nan_to_num(scaled * 255.0).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)
    rgb[~np.isfinite(values)] = 255
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    height_pt = width_pt * values.shape[0] / values.shape[1]
    return Image(io.BytesIO(png.tobytes()), width=width_pt, height=height_pt)


def _colour_bar(lo: float, hi: float, width: float, label: str) -> Drawing:
    drawing = Drawing(width, 24)
    steps = 64
    lut = cv2.applyColorMap(np.arange(256, dtype=np.uint8).reshape(-1, 1), cv2.COLORMAP_VIRIDIS)[:, 0, ::-1]
    for k in range(steps):
        r, g, b = lut[int(k * 255 / (steps - 1))] / 255.0
        drawing.add(Rect(k * width / steps, 12, width / steps + 0.3, 7, fillColor=colors.Color(r, g, b),
                         strokeColor=None))
    drawing.add(Rect(0, 12, width, 7, fillColor=None, strokeColor=colors.black, strokeWidth=0.3))
    for value, anchor, x in ((lo, "start", 0), ((lo + hi) / 2, "middle", width / 2), (hi, "end", width)):
        drawing.add(Line(x, 11, x, 12))
        drawing.add(String(x, 4, f"{value:+.0f}" if abs(hi - lo) >= 6 else f"{value:+.1f}", fontName=FONT,
                           fontSize=6, textAnchor=anchor))
    drawing.add(String(width / 2, 20.5, label, fontName=FONT, fontSize=6, textAnchor="middle"))
    return drawing


def _symmetric_range(values: list[np.ndarray], percentile: float = 98.0) -> float:
    finite = np.concatenate([v[np.isfinite(v)] for v in values]) if values else np.zeros(1)
    if finite.size == 0:
        return 1.0
    return max(float(np.percentile(np.abs(finite), percentile)), 0.5)


def _maps(data: ReportData, styles, width: float) -> list:
    out: list = [Paragraph("Height maps", styles["h2"])]
    if not data.maps:
        out.append(Paragraph("No height maps: " + ("no tidal breath was found to place end inspiration and "
                                                   "end expiration." if data.breath_times_s is None else
                                                   "not computed."), styles["body"]))
        return out
    t_in, t_ex = data.breath_times_s
    out.append(Paragraph(f"The median tidal breath: end inspiration at {t_in:.1f} s, end expiration at {t_ex:.1f} s. "
                         "Height is above each map's mean surface (towards the camera); the movement map shows "
                         "how far each point moved towards the camera from end expiration to end inspiration, "
                         "after removing the subject's sway.", styles["small"]))
    column = (width - 12) / 3
    height_range = _symmetric_range([m.inspiration_mm for m in data.maps] + [m.expiration_mm for m in data.maps])
    rows = [[Paragraph(f"<b>{m.head.capitalize()} head</b> ({_distance_text(m)})", styles["small"]), "", ""]
            for m in data.maps]
    table_rows = []
    for m, title in zip(data.maps, rows):
        moved = _symmetric_range([m.displacement_mm])
        table_rows.append(title)
        table_rows.append([_colour_image(m.inspiration_mm, -height_range, height_range, column - 6),
                           _colour_image(m.expiration_mm, -height_range, height_range, column - 6),
                           _colour_image(m.displacement_mm, -moved, moved, column - 6)])
        table_rows.append([_colour_bar(-height_range, height_range, column - 10, "height at end inspiration (mm)"),
                           _colour_bar(-height_range, height_range, column - 10, "height at end expiration (mm)"),
                           _colour_bar(-moved, moved, column - 10, "movement on inspiration (mm)")])
    table = Table(table_rows, colWidths=[column] * 3)
    table.setStyle(TableStyle([("FONT", (0, 0), (-1, -1), FONT, 8), ("ALIGN", (0, 0), (-1, -1), "CENTER"),
                               ("VALIGN", (0, 0), (-1, -1), "MIDDLE"),
                               ("TOPPADDING", (0, 0), (-1, -1), 3), ("BOTTOMPADDING", (0, 0), (-1, -1), 3)]
                              # each head's title across the three columns
                              + [("SPAN", (0, 3 * k), (-1, 3 * k)) for k in range(len(data.maps))]))
    out.append(table)
    return out


def _distance_text(maps: HeadMaps) -> str:
    """The subject's distance for a head's maps, with where it comes from; none when refused."""
    if maps.distance_from == DISTANCE_REFUSED:
        return f"subject distance {maps.distance_from}"
    return f"subject at {maps.distance_mm:.0f} mm, {maps.distance_from}"


def _regions(data: ReportData, styles) -> list:
    out: list = [Paragraph("Regional contributions", styles["h2"])]
    if not data.maps:
        out.append(Paragraph("Not available without height maps.", styles["body"]))
        return out
    names = ("upper left", "upper right", "lower left", "lower right")
    rows = [["Head", "Upper\nleft", "Upper\nright", "Lower\nleft", "Lower\nright", "Left", "Right",
             "Upper\n(chest)", "Lower\n(abdomen)"]]
    for m in data.maps:
        if not m.regions:
            rows.append([m.head.capitalize(), "not measurable: no net outward movement beyond the alignment's "
                                              "uncertainty", "", "", "", "", "", "", ""])
            continue
        r = m.regions
        share = [r.get(n, float("nan")) for n in names]
        rows.append([m.head.capitalize()] + [f"{100 * s:.0f} %" for s in share]
                    + [f"{100 * (share[0] + share[2]):.0f} %", f"{100 * (share[1] + share[3]):.0f} %",
                       f"{100 * (share[0] + share[1]):.0f} %", f"{100 * (share[2] + share[3]):.0f} %"])
    table = _grid(rows, [16 * mm] + [19 * mm] * 8)
    spans = [("SPAN", (1, k), (-1, k)) for k, row in enumerate(rows) if row[2] == "" and k > 0]
    if spans:
        table.setStyle(TableStyle(spans + [("ALIGN", (1, k), (1, k), "LEFT") for (_, (_, k), _) in spans]))
    out.append(table)
    out.append(Paragraph("Share of the surface movement each quadrant of the trunk (upper and lower half of the "
                         "trunk, left and right of the midline, as the patient's own sides) contributes to the "
                         "mapped breath, weighted by each pixel's area on the body.", styles["small"]))
    return out


def _tidal(data: ReportData, styles) -> list:
    sources = _sources(data)
    out: list = [Paragraph("Tidal breathing indices and other values", styles["h2"])]
    rows = [["Value", "Unit"] + [s.capitalize() for s in sources]]
    for row in data.tidal_rows:
        rows.append([row.label, row.unit] + [fmt(row.values.get(s), row.unit, row.decimals) for s in sources])
    out.append(_grid(rows, [62 * mm, 14 * mm] + [26 * mm] * len(sources), align_from=2))
    return out


def write_report(data: ReportData, output: str | os.PathLike, page_size: str = "a4") -> Path:
    """Write the report (values, interpretation, curves, review and comparison; then maps, regions,
    tidal indices and trend); returns its path."""
    _register_fonts()
    styles = _styles()
    size = PAGE_SIZES[page_size]
    output = Path(output)
    margin = 14 * mm
    width = size[0] - 2 * margin

    def footer(canvas, doc) -> None:
        canvas.saveState()
        canvas.setFont(FONT, 6.5)
        canvas.drawString(margin, 8 * mm, f"photopft {__version__} · {data.session_path.name} · "
                                           f"{'SIMULATED SESSION · ' if data.kind == 'simulation' else ''}"
                                           f"page {doc.page}")
        canvas.restoreState()

    story: list = []
    title = "Pulmonary function report"
    if data.kind == "simulation":
        title += " — simulated session, not a patient"
    story.append(Paragraph(title, styles["title"]))
    story.append(_patient_block(data, styles))
    story.append(Paragraph("Calibration in force: " + _escape("; ".join(data.calibration)), styles["small"]))
    story.append(Paragraph("Values", styles["h2"]))
    if data.main_source is None:
        story.append(Paragraph("No volume curve in litres was recorded (neither an optical volume nor a flow "
                               "sensor): no pulmonary function values.", styles["body"]))
    else:
        story.append(_values_table(data))
        story += [Paragraph(line, styles["small"]) for line in _quality_lines(data)]
    story += _interpretation(data, styles)
    curves = _curves(data, width)
    story.append(Paragraph(f"Forced expirations ({data.main_source or 'none'}): the best manoeuvres",
                           styles["h2"]))
    if curves is None:
        story.append(Paragraph("No forced expiration to show.", styles["body"]))
    else:
        story += [curves[0], Paragraph(curves[1], styles["small"])]
        story += _blows(data, styles)
    story += _review(data, styles)
    story.append(KeepTogether(_bronchodilator(data, styles, width)))
    story += _comparison(data, styles, width)
    story += _loops(data, styles, width)
    if data.notes:
        story.append(Paragraph("Notes", styles["h2"]))
        story += [Paragraph(_escape(note), styles["small"]) for note in data.notes]
    story.append(PageBreak())
    story += _maps(data, styles, width)
    story.append(KeepTogether(_regions(data, styles)))
    story.append(Spacer(1, 4))
    story.append(KeepTogether(_tidal(data, styles)))
    story.append(KeepTogether(_trend(data, styles, width)))
    with atomic_output(output, private=data.patient is not None) as partial:  # a named patient: owner only
        doc = SimpleDocTemplate(str(partial), pagesize=size, leftMargin=margin, rightMargin=margin,
                                topMargin=12 * mm, bottomMargin=14 * mm, title="Pulmonary function report",
                                author=f"photopft {__version__}", subject=data.session_path.name)
        doc.build(story, onFirstPage=footer, onLaterPages=footer)
    return output
