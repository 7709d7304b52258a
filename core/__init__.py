"""photopft core: the science, free of Qt and of drivers."""

import os

__version__ = "0.1.0"

# numba's parallel kernels run on OpenMP threads; left spinning between kernels they take the cores
# from scipy's FFT threads, h5py and, in the application, the capture and GUI threads. Waiting
# passively, `photopft process` on a 1 s full-resolution session took 84 s instead of 95 s here
# (docs/benchmarks.md). Set before any kernel loads OpenMP; a value already set is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# numba colours its typing messages through colorama, each use of which takes `sys.stderr` as it
# finds it, swaps it and puts it back: a cold compile did it 76,524 times in `photopft process` here,
# in whatever thread compiled, so a compile running beside a change of `sys.stderr` could put back a
# stream that was no longer the process's (under pytest, a finished test's capture). Plain messages
# leave `sys.stderr` alone. Set before numba is imported; a value already set is kept.
os.environ.setdefault("NUMBA_DISABLE_ERROR_MESSAGE_HIGHLIGHTING", "1")

# The live view calls parallel kernels from several threads at once (each camera's, the
# reconstruction's). numba's own workqueue layer, its last resort where neither OpenMP nor TBB loads,
# aborts the process on that (seen 2026-11-29 in a bundle whose OpenMP pool no longer loaded): ask
# for a thread-safe layer, so that a machine without one fails at the first kernel with numba's
# message instead of the engine aborting mid-session. A value already set is kept.
os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")
