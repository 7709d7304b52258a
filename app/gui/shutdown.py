"""SIGTERM and SIGINT (a logout, a shutdown, Ctrl-C in the terminal) end the application cleanly.

Python runs a signal handler only when the interpreter gets control, and Qt's event loop is C++:
the handler writes the signal's number to a socket (signal.set_wakeup_fd) whose QSocketNotifier
wakes the event loop, which then calls `on_signal` on the GUI thread. The window's `shut_down`
finishes a recording (file closed, the visit marked), stops the engine process and quits with 0,
with no dialog: nobody may be there to answer one.
"""

from __future__ import annotations

import signal
import socket

from PySide6.QtCore import QObject, QSocketNotifier

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class ShutdownSignals(QObject):
    """While it lives, SIGTERM and SIGINT call `on_signal(signum)` on the GUI thread."""

    def __init__(self, parent: QObject, on_signal) -> None:
        super().__init__(parent)
        self.on_signal = on_signal
        self._read, self._write = socket.socketpair()
        for end in (self._read, self._write):
            end.setblocking(False)
        self._previous_fd = signal.set_wakeup_fd(self._write.fileno())
        self._previous = {sig: signal.signal(sig, lambda *_: None) for sig in SIGNALS}
        self._notifier = QSocketNotifier(self._read.fileno(), QSocketNotifier.Type.Read, self)
        self._notifier.activated.connect(self._woken)
        self.received: list[int] = []

    def _woken(self) -> None:
        try:
            data = self._read.recv(64)
        except BlockingIOError:
            return
        for signum in data:
            if signum in SIGNALS:
                self.received.append(signum)
                self.on_signal(signum)
                return

    def restore(self) -> None:
        self._notifier.setEnabled(False)
        signal.set_wakeup_fd(self._previous_fd)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._read.close()
        self._write.close()
