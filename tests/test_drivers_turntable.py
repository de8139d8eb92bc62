"""Turntable driver pinned to SMC100 write/reply pairs (pymeasure expected_protocol style), plus
real-pty tests for the transport's user-facing errors."""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from helpers import ExpectedProtocol

from northfinder.codecs import kvh
from northfinder.drivers.turntable import StageError, Turntable
from northfinder.errors import DeviceError
from northfinder.transport import SerialTransport


def _stage(pairs):
    proto = ExpectedProtocol(pairs, terminator=b"\r\n", url="expected://smc100")
    return Turntable("expected://smc100", transport=proto), proto


def test_golden_exchange_on_a_freshly_reset_stage(golden):
    # The golden exchange, as this driver performs it: after an error letter it also reads TS to
    # name the state, and waiting for READY polls TS.
    g = {(s["send"], s.get("reply")) for s in golden["smc100"]["exchange"] if "send" in s}
    pairs = [
        ("1TS", "1TS00000A"),
        ("1PA90", None), ("1TE", "1TEH"), ("1TS", "1TS00000A"),
        ("1TE", "1TE@"),
        ("1OR", None), ("1TE", "1TE@"), ("1TS", "1TS00001E"), ("1TS", "1TS000032"),
        ("1PA90", None), ("1TE", "1TE@"), ("1TS", "1TS000028"), ("1TS", "1TS000033"),
        ("1TP", "1TP90.00010"),
        ("1PA400", None), ("1TE", "1TEG"), ("1TS", "1TS000033"),
    ]
    assert {p for p in pairs if p[0] != "1TS" and p[0] != "1TP"} <= g | {("1TE", "1TE@")}
    stage, proto = _stage(pairs)
    with stage:
        st = stage.status()
        assert (st.state, st.is_referenced, st.is_ready) == (0x0A, False, False)
        assert st.state_name == "NOT REFERENCED after reset"
        with pytest.raises(StageError) as exc:
            stage.move_absolute_deg(90)
        assert (exc.value.letter, exc.value.state) == ("H", 0x0A)
        assert "NOT REFERENCED" in str(exc.value) and "'H'" in str(exc.value)
        assert stage.last_error() == "@"
        assert stage.home(timeout_s=5).state == 0x32
        assert stage.move_absolute_deg(90.0, timeout_s=5).state_name == "READY from MOVING"
        assert stage.position_deg() == 90.0001
        with pytest.raises(StageError) as exc:
            stage.move_absolute_deg(400)
        assert exc.value.letter == "G" and "out of limits" in str(exc.value)
        assert "READY from MOVING" in str(exc.value)
    proto.assert_done()
    assert proto.closed


def test_ensure_referenced_homes_only_when_needed():
    stage, proto = _stage([("1TS", "1TS000033")])
    assert stage.ensure_referenced().is_ready
    proto.assert_done()
    stage, proto = _stage([("1TS", "1TS00000A"), ("1OR", None), ("1TE", "1TE@"), ("1TS", "1TS000032")])
    assert stage.ensure_referenced().state == 0x32
    proto.assert_done()
    stage, proto = _stage([("1TS", "1TS00000A")])
    with pytest.raises(StageError, match="not referenced"):
        stage.ensure_referenced(allow_home=False)


def test_relative_move_stop_limits_version():
    stage, proto = _stage([
        ("1PR-45.5", None), ("1TE", "1TE@"),
        ("1ST", None), ("1TE", "1TE@"), ("1TS", "1TS000028"), ("1TS", "1TS000033"),
        ("1SL?", "1SL-360"), ("1SR?", "1SR360"),
        ("1VE", "1VE SMC_CC - 2.0.0"),
    ])
    assert stage.move_relative_deg(-45.5, wait=False) is None
    assert stage.stop(poll_s=0.001).state == 0x33
    assert stage.soft_limits_deg() == (-360.0, 360.0)
    assert stage.version() == "SMC_CC - 2.0.0"
    proto.assert_done()


