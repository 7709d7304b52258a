"""`photopft bench compression`: every filter gives the frames back bit for bit, with its ratio and speeds."""

from __future__ import annotations

import re

from app.cli import main


def test_compression_bench_measures_lossless_filters(capsys):
    assert main(["bench", "compression", "--scale", "0.1", "--frames", "20", "--no-write"]) == 0
    out = capsys.readouterr().out
    rows = dict(re.findall(r"^\| ([^|]+?) \| ([\d.]+) \|", out, flags=re.M))
    assert abs(float(rows["none"]) - 1.0) < 0.05  # the file's own overhead on small frames
    assert "Blosc2 lz4 5 + bitshuffle" in rows and "gzip 1 + shuffle (HDF5's own)" in rows
    assert all(float(ratio) > 1.2 for name, ratio in rows.items() if name != "none")  # 12-bit data in 16 bits
