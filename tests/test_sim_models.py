"""The second models' firmware_sim devices through real ptys and a real python-can bus.

Each device is driven by an independent minimal client written here from the manufacturer's
document (struct and the bytes, not northfinder's codecs), and the CiA 410 node by the `canopen`
library as master with the shipped EDS. A small loop runs the devices in device time (wall time ×
scale); assertions are on device quantities (counts, samples), waits have generous timeouts.
"""

from __future__ import annotations

import math
import select
import struct
import threading
import time
from pathlib import Path

import can
import canopen
import numpy as np
import pytest
import serial
from helpers import crc32_mpeg2_bitwise, recv_frames

from firmware_sim.config import SimConfig
from firmware_sim.devices.apt import AptStage
from firmware_sim.devices.cia410 import Cia410Node
from firmware_sim.devices.stim import StimImu
from firmware_sim.physics import sensors
from firmware_sim.simulator import build_world
from northfinder.constants import normal_gravity_m_s2

ROOT = Path(__file__).resolve().parent.parent
COUNTS_PER_DEG = 1919.6418578623391  # PRM1-Z8, APT Issue 28 §8


class Loop(threading.Thread):
    """Runs devices as the simulator does: readable ports first, then advance to device time."""

    def __init__(self, devices, scale: float = 1.0) -> None:
        super().__init__(daemon=True)
        self.devices, self.scale = devices, scale
        self.stop_flag = threading.Event()
        self.t0 = time.monotonic()

    def now(self) -> float:
        return (time.monotonic() - self.t0) * self.scale

    def run(self) -> None:
        while not self.stop_flag.is_set():
            fds = {d.fileno(): d for d in self.devices if d.fileno() is not None}
            ready = select.select(list(fds), [], [], 0.005)[0] if fds else time.sleep(0.005) or []
            t = self.now()
            for fd in ready:
                fds[fd].on_readable(t)
            for d in self.devices:
                d.advance(t)

    def close(self) -> None:
        self.stop_flag.set()
        self.join(10)
        for d in self.devices:
            d.close()


def _world(**kw):
    return build_world(SimConfig(**kw))


# ---------------------------------------------------------------------------------------------
# Thorlabs APT (KDC101 + PRM1-Z8): a client from Issue 28's layouts
# ---------------------------------------------------------------------------------------------
class AptClient:
    def __init__(self, path: str) -> None:
        self.port = serial.Serial(path, 115200, timeout=0.05)
        self.buf = b""

    def send(self, msg_id: int, p1: int = 0, p2: int = 0, data: bytes | None = None) -> None:
        if data is None:
            self.port.write(struct.pack("<HBBBB", msg_id, p1, p2, 0x50, 0x01))
        else:
            self.port.write(struct.pack("<HHBB", msg_id, len(data), 0xD0, 0x01) + data)

    def wait(self, msg_id: int, timeout_s: float = 30.0) -> bytes:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            while len(self.buf) >= 6:
                mid, length = struct.unpack_from("<HH", self.buf)
                size = 6 + (length if self.buf[4] & 0x80 else 0)
                if len(self.buf) < size:
                    break
                msg, self.buf = self.buf[:size], self.buf[size:]
                assert msg[5] == 0x50 and msg[4] & 0x7F == 0x01  # unit → host
                if mid == msg_id:
                    return msg
            self.buf += self.port.read(256)
        raise AssertionError(f"no message 0x{msg_id:04X} within {timeout_s} s")


@pytest.fixture
def apt_bench():
    world = _world()
    stage = AptStage(world, stall_move=3)
    loop = Loop([stage], scale=4.0)
    loop.start()
    client = AptClient(stage.endpoint())
    yield stage, client
    client.port.close()
    loop.close()


