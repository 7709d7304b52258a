"""`photopft report`, `photopft export` and `photopft patients`: what clinicians keep and hand on."""

from __future__ import annotations

import argparse
from datetime import date, datetime
from pathlib import Path

from app.args import add_force, positive
from app.errors import UserError

# A verb imports its work when it runs: app/cli.py builds every verb's parser at start-up (docs/architecture.md)


def _records_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--records", type=Path, help="patient records database (default: the user's data folder)")


def add_records_verbs(sub: argparse._SubParsersAction) -> None:
    r = sub.add_parser("report", help="the PDF report of a session or a results file",
                       description="Two pages: patient, values with predicted values, grade, curves and the "
                                   "optical method against the flow sensor; height maps, regional contributions "
                                   "and tidal indices. The patient's name comes from the records database.")
    r.add_argument("input", type=Path, help="a session file or a results file (photopft process)")
    r.add_argument("-o", "--output", type=Path, required=True, help="the PDF to write")
    r.add_argument("--page-size", choices=("a4", "letter"), default="a4")
    r.add_argument("--equations", choices=("gli-global", "gli-2012"), default="gli-global")
    _records_arg(r)
    r.add_argument("--user", help="who asks for the report: a clinician's names the patient (their password is "
                                  "asked), anyone else's is pseudonymous")
    add_force(r)
    r.set_defaults(run=run_report)

    e = sub.add_parser("export", help="a research copy, CSV, a FHIR R4 bundle or a GDT 3.0 file",
                       description="--research writes a copy of the session with a study pseudonym; --csv writes "
                                   "volume.csv and values.csv into a folder; --fhir a FHIR R4 Bundle (Patient, "
                                   "DiagnosticReport, Observations with LOINC codes) for a hospital system; --gdt a "
                                   "GDT 3.0 record (6310) for a practice system. Exports are logged in the records' "
                                   "audit trail.")
    e.add_argument("input", type=Path, help="a session file (--research) or a session or results file")
    what = e.add_mutually_exclusive_group(required=True)
    what.add_argument("--research", type=Path, metavar="COPY.h5", help="write the pseudonymised copy here")
    what.add_argument("--csv", type=Path, metavar="FOLDER", help="write volume.csv and values.csv here")
    what.add_argument("--fhir", type=Path, metavar="OUT.json", help="write a FHIR R4 Bundle here")
    what.add_argument("--gdt", type=Path, metavar="OUT.gdt", help="write a GDT 3.0 record here")
    e.add_argument("--identified", action="store_true",
                   help="--fhir: name, birth date and patient number from the records (default: the pseudonym only)")
    e.add_argument("--receiver", default="PRAXIS", help="--gdt: the practice system's GDT id (field 8315)")
    e.add_argument("--study-key-file", type=Path, help="the study's secret key (16 bytes or more; --research)")
    e.add_argument("--study", default="", help="study name stored in the copy")
    e.add_argument("--equations", choices=("gli-global", "gli-2012"), default="gli-global")
    _records_arg(e)
    e.add_argument("--user", help="who exports (default: $PHOTOPFT_USER or the computer account)")
    add_force(e)
    e.set_defaults(run=run_export)

    p = sub.add_parser("patients", help="patient records: add, list, history, register a session",
                       description="Names live only in the records database; sessions carry the pseudonym.")
    _records_arg(p)
    verbs = p.add_subparsers(dest="patients_verb", metavar="ACTION", required=True)
    add = verbs.add_parser("add", help="a new patient; prints the pseudonym for the session")
    add.add_argument("--family-name", required=True)
    add.add_argument("--given-name", default="")
    add.add_argument("--sex", choices=("male", "female"), required=True)
    add.add_argument("--birth-date", required=True, help="YYYY-MM-DD")
    add.add_argument("--height", type=positive, required=True, help="cm")
    add.add_argument("--weight", type=positive, required=True, help="kg")
    add.add_argument("--number", help="the hospital's patient number")
    add.add_argument("--pseudonym", help="keep this pseudonym (sessions recorded elsewhere); default: a new one")
    find = verbs.add_parser("list", help="patients whose name, number or pseudonym contains TEXT")
    find.add_argument("text", nargs="?", default="")
    history = verbs.add_parser("history", help="a patient's sessions and key values")
    history.add_argument("pseudonym")
    register = verbs.add_parser("register", help="put a recorded session (and its results) on record")
    register.add_argument("session", type=Path)
    register.add_argument("--results", type=Path)
    register.add_argument("--operator", default="")
    p.set_defaults(run=run_patients)


def _open_records(path: Path | None, create: bool, read_only: bool = False):
    from app.records import Records, RecordsError, default_path

    target = path or default_path()
    if not create and not target.exists():
        if path is not None:
            raise UserError(f"--records {path}: no records database there")
        return None
    try:
        return Records(target, read_only=read_only)
    except RecordsError as exc:
        raise UserError(str(exc)) from exc


def run_report(args: argparse.Namespace) -> int:
    from app.records import RecordsError, existing_records
    from app.report_access import log_report, report_for
    from app.report_pdf import write_report
    from core.io.outputs import check_output

    check_output(args.output, [p for p in (args.input, args.records) if p is not None], force=args.force)
    if args.records is not None and not args.records.exists():
        raise UserError(f"--records {args.records}: no records database there")
    try:
        records = existing_records(args.records, args.user)
    except RecordsError as exc:
        raise UserError(str(exc)) from exc
    try:
        data, withheld = report_for(args.input, records, args.equations)
        write_report(data, args.output, args.page_size)
        log_report(records, args.input, args.output, data.patient is not None)
    finally:
        if records is not None:
            records.close()
    print(f"wrote {args.output}: {data.main_source or 'no'} values"
          + (f", {len(data.maps)} head(s) mapped" if data.maps else ", no height maps")
          + ("" if withheld is None else "; pseudonymous"))
    for note in data.notes:
        print(f"  note: {note}")
    return 0


def _exporting(args: argparse.Namespace, output: Path):
    """The records database to log the export in (None where there is none): refused before any work
    when the acting user may not export."""
    from app.records import RecordsError, existing_records

    if args.records is not None and not args.records.exists():
        raise UserError(f"--records {args.records}: no records database there")
    identified = args.identified or args.gdt is not None  # a GDT record names the patient from the records
    try:
        return existing_records(args.records, args.user, may="export identified" if identified else "export")
    except RecordsError as exc:
        raise UserError(str(exc)) from exc


def _log_export(records, args: argparse.Namespace, kind: str, output: Path) -> None:
    if records is not None:
        records.log("export", str(args.input.resolve()), {kind: str(output.resolve())})


def run_export(args: argparse.Namespace) -> int:
    output = args.research or args.csv or args.fhir or args.gdt
    records = _exporting(args, output)
    try:
        return _export(args, records)
    finally:
        if records is not None:
            records.close()


def _export(args: argparse.Namespace, records) -> int:
    from app.export import research_copy, values_csv, volume_csv
    from app.report_data import build_report
    from core.io.outputs import check_output

    if args.fhir is not None or args.gdt is not None:
        from app.fhir_export import write_fhir
        from app.gdt_export import write_gdt

        target = args.fhir or args.gdt
        check_output(target, [p for p in (args.input, args.records) if p is not None], force=args.force)
        data = build_report(args.input, records=records, equations=args.equations, with_maps=False)
        try:
            if args.fhir is not None:
                out = write_fhir(data, target, identified=args.identified)
                warnings: list[str] = []
            else:
                out, warnings = write_gdt(data, target, receiver=args.receiver)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
        _log_export(records, args, "fhir" if args.fhir is not None else "gdt", out)
        print(f"wrote {out}: {'FHIR R4 bundle' if args.fhir is not None else 'GDT 3.0 record'} of the "
              f"{data.main_source or 'no'} values" + ("" if data.review is None or not data.review.signed else
                                                      ", signed report" if data.review.signature_valid else
                                                      f"; {data.review.signature_broken}"))
        for warning in warnings:
            print(f"  warning: {warning}")
        return 0
    if args.research is not None:
        if args.study_key_file is None:
            raise UserError("--research needs --study-key-file (the study's secret key)")
        check_output(args.research, [args.input, args.study_key_file], force=args.force)
        try:
            key = args.study_key_file.read_bytes().strip()
            out = research_copy(args.input, args.research, key, args.study)
        except ValueError as exc:
            raise UserError(str(exc)) from exc
        _log_export(records, args, "research", out)
        print(f"wrote {out}: pseudonymised research copy")
        return 0
    if args.csv.exists() and not args.csv.is_dir():
        raise UserError(f"--csv {args.csv} is a file, not a folder")
    args.csv.mkdir(parents=True, exist_ok=True)
    for name in ("volume.csv", "values.csv"):
        check_output(args.csv / name, [args.input], force=args.force)
    data = build_report(args.input, with_maps=False)
    try:
        volume = volume_csv(data, args.csv / "volume.csv")
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    values = values_csv(data, args.csv / "values.csv")
    _log_export(records, args, "csv", args.csv)
    print(f"wrote {volume} and {values}")
    return 0


def _parse_date(text: str) -> date:
    try:
        return date.fromisoformat(text)
    except ValueError as exc:
        raise UserError(f"birth date: expected YYYY-MM-DD, got {text!r}") from exc


def run_patients(args: argparse.Namespace) -> int:
    from app.records import RecordsError

    looks = args.patients_verb in ("list", "history")
    records = _open_records(args.records, create=not looks, read_only=looks)
    if records is None:
        if args.patients_verb == "list":
            print("no patients on record yet: `photopft patients add` starts the records")
            return 0
        raise UserError("no records database yet: `photopft patients add` starts one")
    try:
        with records:
            return _patients(records, args)
    except RecordsError as exc:
        raise UserError(str(exc)) from exc


def _patients(records, args: argparse.Namespace) -> int:
    if args.patients_verb == "add":
        p = records.add_patient(args.family_name, args.given_name, args.sex, _parse_date(args.birth_date),
                                args.height, args.weight, args.number, args.pseudonym)
        print(p.pseudonym)
        return 0
    if args.patients_verb == "list":
        for p in records.find_patients(args.text):
            print(f"{p.pseudonym}  {p.display_name}  {p.patient_number or '-'}  {p.sex}  born "
                  f"{p.birth_date.isoformat()}  {p.height_cm:g} cm  {p.weight_kg:g} kg")
        return 0
    if args.patients_verb == "history":
        patient = records.patient_by_pseudonym(args.pseudonym)
        if patient is None:
            raise UserError(f"no patient with pseudonym {args.pseudonym}")
        print(f"{patient.display_name} ({patient.pseudonym})")
        for s in records.history(patient.id):
            values = next(iter(s.summary.values()), {}) if s.summary else {}
            shown = ", ".join(f"{k} {values[k]:.2f}" for k in ("FEV1_l", "FVC_l", "TV_l") if k in values)
            print(f"  {s.recorded:%Y-%m-%d %H:%M}  {s.status:<9} {shown or 'no values'}  {s.session_path}")
        return 0
    return _register(records, args)


def _register(records, args: argparse.Namespace) -> int:
    from app.report_data import build_report
    from core.io.session import SessionFile

    with SessionFile(args.session) as s:
        if s.subject is None:
            raise UserError(f"{args.session} has no /subject: it cannot be put on a patient's record")
        patient = records.patient_by_pseudonym(s.subject.id)
        if patient is None:
            raise UserError(f"{args.session}: no patient with pseudonym {s.subject.id} (add the patient first)")
        recorded = datetime.fromisoformat(s.created)
        rig = s.rig.name
        operator = args.operator or str(s.attrs.get("operator", ""))
    session_id = records.add_session(patient.id, args.session, recorded, operator=operator, rig=rig)
    data = build_report(args.results or args.session, with_maps=False)
    records.set_results(session_id, args.results, {source: data.parameters(source) for source in data.sources},
                        status="processed" if args.results else "analysed")
    print(f"registered {args.session} for {patient.pseudonym}")
    return 0
