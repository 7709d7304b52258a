"""A session's results as a GDT 3.0 file for practice systems (record type 6310, "transmit examination data").

GDT lines are `LLLFFFFcontent` + CR LF: LLL the line's length in bytes including the three digits
and the CR LF, FFFF the field identifier. Field 8100 holds the record's length in bytes. Text is
ISO 8859-15 (field 9206 = 3); a character it cannot hold is written as '?' and reported.
Each value is one test (8410 identifier, 8411 name, 8420 value, 8421 unit, 8461 the lower limit of
normal); the interpretation and the clinician's comment are findings text (6220, 6227), the
report's amendments too (6227 lines after the signature).

Every field's content is sanitised: control characters (CR, LF, tab, C1) become a space, so no
content can start a line of its own; a line holds at most 999 bytes (the three-digit length), so a
long text is split over several lines of the same field and a long name cut, with a warning. The
receiver's id (8315) is refused unless it is 1-8 letters or digits.
"""

from __future__ import annotations

import os
import re
from datetime import datetime
from pathlib import Path

from app.report_data import ReportData
from core.analysis import registry
from core.io.outputs import atomic_output

ENCODING = "iso8859_15"
GDT_VERSION = "03.00"
SENDER = "PHOTOPFT"
RECORD_TYPE = "6310"

MAX_LINE_BYTES = 999  # the length field has three digits
MAX_CONTENT_BYTES = MAX_LINE_BYTES - 3 - 4 - 2  # less the length, the field id and CR LF
_CONTROL = re.compile(r"[\x00-\x1f\x7f-\x9f]")


def clean(content: str) -> str:
    """The content with every control character (CR and LF among them) made a space."""
    return _CONTROL.sub(" ", content)


def _line(field: str, content: str) -> bytes:
    """One line; the content must fit (see `_lines` for text that may not)."""
    body = f"{field}{clean(content)}".encode(ENCODING, errors="replace") + b"\r\n"
    if len(body) + 3 > MAX_LINE_BYTES:
        raise ValueError(f"GDT field {field}: {len(body) + 3} bytes, a line holds at most {MAX_LINE_BYTES}")
    return f"{len(body) + 3:03d}".encode("ascii") + body


def _lines(field: str, text: str) -> list[bytes]:
    """A free text over as many lines of `field` as it needs (findings, comments, amendments)."""
    text, out = clean(text), []
    while True:
        out.append(_line(field, text[:MAX_CONTENT_BYTES]))
        text = text[MAX_CONTENT_BYTES:]
        if not text:
            return out


def _short(field: str, text: str, warnings: list[str], limit: int = 60) -> bytes:
    """A field that must stay one short line (a name): cut at `limit` characters, with a warning."""
    text = clean(text)
    if len(text) > limit:
        warnings.append(f"GDT field {field}: {len(text)} characters cut to {limit}")
        text = text[:limit]
    return _line(field, text)


def check_receiver(receiver: str) -> str:
    if not re.fullmatch(r"[A-Za-z0-9]{1,8}", receiver):
        raise ValueError(f"--receiver {receiver!r}: a GDT id is 1-8 letters or digits")
    return receiver


def _number(value: float, unit: str) -> str:
    return f"{value:.2f}" if unit in ("L", "L/s", "") else f"{value:.1f}"


