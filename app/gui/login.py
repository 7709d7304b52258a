"""Signing in to the application, and the lock after it sits idle (app/auth.py).

Where the records have registered users with passwords, the application asks who is at it before
its window opens; after IDLE_MINUTES without a key or a click it forgets them and asks again over
the window (the live view goes on behind). Each wrong password is in the audit trail.
"""

from __future__ import annotations

from PySide6.QtCore import QEvent, QObject, QTimer
from PySide6.QtWidgets import (QApplication, QDialog, QDialogButtonBox, QFormLayout, QInputDialog, QLabel, QLineEdit,
                               QVBoxLayout, QWidget)

from app.auth import AuthenticationError, forget, proven_user
from app.records import Records, RecordsError, default_path

IDLE_MINUTES = 10.0  # a workstation left in a clinic room; the settings' security/idle_minutes overrides it


def login_needed() -> bool:
    """The records have users with passwords: who acts must sign in."""
    try:
        path = default_path()
        if not path.exists():
            return False
        with Records(path, read_only=True) as records:
            return records.roles_enforced and records.passwords_in_use
    except RecordsError:
        return False


class LoginDialog(QDialog):
    """User name and password, checked against the records; stays open until they are right or it is cancelled."""

    def __init__(self, parent: QWidget | None = None, name: str = "", why: str = "") -> None:
        super().__init__(parent)
        self.setWindowTitle("photopft: sign in")
        self.setModal(True)
        self.setMinimumWidth(420)
        layout = QVBoxLayout(self)
        layout.addWidget(QLabel(why or "Sign in with your photopft user name and password."))
        form = QFormLayout()
        self.name = QLineEdit(name)
        self.password = QLineEdit(echoMode=QLineEdit.EchoMode.Password)
        form.addRow("User", self.name)
        form.addRow("Password", self.password)
        layout.addLayout(form)
        self.message = QLabel(wordWrap=True)
        self.message.setStyleSheet("color: #b00020")
        layout.addWidget(self.message)
        buttons = QDialogButtonBox(QDialogButtonBox.StandardButton.Ok | QDialogButtonBox.StandardButton.Cancel)
        buttons.button(QDialogButtonBox.StandardButton.Ok).setText("Sign in")
        buttons.accepted.connect(self.try_sign_in)
        buttons.rejected.connect(self.reject)
        layout.addWidget(buttons)
        (self.password if name else self.name).setFocus()

    def try_sign_in(self) -> None:
        name = self.name.text().strip()
        try:
            with Records(user=name) as records:
                records.authenticate(self.password.text())
        except RecordsError as exc:
            self.message.setText(str(exc))
            self.password.clear()
            return
        self.accept()


class IdleLock(QObject):
    """Forgets the signed-in user after `minutes` without input and asks again; `quit` runs where
    the dialog is cancelled."""

    def __init__(self, window: QWidget, minutes: float, quit) -> None:
        super().__init__(window)
        self._window, self._quit = window, quit
        self._timer = QTimer(self, singleShot=True, interval=max(1, int(minutes * 60_000)))
        self._timer.timeout.connect(self.lock)
        self.locked = False
        QApplication.instance().installEventFilter(self)
        self._timer.start()

    def eventFilter(self, watched, event) -> bool:
        if not self.locked and event.type() in (QEvent.Type.KeyPress, QEvent.Type.MouseButtonPress,
                                                QEvent.Type.MouseMove, QEvent.Type.Wheel):
            self._timer.start()
        return False

    def lock(self) -> None:
        name = proven_user() or ""
        forget()
        self.locked = True
        dialog = LoginDialog(self._window, name, "The application was idle and locked itself: sign in again.")
        self.dialog = dialog
        accepted = dialog.exec() == QDialog.DialogCode.Accepted
        self.locked = False
        if accepted:
            self._timer.start()
        else:
            self._quit()


def ask_in_dialog(user: str) -> str:
    """auth's asker in the application: the password in a dialog over the active window."""
    text, given = QInputDialog.getText(QApplication.activeWindow(), "photopft: password",
                                       f"This needs the password of {user}:", QLineEdit.EchoMode.Password)
    if not given:
        raise AuthenticationError(f"no password given for {user}")
    return text
