"""A new spirometric value is added in one place: computed where the values are (its key in
SessionValues.parameters()) and registered once in core/analysis/registry.py; the report, its PDF,
`analyze`, the values CSV, FHIR and GDT then carry it."""

from __future__ import annotations

from pypdf import PdfReader

from app.cli import main
from app.export import values_csv
from app.fhir_export import fhir_bundle
from app.gdt_export import gdt_record
from app.report_data import build_report
from app.report_pdf import write_report
from core.analysis import registry
from core.analysis.values import SessionValues

FEV3 = registry.SpirometricValue("FEV3_l", "FEV3", "FEV3", "L", 2, "main",
                                 loinc=("19874-7", "Forced expiratory volume in 3 seconds"), gdt_test="FEV3")


def test_a_value_registered_once_reaches_every_output(processed_full_session, tmp_path, monkeypatch, capsys):
    _, results = processed_full_session
    parameters = SessionValues.parameters

    def with_fev3(self: SessionValues) -> dict:
        values = parameters(self)
        if self.forced is not None:  # as values.py would compute it: here a stand-in tied to the blow's FEV1
            values["FEV3_l"] = round(1.05 * self.forced.fev1_l, 4)
        return values

    monkeypatch.setattr(SessionValues, "parameters", with_fev3)
    monkeypatch.setattr(registry, "VALUES", registry.VALUES + (FEV3,))

    data = build_report(results, with_maps=False)
    row = next(r for r in data.rows if r.key == "FEV3_l")
    expected = 1.05 * data.sources[data.main_source].forced.fev1_l
    assert abs(row.values[data.main_source] - expected) < 1e-3

    pdf = write_report(data, tmp_path / "report.pdf")
    assert "FEV3" in PdfReader(pdf).pages[0].extract_text()

    csv_text = values_csv(data, tmp_path / "values.csv").read_text()
    assert any(line.startswith(f"FEV3_l,L,{data.main_source},") for line in csv_text.splitlines())

    coded = [o for o in fhir_bundle(data)["entry"] if o["resource"]["resourceType"] == "Observation"
             and o["resource"]["code"]["coding"][0]["code"] == "19874-7"]
    assert len(coded) == 1 and abs(coded[0]["resource"]["valueQuantity"]["value"] - expected) < 1e-3

    record, _ = gdt_record(data)
    assert b"FEV3" in record

    assert main(["analyze", str(results)]) == 0
    assert any(line.split()[:2] == ["FEV3", "L"] for line in capsys.readouterr().out.splitlines())
