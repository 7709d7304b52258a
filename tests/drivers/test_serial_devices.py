"""The sequencer and flow sensor drivers against their emulators, over real pseudo-terminals."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.flowsensor import FlowSensor, FlowSensorEmulator, FlowSensorError
from drivers.framing import FrameReader, crc16_ccitt, encode
from drivers.sequencer import Sequencer, SequencerEmulator, SequencerError
from tests.waiting import wait_until


def test_crc_and_framing_resynchronise():
    assert crc16_ccitt(b"123456789") == 0x29B1  # the standard check value of CRC-16/CCITT-FALSE
    frames = [encode(bytes([k]) * (k + 1)) for k in range(5)]
    stream = b"\x00\xa5junk" + frames[0] + frames[1][:-1] + b"\x13" + frames[2] + b"\xa5" + frames[3] + frames[4]
    reader = FrameReader()
    got = []
    for k in range(0, len(stream), 3):  # arriving in pieces
        got += reader.feed(stream[k:k + 3])
    assert got == [bytes([0]), bytes([2]) * 3, bytes([3]) * 4, bytes([4]) * 5]
    assert reader.bad_frames >= 1 and reader.skipped_bytes > 0


def test_sequencer_session_over_a_serial_line():
    with SequencerEmulator("SN-42") as emulator:
        seq = Sequencer(emulator.port)
        try:
            assert seq.identify() == "photopft-sequencer,1.0,SN-42"
            with pytest.raises(SequencerError, match="arm before starting"):
                seq.start()
            with pytest.raises(SequencerError, match="once each"):
                seq.configure((0, 1, 2, 2, -1), 1000, 110.0)
            seq.configure((0, 1, 2, 3, -1), 1000, 110.0)
            seq.arm()
            before = time.monotonic()
            seq.start()
            wait_until(lambda: seq.status().trigger_count >= 33, 5, "33 triggers (0.3 s at 110 Hz)")
            status = seq.status()
            elapsed = time.monotonic() - before
            assert status.state == "running" and 33 <= status.trigger_count <= elapsed * 110 + 1
            seq.stop()
            assert seq.status().state == "configured"
        finally:
            seq.close()


def test_sequencer_that_stops_answering_gives_a_clear_error():
    with SequencerEmulator() as emulator:
        seq = Sequencer(emulator.port, timeout_s=0.2)
        try:
            emulator.silent = True
            with pytest.raises(SequencerError, match="did not answer I within 0.2 s"):
                seq.identify()
        finally:
            seq.close()


def _collect(sensor: FlowSensor, samples: int):
    """The sensor's blocks until they hold `samples` samples."""
    blocks = []

    def enough() -> bool:
        blocks.append(sensor.read())
        return sum(len(b.counter) for b in blocks) >= samples

    wait_until(enough, 30, f"{samples} flow samples")
    return blocks


def test_flow_sensor_stream_is_complete_and_on_the_session_clock():
    with FlowSensorEmulator() as emulator:
        sensor = FlowSensor(emulator.port)
        try:
            assert "photopft-flowsensor" in sensor.identify()
            sensor.start()
            blocks = _collect(sensor, 500)
            sensor.stop()
        finally:
            sensor.close()
    counter = np.concatenate([b.counter for b in blocks])
    stamps = np.concatenate([b.timestamp_ns for b in blocks])
    adc = np.concatenate([b.adc for b in blocks])
    assert len(counter) > 400 and np.all(np.diff(counter) == 1) and sensor.lost_samples == 0
    np.testing.assert_array_equal(np.diff(stamps), 1_000_000)
    expected = [emulator.adc_for(0.5 * np.sin(2 * np.pi * c / 1000.0 / 4.0)) for c in counter[:50]]
    np.testing.assert_array_equal(adc[:50], expected)


def test_flow_sensor_resyncs_after_corruption_and_counts_losses():
    with FlowSensorEmulator(corrupt_rate=0.03, drop_rate=0.02, seed=3) as emulator:
        sensor = FlowSensor(emulator.port)
        try:
            sensor.start()
            blocks = _collect(sensor, 600)
            sensor.stop()
        finally:
            sensor.close()
    counter = np.concatenate([b.counter for b in blocks])
    adc = np.concatenate([b.adc for b in blocks])
    assert sensor.corrupted_frames > 0 and sensor.lost_samples > 0
    assert np.all(np.diff(counter) >= 1)
    assert sensor.lost_samples == int(counter[-1] - counter[0] + 1 - len(counter))
    expected = np.array([emulator.adc_for(0.5 * np.sin(2 * np.pi * c / 1000.0 / 4.0)) for c in counter])
    np.testing.assert_array_equal(adc, expected)  # no corrupted value passed on


def test_silent_flow_sensor_and_missing_port():
    with FlowSensorEmulator() as emulator:
        sensor = FlowSensor(emulator.port, timeout_s=0.2)
        try:
            with pytest.raises(FlowSensorError, match="sent nothing"):
                wait_until(lambda: sensor.read() is None, 5, "the sensor's silence to be said")
        finally:
            sensor.close()
    with pytest.raises(FlowSensorError, match="cannot open"):
        FlowSensor("/dev/does-not-exist")
