"""The PDF report, read back: its numbers are the results file's, and sessions with less in them
(no flow sensor, front only, no acceptable blow) still give a complete, honest report."""

from __future__ import annotations

import re
from datetime import date

import h5py
import pytest
from pypdf import PdfReader

from app.cli import main
from app.records import Records
from app.report_pdf import fmt
from core.sim.breathing import ForcedBlow
from core.sim.simulate import SimConfig, simulate

# the module's sessions (small_sessions) are made once: its tests on one xdist worker, not on both
pytestmark = pytest.mark.xdist_group("report-sessions")


def _text(pdf) -> list[str]:
    """Each page's text with its table rows on one line and runs of spaces as one."""
    pages = [page.extract_text(extraction_mode="layout") for page in PdfReader(pdf).pages]
    return ["\n".join(" ".join(line.split()) for line in page.splitlines() if line.strip()) for page in pages]


def _parts(pdf) -> tuple[str, str]:
    """(the clinician's pages, the pages from the height maps on)."""
    pages = _text(pdf)
    maps = next(k for k, page in enumerate(pages) if "Height maps" in page.splitlines())
    return "\n".join(pages[:maps]), "\n".join(pages[maps:])


def _row(text: str, label: str, unit: str) -> list[str]:
    """The cells after the unit of the values table's row."""
    prefix = f"{label} {unit} " if unit else f"{label} "
    line = next(line for line in text.splitlines() if line.startswith(prefix) and line[len(prefix):][:1] in
                "0123456789–-")
    return line[len(prefix):].split()


def test_report_numbers_equal_the_results_file(processed_full_session, tmp_path):
    session, results = processed_full_session
    records_path = tmp_path / "records.sqlite3"
    with Records(records_path) as records:
        records.add_patient("Łukasiewicz-Дмитриев", "Zoë Ψ", "male", date(1996, 3, 1), 175.0, 75.0,
                            patient_number="H-77", pseudonym="SIM-0001")
    pdf = tmp_path / "report.pdf"
    assert main(["report", str(results), "-o", str(pdf), "--records", str(records_path)]) == 0
    page1, page2 = _parts(pdf)
    assert "Łukasiewicz-Дмитриев, Zoë Ψ" in page1 and "H-77" in page1  # the embedded font prints every name
    assert "simulated session" in page1
    with h5py.File(results, "r") as r:
        p = dict(r["parameters"].attrs)
        assert r["parameters"].attrs["source"] == "flow sensor"
    for label, key, unit in (("Tidal volume", "TV_l", "L"), ("FVC", "FVC_l", "L"), ("FEV1", "FEV1_l", "L"),
                             ("PEF", "PEF_lps", "L/s"), ("VC", "VC_l", "L"), ("Respiratory rate", "RR_bpm", "/min")):
        cells = _row(page1, label, unit)
        # columns: optical, flow sensor, predicted, ...
        assert cells[1] == fmt(float(p[key]), unit), (label, cells, p[key])
    assert _row(page1, "FEV1/FVC", "")[1] == fmt(float(p["FEV1_FVC"]), "", 2)
    assert f"Flow sensor: ATS/ERS 2019 grade {p['grade']}" in page1
    assert f"{p['acceptable_FVC']} for FVC, of {p['manoeuvres']}" in page1
    # the optical column comes with what its litres are
    assert "Optical litres: optical, calibrated on the subject (residual" in " ".join(page1.split())
    assert re.search(r"Volume curves \(litres\): r = (0\.\d{3}|1\.000)", page1)  # 1.000 where r rounds up
    assert "Height maps" in page2 and "Front head" in page2 and "Back head" in page2
    # the maps are made at the distance `process` measured (the two heads' geometry), not the photometric fit's
    with h5py.File(results, "r") as r:
        for head in ("front", "back"):
            shown = float(re.search(rf"{head.capitalize()} head \(subject at (\d+) mm, as processed\)", page2).group(1))
            processed = r[f"heads/{head}/distance_mm"][:]
            assert processed.min() - 1 <= shown <= processed.max() + 1, (head, shown, processed.min(), processed.max())
    assert "Regional contributions" in page2 and "Tidal breathing indices" in page2
    reader = PdfReader(pdf)
    fonts = [f.get_object() for page in reader.pages for f in page["/Resources"]["/Font"].values()]
    assert fonts and all("DejaVu" in str(f["/BaseFont"]) for f in fonts), [f["/BaseFont"] for f in fonts]
    assert all("/FontFile2" in f["/FontDescriptor"] for f in fonts)  # embedded, every one


