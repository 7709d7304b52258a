"""Errors reach the user as dialogs that say what happened and what to do; the detail goes to
the log file in the user's state folder (never a traceback on screen)."""

from __future__ import annotations

import logging
import sys
import traceback
from pathlib import Path

from PySide6.QtWidgets import QMessageBox, QWidget

from app.logs import log_file, log_to_file

log = logging.getLogger("photopft.gui")

ENGINE_LOG = "photopft-engine.log"


def setup_logging() -> Path:
    """The GUI's log file; the engine process writes ENGINE_LOG beside it."""
    return log_to_file(log_file())


def show_error(parent: QWidget | None, what: str, todo: str, detail: str = "") -> None:
    """A modal message: what happened, what to do; the detail is logged, not shown."""
    log.error("%s | %s%s", what, todo, f"\n{detail}" if detail else "")
    box = QMessageBox(QMessageBox.Icon.Warning, "photopft", what, QMessageBox.StandardButton.Ok, parent)
    box.setInformativeText(f"{todo}\n\nDetails are in the log files: {log_file()} and {log_file(ENGINE_LOG)}")
    box.exec()


def install_excepthook(parent_of: callable) -> None:
    """An unexpected error becomes a dialog (and a log entry with the traceback)."""

    def hook(kind, value, tb) -> None:
        detail = "".join(traceback.format_exception(kind, value, tb))
        show_error(parent_of(), f"Something went wrong: {value}",
                   "The session so far is kept. Save your work, then restart photopft; if it happens again, "
                   "send the log file to support.", detail)

    sys.excepthook = hook
