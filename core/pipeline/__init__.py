"""The top of core: a session in, a results file out (process.py), by the stages below it (io,
reconstruction and calibration, volume, analysis; the layers are kept by import-linter), and the
quality rules that refuse or withhold the optical volume (quality.py)."""
