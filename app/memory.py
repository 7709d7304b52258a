"""Memory of a long live session (Linux): how much a process holds, and handing freed heap back."""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
import time

_trimmer: threading.Thread | None = None


def rss_mb(pid: int | str = "self") -> float:
    """Resident memory of a process (this one by default), NaN once it has gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def start_memory_trimmer(interval_s: float = 10.0) -> None:
    """Hand the memory the C heap holds free back to the system every `interval_s` (glibc's
    malloc_trim; ctypes lets go of the GIL during the call, so nothing waits for it). The frames
    and maps that several threads allocate and free otherwise stay with the process (3-minute
    recording at scale 0.5: +110 MB without, +87 MB with it)."""
    global _trimmer
    if _trimmer is not None:
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        trim = libc.malloc_trim
    except (OSError, AttributeError):  # not glibc
        return

    def loop() -> None:
        while True:
            time.sleep(interval_s)
            trim(0)

    _trimmer = threading.Thread(target=loop, name="memory-trim", daemon=True)
    _trimmer.start()
