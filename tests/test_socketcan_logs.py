"""Replay decides by content: the node's frames are taken by COB-ID, whatever a log's direction flag.

tests/data/can-logs/ holds one fixed stream of the node's frames (tools/record_can_logs.py) as the
driver logged it in the User-Mode Linux guest three ways: sent by another process on a vcan and read
with socketcan (python-can logs those `Tx`: the kernel flags them as sent from this host), through
firmware_sim's emulated adapter with the kernel's slcan driver (`slcand` → socketcan, `Rx`), and
through the same adapter with python-can's own slcan (`Rx`). All three must replay identically.
"""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest
from helpers import load_tool

from northfinder.codecs.canopen import (
    CanCodec,
    MappedObject,
    PdoLayout,
    TpdoLayout,
    decode_accel_frames,
    default_layout,
    node_frames,
)
from northfinder.drivers.accelerometer import decode_can_log

LOGS = Path(__file__).parent / "data" / "can-logs"
TRANSPORTS = ("vcan", "kernel-slcan", "python-slcan")


@pytest.fixture(scope="module")
def expected():
    """The recorder's own stream, decoded straight from its frames."""
    record = load_tool("record_can_logs")
    frames = [(can_id, data, 0.0, False, False) for can_id, data in record.node_frames()]
    return decode_accel_frames(frames)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_a_log_replays_to_the_stream_that_was_sent(transport, expected):
    block, stats = decode_can_log(LOGS / f"{transport}.asc")
    want_block, want_stats = expected
    assert len(block) == 40 and block.lost_samples == 1 and stats.lost_samples == 1
    assert np.array_equal(block.counter, want_block.counter)
    assert np.array_equal(block.accel_g, want_block.accel_g)  # bit for bit
    assert np.array_equal(block.temperature_c, want_block.temperature_c)
    assert np.array_equal(block.status, want_block.status)
    assert (stats.pairs, stats.heartbeats, stats.emcy) == (want_stats.pairs, want_stats.heartbeats, 1)


def test_the_vcan_log_marks_the_nodes_frames_sent_yet_replays_like_the_slcan_ones():
    """The defect of issue 21: python-can's socketcan logs a frame another process on this host sent
    as Tx; a replay that kept only received frames had no samples at all (accel_g NaN)."""
    directions = {t: {m.is_rx for m in can.LogReader(str(LOGS / f"{t}.asc"))} for t in TRANSPORTS}
    assert directions == {"vcan": {False}, "kernel-slcan": {True}, "python-slcan": {True}}
    blocks = [decode_can_log(LOGS / f"{t}.asc")[0] for t in TRANSPORTS]
    for other in blocks[1:]:
        assert np.array_equal(other.counter, blocks[0].counter)
        assert np.array_equal(other.accel_g, blocks[0].accel_g)


def test_node_frames_takes_the_mapping_cob_ids_heartbeat_and_emcy_only():
    codec = CanCodec(0x10)
    remapped = PdoLayout((
        TpdoLayout(1, 0x1A5, (MappedObject(0x2000, 1, 32, True, "Acceleration x", "x", 1e-6, "ug"),
                              MappedObject(0x2000, 2, 32, True, "Acceleration y", "y", 1e-6, "ug"))),
        TpdoLayout(2, 0x2A5, (MappedObject(0x2000, 3, 32, True, "Acceleration z", "z", 1e-6, "ug"),
                              MappedObject(0x2002, 0, 8, False, "Sample counter", "counter", 1.0, ""))),
    ))
    frames = [(0x000, b"\x01\x10", 0.0, False, False),  # NMT from the host
              (0x610, b"\x40\x00\x10\x00\x00\x00\x00\x00", 0.0, False, False),  # SDO request
              (0x590, bytes(8), 0.0, False, False),  # SDO response
              (0x190, bytes(8), 0.0, False, False),  # the default TPDO1 COB-ID, not this mapping's
              (0x1A5, bytes(8), 0.0, False, False),
              (0x2A5, bytes(5), 0.0, False, False),
              (0x2A5, bytes(5), 0.0, False, True),  # a remote request on the COB-ID: not data
              (0x1A5, bytes(8), 0.0, True, False),  # an extended ID that happens to match
              (0x710, b"\x05", 0.0, False, False),
              (0x090, bytes(8), 0.0, False, False),
              (0x711, b"\x05", 0.0, False, False)]  # another node's heartbeat
    assert [f[0] for f in node_frames(frames, 0x10, remapped)] == [0x1A5, 0x2A5, 0x710, 0x090]
    assert [f[0] for f in node_frames(frames, 0x10, remapped.to_dict())] == [0x1A5, 0x2A5, 0x710, 0x090]
    assert [f[0] for f in node_frames(frames, 0x10)] == [0x190, 0x710, 0x090]
    assert default_layout(codec.node_id).tpdos[0].cob_id == 0x190