def test_apt_identify_enable_home_move_stop(apt_bench):
    stage, c = apt_bench
    c.send(0x0005)
    info = c.wait(0x0006)
    assert len(info) == 90 and struct.unpack_from("<HH", info)[1] == 84
    serial_no, model = struct.unpack_from("<i8s", info, 6)
    assert serial_no // 1_000_000 == 27 and model.rstrip(b"\0") == b"KDC101"  # K-Cube DC servo prefix
    assert struct.unpack_from("<H", info, 6 + 82)[0] == 1  # one channel

    c.send(0x0443, 1, 0)  # home while disabled: nothing happens
    c.send(0x0490, 1, 0)
    bits = struct.unpack_from("<I", c.wait(0x0491), 16)[0]
    assert not bits & 0x80000000 and not bits & 0x400

    c.send(0x0210, 1, 1)  # enable, then home
    c.send(0x0443, 1, 0)
    homed = c.wait(0x0444, timeout_s=60)
    assert homed[2] == 1
    c.send(0x0411, 1, 0)
    _, counts = struct.unpack_from("<Hi", c.wait(0x0412), 6)
    assert counts == 0

    target = int(round(90.0 * COUNTS_PER_DEG))
    c.send(0x0453, data=struct.pack("<Hi", 1, target))
    done = c.wait(0x0464, timeout_s=60)
    _, pos, _, _, bits = struct.unpack_from("<HiHhI", done, 6)
    assert pos == target  # the physics' motor angle rounded to counts: the planned target
    assert bits & 0x400 and bits & 0x80000000 and not bits & 0x30  # homed, enabled, not moving

    c.send(0x0453, data=struct.pack("<Hi", 1, int(round(-30 * COUNTS_PER_DEG))))
    time.sleep(0.2)
    c.send(0x0465, 1, 2)  # profiled stop half-way
    stopped = c.wait(0x0466, timeout_s=60)
    _, pos, _, _, bits = struct.unpack_from("<HiHhI", stopped, 6)
    assert -30 * COUNTS_PER_DEG < pos < 90 * COUNTS_PER_DEG and not bits & 0x30


def test_apt_stall_fault_trips_the_servo(apt_bench):
    stage, c = apt_bench
    c.send(0x0210, 1, 1)
    c.send(0x0443, 1, 0)
    c.wait(0x0444, timeout_s=60)
    for k, angle in enumerate((10.0, 20.0, 60.0), 1):  # the third move stalls (stall_move=3)
        c.send(0x0453, data=struct.pack("<Hi", 1, int(round(angle * COUNTS_PER_DEG))))
        if k < 3:
            c.wait(0x0464, timeout_s=60)
    stopped = c.wait(0x0466, timeout_s=60)
    _, pos, _, _, bits = struct.unpack_from("<HiHhI", stopped, 6)
    assert bits & 0x4000 and bits & 0x40000000 and not bits & 0x80000000  # position error, error, disabled
    assert 20 * COUNTS_PER_DEG < pos < 60 * COUNTS_PER_DEG


# ---------------------------------------------------------------------------------------------
# STIM: a client from TS1524 rev.31 Tables 5-20..5-23
# ---------------------------------------------------------------------------------------------
def _s24(b: bytes) -> int:
    v = int.from_bytes(b, "big")
    return v - (1 << 24) if v & 0x800000 else v


def _first_0x93(raw: bytes) -> int:
    """Where the first whole 0x93 datagram with a good CRC starts in `raw` (the stream may begin
    mid-datagram)."""
    start = raw.find(b"\x93")
    while (crc32_mpeg2_bitwise(raw[start : start + 34] + b"\0\0")
           != int.from_bytes(raw[start + 34 : start + 38], "big")):
        start = raw.find(b"\x93", start + 1)
    return start


def _parse_0x93(dg: bytes) -> tuple[list[float], list[float], list[float], int, int]:
    """(gyro °, acc m/s, incl g, counter, statuses OR) of one 38-byte 0x93 datagram, CRC checked."""
    assert dg[0] == 0x93 and len(dg) == 38
    assert int.from_bytes(dg[34:38], "big") == crc32_mpeg2_bitwise(dg[:34] + b"\0\0")  # 2 dummies, Table 5-22
    gyro = [_s24(dg[1 + 3 * i : 4 + 3 * i]) / 2**21 for i in range(3)]
    acc = [_s24(dg[11 + 3 * i : 14 + 3 * i]) / 2**22 for i in range(3)]
    incl = [_s24(dg[21 + 3 * i : 24 + 3 * i]) / 2**22 for i in range(3)]
    return gyro, acc, incl, dg[31], dg[10] | dg[20] | dg[30]


