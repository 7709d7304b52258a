"""Signing in to the application and its idle lock (issue 76): a wrong password stays out and is
audited, the right one proves the user, and an idle window forgets them and asks again."""

from __future__ import annotations

from PySide6.QtCore import QTimer
from PySide6.QtWidgets import QApplication, QWidget

from app import auth
from app.gui.login import IdleLock, LoginDialog, login_needed
from app.records import Records, default_path


def _users(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))  # these users stay out of other tests' records
    with Records(default_path(), user="ed") as r:
        r.add_user("ed", "engineer", "ed-secret")
        r.authenticate("ed-secret")
        r.add_user("anna", "clinician", "anna-secret")
    auth.forget()


def test_nobody_signs_in_where_no_user_has_a_password(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert not login_needed()
    _users(monkeypatch, tmp_path)
    assert login_needed()


def test_the_login_dialog_refuses_a_wrong_password_and_proves_the_right_one(qtbot, monkeypatch, tmp_path):
    _users(monkeypatch, tmp_path)
    dialog = LoginDialog(None, "anna")
    qtbot.addWidget(dialog)
    dialog.password.setText("guess-one")
    dialog.try_sign_in()
    assert "anna: wrong password" in dialog.message.text() and dialog.result() == 0
    assert auth.proven_user() is None and dialog.password.text() == ""
    dialog.name.setText("mallory")
    dialog.password.setText("anything")
    dialog.try_sign_in()
    assert "mallory: not a registered user" in dialog.message.text()
    dialog.name.setText("anna")
    dialog.password.setText("anna-secret")
    dialog.try_sign_in()
    assert dialog.result() == LoginDialog.DialogCode.Accepted and auth.proven_user() == "anna"
    with Records(read_only=True) as r:
        assert r.actor.name == "anna" and r.actor.role == "clinician"
        failed = [(e.user, e.details["reason"]) for e in r.audit_trail() if e.action == "authentication failed"]
    assert failed == [("anna", "wrong password"), ("mallory", "not a registered user")]


def test_an_idle_window_forgets_who_signed_in_and_asks_again(qtbot, monkeypatch, tmp_path):
    _users(monkeypatch, tmp_path)
    auth.prove("anna", 0.0)
    window = QWidget()
    qtbot.addWidget(window)
    closed: list[bool] = []
    seen: dict = {}

    def answer() -> None:
        dialog = QApplication.activeModalWidget()
        if not isinstance(dialog, LoginDialog):
            QTimer.singleShot(10, answer)
            return
        seen["proven while asked"] = auth.proven_user()
        seen["name"] = dialog.name.text()
        dialog.reject()

    lock = IdleLock(window, 0.001, lambda: closed.append(True))  # 60 ms
    QTimer.singleShot(200, answer)
    qtbot.waitUntil(lambda: bool(closed), timeout=5000)
    assert seen == {"proven while asked": None, "name": "anna"} and not lock.locked
