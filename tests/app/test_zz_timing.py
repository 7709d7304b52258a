import time
import tests.app.test_gui as g
T0 = time.monotonic()
_orig = g._press
def _press(qtbot, wizard):
    print(f"\n[{time.monotonic()-T0:7.1f}] leaving {type(wizard.currentPage()).__name__}", flush=True)
    _orig(qtbot, wizard)
g._press = _press
def test_timed(qtbot, tmp_path):
    global T0
    T0 = time.monotonic()
    g.test_a_whole_patient_session(qtbot, tmp_path)
    print(f"\n[{time.monotonic()-T0:7.1f}] end", flush=True)