def test_wait_ready_raises_on_error_bits_and_disable():
    stage, _ = _stage([("1TS", "1TS002033"), ("1TE", "1TE@")])
    with pytest.raises(StageError) as exc:
        stage.wait_ready(timeout_s=1)
    assert exc.value.errors == 0x0020 and "following error" in str(exc.value)
    stage, _ = _stage([("1TS", "1TS00003D"), ("1TE", "1TEV")])
    with pytest.raises(StageError) as exc:
        stage.wait_ready(timeout_s=1)
    assert exc.value.state_name == "DISABLE from MOVING" and exc.value.letter == "V"
    stage, _ = _stage([("1TS", "1TS000028")])
    with pytest.raises(StageError, match="not READY after 0 s"):
        stage.wait_ready(timeout_s=0.0)


def test_a_reply_that_is_not_an_smc100_reply_names_the_port():
    stage, _ = _stage([("1TS", "DR,1000")])
    with pytest.raises(DeviceError, match="does not answer like an SMC100 .* is it the right port"):
        stage.status()
    stage, _ = _stage([("1TS", None)])
    with pytest.raises(DeviceError, match="no answer to 1TS"):
        stage.status()


# ---------------------------------------------------------------------------- real ptys


def test_same_port_twice_is_busy_and_named(pty_pair):
    _, path = pty_pair
    with SerialTransport(path, device="turntable", baudrate=57600):
        with pytest.raises(DeviceError) as exc:
            Turntable(path)
    assert path in str(exc.value) and "busy" in str(exc.value)
    assert exc.value.port == path and exc.value.device == "turntable"


def test_missing_port_is_named(tmp_path):
    missing = str(tmp_path / "ttyUSB9")
    with pytest.raises(DeviceError) as exc:
        Turntable(missing)
    assert f"no such port {missing}" in str(exc.value)


def test_imu_port_given_as_the_turntable(pty_pair):
    """A KVH stream on the port: the driver says it is not an SMC100, naming the port."""
    master, path = pty_pair
    n = 200
    zeros = np.zeros((n, 3))
    frames = kvh.encode_frames(zeros, zeros, np.full(n, 0x77), np.arange(n), np.full(n, 20))
    stop = threading.Event()

    def stream():
        while not stop.is_set():
            try:
                os.write(master, frames)
            except OSError:
                return
            time.sleep(0.01)

    t = threading.Thread(target=stream, daemon=True)
    t.start()
    try:
        with Turntable(path, timeout_s=0.3) as stage, pytest.raises(DeviceError) as exc:
            stage.status()
    finally:
        stop.set()
        t.join()
    assert f"the device on {path} does not answer like an SMC100" in str(exc.value)


def test_transcript_logs_both_directions_with_timestamps(tmp_path):
    log = tmp_path / "stage.log"
    with SerialTransport("loop://", device="turntable", baudrate=57600, timeout_s=0.2, transcript=log) as t:
        t.write(b"1TS\r\n")
        assert t.read_until(b"\r\n") == b"1TS\r\n"
    lines = log.read_text().splitlines()
    assert len(lines) == 2
    assert lines[0].endswith(" > 1TS\\r\\n") and lines[1].endswith(" < 1TS\\r\\n")
    assert lines[0][:4].isdigit() and "T" in lines[0].split()[0]


def test_stage_identity_and_limits_the_manual_way():
    """ID? (the manual's Get stage identifier) and SL?/SR?, each a query with its one-line reply."""
    stage, proto = _stage([("1ID?", "1IDURS100BCC"), ("1SL?", "1SL-170"), ("1SR?", "1SR170")])
    assert stage.stage_id() == "URS100BCC"
    assert stage.soft_limits_deg() == (-170.0, 170.0)
    proto.assert_done()


def test_stage_identity_from_firmware_sim():
    from firmware_sim.config import SimConfig
    from firmware_sim.simulator import Simulator

    cfg = SimConfig(seed=1, time_scale=10.0, accel_enabled=False)
    with Simulator(cfg) as ep, Turntable(ep["turntable"]) as st:
        assert st.stage_id() == "URS100BCC" and st.soft_limits_deg() == (-360.0, 360.0)
