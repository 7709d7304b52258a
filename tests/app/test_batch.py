"""`photopft batch` on a Dask LocalCluster of two workers: the results equal `process`'s, a broken
file is one line and does not stop the others, and a second run skips what is done."""

from __future__ import annotations

import h5py
import numpy as np

from app.cli import main
from core.sim.simulate import SimConfig, simulate


def test_batch_on_a_local_cluster(tmp_path, capsys):
    folder, out = tmp_path / "sessions", tmp_path / "results"
    folder.mkdir()
    for seed in (1, 2):
        simulate(folder / f"s{seed}.h5", SimConfig(protocol="tidal", seconds=0.5, scale=0.05, seed=seed))
    (folder / "broken.h5").write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    assert main(["process", str(folder / "s1.h5"), "-o", str(tmp_path / "direct.h5")]) == 0
    capsys.readouterr()
    assert main(["batch", str(folder), "-o", str(out), "--workers", "2"]) == 0
    printed = capsys.readouterr().out
    assert "skipped broken.h5: cannot be opened (truncated, damaged or not HDF5" in printed
    assert "Dask dashboard: http" in printed
    assert "s1.h5: done" in printed and "s2.h5: done" in printed
    with h5py.File(tmp_path / "direct.h5") as a, h5py.File(out / "s1-results.h5") as b:
        for head in ("front", "back"):
            for key in ("frame_index", "valid_pixels"):
                np.testing.assert_array_equal(a[f"heads/{head}/{key}"][:], b[f"heads/{head}/{key}"][:])
            for key in ("distance_mm", "gradient_volume"):
                np.testing.assert_allclose(a[f"heads/{head}/{key}"][:], b[f"heads/{head}/{key}"][:], rtol=1e-8)
    (folder / "s3.h5").write_bytes((folder / "s2.h5").read_bytes())
    with h5py.File(folder / "s3.h5", "a") as f:  # a session that opens but cannot be processed
        del f["heads/front/frames"]
    assert main(["batch", str(folder), "-o", str(out), "--workers", "2"]) == 1
    printed = capsys.readouterr().out
    assert "3 session(s)" in printed and "2 already processed, 1 to do" in printed
    assert "s3.h5: failed: " in printed and "1 failed" in printed
    assert not (out / "s3-results.h5").exists()


def test_batch_never_removes_what_it_did_not_write(tmp_path, capsys):
    folder, out = tmp_path / "sessions", tmp_path / "results"
    folder.mkdir()
    out.mkdir()
    simulate(folder / "x.h5", SimConfig(protocol="tidal", seconds=0.3, scale=0.05, seed=1))
    simulate(folder / "y.h5", SimConfig(protocol="tidal", seconds=0.3, scale=0.05, seed=2))
    recorded = out / "x-results.h5"
    recorded.write_bytes((folder / "y.h5").read_bytes())  # a recorded session where x's results would go
    foreign = out / "y-results.h5"
    foreign.write_bytes(b"someone's notes, not HDF5")
    before = {p: p.read_bytes() for p in (recorded, foreign)}
    assert main(["batch", str(folder), "-o", str(out), "--workers", "1"]) == 1
    printed = capsys.readouterr().out
    assert "x.h5: refused: " in printed and "is a recorded session, never replaced" in printed
    assert "y.h5: refused: " in printed and "is not a photopft results file: left alone" in printed
    assert {p: p.read_bytes() for p in (recorded, foreign)} == before
    assert sorted(p.name for p in out.iterdir()) == ["x-results.h5", "y-results.h5"]
