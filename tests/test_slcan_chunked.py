"""ChunkedSlcanBus (northfinder.transport): the same frames as python-can's stock slcan client on
the same bytes from a real pty, and the test that says when python-can's release makes it moot.

The stream is recorded once (fixed seed): the golden slcan lines, TPDO lines as firmware_sim sends
them, remote frames, extended ids, and the adapter's OK (``\\r``) and error (``\\a``) replies between
frames. It is written into the pty in uneven pieces (a line cut anywhere, several lines at once)
so the chunked reader meets every kind of partial line.
"""

from __future__ import annotations

import os
import threading
import time

import can
import numpy as np
import pytest
from can.interfaces.slcan import slcanBus
from helpers import load_tool

from northfinder.transport import (
    SLCAN_STOCK_READS_BYTEWISE,
    ChunkedSlcanBus,
    _release,
    open_can_bus,
)

SLCAN_SPEED = load_tool("slcan_speed")  # the pty + client + read counter the speed tool measures with


def _recorded_stream(golden: dict, n_random: int = 600, seed: int = 7) -> tuple[bytes, int]:
    """slcan bytes as an adapter sends them, and how many of its lines are frames."""
    rng = np.random.default_rng(seed)
    lines = [v["line"].encode() for v in golden["slcan"]["frames"]]
    lines += [b"r1232\r", b"R1ABCDEF04\r", b"t7FF0\r"]
    for k in range(n_random):
        kind = k % 4
        dlc = int(rng.integers(0, 9))
        data = rng.integers(0, 256, dlc).astype(np.uint8).tobytes().hex().upper().encode()
        if kind == 0:
            lines.append(b"t190" + str(dlc).encode() + data + b"\r")
        elif kind == 1:
            lines.append(b"T%08X" % int(rng.integers(0, 1 << 29)) + str(dlc).encode() + data + b"\r")
        elif kind == 2:
            lines.append(b"t%03X" % int(rng.integers(0, 1 << 11)) + str(dlc).encode() + data + b"\r")
        else:
            lines.append(b"t2908" + b"%016X" % int(rng.integers(0, 1 << 62)) + b"\r")
    frames = len(lines)
    # adapter replies between frames: OK and error, which are not frames
    order = rng.permutation(frames + 40)
    replies = [b"\r"] * 20 + [b"\a"] * 20
    stream = b"".join((lines + replies)[i] for i in order)
    return stream, frames


def _pieces(stream: bytes, seed: int = 3) -> list[bytes]:
    """The stream cut at random places: 1 to 200 bytes a piece."""
    rng = np.random.default_rng(seed)
    out, i = [], 0
    while i < len(stream):
        n = int(rng.integers(1, 200))
        out.append(stream[i:i + n])
        i += n
    return out


def _receive(bus_class: type[slcanBus], pieces: list[bytes], n_frames: int) -> tuple[list[tuple], int]:
    """The frames `bus_class` receives from a pty fed `pieces`, and its pyserial read calls."""
    with SLCAN_SPEED.slcan_client_on_pty(bus_class) as (master, bus, reads):

        def write() -> None:
            for k, piece in enumerate(pieces):
                os.write(master, piece)
                if k % 50 == 0:
                    time.sleep(0.002)  # let the reader catch up: it sees partial lines

        writer = threading.Thread(target=write, daemon=True)
        writer.start()
        frames = []
        while len(frames) < n_frames:
            msg = bus.recv(timeout=10.0)  # host-time bound only; the test decides on the frames
            if msg is None:
                break
            frames.append((msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.dlc,
                           bytes(msg.data), msg.is_error_frame))
        writer.join(10)
    return frames, reads[0]


def test_same_frames_as_the_stock_client_on_the_same_stream(golden):
    stream, n_frames = _recorded_stream(golden)
    pieces = _pieces(stream)
    stock, stock_reads = _receive(slcanBus, pieces, n_frames)
    ours, our_reads = _receive(ChunkedSlcanBus, pieces, n_frames)
    assert len(stock) == n_frames
    assert ours == stock
    # the golden lines come first in the recording's frame list: spot-check them by value
    golden_ids = {(v["id"], bytes.fromhex(v["data"])) for v in golden["slcan"]["frames"]}
    assert golden_ids <= {(f[0], f[4]) for f in ours}
    assert our_reads < stock_reads / 4, (our_reads, stock_reads)


def test_a_line_split_across_reads_and_many_lines_in_one_read(golden):
    stream, n_frames = _recorded_stream(golden, n_random=40)
    one_byte = [stream[i:i + 1] for i in range(len(stream))]
    whole = [stream]
    expected, _ = _receive(slcanBus, whole, n_frames)
    assert _receive(ChunkedSlcanBus, one_byte, n_frames)[0] == expected
    assert _receive(ChunkedSlcanBus, whole, n_frames)[0] == expected


def test_open_can_bus_gives_the_chunked_client_for_slcan_only():
    master, slave = os.openpty()
    try:
        bus = open_can_bus("slcan", os.ttyname(slave), bitrate=500000, sleep_after_open=0)
        try:
            assert isinstance(bus, ChunkedSlcanBus) == SLCAN_STOCK_READS_BYTEWISE
        finally:
            bus.shutdown()
    finally:
        os.close(master)
        os.close(slave)
    bus = open_can_bus("virtual", "nf-chunked-slcan-test", bitrate=500000)
    try:
        assert not isinstance(bus, slcanBus)
    finally:
        bus.shutdown()


def test_release_parser():
    assert _release("4.6.1") == (4, 6, 1)
    assert _release("4.7.0rc1") == (4, 7, 0)
    assert _release("4.6.2.dev3+gabc") == (4, 6, 2)
    assert _release("4.6.1") <= (4, 6, 1) < _release("4.6.2")


def test_says_when_to_drop_the_chunked_client(golden):
    """Fails once the installed python-can reads slcan in chunks itself (python-can pull request
    #2028 released): then delete ChunkedSlcanBus and open_can_bus's slcan branch. Also fails if the
    version bound disagrees with what the stock client does."""
    stream, n_frames = _recorded_stream(golden, n_random=200)
    frames, reads = _receive(slcanBus, [stream], n_frames)
    assert len(frames) == n_frames
    reads_per_frame = reads / n_frames
    assert reads_per_frame > 5, (
        f"python-can {can.__version__}'s slcan client made {reads_per_frame:.1f} reads a frame: it reads "
        "in chunks now — drop northfinder.transport.ChunkedSlcanBus and open_can_bus's slcan branch")
    assert SLCAN_STOCK_READS_BYTEWISE, (
        f"python-can {can.__version__} still reads slcan a byte at a time: raise LAST_BYTEWISE_PYTHON_CAN")


if __name__ == "__main__":  # pragma: no cover
    pytest.main([__file__, "-q", "-n", "0"])
