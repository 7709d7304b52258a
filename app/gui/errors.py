"""Errors reach the user as dialogs that say what happened and what to do; the detail goes to
the log file in the user's state folder (never a traceback on screen)."""

from __future__ import annotations

import logging
import sys
import traceback
from logging.handlers import RotatingFileHandler
from pathlib import Path

from PySide6.QtWidgets import QMessageBox, QWidget

from app.paths import state_dir

log = logging.getLogger("photopft.gui")


def log_file() -> Path:
    return state_dir() / "photopft.log"


def setup_logging() -> Path:
    path = log_file()
    path.parent.mkdir(parents=True, exist_ok=True)
    handler = RotatingFileHandler(path, maxBytes=5_000_000, backupCount=3, encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(threadName)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    return path


def show_error(parent: QWidget | None, what: str, todo: str, detail: str = "") -> None:
    """A modal message: what happened, what to do; the detail is logged, not shown."""
    log.error("%s | %s%s", what, todo, f"\n{detail}" if detail else "")
    box = QMessageBox(QMessageBox.Icon.Warning, "photopft", what, QMessageBox.StandardButton.Ok, parent)
    box.setInformativeText(f"{todo}\n\nDetails are in the log file: {log_file()}")
    box.exec()


def install_excepthook(parent_of: callable) -> None:
    """An unexpected error becomes a dialog (and a log entry with the traceback)."""

    def hook(kind, value, tb) -> None:
        detail = "".join(traceback.format_exception(kind, value, tb))
        show_error(parent_of(), f"Something went wrong: {value}",
                   "The session so far is kept. Save your work, then restart photopft; if it happens again, "
                   "send the log file to support.", detail)

    sys.excepthook = hook
