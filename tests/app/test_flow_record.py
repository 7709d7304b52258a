"""The live engine's store of the recording's flow samples (app.engine.FlowRecord)."""

import numpy as np

from app.engine.flow_record import FlowRecord
from drivers.flowsensor import FlowBlock


def _block(start: int, n: int) -> FlowBlock:
    counter = np.arange(start, start + n, dtype=np.int64)
    return FlowBlock(adc=(counter % 4096).astype(np.int32), counter=counter,
                     timestamp_ns=1_000_000 * counter, lost=0)


def test_samples_are_every_block_in_order_however_joined():
    record = FlowRecord()
    assert record.last_ns == 0
    adc, stamps = record.samples()
    assert len(adc) == len(stamps) == 0
    start = 0
    for k in range(2 * FlowRecord.JOIN_BLOCKS + 37):
        n = 7 + k % 5
        record.append(_block(start, n))
        start += n
    adc, stamps = record.samples()
    np.testing.assert_array_equal(stamps, 1_000_000 * np.arange(start))
    np.testing.assert_array_equal(adc, np.arange(start) % 4096)
    assert adc.dtype == np.int32 and stamps.dtype == np.int64
    assert record.last_ns == 1_000_000 * (start - 1)
    assert len(record._adc) == 2 + 37  # two joined parts and the blocks since, not every block
