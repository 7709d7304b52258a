"""A device emulator served on a pseudo-terminal: the part every emulator shares."""

from __future__ import annotations

import os
import threading


class PtyDevice:
    """Opens a pseudo-terminal (`port` is its path for a driver to open) and serves it from a thread."""

    def __init__(self) -> None:
        self.master, self._slave = os.openpty()
        self.port = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"{type(self).__name__}", daemon=True)

    def _serve(self) -> None:
        raise NotImplementedError

    def start(self):
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=1)
        for fd in (self.master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
