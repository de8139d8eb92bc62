"""Imu driver: real ptys carrying golden / perturbed KVH frames, the config dance pinned write by
write, and the replay path giving bit-identical arrays."""

from __future__ import annotations

import os
import threading
import time
import tty

import numpy as np
import pytest
from helpers import ExpectedProtocol, write_all

from northfinder.codecs import kvh
from northfinder.drivers.imu import Imu, decode_imu_stream
from northfinder.errors import ConfigError, DeviceError

F = kvh.FRAME_SIZE


def _wait_bytes(imu: Imu, n_bytes: int, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while imu.stats.bytes < n_bytes and time.monotonic() < deadline:
        time.sleep(0.01)
    assert imu.stats.bytes == n_bytes


def _frames(n: int, start_seq: int = 0, seed: int = 3):
    gyro = np.random.default_rng(seed).normal(scale=1e-5, size=(n, 3))
    accel = np.tile([0.01, -0.02, 1.0], (n, 1))
    seq = np.arange(start_seq, start_seq + n)
    data = kvh.encode_frames(gyro, accel, np.full(n, 0x77), seq, np.full(n, 25))
    return [data[i * F:(i + 1) * F] for i in range(n)], gyro.astype(np.float32).astype(np.float64)


def test_golden_frames_over_a_real_pty(pty_pair, golden):
    master, path = pty_pair
    msgs = [bytes.fromhex(v["hex"]) for v in golden["kvh_format_a"]]
    with Imu(path, wait_for_data=False, rot_format="RATE", rot_units="DEG") as imu:
        write_all(master, b"".join(msgs))
        block = imu.read(3, timeout_s=5)
    for k, v in enumerate(golden["kvh_format_a"]):
        # a field whose status bit is cleared (PROTOCOLS.md §2) is NaN: left out, never averaged
        bits = [(v["status"] >> b) & 1 for b in (0, 1, 2, 4, 5, 6)]
        gyro = [g * (np.pi / 180) if ok else None for g, ok in zip(v["gyro_f32"], bits[:3], strict=True)]
        accel = [a if ok else None for a, ok in zip(v["accel_f32"], bits[3:], strict=True)]
        assert [None if np.isnan(x) else x for x in block.gyro_rad_s[k].tolist()] == gyro
        assert [None if np.isnan(x) else x for x in block.accel_g[k].tolist()] == accel
        assert block.status[k] == v["status"] and block.temperature_c[k] == v["temperature_c"]
    # sequence 42 → 127 → 0: steps of 85 and 1 → indices 0, 85, 86 with 84 lost inside the block
    assert block.sample_index.tolist() == [0, 85, 86]
    assert block.lost_samples == 84
    assert np.allclose(block.time_s, np.array([0, 85, 86]) / 1000.0)


def test_perturbed_stream_counts_and_resync_are_exact(pty_pair, tmp_path):
    master, path = pty_pair
    n = 300  # the 7-bit sequence wraps twice
    frames, gyro = _frames(n)
    bad = bytearray(frames[50])
    bad[33] ^= 0x40
    frames[50] = bytes(bad)  # CRC corrupted
    frames[100] = frames[100][:20] + frames[100][25:]  # 5 bytes dropped
    for k in (200, 201, 202):
        frames[k] = b""  # three whole frames lost
    frames[10] += b"\x00\x13garbage\r\n"  # garbage between frames
    frames[250] += kvh.HEADER + bytes(40)  # a header-like pattern in garbage
    stream = b"".join(frames)
    raw_log = tmp_path / "imu.raw"
    with Imu(path, wait_for_data=False, raw_log=raw_log) as imu:
        write_all(master, stream)
        _wait_bytes(imu, len(stream))
        block = imu.read(n - 5, timeout_s=2)
        stats = imu.stats
        with pytest.raises(DeviceError, match=f"only 0 of 1 samples arrived .* on {path}"):
            imu.read(1, timeout_s=0.1)
    kept = [k for k in range(n) if k not in (50, 100, 200, 201, 202)]
    assert block.sample_index.tolist() == kept
    assert np.array_equal(block.gyro_rad_s, gyro[kept] * 1000.0)  # DELTA/RAD at 1000 Hz → rad/s
    assert (stats.frames, stats.bad_crc, stats.resyncs) == (n - 5, 3, 4)
    assert (stats.sequence_gaps, stats.lost_samples) == (3, 5)
    assert block.lost_samples == 5
    # replay of the raw log: the very bytes, the same arrays and counters
    assert raw_log.read_bytes() == stream
    replayed, rstats = decode_imu_stream(raw_log.read_bytes())
    for field in ("sample_index", "gyro_rad_s", "accel_g", "status", "temperature_c"):
        assert np.array_equal(getattr(replayed, field), getattr(block, field))
    assert rstats == stats


def test_joining_mid_frame_is_one_resync(pty_pair):
    master, path = pty_pair
    frames, _ = _frames(20)
    stream = b"".join(frames)[17:]
    with Imu(path, wait_for_data=False) as imu:
        write_all(master, stream)
        block = imu.read(19, timeout_s=5)
        st = imu.stats
    assert block.sample_index.tolist() == list(range(19))
    assert (st.resyncs, st.bad_crc, st.frames, st.skipped_bytes) == (1, 0, 19, 19)


class _Repeater:
    """Writes `data` to the pty master every 20 ms until stopped: whenever the driver opens the
    slave (pyserial flushes input on open), data keeps coming."""

    def __init__(self, fd: int, data: bytes):
        self._fd, self._data, self._stop = fd, data, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            write_all(self._fd, self._data)

    def __enter__(self) -> _Repeater:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def test_open_waits_for_data_and_names_the_port(pty_pair):
    master, path = pty_pair
    with pytest.raises(DeviceError, match=f"no KVH format-A data on {path} .* is it the IMU's port"):
        Imu(path, timeout_s=0.2)
    frames, _ = _frames(5)
    with _Repeater(master, b"".join(frames)), Imu(path, timeout_s=3) as imu:
        assert imu.stats.frames >= 1


def test_turntable_port_given_as_the_imu(pty_pair):
    master, path = pty_pair
    with _Repeater(master, b"1TS000033\r\n"), pytest.raises(DeviceError) as exc:
        Imu(path, timeout_s=0.5)
    assert f"no KVH format-A data on {path}" in str(exc.value) and "is it the IMU's port" in str(exc.value)
    n_bytes = int(str(exc.value).split("(")[1].split(" bytes")[0])
    assert n_bytes > 0  # SMC100 replies arrived, and none of them is a frame


def test_port_opened_twice_fails_naming_it(pty_pair):
    _, path = pty_pair
    with Imu(path, wait_for_data=False):
        with pytest.raises(DeviceError, match=f"port {path} is busy"):
            Imu(path, wait_for_data=False)


def test_missing_port(tmp_path):
    with pytest.raises(DeviceError, match="no such port .*ttyKVH"):
        Imu(str(tmp_path / "ttyKVH"))


# ---------------------------------------------------------------- configuration, pinned


def test_configure_dance_discards_the_two_invalid_messages():
    before, _ = _frames(5, start_seq=0)
    after, gyro = _frames(7, start_seq=5, seed=4)
    proto = ExpectedProtocol(
        [
            (b"=CONFIG,1\n", b"CONFIG,1\r\n"),
            (b"=DR,100\n", b"DR,100\r\n"),
            (b"=ROTFMT,RATE\n", b"ROTFMT,RATE\r\n"),
            (b"=ROTUNITS,DEG\n", b"ROTUNITS,DEG\r\n"),
            (b"?DR\n", b"DR,100\r\n"),
            (b"?ROTFMT\n", b"ROTFMT,RATE\r\n"),
            (b"?ROTUNITS\n", b"ROTUNITS,DEG\r\n"),
            (b"=CONFIG,0\n", b"CONFIG,0\r\n" + b"".join(after)),
        ],
        initial=b"".join(before),
    )
    with Imu("expected://kvh", transport=proto, timeout_s=2) as imu:
        values = imu.configure(rate_hz=100, rot_format="RATE", rot_units="DEG")
        assert values == {"DR": "100", "ROTFMT": "RATE", "ROTUNITS": "DEG"}
        assert (imu.rate_hz, imu.rot_format, imu.rot_units) == (100.0, "RATE", "DEG")
        block = imu.read(5, timeout_s=2)
        stats = imu.stats
    proto.assert_done()
    assert block.sample_index.tolist() == [7, 8, 9, 10, 11]  # after 0..4 and the 2 invalid (5, 6)
    assert np.array_equal(block.gyro_rad_s, gyro[2:] * (np.pi / 180))
    assert stats.discarded_frames == 2 and stats.frames == 12


def test_query_outside_config_mode_enters_and_leaves():
    proto = ExpectedProtocol([(b"=CONFIG,1\n", b"CONFIG,1\r\n"), (b"?DR\n", b"DR,1000\n"),
                              (b"=CONFIG,0\n", b"CONFIG,0\r\n")])
    with Imu("expected://kvh", transport=proto, wait_for_data=False) as imu:
        assert imu.query("dr") == "1000"
    proto.assert_done()


def test_configure_rejects_bad_values_and_silence():
    with pytest.raises(ConfigError, match="rot_format"):
        Imu("expected://kvh", transport=ExpectedProtocol([]), rot_format="ANGLE")
    with Imu("expected://kvh", transport=ExpectedProtocol([]), wait_for_data=False) as imu:
        with pytest.raises(ConfigError, match="rate_hz 333"):
            imu.configure(rate_hz=333)
        with pytest.raises(ConfigError, match="rot_units"):
            imu.configure(rot_units="GRAD")
    proto = ExpectedProtocol([(b"=CONFIG,1\n", b"CONFIG,1\r\n"), (b"?DR\n", None),
                              (b"=CONFIG,0\n", b"CONFIG,0\r\n")])
    with Imu("expected://kvh", transport=proto, wait_for_data=False, timeout_s=0.2) as imu:
        with pytest.raises(DeviceError, match="no answer to \\?DR"):
            imu.query("DR")


def test_unplugged_device_is_one_clear_error():
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    path = os.ttyname(slave)
    try:
        frames, _ = _frames(10)
        with Imu(path, wait_for_data=False) as imu:
            write_all(master, b"".join(frames))
            assert len(imu.read(10, timeout_s=5)) == 10
            os.close(master)  # the far end goes away: reads on the slave fail
            master = None
            with pytest.raises(DeviceError, match=f"I/O error on {path}.*unplugged"):
                imu.read(1, timeout_s=5)
    finally:
        if master is not None:
            os.close(master)
        os.close(slave)


def test_caught_up_index_is_the_newest_index_when_the_reader_had_read_all_the_unit_sent(pty_pair):
    """caught_up_index: the newest sample index decoded at the reader's next moment with nothing
    waiting — a lower bound of the unit's clock taken after the call (never an older one), behind
    what came after it; with no such moment within its time-out, the newest index."""
    master, path = pty_pair
    frames, _ = _frames(400)
    with Imu(path, wait_for_data=False) as imu:
        write_all(master, b"".join(frames[:100]))
        _wait_bytes(imu, 100 * F)
        assert imu.newest_index() == 99
        assert imu.caught_up_index(0.1) == 99  # nothing more comes: the newest
        got: list[int | None] = []
        waiting = threading.Thread(target=lambda: got.append(imu.caught_up_index(5.0)))
        waiting.start()
        sent = 100
        while waiting.is_alive() and sent < 400:
            write_all(master, b"".join(frames[sent:sent + 10]))
            sent += 10
            _wait_bytes(imu, sent * F)
        waiting.join(5.0)
        assert got and got[0] is not None
        assert 99 <= got[0] < imu.newest_index() == sent - 1


def test_next_index_is_the_index_the_next_read_returns_and_reads_nothing(pty_pair):
    """next_index: the device index of the first sample not yet read — the sequencer lines a dwell up
    on its grid with it without dropping a sample when the stream is on the grid already; a lost
    sample moves it on; a silent unit is a DeviceError naming the port."""
    master, path = pty_pair
    frames, _ = _frames(20)
    with Imu(path, wait_for_data=False) as imu:
        with pytest.raises(DeviceError, match=path):
            imu.next_index(0.2)
        write_all(master, b"".join(frames[:5]))
        assert imu.next_index(5.0) == 0
        assert imu.next_index(5.0) == 0  # reads nothing
        assert imu.read(3, timeout_s=5).sample_index.tolist() == [0, 1, 2]
        assert imu.next_index(5.0) == 3
        assert imu.read(2, timeout_s=5).sample_index.tolist() == [3, 4]
        write_all(master, b"".join(frames[6:8]))  # frame 5 lost on the line
        assert imu.next_index(5.0) == 6
        assert imu.read(2, timeout_s=5).sample_index.tolist() == [6, 7]