def test_a_volume_calibration_gives_the_thesis_regression_and_the_report_names_it(processed_full_session,
                                                                                   small_session, tmp_path):
    """`calibrate volume` fits the regression (eqs 5.1-5.3) on one session's results; `process
    --volume-calibration` gives the next session's volume from it, and its report says which profile."""
    profile = tmp_path / "volume.json"
    assert main(["calibrate", "volume", str(processed_full_session[1]), "-o", str(profile)]) == 0
    results = tmp_path / "calibrated.h5"
    assert main(["process", str(small_session), "-o", str(results), "--every", "5",
                 "--volume-calibration", str(profile)]) == 0
    with h5py.File(results, "r") as r:
        volume = dict(r["volume"].attrs)
        assert len(r["volume/volume_l"]) > 5
    assert str(volume["method"]).startswith("thesis regression")
    pdf = tmp_path / "report.pdf"
    assert main(["report", str(results), "-o", str(pdf)]) == 0
    words = " ".join(" ".join(_text(pdf)).split())  # the line may wrap anywhere
    assert f"volume calibration of {volume['calibration_created']}" in words


def test_letter_and_a4(processed_full_session, tmp_path):
    session, _ = processed_full_session
    sizes = {}
    for size in ("a4", "letter"):
        pdf = tmp_path / f"{size}.pdf"
        assert main(["report", str(session), "-o", str(pdf), "--page-size", size]) == 0
        box = PdfReader(pdf).pages[0].mediabox
        sizes[size] = (round(float(box.width)), round(float(box.height)))
        assert len(PdfReader(pdf).pages) == 2
    assert sizes == {"a4": (595, 842), "letter": (612, 792)}


@pytest.fixture(scope="module")
def small_sessions(tmp_path_factory):
    folder = tmp_path_factory.mktemp("report-sessions")
    paths = {
        "no-flow": SimConfig(protocol="tidal", seconds=12.0, scale=0.1, seed=7, flow_sensor=None),
        "front-only": SimConfig(protocol="tidal", seconds=12.0, scale=0.1, seed=8, heads=("front",)),
        "bad-blows": SimConfig(protocol="forced", scale=0.1, seed=9,
                               blows=[ForcedBlow(rise_time_s=0.4), ForcedBlow(rise_time_s=0.4, stop_after_s=1.5)]),
    }
    for name, config in paths.items():
        simulate(folder / f"{name}.h5", config)
    return {name: folder / f"{name}.h5" for name in paths}


def test_a_session_without_a_flow_sensor_says_so(small_sessions, tmp_path):
    pdf = tmp_path / "r.pdf"
    assert main(["report", str(small_sessions["no-flow"]), "-o", str(pdf)]) == 0
    page1, page2 = _parts(pdf)
    assert "No flow sensor was recorded" in page1
    assert "No volume curve in litres was recorded" in page1
    assert "No forced expiration to show" in page1
    assert "No height maps" in page2  # no breathing curve to place the breath on


def test_without_a_flow_sensor_the_notes_say_why_the_optical_values_were_refused(processed_full_session, tmp_path):
    """With no flow sensor there is no comparison to give the reason in: the notes give it."""
    import shutil

    from app.report_data import build_report

    # the session without its flow sensor (/flow is optional), not the module's small sessions: this
    # test runs with the full session's group, and the small ones were built a second time for it
    no_flow = tmp_path / "no-flow.h5"
    shutil.copy(processed_full_session[0], no_flow)
    with h5py.File(no_flow, "r+") as s:
        del s["flow"]
    refused = tmp_path / "refused.h5"
    shutil.copy(processed_full_session[1], refused)
    with h5py.File(refused, "r+") as r:
        for name in ("volume", "metric_volume"):
            if name in r:
                del r[name]
        r.attrs["optical_refused"] = "head front: an arm lies against the trunk"
        r.attrs["session"] = str(no_flow)
    notes = build_report(refused, with_maps=False).notes
    assert sum("an arm lies against the trunk" in n for n in notes) == 1
    assert any(n.startswith("Optical volume in litres: refused when the session was processed") for n in notes)


def test_a_front_only_session(small_sessions, tmp_path):
    pdf = tmp_path / "r.pdf"
    assert main(["report", str(small_sessions["front-only"]), "-o", str(pdf)]) == 0
    page1, page2 = _parts(pdf)
    assert "Front head" in page2 and "Back head" not in page2
    assert re.search(r"Front head \(subject at \d+ mm, photometric fit, not processed\)", page2)
    assert _row(page1, "Tidal volume", "L")[0] != "–"
    assert "the session has not been processed" in page1.replace("\n", " ").lower()


