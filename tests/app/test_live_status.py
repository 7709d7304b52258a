"""The live view's camera line: red means a fault. The simulated rig's renderer skipping frames it
cannot make in time is not one; a real camera losing over 1 % of its frames of the last 10 s is,
and an old loss no longer is."""

from __future__ import annotations

from app.gui.live_view import LostFrames, camera_status


def test_a_simulated_renderer_skipping_frames_is_not_a_fault():
    text, warn = camera_status(35.0, 20, 350, 400, 4135, simulated=True)
    assert not warn and "rendered" in text and "not a fault" in text
    assert "fewer maps than the rig makes" in text  # said plainly: the blows are read from fewer maps
    text, _ = camera_status(108.0, 20, 1080, 20, 20, simulated=True)
    assert "fewer maps" not in text


def test_a_real_camera_is_red_only_while_it_loses_frames():
    lost = LostFrames()
    for second in range(0, 31):
        frames = 110 * second
        dropped = 50 if second >= 5 else 0  # 50 frames lost around 5 s, none after
        recent = lost.recent(float(second), frames, dropped)
        text, warn = camera_status(110.0, second, *recent, dropped, simulated=False)
        if 5 <= second <= 14:
            assert warn and "50 lost in the last 10 s" in text
        if second >= 16:
            assert not warn and "0 lost in the last 10 s (50 in all)" in text