def test_stim_datagrams_measure_the_world_and_service_mode_names_the_unit():
    world = _world(latitude_deg=45.0)
    gyro = sensors.GyroModel(sensors.gyro_errors("stim300"), 500, 1)
    acc = sensors.AccelModel(sensors.accel_errors("stim300"), 500, 2)
    imu = StimImu(world, gyro, acc, rate_hz=500)
    loop = Loop([imu], scale=1.0)
    loop.start()
    try:
        port = serial.Serial(imu.endpoint(), 921600, timeout=0.1)
        n = 2000
        raw = b""
        deadline = time.monotonic() + 60
        while len(raw) < 38 * (n + 2) and time.monotonic() < deadline:
            raw += port.read(38 * 200)
        start = _first_0x93(raw)
        rows = [_parse_0x93(raw[start + 38 * i : start + 38 * (i + 1)]) for i in range(n)]
        counters = np.array([r[3] for r in rows])
        assert set(np.diff(counters) % 256) == {4}  # 2000/500 internal samples per datagram, no gap
        assert all(r[4] == 0 for r in rows)
        dt, t_total = 1 / 500, n / 500
        g = normal_gravity_m_s2(45.0, 0.0)
        ge, ae = sensors.gyro_errors("stim300"), sensors.accel_errors("stim300")
        # expected means from the preset (bias and scale factor); tolerances 5σ of its white noise
        acc_z = np.mean([r[1][2] for r in rows]) / dt
        acc_expected = g * (1 + ae.scale_factor_ppm[2] * 1e-6) + ae.bias_ug[2] * 1e-6 * 9.80665
        acc_sigma = ae.noise_ug_rt_hz[2] * 1e-6 * 9.80665 / math.sqrt(t_total)
        assert abs(acc_z - acc_expected) < 5 * acc_sigma + ae.bias_instability_ug[2] * 3e-5
        incl_z = np.mean([r[2][2] for r in rows])  # no error model on the inclinometers here
        assert abs(incl_z * 9.80665 - g) < 2e-6 * g
        gyro_y_dph = np.mean([r[0][1] for r in rows]) / dt * 3600  # north gyro sees Ω·cos L
        gyro_expected = 15.041067 * math.cos(math.radians(45)) + ge.bias_dph[1]
        gyro_sigma = ge.arw_deg_rt_h[1] * 60 / math.sqrt(t_total)
        assert abs(gyro_y_dph - gyro_expected) < 5 * gyro_sigma + 3 * ge.bias_instability_dph[1]

        port.reset_input_buffer()
        port.write(b"SERVICEMODE\r")
        text = b""
        deadline = time.monotonic() + 30
        while b"SAMPLE RATE" not in text and time.monotonic() < deadline:
            text += port.read(4096)
        listing = text[text.find(b"SERIAL NUMBER") :].decode("utf-8", "replace")
        assert "PRODUCT = STIM300" in listing and "SERIAL NUMBER = N" in listing
        port.write(b"x N\r")
        again = b""
        deadline = time.monotonic() + 30
        while again.count(b"\x93") < 5 and time.monotonic() < deadline:
            again += port.read(1024)
        assert again.count(b"\x93") >= 5
        port.close()
    finally:
        loop.close()


