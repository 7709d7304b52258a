"""`photopft bench population --quick`: two small subjects through calibration, recording,
processing and analysis in the clinic world; the table, the per-subject lines and the plots."""

from __future__ import annotations

import json
import shutil

import cv2
import pytest

from benchmarks.common import SHARED
from benchmarks.population import agreement, run_population_bench
from benchmarks.renders import RenderCache
from core.io.results import ResultsFile


@pytest.mark.slow
def test_the_quick_population_runs_end_to_end_and_reports_what_it_found(tmp_path, shared_data):
    # scale 0.1: at 0.08 the specular sphere's highlights are too small to triangulate in the clinic's light
    waveforms, kept = SHARED / "data" / "spirometry-waveforms", tmp_path / "kept"
    renders = RenderCache(tmp_path / "renders", 1e12)  # the sessions kept, for --reread below
    text, rows = run_population_bench(2, 0.1, 1, True, 1, waveforms, tmp_path, keep=kept, renders=renders)
    assert len(rows) == 2
    for row in rows:
        # each subject either gave its values or says at which stage and why it stopped
        assert "truth" in row or row["refused"].startswith(("light calibration:", "process:"))
        # 16-px spheres on LEDs that drift between the wizard's captures leave the lights 20-25 mm off (the
        # shading cannot hold them; docs/reconstruction.md), which the light model's misfit then refuses
        refused = row.get("optical_refused")
        assert refused is None or any(reason in refused for reason in (
            "outside the rig's working range", "an arm lies against", "the shading does not follow the light model",
            "jumps away and back"))
        assert row["body"]["name"] in ("average-woman", "arms-close")
    analysed = [r for r in rows if "truth" in r]
    assert analysed, "no subject reached the analysis"
    # each analysed subject's results are kept beside its row, to read other signals off without processing
    assert len(list(kept.glob("*.results.h5"))) == len(analysed) and not list(kept.glob("*.stages"))
    for row in analysed:
        with ResultsFile(next(kept.glob(f"subject-{row['subject']['seed']}-*.results.h5"))) as r:
            assert (r.metric_volume() is not None) == bool(row["optical"])
    sources = {(label, source) for label, _, source, *_ in agreement(rows)}
    # an optical value refused counts as one; 8 s hold no slow VC to calibrate on: the litres are estimates
    assert ("TV", "flow") in sources and ("TV", "estimate") in sources
    assert all(r.get("calibrated") == {} for r in analysed)
    assert all("no quiet breathing and slow VC" in (r.get("subject_calibration") or {}).get("not_calibrated", "")
               for r in analysed if r.get("estimate"))
    flow_tv = next(r for r in agreement(rows) if r[0] == "TV" and r[2] == "flow")
    assert flow_tv[8] == 1.0  # the flow sensor's tidal volume is within 50 mL of the truth on every subject
    assert "| TV (L) | flow sensor |" in text and "arms-close" in text and "ISO26782" in text
    plots = sorted(tmp_path.glob("population-0.1-*.png"))
    assert {p.stem.split("-")[-1] for p in plots} >= {"TV", "RR"}
    image = cv2.imread(str(plots[0]))
    assert image is not None and image.shape[0] > 200 and image.std() > 5
    # run again with the same folder: the finished subjects are taken, not run again
    again, rows_again = run_population_bench(2, 0.1, 1, True, 1, waveforms, None, keep=kept)
    assert "2 subjects kept from an earlier run" in again
    assert [r.get("truth") for r in rows_again] == [r.get("truth") for r in rows]
    # after a change to the analysis only: --reread reads the kept results again, processes nothing, and
    # says which commit processed and which read them; a subject without its results file stays as it was
    import benchmarks.population as population
    import core.pipeline.process as process

    def no_processing(*args, **kwargs):
        raise AssertionError("processed again")

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(process, "process_session", no_processing)
        patch.setattr(population, "source_commit", lambda: "analysis-change")
        missing = next(kept.glob(f"subject-{analysed[-1]['subject']['seed']}-*.results.h5"))
        missing.rename(tmp_path / "aside.h5")
        reread_text, reread_rows = run_population_bench(2, 0.1, 1, True, 1, waveforms, None, keep=kept, reread=True)
    read_again = [r for r in reread_rows if r.get("processed_by")]
    assert len(read_again) == len(analysed) - 1 and all(r["commit"] == "analysis-change" for r in read_again)
    assert all(r["processed_by"] == rows[0]["commit"] for r in read_again)
    assert [r.get("truth") for r in reread_rows] == [r.get("truth") for r in rows]
    assert "read again at analysis-change (`--reread`)" in reread_text
    assert json.loads(next(kept.glob(f"subject-{read_again[0]['subject']['seed']}-*.json")).read_text())[
        "commit"] == "analysis-change"  # kept so
    # the renders gone (pruned, or a run longer than a disk keeps): read again off the sessions kept
    # beside the rows without their frames, to the same values
    shutil.rmtree(tmp_path / "renders")
    copies = sorted(kept.glob("*.session.h5"))
    assert len(copies) == len(analysed) and all(c.stat().st_size < 5e6 for c in copies)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(process, "process_session", no_processing)
        patch.setattr(population, "source_commit", lambda: "later")
        _, without_renders = run_population_bench(2, 0.1, 1, True, 1, waveforms, None, keep=kept, reread=True)
    later = [r for r in without_renders if r.get("commit") == "later"]
    assert read_again and len(later) == len(read_again)
    for before, after in zip(read_again, later):
        assert (after["calibrated"], after["estimate"], after["truth"]) == (
            before["calibrated"], before["estimate"], before["truth"])


