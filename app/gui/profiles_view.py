"""Calibration > Profiles in force: each kind of calibration of this rig, the profile in force with
its date, the ones it replaced, and putting one of those back (engineer; logged)."""

from __future__ import annotations

import json
from contextlib import nullcontext
from pathlib import Path

from PySide6.QtWidgets import (QDialog, QDialogButtonBox, QHBoxLayout, QLabel, QListWidget, QListWidgetItem,
                               QPushButton, QVBoxLayout)

from app.calibration_store import PROFILES, calibration_audit, calibration_dir, history, restore, to_factory
from app.gui.errors import show_error
from app.records import RecordsError


def profile_created(path: Path) -> str:
    """A profile's creation time as written in it, or what is wrong with reading it."""
    try:
        created = str(json.loads(path.read_text()).get("created", ""))
    except (OSError, ValueError, AttributeError) as exc:
        return f"unreadable ({exc.__class__.__name__})"
    return created[:16].replace("T", " ") or "no date"


class ProfilesWindow(QDialog):
    def __init__(self, parent, rig_name: str, in_force_text: str) -> None:
        super().__init__(parent)
        self.rig_name = rig_name
        self.restored: Path | None = None
        self.outcome = ""  # what changed, for the status bar
        self.setWindowTitle(f"Calibration profiles of the rig {rig_name!r}")
        layout = QVBoxLayout(self)
        heading = QLabel(f"<b>In force now:</b> {in_force_text or 'as recorded in the file being replayed'}<br>"
                         f"Folder: {calibration_dir(rig_name)}")
        heading.setWordWrap(True)
        layout.addWidget(heading)
        self.lists: dict[str, QListWidget] = {}
        self.factory_buttons: dict[str, QPushButton] = {}
        for name, kind in PROFILES.items():
            current = calibration_dir(rig_name) / name
            label = QLabel(f"<b>{kind[0].upper() + kind[1:]}</b>: "
                           + (f"{name} of {profile_created(current)}" if current.is_file() else "none saved yet"))
            layout.addWidget(label)
            earlier = QListWidget()
            earlier.setMaximumHeight(90)
            for path in history(rig_name, name):
                item = QListWidgetItem(f"{profile_created(path)}  ({path.name})")
                item.setData(256, str(path))
                earlier.addItem(item)
            if earlier.count() == 0:
                earlier.addItem("no earlier profile")
            row = QHBoxLayout()
            row.addWidget(earlier, 1)
            button = QPushButton("Put back in force")
            button.setEnabled(bool(history(rig_name, name)))
            button.clicked.connect(lambda _=False, w=earlier: self._restore(w))
            factory = QPushButton("The rig's own (as built)")
            factory.setToolTip("No profile of this kind in force: the rig's file, or its parts as built; the "
                               "profile in force now joins the list above and can be put back")
            factory.setEnabled(current.is_file())
            factory.clicked.connect(lambda _=False, n=name: self._factory(n))
            buttons_column = QVBoxLayout()
            buttons_column.addWidget(button)
            buttons_column.addWidget(factory)
            row.addLayout(buttons_column)
            layout.addLayout(row)
            self.lists[name] = earlier
            self.factory_buttons[name] = factory
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Close)
        buttons.rejected.connect(self.reject)
        layout.addWidget(buttons)
        self.resize(720, 480)

    def _factory(self, profile: str) -> None:
        def change(records) -> Path:
            to_factory(self.rig_name, profile, records)
            return calibration_dir(self.rig_name) / profile

        self._change(change, f"No {PROFILES[profile]} profile in force: the rig's own, as built",
                     "The rig's own calibration cannot be put in force.")

    def _restore(self, earlier: QListWidget) -> None:
        item = earlier.currentItem()
        if item is None or not item.data(256):
            show_error(self, "Choose the earlier profile to put back.", "Click one in the list first.")
            return
        self._change(lambda records: restore(self.rig_name, Path(item.data(256)), records),
                     "Calibration profile restored and in force: {name}", "That profile cannot be put back.")

    def _change(self, change, outcome: str, failed: str) -> None:
        """A change of the profiles in force by an engineer (calibration_audit), logged; `change(records)`
        returns the profile's path in force, `outcome` says what changed ({name}: its file's)."""
        try:
            records = calibration_audit()
        except RecordsError as exc:
            show_error(self, "You may not change the rig's calibration.", str(exc))
            return
        try:
            with records or nullcontext():
                self.restored = change(records)
        except (OSError, ValueError) as exc:
            show_error(self, failed, str(exc))
            return
        self.outcome = outcome.format(name=self.restored.name)
        self.accept()