# ---------------------------------------------------------------------------------------------
# CiA 410: the canopen library as master, with the EDS shipped for the simulated node
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("eds", ["firmware_sim/data/cia410.eds", "northfinder/data/cia410.eds"])
def test_cia410_node_with_canopen_master(eds):
    channel = f"cia410-{id(eds)}"
    dev_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    world = _world(pitch_deg=2.0, roll_deg=-1.0, stage_power_on_deg=0.0)  # b = p: table at α = 0
    node_dev = Cia410Node(dev_bus, world, None, node_id=0x20, event_ms=10)
    loop = Loop([node_dev], scale=2.0)
    loop.start()
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel)
    try:
        node = network.add_node(0x20, str(ROOT / eds))
        assert node.sdo["Resolution"].raw == 1
        assert node.sdo[0x1018][1].raw == 0x4E2
        assert node.sdo[0x1000].raw & 0xFFFF == 410
        node.tpdo.read()
        assert [v.index for v in node.tpdo[1].map] == [0x6010, 0x6020]
        node.sdo[0x1800][5].raw = 20  # 50 Hz the profile's way: the event timer, in pre-operational
        got: list[tuple[int, int]] = []
        node.tpdo[1].add_callback(lambda m: got.append((m[0].raw, m[1].raw)))
        node.nmt.state = "OPERATIONAL"
        deadline = time.monotonic() + 30
        while len(got) < 100 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(got) >= 100
        long_deg = np.mean([g[0] for g in got]) * 1e-3
        lat_deg = np.mean([g[1] for g in got]) * 1e-3
        # truth: f^p = g·[−sinγ·cosθ, sinθ, cosγ·cosθ]; each slope is asin of its component
        theta, gamma = math.radians(2.0), math.radians(-1.0)
        assert abs(long_deg - math.degrees(math.asin(-math.sin(gamma) * math.cos(theta)))) < 0.002
        assert abs(lat_deg - math.degrees(math.asin(math.sin(theta)))) < 0.002
        node.nmt.state = "PRE-OPERATIONAL"
        time.sleep(0.3)
        node.sdo[0x6011].raw = 0x01  # invert the longitudinal slope
        with pytest.raises(canopen.SdoAbortedError):
            node.sdo["Resolution"].raw = 7  # not one of 1, 10, 100, 1000
        node.sdo["Resolution"].raw = 10
        got.clear()
        node.nmt.state = "OPERATIONAL"
        deadline = time.monotonic() + 30
        while len(got) < 20 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert abs(np.mean([g[0] for g in got[5:]]) * 0.01 + long_deg) < 0.01
    finally:
        network.disconnect()
        loop.close()
        dev_bus.shutdown()


# ---------------------------------------------------------------------------------------------
# The simulator with the second models: one world under APT + STIM + CiA 410 (slcan adapter)
# ---------------------------------------------------------------------------------------------
def test_mixed_bench_apt_stim_cia410_on_the_simulator():
    from firmware_sim.simulator import Simulator

    sim = Simulator(SimConfig(seed=3, time_scale=5.0, latitude_deg=40.0, grade="stim300", stage_model="apt",
                              imu_model="stim", tilt_model="cia410", imu_rate_hz=500, accel_rate_hz=50.0))
    ep = sim.start()
    try:
        stage = AptClient(ep["turntable"])
        stage.send(0x0005)
        assert struct.unpack_from("<8s", stage.wait(0x0006), 10)[0].rstrip(b"\0") == b"KDC101"
        stage.port.close()
        imu = serial.Serial(ep["imu"], 921600, timeout=0.2)
        raw = b""
        deadline = time.monotonic() + 30
        while raw.count(b"\x93") < 50 and time.monotonic() < deadline:
            raw += imu.read(4096)
        imu.close()
        start = _first_0x93(raw)
        assert _parse_0x93(raw[start : start + 38])[4] == 0
        bus = can.Bus(interface="slcan", channel=ep["can"]["channel"], bitrate=ep["can"]["bitrate"],
                      sleep_after_open=0.0)
        try:
            first = bus.recv(timeout=10.0)
            assert first is not None and (first.arbitration_id, bytes(first.data)) == (0x710, b"\x00")
            bus.send(can.Message(arbitration_id=0x000, data=[0x01, 0x10], is_extended_id=False))
            slopes = [struct.unpack("<hh", bytes(msg.data))
                      for msg in recv_frames(bus, (0x190,), 20, timeout_s=20)]
        finally:
            bus.shutdown()
        assert len(slopes) == 20
        # level platform: both slopes within the stim300 accelerometer's bias (≤ 0.8 mg ≈ 0.046°)
        assert max(abs(s) for pair in slopes for s in pair) * 1e-3 < 0.06
    finally:
        sim.stop()


def test_model_names_are_checked():
    from firmware_sim.config import ConfigError

    with pytest.raises(ConfigError, match="stage_model"):
        SimConfig(stage_model="k10cr1")
    with pytest.raises(ConfigError, match="STIM samples"):
        SimConfig(imu_model="stim", imu_rate_hz=750)