def test_wrong_arguments_get_one_line_before_any_subject_runs(tmp_path, capsys):
    """A keep folder that is a file would have failed after the first subject (tens of minutes in);
    no subjects at all is refused, and the complaint about an option names no file."""
    from app.cli import main

    not_a_folder = tmp_path / "kept"
    not_a_folder.write_text("")
    assert main(["bench", "population", "--subjects", "1", "--no-write", "--keep", str(not_a_folder)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"photopft bench: error: {not_a_folder}: --keep must be a folder (the finished subjects are kept in it), this is a file"
    assert main(["bench", "population", "--subjects", "0", "--no-write"]) == 2
    assert capsys.readouterr().err.strip() == "photopft bench: error: --subjects must be 1 or more"
    assert main(["bench", "population", "--reread", "--no-write"]) == 2
    assert capsys.readouterr().err.strip() == "photopft bench: error: --reread reads the subjects kept in --keep FOLDER again"
    assert main(["bench", "population", "--reread", "--keep", str(tmp_path / "none"), "--no-write"]) == 2
    assert capsys.readouterr().err.strip() == (f"photopft bench: error: --reread reads the subjects kept in --keep "
                                               f"FOLDER again: {tmp_path / 'none'} is not a folder")


def test_the_table_tallies_why_the_optical_values_were_refused():
    """Each refusal `process` can give is named by its kind (the words taken from the refusals
    themselves, so a reworded reason is caught here), and the table counts them, most first."""
    import numpy as np

    from benchmarks.population import refusal_kind, refusal_tally
    from core.pipeline.quality import (bend_refusal, coverage_refusal, distance_refusal, occlusion_refusal,
                                       reflectance_refusal, volume_refusal)
    from core.volume.metric import MetricVolume

    arm = occlusion_refusal({"front": np.full(10, 0.6)})
    reasons = {arm: "an arm against the trunk",
               occlusion_refusal({}, {"back": np.full(10, 0.6)}): "the trunk out of the image",
               distance_refusal({"front": 2700.0}): "a distance outside the working range",
               distance_refusal({"front": float("nan")}): "no distance",
               coverage_refusal({"front": np.full(5, 0.01)}): "too little of the trunk",
               reflectance_refusal({"front": 0.3}): "a sheen on the skin",
               bend_refusal(np.full(5, 0.75)): "bent maps"}
    t = np.arange(200) * 50_000_000  # 20 maps a second for 10 s

    def metric(volume_l, mismatch=0.0):
        return volume_refusal(MetricVolume(t, volume_l, {}, {}, {}, "", {"front": mismatch}))

    breath = 0.5 * np.sin(2 * np.pi * t / 4e9)
    jumps = breath.copy()
    jumps[::25] += 0.4
    reasons[metric(breath + np.random.default_rng(0).normal(0, 0.2, len(t)))] = "a noisy curve"
    reasons[metric(jumps)] = "jumps"
    reasons[metric(breath, mismatch=0.2)] = "a head's scale"
    for reason, kind in reasons.items():
        assert refusal_kind(str(reason)) == kind, reason  # a row keeps the refusal's words
    assert refusal_kind("something new") == "other"
    shading = reflectance_refusal({"front": 0.5})
    rows = [{"optical_refused": str(arm)}, {"optical_refused": str(shading)}, {"optical_refused": str(arm)},
            {"optical_refused": None},
            {"refused": "process: truncated"}]
    assert refusal_tally(rows) == "2 for an arm against the trunk, 1 for a sheen on the skin"
    assert refusal_tally([{}]) == ""


def test_the_table_sets_the_calibration_s_groupings_against_the_truth():
    from benchmarks.population import grouping_lines

    truth = {"TV_l": 0.5, "VC_l": 4.0, "FVC_l": 4.0, "FEV1_l": 3.0, "FEV1_FVC": 0.75}

    def row(scale_one, scale_two):
        return {"truth": truth, "groupings": {
            "chosen": {"values": {k: scale_two * v for k, v in truth.items()}},
            "one gain": {"values": {k: scale_one * v for k, v in truth.items()}},
            "chest and abdomen": {"values": {k: scale_two * v for k, v in truth.items()}},
            "each region": {"values": {}, "refused": "the front chest signal would be weighed 7.0 times"}}}

    lines = grouping_lines([row(1.01, 1.10), row(0.98, 1.20), {"truth": truth, "groupings": {}}])
    table = {line.split(" | ")[0].strip("| "): line for line in lines if line.startswith("| ")}
    assert "2 subjects with one" in "\n".join(lines)
    assert table["one gain"].split(" | ")[1] == "2, -0.5, -2.0, 100%"  # TV: n, median, worst, within 3 % or 50 mL
    assert table["chest and abdomen"].split(" | ")[3] == "2, +15.0, +20.0, 0%"  # FVC
    assert table["each region"].endswith("| none | none | none | none | none |")
    assert grouping_lines([{"truth": truth}]) == []


def _blows(shared_data, gains: list[float]):
    """Three forced blows of a standard waveform, each exhaled `gain` times, read as the flow sensor's."""
    import numpy as np

    from core.analysis.spirometry import read_waveform
    from core.analysis.values import analyse_volume

    wave = read_waveform(shared_data / "spirometry-waveforms" / "ISO26782" / "2678201.wf")
    rate = 100.0
    exhaled = np.interp(np.arange(0.0, len(wave.volume_l) / wave.rate_hz, 1.0 / rate),
                        np.arange(len(wave.volume_l)) / wave.rate_hz, wave.volume_l)
    curve, events, level = [], [], 0.0
    for gain in gains:
        top = level + float(exhaled.max())
        start = sum(map(len, curve)) / rate
        curve += [np.full(300, level), np.linspace(level, top, 150), top - gain * exhaled]
        curve.append(np.linspace(curve[-1][-1], curve[-1][-1] + 1.0, 200))  # breathing in again, up
        level = float(curve[-1][-1])
        events += [(start + 4.3, "forced-start"), (sum(map(len, curve)) / rate - 0.5, "maneuver-end")]
    volume = np.concatenate(curve)
    return analyse_volume(np.arange(len(volume)) / rate, volume, events, 40.0)


def test_each_blow_is_set_beside_the_truth_s_reading_of_it(shared_data):
    """A session's FVC is its largest blow's: read one by one, the blows show how each is read, apart from
    which one the largest picks."""
    from benchmarks.population import blow_lines, blow_pairs

    truth, optical = _blows(shared_data, [1.0, 1.0, 1.0]), _blows(shared_data, [1.04, 0.98, 1.0])
    pairs = blow_pairs(optical, truth)
    assert [round(p["mark_s"], 1) for p in pairs] == [round(m.mark_s, 1) for m in truth.forced.manoeuvres]
    fvc = [p["optical"]["FVC_l"] / p["truth"]["FVC_l"] for p in pairs]
    assert fvc == pytest.approx([1.04, 0.98, 1.0], abs=1e-4)
    assert blow_pairs(optical, None) == [] and blow_pairs(None, truth) == []

    true_fvc = pairs[0]["truth"]["FVC_l"]
    row = {"calibrated": {"FVC_l": optical.forced.fvc_l, "FEV1_l": optical.forced.fev1_l},
           "truth": {"FVC_l": truth.forced.fvc_l, "FEV1_l": truth.forced.fev1_l}, "blows": pairs}
    (line,) = [text for text in blow_lines([row, {"calibrated": {}, "truth": {}}]) if text]
    assert line.startswith("Each forced blow calibrated on the subject (3 blows of 1 subjects)")
    mean = (0.04 - 0.02) / 3 * true_fvc
    assert f"FVC {mean:+.3f} L" in line and "67% within tolerance" in line  # 1.04: over 3 %
    assert f"the session's (its largest blow's) {0.04 * true_fvc:+.3f}" in line  # the largest: the one read over
    assert blow_lines([{"truth": {}, "calibrated": {}}]) == []


@pytest.mark.slow
def test_a_subject_stopped_midway_goes_on_from_its_last_finished_stage(tmp_path, shared_data, monkeypatch):
    """At the camera's full resolution a subject takes longer than a working session: with `keep`
    its lights' profile and session are kept as each stage ends, and the next run takes them
    instead of calibrating and recording again; what a stage stopped midway left is cleared."""
    import json

    import core.pipeline.process as process
    from benchmarks.population import SubjectStages, draw_subjects, run_subject, standard_blows

    subject = draw_subjects(1, 1, standard_blows(SHARED / "data" / "spirometry-waveforms"), quick=True)[0]
    folder = tmp_path / "subject.stages"
    real_process = process.process_session

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(process, "process_session", stopped)
    with pytest.raises(KeyboardInterrupt):
        run_subject(subject, 0.1, "short", str(folder), 4.0, 0.1, resume=True)
    state = json.loads((folder / "stages.json").read_text())
    assert set(state["seconds"]) == {"calibrate lights", "simulate subject"}
    session = folder / f"{subject.index}-session.h5"
    assert session.is_file() and (folder / f"{subject.index}-lights.json").is_file()
    (folder / f".{subject.index}-results.123.partial.h5").write_bytes(b"half a file")

    monkeypatch.setattr(process, "process_session", real_process)
    row = run_subject(subject, 0.1, "short", str(folder), 4.0, 0.1, resume=True)
    # the kept stages' seconds stand: they were not run again
    assert "truth" in row and row["stage_seconds"]["simulate subject"] == state["seconds"]["simulate subject"]
    assert row["stage_seconds"]["calibrate lights"] == state["seconds"]["calibrate lights"]
    assert set(row["stage_seconds"]) == {"calibrate lights", "simulate subject", "process", "analyse"}
    assert not folder.exists()  # the row holds what the stages gave

    # stages kept by another commit (or subject, scale, world) are not taken
    folder.mkdir()
    (folder / "stages.json").write_text(json.dumps({"stamp": {"commit": "other"}, "seconds": {"process": 1.0}}))
    session.write_bytes(b"")
    stages = SubjectStages(folder, {"commit": "this"})
    assert not stages.has("process") and list(folder.iterdir()) == []


def test_the_test_population_has_bodies_and_kept_rows_of_its_own(tmp_path, shared_data):
    """`--bodies mesh`: the same rigs, distances and skins as the development population, on MakeHuman
    bodies drawn from seeds of their own; their rows are kept apart and published under their own name."""
    from benchmarks.population import (MESH_SEEDS, _kept, describe_bodies, draw_subjects, population_body,
                                           population_section)
    from core.sim.makehuman import MeshBody

    development = draw_subjects(3, 1, [])
    test = draw_subjects(3, 1, [], bodies="mesh")
    assert [s.body for s in test] == [f"mesh:{MESH_SEEDS + 1000 + k}" for k in range(3)]
    assert [s.distance_mm for s in test] == [s.distance_mm for s in development]
    assert isinstance(population_body(test[0].body, test[0].seed), MeshBody)
    assert _kept(tmp_path, test[0], 0.5) != _kept(tmp_path, development[0], 0.5)
    assert population_section(0.5, 0.3, "clinic", "mesh") == "population-0.5-mesh"
    rows = [{"subject": {"body": s.body, "seed": s.seed}} for s in test]
    describe_bodies(rows)
    assert rows[0]["body"]["kind"] == "makehuman mesh" and rows[0]["body"]["arms"] == "away"


@pytest.mark.slow
def test_a_rerun_on_kept_renders_calibrates_and_processes_only(tmp_path, shared_data, monkeypatch):
    """With --renders, the subject's sphere sessions, its light calibration and its session are made once;
    a rerun at the same code takes them (nothing simulated or calibrated) and gives the same values, and
    the row names the commit that rendered them. A change to the calibrating code calibrates again from
    the kept sphere sessions."""
    import benchmarks.renders as renders_module
    import core.calibration.light_sessions as light_sessions
    import core.sim.simulate as simulator
    from benchmarks.population import draw_subjects, run_subject, standard_blows
    from benchmarks.renders import RenderCache

    subject = draw_subjects(1, 1, standard_blows(SHARED / "data" / "spirometry-waveforms"), quick=True)[0]
    renders = RenderCache(tmp_path / "renders", 1e12)
    first = run_subject(subject, 0.1, "short", str(tmp_path / "a"), 4.0, 0.1, renders=renders)
    assert "truth" in first and first["rendered_by"], first.get("refused")
    kept = renders.renders()
    assert len(kept) == 3 and all(size > 0 for _, size, _ in kept)  # the sphere sessions, the lights, the session

    def no_simulation(*args, **kwargs):
        raise AssertionError("simulated again")

    calibrate_lights = light_sessions.calibrate_lights
    monkeypatch.setattr(simulator, "simulate", no_simulation)
    monkeypatch.setattr(light_sessions, "calibrate_lights", no_simulation)
    again = run_subject(subject, 0.1, "short", str(tmp_path / "b"), 4.0, 0.1, renders=renders)
    assert again["truth"] == first["truth"] and again["optical"] == first["optical"]
    assert again["led_error_mm"] == first["led_error_mm"]
    assert {folder for _, _, folder in renders.renders()} == {folder for _, _, folder in kept}
    assert all(folder.is_dir() for _, _, folder in kept)  # a rerun leaves the renders it used

    calibrated = []
    monkeypatch.setattr(light_sessions, "calibrate_lights", lambda *a: calibrated.append(1) or calibrate_lights(*a))
    monkeypatch.setattr(renders_module, "code_digest", lambda sources: "another calibration")
    changed = run_subject(subject, 0.1, "short", str(tmp_path / "c"), 4.0, 0.1, renders=renders)
    assert calibrated == [1] and changed["led_error_mm"] == first["led_error_mm"]
    assert len(renders.renders()) == 4  # the new calibration beside the old, from the same sphere sessions


def test_kept_renders_are_keyed_by_the_simulator_and_pruned_least_recently_used(tmp_path, monkeypatch):
    import os

    import benchmarks.renders as renders_module
    from benchmarks.renders import RenderCache

    cache = RenderCache(tmp_path, max_bytes=2500)
    made = []

    def render(size):
        def into(folder):
            made.append(size)
            (folder / "session.h5").write_bytes(b"x" * size)
        return into

    a, _ = cache.rendered({"subject": 1}, render(1000), "c1")
    b, _ = cache.rendered({"subject": 2}, render(1000), "c1")
    assert cache.rendered({"subject": 1}, render(1000), "c2") == (a, cache.rendered({"subject": 1}, render(1), "c3")[1])
    assert made == [1000, 1000] and (a / "session.h5").stat().st_size == 1000
    os.utime(b / renders_module.MARK, (1, 1))  # b used longest ago
    c, mark = cache.rendered({"subject": 3}, render(1000), "c4")
    assert mark["commit"] == "c4" and not b.exists() and a.exists() and c.exists()  # 3000 bytes > 2500: b went
    (tmp_path / "not-ours").mkdir()
    (tmp_path / "not-ours" / "data.h5").write_bytes(b"y" * 5000)
    cache.prune()
    assert (tmp_path / "not-ours" / "data.h5").exists()  # only renders (with their mark) are ever removed
    monkeypatch.setattr(renders_module, "simulator_digest", lambda: "another simulator")
    d, _ = cache.rendered({"subject": 1}, render(1000), "c5")
    assert d != a and made[-1] == 1000  # the simulator changed: rendered again

    def fails(folder):
        (folder / "half.h5").write_bytes(b"z")
        raise RuntimeError("render stopped")

    with pytest.raises(RuntimeError):
        cache.rendered({"subject": 9}, fails, "c6")
    assert not any(p.name.startswith(".") for p in tmp_path.iterdir())  # nothing half-made left


def test_the_estimate_is_printed_no_surer_than_the_published_rows_measure():
    """The uncertainty an uncalibrated estimate is printed with covers the widest 95 % limit of its
    errors on both populations' published subset rows (docs/bench-rows; docs/constants.md)."""
    from pathlib import Path

    import numpy as np

    from core.analysis.optical_litres import ESTIMATE_UNCERTAINTY

    folder = Path(__file__).resolve().parents[2] / "docs" / "bench-rows" / "population-0.25-subset-3c3669d-reread"
    rows = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
    assert len(rows) == 16
    widest = 0.0
    for mesh in (False, True):
        for key in ("TV_l", "VC_l", "FVC_l", "FEV1_l"):
            errors = np.array([(r["estimate"][key] - r["truth"][key]) / r["truth"][key] for r in rows
                               if r["subject"]["body"].startswith("mesh:") == mesh and key in (r.get("estimate") or {})])
            assert len(errors) >= 7
            widest = max(widest, abs(errors.mean()) + 1.96 * errors.std(ddof=1))
    assert 0.55 < widest <= ESTIMATE_UNCERTAINTY  # test FEV1: -58.4 %
