"""A visit processed in the background, with its progress and a Cancel button
(app/session_processing.py): after a recording, and from the records window's "Process again".

The work runs on the thread pool with a records connection of its own (one per thread); the panel
shows what it processes, how far it is, and the outcome: the optical values stored, or why the
optical volume was refused.
"""

from __future__ import annotations

import logging
import threading
import traceback

from PySide6.QtCore import QObject, QRunnable, QThreadPool, Signal
from PySide6.QtWidgets import QHBoxLayout, QLabel, QProgressBar, QPushButton, QWidget

from app.records import Records
from app.session_processing import ProcessingCancelled, process_visit


class _Signals(QObject):
    progress = Signal(float)
    done = Signal(object)
    failed = Signal(str, str)


class _ProcessingJob(QRunnable):
    def __init__(self, session_id: int, records_path, cancel: threading.Event) -> None:
        super().__init__()
        self.session_id, self.records_path, self.cancel = session_id, records_path, cancel
        self.signals = _Signals()

    def _emit(self, signal, *args) -> None:
        """A window closed while its visit was processed has nobody to tell: the work stops."""
        try:
            signal.emit(*args)
        except RuntimeError:
            self.cancel.set()

    def run(self) -> None:
        try:
            with Records(self.records_path) as records:
                outcome = process_visit(records, self.session_id, lambda share: self._emit(self.signals.progress, share),
                                        self.cancel.is_set)
        except ProcessingCancelled as exc:
            self._emit(self.signals.failed, str(exc), "")
        except Exception as exc:  # every failure of the job reaches the operator in the panel and the log
            self._emit(self.signals.failed, f"The processing failed: {exc}", traceback.format_exc())
        else:
            self._emit(self.signals.done, outcome)


class ProcessingPanel(QWidget):
    """What is being processed, a progress bar and Cancel; hidden when nothing is. `finished`
    carries the ProcessedVisit, `problem` the one line of a failure or a cancel."""

    finished = Signal(object)
    problem = Signal(str)

    def __init__(self, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        self.label = QLabel()
        self.bar = QProgressBar(minimum=0, maximum=1000, textVisible=True)
        self.bar.setMaximumWidth(220)
        self.cancel_button = QPushButton("Cancel", clicked=self.cancel)
        row = QHBoxLayout(self)
        row.setContentsMargins(0, 0, 0, 0)
        for w in (self.label, self.bar, self.cancel_button):
            row.addWidget(w)
        self._cancel = threading.Event()
        self._job: _ProcessingJob | None = None
        self.last_message = ""
        self.hide()

    @property
    def busy(self) -> bool:
        return self._job is not None

    def start(self, session_id: int, name: str, records_path=None) -> bool:
        """Process the visit in the background; False (and nothing started) while another runs."""
        if self.busy:
            self.problem.emit(f"{name}: another visit is being processed; try again when it is done")
            return False
        self._cancel = threading.Event()
        self._job = _ProcessingJob(session_id, records_path, self._cancel)
        self._job.signals.progress.connect(lambda share: self.bar.setValue(int(share * 1000)))
        self._job.signals.done.connect(self._done)
        self._job.signals.failed.connect(self._failed)
        self.label.setText(f"Processing {name}")
        self.bar.setValue(0)
        self.cancel_button.setEnabled(True)
        self.show()
        QThreadPool.globalInstance().start(self._job)
        return True

    def cancel(self) -> None:
        self._cancel.set()
        self.cancel_button.setEnabled(False)
        self.label.setText(self.label.text() + ": cancelling")

    def _done(self, outcome) -> None:
        self._job = None
        optical = outcome.sources.get("optical")
        self.last_message = (f"Processed {outcome.results_path.name}: " +
                             ("optical values stored" if optical else
                              f"no optical values ({outcome.optical_refused})" if outcome.optical_refused else
                              "no optical values"))
        self.hide()
        self.finished.emit(outcome)

    def _failed(self, message: str, detail: str) -> None:
        self._job = None
        self.last_message = message
        if detail:
            logging.getLogger(__name__).error("%s\n%s", message, detail)
        self.hide()
        self.problem.emit(message)
