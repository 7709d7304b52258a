"""Errors reach the user as dialogs that say what happened and what to do; the detail goes to
the log file in the user's state folder (never a traceback on screen)."""

from __future__ import annotations

import logging
import sys
import traceback
from pathlib import Path
from typing import Callable

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


def file_problem(path: Path, error: BaseException) -> tuple[str, str]:
    """(what, what to do) in plain words for a session or results file that cannot be read; the
    reader's own words (HDF5's among them) go to the log as the detail."""
    text = str(error)
    name = Path(path).name
    if "truncated file" in text:
        return (f"Cannot open {name}: it is cut short (the recording that wrote it was interrupted).",
                f"`photopft recover {name}` makes a whole copy of what it holds (the file itself is not changed).")
    if "signature not found" in text:
        return (f"Cannot open {name}: it is not a photopft session file.",
                "Choose a session (.h5) that photopft or the rig recorded.")
    return (f"Cannot open {name}: it cannot be read as a photopft session.",
            f"`photopft validate {name}` lists what is wrong with it; `photopft recover {name}` saves what a "
            "damaged recording still holds.")


def install_excepthook(parent_of: callable, unattended: Callable[[], None] | None = None) -> None:
    """An unexpected error becomes a dialog (and a log entry with the traceback).

    `unattended`: nobody is there to close a dialog (`photopft gui --smoke-test`): the traceback goes
    to the log (which the GUI's logging prints on stderr too), and `unattended` is called (to close
    the window and leave the event loop) instead. A modal dialog there waited until the installer
    test's 15-minute timeout."""

    def hook(kind, value, tb) -> None:
        detail = "".join(traceback.format_exception(kind, value, tb))
        if unattended is not None:
            log.error("Something went wrong: %s\n%s", value, detail)
            unattended()
            return
        show_error(parent_of(), f"Something went wrong: {value}",
                   "The session so far is kept. Save your work, then restart photopft; if it happens again, "
                   "send the log file to support.", detail)

    sys.excepthook = hook