def gdt_record(data: ReportData, receiver: str = "PRAXIS") -> tuple[bytes, list[str]]:
    """(the record's bytes, warnings such as characters the character set cannot hold)."""
    warnings: list[str] = []
    lines: list[bytes] = [_line("8000", RECORD_TYPE), b"", _line("8315", check_receiver(receiver)), _line("8316", SENDER),
                          _line("9206", "3"), _line("9218", GDT_VERSION)]
    patient, subject = data.patient, data.subject or {}
    if patient is not None:
        lines += [_short("3000", patient.patient_number or patient.pseudonym, warnings),
                  _short("3101", patient.family_name, warnings)]
        if patient.given_name:
            lines.append(_short("3102", patient.given_name, warnings))
        lines.append(_line("3103", patient.birth_date.strftime("%d%m%Y")))
        for text in (patient.family_name, patient.given_name):
            try:
                text.encode(ENCODING)
            except UnicodeEncodeError:
                warnings.append(f"the name {text!r} has characters ISO 8859-15 cannot hold: written as '?'")
    else:
        lines.append(_short("3000", str(subject.get("id", "")), warnings))
    if subject.get("sex") in ("male", "female"):
        lines.append(_line("3110", "1" if subject["sex"] == "male" else "2"))
    if "height_cm" in subject:
        lines += [_line("3622", f"{float(subject['height_cm']):.0f}"), _line("3623", f"{float(subject['weight_kg']):.1f}")]
    try:
        moment = datetime.fromisoformat(data.recorded)
        lines += [_line("6200", moment.strftime("%d%m%Y")), _line("6201", moment.strftime("%H%M%S"))]
    except ValueError:
        warnings.append(f"the recording time {data.recorded!r} is not a date: 6200/6201 left out")
    lines.append(_line("8402", "LUFU01"))
    values = data.parameters(data.main_source) if data.main_source else {}
    references = {row.reference.parameter: row.reference for row in data.rows if row.reference is not None}
    for test in (v for v in registry.VALUES if v.gdt_test is not None):
        key, ident, name, unit, ref_name = test.key, test.gdt_test, test.name, test.unit, test.reference
        if key not in values:
            continue
        value = float(values[key])
        lines += [_line("8410", ident), _line("8411", name), _line("8420", _number(value, unit))]
        if unit:
            lines.append(_line("8421", unit))
        ref = references.get(ref_name) if ref_name else None
        if ref is not None:
            lines += [_line("8461", _number(ref.lln, unit)),
                      _line("8480", f"predicted {_number(ref.predicted, unit)}, z {ref.zscore(value):+.2f}, "
                                    f"{ref.percent(value):.0f} % predicted")]
    if data.main_source:
        kind = f" ({data.optical_label})" if data.main_source == "optical" and data.optical_label else ""
        lines += _lines("6220", f"Values from the {data.main_source}{kind}.")
    if data.interpretation is not None:
        lines += _lines("6220", f"{data.interpretation.summary} (ERS/ATS 2022).")
        for statement in data.interpretation.statements:
            lines += _lines("6220", statement)
    if data.bronchodilator is not None:
        lines += _lines("6220", data.bronchodilator.statement)
    if data.review is not None:
        if data.review.comment:
            lines += _lines("6227", data.review.comment)
        if data.review.signature_broken:
            lines += _lines("6227", f"Not signed: {data.review.signature_broken}.")
        elif data.review.signed:
            lines += _lines("6227", f"Signed by {data.review.signed_by} on {data.review.signed_at:%Y-%m-%d %H:%M}")
        for a in data.review.amendments if data.review.signature_valid else ():
            lines += _lines("6227", f"Amended by {a.user} on {a.time:%Y-%m-%d %H:%M}: {a.text}")
    body_length = sum(len(line) for line in lines)
    total = body_length + len(_line("8100", "00000"))
    lines[1] = _line("8100", f"{total:05d}")
    return b"".join(lines), warnings


def read_gdt(path: str | os.PathLike) -> list[tuple[str, str]]:
    """(field, content) of each line, checking each line's length: what a practice system reads."""
    raw = Path(path).read_bytes()
    out = []
    for number, line in enumerate(raw.split(b"\r\n")[:-1], start=1):
        if len(line) + 2 != int(line[:3]):
            raise ValueError(f"{path}: line {number} says {int(line[:3])} bytes, has {len(line) + 2}")
        out.append((line[3:7].decode("ascii"), line[7:].decode(ENCODING)))
    if not raw.endswith(b"\r\n"):
        raise ValueError(f"{path}: the last line does not end in CR LF")
    return out


def write_gdt(data: ReportData, output: str | os.PathLike, receiver: str = "PRAXIS") -> tuple[Path, list[str]]:
    """An identified record (the patient's name from the records) is readable by its owner only."""
    record, warnings = gdt_record(data, receiver)
    output = Path(output)
    with atomic_output(output, private=data.patient is not None) as partial:
        Path(partial).write_bytes(record)
    return output, warnings