def test_no_acceptable_manoeuvre_is_graded_and_said(small_sessions, tmp_path):
    pdf = tmp_path / "r.pdf"
    assert main(["report", str(small_sessions["bad-blows"]), "-o", str(pdf)]) == 0
    page1, _ = _parts(pdf)
    grade = re.search(r"Flow sensor: ATS/ERS 2019 grade (\w)", page1).group(1)
    assert grade in ("E", "U", "F")
    assert "acceptable manoeuvres: 0 for FEV1 and 0 for FVC, of 2" in page1
    assert "not acceptable)" in page1


def test_a_missing_or_broken_input_is_named(tmp_path, capsys):
    broken = tmp_path / "broken.h5"
    broken.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    assert main(["report", str(broken), "-o", str(tmp_path / "x.pdf")]) == 2
    assert "broken.h5" in capsys.readouterr().err
    assert not (tmp_path / "x.pdf").exists()


def test_the_report_reads_the_stored_values_back_and_says_when_they_have_aged(processed_full_session, tmp_path):
    """The table holds what the results file holds; where this version's analysis of the same
    curves gives another number, a note says so and asks for the session to be processed again."""
    import shutil

    from app.report_data import build_report

    session, results = processed_full_session
    fresh = build_report(results, with_maps=False)
    assert not any("stored when the session was processed" in n for n in fresh.notes)
    aged = tmp_path / "aged.h5"
    shutil.copy(results, aged)
    shutil.copy(session, tmp_path / session.name)  # found beside the results file
    with h5py.File(aged, "r+") as r:
        r["parameters"].attrs["FVC_l"] = 3.333
    report = build_report(aged, with_maps=False)
    fvc = next(row for row in report.rows if row.key == "FVC_l")
    assert fvc.values["flow sensor"] == 3.333
    note = next(n for n in report.notes if "stored when the session was processed" in n)
    assert "flow sensor FVC_l 3.333 stored" in note and "process the session again" in note


def test_no_subject_distance_is_printed_where_process_refused_the_optical_values(processed_full_session, tmp_path):
    """An arm against the trunk puts the two heads' distance hundreds of millimetres off; `process` then
    refuses the optical values, and the report gives no distance for the maps."""
    import shutil

    session, results = processed_full_session
    refused = tmp_path / "refused.h5"
    shutil.copy(results, refused)
    with h5py.File(refused, "r+") as r:
        for name in ("volume", "metric_volume"):
            if name in r:
                del r[name]
        r.attrs["optical_refused"] = "head front: an arm lies against the trunk"
        r.attrs["session"] = str(session)
    pdf = tmp_path / "r.pdf"
    assert main(["report", str(refused), "-o", str(pdf)]) == 0
    page1, page2 = _parts(pdf)
    assert "Optical values refused: head front: an arm lies against the trunk" in page1.replace("\n", " ")
    assert page1.replace("\n", " ").count("an arm lies against the trunk") == 1  # said once, not again in the notes
    assert "no volume calibration profile" not in page1
    assert "Front head (subject distance not given: the optical values were refused)" in page2
    assert not re.search(r"head \(subject at \d+ mm", page2)


def test_every_optical_value_says_what_its_litres_are(processed_full_session, tmp_path, capsys):
    """The full protocol's flow sensor covers the whole session: the subject is calibrated on its first
    quiet breathing and slow VC (core/volume/subject_calibration.py), and the report, `analyze` and its
    JSON say "optical, calibrated on the subject (residual N mL)"."""
    import json

    from app.report_data import build_report
    from core.io.results import ResultsFile

    session, results = processed_full_session
    with ResultsFile(results) as r:
        label = r.optical_label()
        calibration = r.subject_calibration()
    assert label.startswith("optical, calibrated on the subject (residual "), (label, calibration)
    assert calibration["segment_s"][1] > 20.0 and "refused" not in calibration
    assert build_report(results, with_maps=False).optical_label == label
    pdf = tmp_path / "report.pdf"
    assert main(["report", str(results), "-o", str(pdf)]) == 0
    page1, _ = _parts(pdf)
    assert f"Optical litres: {label}." in " ".join(page1.split())
    capsys.readouterr()
    assert main(["analyze", str(results)]) == 0
    assert f"optical: {label}" in capsys.readouterr().out
    assert main(["analyze", str(results), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["optical_label"] == label
