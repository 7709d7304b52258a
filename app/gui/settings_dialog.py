"""Settings: the rig configuration, the reference equations, the report's page size."""

from __future__ import annotations

from pathlib import Path

from PySide6.QtCore import QSettings
from PySide6.QtWidgets import (QComboBox, QDialog, QDialogButtonBox, QFileDialog, QFormLayout, QHBoxLayout, QLabel,
                               QLineEdit, QPushButton, QWidget)

from drivers.rig import RigConfigError, load_rig_config

EQUATIONS = {"gli-global": "GLI Global 2022 (race-neutral)", "gli-2012": "GLI-2012"}
PAGE_SIZES = {"a4": "A4", "letter": "US Letter"}


class SettingsDialog(QDialog):
    def __init__(self, settings: QSettings, parent=None) -> None:
        super().__init__(parent)
        self.setWindowTitle("Settings")
        self.settings = settings
        form = QFormLayout(self)
        self.rig = QLineEdit(str(settings.value("rig/config", "")))
        self.rig.setPlaceholderText("the simulated rig (resources/rigs/simulated.toml)")
        browse = QPushButton("Choose…")
        browse.clicked.connect(self._browse)
        row = QWidget()
        line = QHBoxLayout(row)
        line.setContentsMargins(0, 0, 0, 0)
        line.addWidget(self.rig)
        line.addWidget(browse)
        form.addRow("Rig configuration", row)
        self.equations = QComboBox()
        for key, text in EQUATIONS.items():
            self.equations.addItem(text, key)
        self.equations.setCurrentIndex(list(EQUATIONS).index(str(settings.value("reference/equations",
                                                                                "gli-global"))))
        form.addRow("Reference equations", self.equations)
        self.page = QComboBox()
        for key, text in PAGE_SIZES.items():
            self.page.addItem(text, key)
        self.page.setCurrentIndex(list(PAGE_SIZES).index(str(settings.value("report/page_size", "a4"))))
        form.addRow("Report page size", self.page)
        form.addRow(QLabel("Volumes are in litres (BTPS), flows in litres per second, as ATS/ERS reports them."))
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.accepted.connect(self.accept)
        buttons.rejected.connect(self.reject)
        form.addRow(buttons)

    def _browse(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Rig configuration", str(Path.home()), "Rig configuration (*.toml)")
        if path:
            self.rig.setText(path)

    def accept(self) -> None:
        text = self.rig.text().strip()
        if text:
            try:
                load_rig_config(text)
            except RigConfigError as exc:
                from app.gui.errors import show_error

                show_error(self, "That rig configuration cannot be used.", str(exc))
                return
        self.settings.setValue("rig/config", text)
        self.settings.setValue("reference/equations", self.equations.currentData())
        self.settings.setValue("report/page_size", self.page.currentData())
        super().accept()