def test_stim_faults_crc_and_invalid_rate_are_what_the_decoder_counts():
    """imu-crc-rate spoils the CRC of that share of datagrams, imu-invalid-rate flags the channel
    error in all three STATUS bytes; northfinder's decoder counts both (device driven by hand)."""
    from types import SimpleNamespace

    from northfinder.codecs import stim as codec

    faults = SimpleNamespace(imu_crc_rate=0.1, imu_invalid_rate=0.05)
    imu = StimImu(_world(), rate_hz=500, faults=faults, fault_seed=7)
    port = serial.Serial(imu.endpoint(), 921600, timeout=0.2)
    try:
        dec = codec.StimDecoder(0x93, codec.StimUnits("increment", "increment"), rate_hz=500)
        good = 0
        invalid = 0
        for step in range(1, 21):  # 20 × 0.1 s of device time, 50 datagrams each
            imu.advance(step * 0.1)
            raw = b""
            while len(raw) < 38 * 50:
                chunk = port.read(38 * 50 - len(raw))
                assert chunk, "the device wrote less than it produced"
                raw += chunk
            s = dec.feed(raw)
            if good == 0 and len(s):
                first_counter = int(s.counter[0])  # datagram k carries 4·k: spoiled before it show no gap
            good += len(s)
            if len(s):
                last_counter = int(s.counter[-1])
            invalid += int((~s.valid(0)).all(axis=1).sum())
    finally:
        port.close()
        imu.close()
    spoiled = dec.stats.skipped_bytes // 38  # every byte of a spoiled datagram is skipped
    assert good + spoiled == 1000 and dec.stats.skipped_bytes % 38 == 0
    assert 60 <= spoiled <= 140  # 10 % of 1000, binomial ±4σ
    assert spoiled - 15 <= dec.stats.crc_errors <= spoiled  # two in a row count once
    lost_at_start = first_counter // 4 - 1
    lost_at_end = (4 * 1000 - last_counter) % 256 // 4  # datagram 1000 carries 4000 mod 256
    unseen = lost_at_start + lost_at_end  # no good datagram on one side: no gap to see
    assert dec.stats.counter_gaps == 4 * (spoiled - unseen)  # 4 internal samples per datagram
    assert 15 <= invalid <= 85 and invalid == dec.stats.invalid_samples  # 5 % of the good ones


def test_cli_flags_choose_the_models():
    from firmware_sim.cli import build_parser, config_from_args

    cfg = config_from_args(build_parser().parse_args(["--stage", "apt", "--imu", "stim", "--tilt", "cia410",
                                                      "--grade", "stim300"]))
    assert (cfg.stage_model, cfg.imu_model, cfg.tilt_model, cfg.grade) == ("apt", "stim", "cia410", "stim300")
    default = config_from_args(build_parser().parse_args([]))
    assert (default.stage_model, default.imu_model, default.tilt_model) == ("smc100", "kvh", "nf-accel")
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--stage", "k10cr1"])


def test_apt_device_skips_junk_and_still_answers():
    """Random bytes before a request (no checksum in APT: the device resynchronises on a header
    addressed to it from the host) cost counted bytes, never the dialogue."""
    stage = AptStage(_world())
    port = serial.Serial(stage.endpoint(), 115200, timeout=0.5)
    try:
        junk = np.random.default_rng(3).integers(0, 256, 300, dtype=np.uint8).tobytes()
        junk = junk.replace(b"\x01", b"\x02")  # no host source byte: no false header in the junk
        port.write(junk + struct.pack("<HBBBB", 0x0005, 0, 0, 0x50, 0x01))
        deadline = time.monotonic() + 10
        while stage.messages_in == 0 and time.monotonic() < deadline:
            select.select([stage.port.master_fd], [], [], 0.1)
            stage.on_readable(0.0)
        reply = port.read(90)
        assert reply[:2] == b"\x06\x00" and len(reply) == 90
        assert stage.bad_bytes == len(junk) and stage.messages_in == 1
    finally:
        port.close()
        stage.close()
