"""A clinical session end to end (issue 75): the subject's calibration through the flow sensor, the
mouthpiece off, then litres from the cameras alone, said to be calibrated wherever they are shown."""

from __future__ import annotations

import json

import numpy as np
import pytest

from app.cli import main
from core.volume.subject_calibration import CURVED, GROUPINGS

pytestmark = pytest.mark.slow


def test_a_clinical_session_gives_calibrated_litres_after_the_mouthpiece_comes_off(tmp_path, capsys):
    from app.fhir_export import fhir_bundle
    from app.report_data import OPTICAL, build_report
    from core.io.results import ResultsFile
    from core.io.session import SessionFile

    session, results = tmp_path / "clinical.h5", tmp_path / "results.h5"
    assert main(["simulate", "-o", str(session), "--protocol", "clinical", "--scale", "0.05", "--seed", "3"]) == 0
    # a map every 4 frames: at one a light cycle (the default, every 5) these 70 px maps dip 0.2 L where the
    # subject sways 60 mm in 3 s, and one of the 7 breaths after the calibration is lost; every 2 reads as 4 does
    assert main(["process", str(session), "-o", str(results), "--every", "4"]) == 0
    with SessionFile(session) as s:
        start = s.start_ns()
        off_s = next((t - start) / 1e9 for t, label in s.events() if label == "mouthpiece-off")
        assert (s.flow_samples()[1][-1] - start) / 1e9 <= off_s  # the flow sensor's samples end there
    with ResultsFile(results) as r:
        calibration = r.subject_calibration()
        label = r.optical_label()
    assert "refused" not in calibration and calibration["segment_s"][1] == pytest.approx(off_s, abs=0.01)
    assert calibration["residual_l"] < 0.05 * calibration["range_l"]
    assert calibration["grouping"].split(", ")[0] in GROUPINGS and np.isfinite(calibration["curvature_per_l"])
    assert (calibration["curvature_per_l"] != 0.0) == calibration["grouping"].endswith(CURVED)
    assert label.startswith("optical, calibrated on the subject (residual ")

    capsys.readouterr()
    assert main(["analyze", str(results), "--json"]) == 0
    analysed = json.loads(capsys.readouterr().out)
    flow, optical, truth = (analysed["values"][k] for k in ("flow sensor", "optical", "truth (simulation)"))
    assert "TV_l" in flow and "VC_l" in flow and "FVC_l" not in flow  # the blows came after the mouthpiece
    assert analysed["references"]["FVC"]["source"] == "optical" and analysed["optical_label"] == label
    # read after the calibration: its quiet breathing and slow VC are the fit's own data and the flow sensor's
    assert analysed["optical_read_from_s"] == pytest.approx(off_s, abs=0.01)
    later = analysed["values"][f"truth from {analysed['optical_read_from_s']:.1f} s"]
    assert optical["breaths"] == later["breaths"] < truth["breaths"]
    assert optical["TV_l"] == pytest.approx(later["TV_l"], rel=0.15)
    from app.volume_summary import volume_summary
    assert f"read from {off_s:.1f} s, after the subject's calibration" in volume_summary(session, results)
    # measured at this scale (0.05: 70 px wide maps, a map every 4 frames): FVC +3.8 %, FEV1 +2.9 %, VC +1.0 %
    # (every 2: +3.6, +2.8, +0.7 %)
    for key in ("FVC_l", "FEV1_l", "VC_l"):
        assert optical[key] == pytest.approx(truth[key], rel=0.06), key

    data = build_report(results, with_maps=False)
    assert data.main_source == OPTICAL and data.interpretation is not None and data.optical_label == label
    # the report reads the optical values of the one analysis `analyze` prints, not an analysis of its own
    reported = data.sources[OPTICAL].parameters()
    assert {k: reported[k] for k in optical} == pytest.approx(optical)
    # its tidal volumes read with the quiet breathing's own gain, alike in the results, the analysis and the report
    assert any("quiet-breathing gain" in p for p in data.sources[OPTICAL].problems)
    assert not any("analyses the same curves differently" in n for n in data.notes), data.notes
    bundle = fhir_bundle(data)
    methods = {e["resource"].get("method", {}).get("text") for e in bundle["entry"]}
    assert f"optical (near-light photometric stereo, photopft): {label}" in methods
