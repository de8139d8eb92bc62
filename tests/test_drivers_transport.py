"""SerialTransport over the pyserial URLs the drivers accept: a pty path, spy://, socket://, loop://."""

from __future__ import annotations

import os
import socket
import threading

import numpy as np
import pytest

from northfinder.drivers.turntable import Turntable
from northfinder.errors import DeviceError
from northfinder.transport import SerialTransport


def test_raw_log_gets_exactly_the_bytes_read(tmp_path):
    raw = tmp_path / "sub" / "x.raw"
    with SerialTransport("loop://", device="imu", baudrate=921600, timeout_s=0.2, raw_log=raw) as t:
        t.write(b"\xfe\x81\xff\x55" + bytes(range(40)))
        got = t.read_available()
        got += t.read_available()
    assert got == b"\xfe\x81\xff\x55" + bytes(range(40))
    assert raw.read_bytes() == got  # written bytes are not in the raw log, read bytes are


def test_spy_url_taps_a_real_pty_and_stays_exclusive(pty_pair, tmp_path):
    master, path = pty_pair
    spy_file = tmp_path / "spy.txt"
    url = f"spy://{path}?file={spy_file}"

    def answer():
        line = b""
        while not line.endswith(b"\r\n"):
            line += os.read(master, 64)
        os.write(master, b"1TS000033\r\n")

    t = threading.Thread(target=answer)
    t.start()
    with Turntable(url, timeout_s=2) as stage:
        assert stage.status().state_name == "READY from MOVING"
        with pytest.raises(DeviceError, match="busy"):
            SerialTransport(path, device="turntable", baudrate=57600)
    t.join()
    tap = spy_file.read_text()
    assert "TX   0000  31 54 53 0D 0A" in tap and "RX" in tap  # the query out, the reply in


def test_socket_url_to_a_local_server():
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]

    def serve():
        conn, _ = server.accept()
        with conn:
            data = b""
            while not data.endswith(b"\r\n"):
                data += conn.recv(64)
            conn.sendall(b"1VE SMC_CC socket\r\n")

    t = threading.Thread(target=serve)
    t.start()
    try:
        with Turntable(f"socket://127.0.0.1:{port}", timeout_s=2) as stage:
            assert stage.version() == "SMC_CC socket"
    finally:
        t.join()
        server.close()


def test_socket_url_refused_is_one_clear_line():
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # nothing listens there now
    with pytest.raises(DeviceError) as exc:
        SerialTransport(f"socket://127.0.0.1:{port}", device="turntable", baudrate=57600)
    assert f"socket://127.0.0.1:{port}" in str(exc.value)


def test_empty_port_is_a_user_error():
    with pytest.raises(DeviceError, match="no port given"):
        SerialTransport("", device="imu", baudrate=921600)


def test_a_stream_over_socket_url_is_read_in_chunks_not_bytes(monkeypatch):
    """pyserial's socket:// says 1 byte waiting whatever is there: read_available takes all that is
    there in one call (the generic path read a KVH stream one byte per call), and the IMU driver
    decodes every frame sent through a local server."""
    from northfinder.codecs import kvh
    from northfinder.drivers.imu import Imu

    n = 3000
    data = kvh.encode_frames(np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, 0x77),
                             np.arange(n), np.full(n, 25))
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]
    calls = []
    read_available = SerialTransport.read_available

    def counted(self, *args, **kwargs):
        out = read_available(self, *args, **kwargs)
        calls.append(len(out))
        return out

    monkeypatch.setattr(SerialTransport, "read_available", counted)

    opened = threading.Event()

    def serve():
        conn, _ = server.accept()
        with conn:
            opened.wait(10.0)  # pyserial's socket:// drops what came before its open ended
            conn.sendall(data)
            conn.recv(1)  # until the client closes

    t = threading.Thread(target=serve)
    t.start()
    try:
        with Imu(f"socket://127.0.0.1:{port}", wait_for_data=False) as imu:
            opened.set()
            block = imu.read(n, timeout_s=10.0)
    finally:
        t.join()
        server.close()
    assert block.sample_index.tolist() == list(range(n))
    assert sum(calls) == len(data)
    assert sum(1 for c in calls if c) < 200  # 108 kB: chunks of kilobytes, not 108 000 reads


def test_read_pacer_pauses_only_while_the_stream_is_slow():
    """ReadPacer: no pause until a window has passed; then a pause after each small read while the
    last window's rate was under the threshold, none after a read that found bytes waiting (the
    reader is behind), none once the rate is at or above it (a fast stream, where the latency
    counts). A fake clock: the decision is on bytes per window, not on this host's speed."""
    from northfinder.transport import ReadPacer

    now, slept = [0.0], []
    pacer = ReadPacer(1000.0, pause_s=0.01, window_s=0.25, clock=lambda: now[0], sleep=slept.append)
    pacer.after_read(10)
    assert slept == [] and not pacer.slow  # no window measured yet
    now[0] = 0.3
    pacer.after_read(10)  # 20 B in 0.3 s: slow
    assert pacer.slow and slept == [0.01]
    pacer.after_read(10)
    assert slept == [0.01, 0.01]
    pacer.after_read(4095)  # bytes were waiting: behind, however slow the last window was
    assert slept == [0.01, 0.01]
    pacer.after_read(20)  # two pauses' worth at 1 kB/s (the default small_bytes): behind too
    assert pacer.small_bytes == 20 and slept == [0.01, 0.01]
    now[0] = 0.6
    pacer.after_read(10_000)  # 14,105 B in 0.3 s: fast, no pause
    assert not pacer.slow and slept == [0.01, 0.01]
    pacer.after_read(10)
    assert slept == [0.01, 0.01]
