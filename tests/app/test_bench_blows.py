"""`photopft bench blows`: the standard waveforms read as optical maps, straight and fitted."""

from __future__ import annotations

import numpy as np

from benchmarks.blows import maps_of, readings
from benchmarks.population import within
from app.cli import main


def test_a_map_is_the_mean_volume_over_its_light_cycle():
    rate = 1000.0
    t = np.arange(0, 2, 1 / rate)
    times, volumes = maps_of(2.0 * t, rate, 0.0)  # a straight ramp: the mean is the cycle's middle
    assert np.allclose(volumes, 2.0 * (times - 0.5 / 22.0), atol=2e-3)


def test_fitted_blows_keep_fev1_where_the_noise_moves_it_read_straight(shared_data):
    rows = readings(shared_data / "spirometry-waveforms", [0.025], phases=1, draws=1, seed=0)
    assert len(rows) == 37
    noisy = [r for r in rows if r.noise_ratio >= 0.2]
    assert len(noisy) >= 5

    def share(kind: str) -> float:
        return float(np.mean([within(getattr(r, kind).fev1_l, r.truth.fev1_l, 0.05, 0.03) for r in noisy]))

    assert share("fitted") >= 0.95 and share("straight") < share("fitted")


def test_the_bench_prints_its_bands_and_names_missing_waveforms(shared_data, tmp_path, capsys):
    assert main(["bench", "blows", "--noise-ml", "5", "--phases", "1", "--draws", "1",
                 "--waveforms", str(shared_data / "spirometry-waveforms"), "--no-write"]) == 0
    out = capsys.readouterr().out
    assert "| 0-3 % |" in out and "PEF is given where the ratio is at most 5 %" in out
    assert main(["bench", "blows", "--waveforms", str(tmp_path), "--no-write"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no standard waveforms" in err[0] and str(tmp_path) in err[0]


def test_at_a_map_every_frame_the_pef_is_read_as_the_analysis_reads_maps_at_every_frame(shared_data, tmp_path):
    """Three ATS waveforms, error-free and with 10 mL of noise a map, one map a frame: every error-free
    PEF within 10 %, read unsmoothed; the noisy ones smoothed first, and those given within 10 % too."""
    folder = tmp_path / "ATS24"
    folder.mkdir()
    for path in sorted((shared_data / "spirometry-waveforms" / "ATS24").glob("*.wf"))[:3]:
        (folder / path.name).symlink_to(path)
    rows = readings(tmp_path, [0.0, 0.010], phases=1, draws=1, seed=0, every_frame=True)
    clean, noisy = rows[0::2], rows[1::2]
    assert all(r.straight.pef_smoothing_s == 0.0 and r.given for r in clean)
    assert all(r.straight.pef_smoothing_s > 0.0 for r in noisy)
    assert all(within(r.straight.pef_lps, r.truth.pef_lps, 0.30, 0.10) for r in rows if r.given)


def test_the_start_s_table_shows_sparse_maps_calling_good_starts_hesitant(shared_data, tmp_path, capsys):
    """`bench blows --bev-steps-ms`: one map a light cycle judges the standard waveforms' starts as
    their own curves do; one every 290 ms calls good starts hesitant, the reason a start on maps that
    far apart is not judged (core.analysis.spirometry.start_not_judged)."""
    assert main(["bench", "blows", "--bev-steps-ms", "45.5,290", "--phases", "1", "--no-write",
                 "--waveforms", str(shared_data / "spirometry-waveforms")]) == 0
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| 45.5 ") or line.startswith("| 290.0 ")}
    assert rows["45.5"][1] == "37" and rows["45.5"][5].strip(" |") == "0 % / 0 %"
    hesitant = [float(x.strip(" %|")) for x in rows["290.0"][5].split(" / ")]
    assert min(hesitant) >= 5  # at phase 0 alone: 8 % straight, 5 % fitted
    assert main(["bench", "blows", "--bev-steps-ms", "45,x", "--no-write"]) == 2
    assert "--bev-steps-ms takes numbers" in capsys.readouterr().err
