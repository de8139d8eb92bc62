"""firmware_sim devices through their real ptys with real pyserial clients.

Golden vectors on firmware_sim's own codecs, the SMC100 state machine and TE letters, KVH
configuration mode, variants and faults, determinism, a physics check through the pty, and the
time-scaled stream without a sequence gap. No timing assertions: waits have generous timeouts.
"""

from __future__ import annotations

import math
import os
import time

import numpy as np
import pytest
import serial
from helpers import SerialKeepingInput, crc32_mpeg2_bitwise, recv_frames

from firmware_sim.config import SimConfig
from firmware_sim.devices import kvh, smc100
from firmware_sim.faults import FaultError, Faults, parse_faults
from firmware_sim.physics.sensors import ACCEL_PRESETS, GYRO_PRESETS
from firmware_sim.simulator import Simulator
from northfinder.constants import DPH, earth_rate_enu_rad_s, normal_gravity_m_s2

HEADER = b"\xfe\x81\xff\x55"


# ---------------------------------------------------------------------------------------------
# codecs against the golden vectors
# ---------------------------------------------------------------------------------------------
def test_crc_golden_vectors(golden):
    for v in golden["crc32_mpeg2"]:
        data = v["ascii"].encode() if "ascii" in v else bytes.fromhex(v["hex"])
        assert kvh.crc32_mpeg2(data) == int(v["crc"], 16)
    assert kvh.crc32_mpeg2(b"123456789") == 0x0376E6E7


def test_crc_vectorized_matches_bitwise_reference():
    for width in (32, 7, 1, 0):  # each width has its own position tables; 0 is the init value
        rows = np.random.default_rng(width).integers(0, 256, (64, width), dtype=np.uint8)
        got = kvh.crc32_mpeg2_rows(rows)
        assert [int(c) for c in got] == [crc32_mpeg2_bitwise(bytes(r)) for r in rows]


def test_kvh_messages_golden(golden):
    for v in golden["kvh_format_a"]:
        packed = kvh.pack_messages([v["gyro"]], [v["accel_g"]], v["status"], v["sequence"],
                                   v["temperature_c"])
        assert packed.hex() == v["hex"], v["name"]
        msg = kvh.unpack_messages(bytes.fromhex(v["hex"]))
        assert msg["crc_ok"].all()
        assert msg["gyro"][0].tolist() == v["gyro_f32"]
        assert msg["accel"][0].tolist() == v["accel_f32"]
        assert (int(msg["status"][0]), int(msg["sequence"][0]), int(msg["temperature"][0])) == (
            v["status"], v["sequence"], v["temperature_c"])
    # many messages at once: the vectorized packer equals the one-by-one packer
    vs = golden["kvh_format_a"]
    many = kvh.pack_messages([v["gyro"] for v in vs], [v["accel_g"] for v in vs], [v["status"] for v in vs],
                             [v["sequence"] for v in vs], [v["temperature_c"] for v in vs])
    assert many.hex() == "".join(v["hex"] for v in vs)


def test_smc100_codec_golden(golden):
    for v in golden["smc100"]["commands"]:
        cmd = smc100.parse_command(bytes.fromhex(v["hex"]))
        assert (cmd.address, cmd.command, cmd.value) == (v["address"], v["command"], v["value"])
        assert cmd.query == v.get("query", False)
    for v in golden["smc100"]["replies"]:
        raw = bytes.fromhex(v["hex"])
        address, command, payload = smc100.parse_reply(raw)
        assert address == v["address"]
        if "state" in v:
            assert smc100.encode_status(v["address"], v["errors"], v["state"]) == raw
        elif "error_letter" in v:
            assert smc100.encode_reply(address, "TE", v["error_letter"]) == raw
        elif "position" in v:
            assert float(payload) == v["position"]
            line = smc100.encode_reply(1, "TP", smc100.format_number(v["position"]))
            assert float(smc100.parse_reply(line)[2]) == v["position"]
        else:
            assert smc100.encode_reply(address, command, smc100.format_number(v["soft_limit"])) == raw
    assert smc100.encode_command(1, "PA", 90.0) == b"1PA90\r\n"


# ---------------------------------------------------------------------------------------------
# SMC100 through its pty
# ---------------------------------------------------------------------------------------------
class Stage:
    """A tiny SMC100 host for the tests: send a line, read the reply line."""

    def __init__(self, path: str) -> None:
        # a host-time bound only: at 100× the IMU's stream shares the simulator's process, and on a
        # loaded host a reply has taken over 2 s to be written (never in device time)
        self.port = serial.Serial(path, 57600, timeout=10.0)

    def send(self, text: str) -> None:
        self.port.write(text.encode("ascii") + b"\r\n")

    def ask(self, text: str) -> str:
        self.send(text)
        line = self.port.readline()
        assert line.endswith(b"\r\n"), f"no reply to {text!r}: {line!r}"
        return line[:-2].decode("ascii")

    def status(self) -> tuple[int, int]:
        payload = self.ask("1TS")
        assert payload.startswith("1TS") and len(payload) == 9
        return int(payload[3:7], 16), int(payload[7:9], 16)

    def wait_state(self, states: tuple[int, ...], timeout_s: float = 20.0) -> tuple[int, int]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            errors, state = self.status()
            if state in states:
                return errors, state
            time.sleep(0.01)
        raise AssertionError(f"state never reached {states}, last {state:#x}")

    def position_deg(self) -> float:
        reply = self.ask("1TP")
        assert reply.startswith("1TP")
        return float(reply[3:])

    def close(self) -> None:
        self.port.close()


@pytest.fixture
def bench(request):
    """A running simulator (time scale 100 unless the test says) and its endpoints."""
    kwargs = dict(seed=5, latitude_deg=40.0, heading_deg=30.0, time_scale=100.0, accel_enabled=False)
    kwargs.update(getattr(request, "param", {}))
    sim = Simulator(SimConfig(**kwargs))
    endpoints = sim.start()
    yield sim, endpoints
    sim.stop()


@pytest.fixture
def stage(bench):
    """A serial host on the running bench's SMC100 pty (closed after the test)."""
    _, ep = bench
    host = Stage(ep["turntable"])
    yield host
    host.close()


def test_smc100_golden_exchange(golden, bench, stage):
    sim, _ = bench
    for step in golden["smc100"]["exchange"]:
        if step.get("wait_ready"):
            assert stage.wait_state((step["state"],)) == (0, step["state"])
        elif "reply_position_near" in step:
            step_deg = math.degrees(sim.world.table.encoder_step_rad)
            assert abs(stage.position_deg() - step["reply_position_near"]) <= step_deg
        elif step["reply"] is None:
            stage.send(step["send"])
        else:
            assert stage.ask(step["send"]) == step["reply"], step


@pytest.mark.parametrize("bench", [{"time_scale": 10.0}], indirect=True)
def test_smc100_state_machine_and_te_letters(stage):
    """(time scale 10: the 300° move below lasts long enough in host time for PA in MOVING to
    arrive while it runs, even on a loaded host)"""
    assert stage.ask("1TS") == "1TS00000A"
    assert stage.ask("1TS?") == "1TS00000A"
    assert stage.ask("1VE").startswith("1VE ")
    stage.send("1PA90")
    assert stage.ask("1TE") == "1TEH"
    stage.send("1OR")
    stage.send("1OR")
    assert stage.ask("1TE") == "1TEE"  # home already started
    stage.send("1PA10")
    assert stage.ask("1TE") == "1TEL"  # not allowed in HOMING
    stage.wait_state((smc100.READY_FROM_HOMING,))
    assert stage.position_deg() == 0.0
    stage.send("1OR")
    assert stage.ask("1TE") == "1TEK"  # not allowed in READY
    stage.send("1PA")
    assert stage.ask("1TE") == "1TEC"  # parameter missing
    stage.send("1PAabc")
    assert stage.ask("1TE") == "1TEC"
    stage.send("0TS")
    assert stage.ask("1TE") == "1TEB"  # bad address
    stage.send("1ZZ")
    assert stage.ask("1TE") == "1TEA"
    # soft limits: query forms, set, refuse a move beyond, refuse a bad value
    assert stage.ask("1SL?") == "1SL-360"
    assert stage.ask("1SR") == "1SR360"
    stage.send("1SL-10")
    assert stage.ask("1TE") == "1TE@"
    assert stage.ask("1SL?") == "1SL-10"
    stage.send("1PA-20")
    assert stage.ask("1TE") == "1TEG"  # the manual: displacement out of limits
    stage.send("1PR-10.5")
    assert stage.ask("1TE") == "1TEG"
    stage.send("1SL5")
    assert stage.ask("1TE") == "1TEC"
    # a long move: MOVING; PA is "only accepted in READY state" (manual p. 41): M; ST ends it
    stage.send("1PA300")
    assert stage.ask("1TE") == "1TE@"
    assert stage.status() == (0, smc100.MOVING)
    stage.send("1PA290")
    assert stage.ask("1TE") == "1TEM"
    assert stage.ask("1PA?") == "1PA300"
    stage.send("1ST")
    assert stage.ask("1TE") == "1TE@"  # ST is accepted in MOVING and in READY (p. 56)
    errors, state = stage.wait_state((smc100.READY_FROM_MOVING,))
    stopped = stage.position_deg()
    # short of 300° unless a loaded host let the move end before ST arrived (ST stopping short is
    # pinned in device time by tests/test_conformance.py::test_smc100_bare_st_stops_the_move)
    assert errors == 0 and 0.0 < stopped < 300.001
    # RS: back to NOT REFERENCED, limits back to their defaults
    stage.send("1RS")
    assert stage.ask("1TS") == "1TS00000A"
    assert stage.ask("1SL") == "1SL-360"


def test_smc100_move_to_90_ends_ready_at_90_within_encoder_step(bench, stage):
    sim, _ = bench
    stage.send("1OR")
    stage.wait_state((smc100.READY_FROM_HOMING,))
    stage.send("1PA90")
    assert stage.ask("1TE") == "1TE@"
    assert stage.wait_state((smc100.READY_FROM_MOVING,)) == (0, smc100.READY_FROM_MOVING)
    step_deg = math.degrees(sim.world.table.encoder_step_rad)
    assert abs(stage.position_deg() - 90.0) <= step_deg
    stage.send("1PR-45.5")
    stage.wait_state((smc100.READY_FROM_MOVING,))
    assert abs(stage.position_deg() - 44.5) <= step_deg


@pytest.mark.parametrize("bench", [{"faults": ["stage-stall=2"]}], indirect=True)
def test_smc100_stall_fault_gives_following_error_and_disable(stage):
    stage.send("1OR")
    stage.wait_state((smc100.READY_FROM_HOMING,))
    stage.send("1PA20")
    assert stage.wait_state((smc100.READY_FROM_MOVING,)) == (0, smc100.READY_FROM_MOVING)
    stage.send("1PA120")  # the second move jams
    errors, state = stage.wait_state((smc100.DISABLE_FROM_MOVING,))
    assert errors & 0x20  # following error
    stalled = stage.position_deg()
    assert 20.0 < stalled < 120.0
    stage.send("1PA10")
    assert stage.ask("1TE") == "1TEJ"  # not allowed in DISABLE
    stage.send("1MM1")
    assert stage.status() == (0, smc100.READY_FROM_DISABLE)
    stage.send("1PA120")  # only that one move stalls
    assert stage.wait_state((smc100.READY_FROM_MOVING,)) == (0, smc100.READY_FROM_MOVING)


# ---------------------------------------------------------------------------------------------
# KVH through its pty
# ---------------------------------------------------------------------------------------------
def _messages(raw: bytes) -> np.ndarray:
    start = raw.find(HEADER)
    assert start >= 0, "no format-A header in the stream"
    return kvh.unpack_messages(raw[start:])


def _read_quiet(port: serial.Serial, quiet_s: float = 0.3) -> bytes:
    """Read until nothing arrives for quiet_s of wall time."""
    out = bytearray()
    port.timeout = quiet_s
    while chunk := port.read(65536):
        out += chunk
    return bytes(out)


def _read_exact(port: serial.Serial, n_bytes: int, timeout_s: float = 30.0) -> bytes:
    out = bytearray()
    port.timeout = 0.5
    deadline = time.monotonic() + timeout_s
    while len(out) < n_bytes and time.monotonic() < deadline:
        out += port.read(n_bytes - len(out))
    assert len(out) == n_bytes, f"read {len(out)} of {n_bytes} bytes"
    return bytes(out)


@pytest.mark.parametrize("bench", [{"time_scale": 10.0}], indirect=True)
def test_kvh_configuration_mode(bench):
    sim, ep = bench
    port = serial.Serial(ep["imu"], 921600, timeout=1.0)
    try:
        first = _messages(_read_exact(port, 36 * 200))
        assert first["crc_ok"][:100].all() and (first["status"][:100] == 0x77).all()
        port.write(b"=CONFIG,1\n")
        port.timeout = 5.0
        assert port.read_until(b"CONFIG,1\r\n").endswith(b"CONFIG,1\r\n")  # the echo (manual §7)
        _read_quiet(port)  # what was already on its way
        port.write(b"?DR\n")
        port.timeout = 5.0  # (_read_quiet left 0.3 s: a loaded CI host once took longer to answer)
        assert port.read_until(b"DR,1000\r\n").endswith(b"DR,1000\r\n")
        assert _read_quiet(port, 0.3) == b""  # 3 s of device time: configuration mode sends no data
        for line in (b"=DR,100\n", b"=ROTFMT,RATE\n", b"=ROTUNITS,DEG\n", b"=DR,333\n", b"=ROTFMT,FOO\n",
                     b"=FOO\n"):
            port.write(line)
        port.write(b"?DR\n?ROTFMT\n?ROTUNITS\n")
        port.timeout = 2.0
        assert [port.readline() for _ in range(9)] == [
            b"DR,100\r\n", b"ROTFMT,RATE\r\n", b"ROTUNITS,DEG\r\n",  # echoes
            b"USAGE,=DR,<1|5|10|25|50|100|250|500|750|1000|3600|5000>\r\n",  # bad parameters: the prompt
            b"USAGE,=ROTFMT,<DELTA|RATE>\r\n",
            b"INVALID,=FOO\r\n",  # unknown input: INVALID + the echo
            b"DR,100\r\n", b"ROTFMT,RATE\r\n", b"ROTUNITS,DEG\r\n"]
        port.write(b"=CONFIG,0\n")
        assert _read_exact(port, 10) == b"CONFIG,0\r\n"
        msgs = kvh.unpack_messages(_read_exact(port, 36 * 50))  # data again, from a message boundary
        assert msgs["crc_ok"].all()
        assert (msgs["status"][:2] == 0).all() and (msgs["status"][2:] == 0x77).all()
        assert (np.diff(msgs["sequence"].astype(int)) % 128 == 1).all()
        # rates in deg/s now: the gyro sees the Earth rate (15.04 deg/h) plus the nav preset's
        # errors; the mean over 48 samples at 100 Hz is within 3σ of white noise of it
        rate_dps = msgs["gyro"][2:].astype(float).mean(axis=0)
        g = GYRO_PRESETS["nav"]
        sigma = max(g.arw_deg_rt_h) / 60.0 / math.sqrt(48 / 100.0)  # deg/s over 0.48 s
        systematic = (max(np.abs(g.bias_dph)) + 3.0 * max(g.bias_instability_dph)) / 3600.0
        earth_dps = 7.2921150e-5 * 180.0 / math.pi
        assert abs(np.linalg.norm(rate_dps) - earth_dps) < math.sqrt(3.0) * (3.0 * sigma + systematic)
    finally:
        port.close()


@pytest.mark.parametrize("variant, status", [("gyro-1axis", 0x02), ("gyro-3axis", 0x07)])
def test_kvh_gyro_only_variants(variant, status):
    with Simulator(SimConfig(seed=1, time_scale=20.0, imu_variant=variant, accel_enabled=False)) as ep:
        port = serial.Serial(ep["imu"], 921600, timeout=1.0)
        try:
            msgs = _messages(_read_exact(port, 36 * 101))
        finally:
            port.close()
    assert msgs["crc_ok"].all() and (msgs["status"] == status).all()
    assert (msgs["accel"] == 0.0).all()
    if variant == "gyro-1axis":
        assert (msgs["gyro"][:, [0, 2]] == 0.0).all() and (msgs["gyro"][:, 1] != 0.0).all()


def _drive(faults, splits, n_samples=3000, seed=11):
    """The IMU alone, driven at chosen device times; a pyserial client reads everything."""
    sim = Simulator(SimConfig(seed=seed, accel_enabled=False, faults=faults))
    sim._build()  # no loop thread: this test chooses the device times itself
    try:
        client = serial.Serial(sim.imu.endpoint(), 921600, timeout=0.2)
        out = bytearray()
        for t in np.linspace(0.0, n_samples / 1000.0, splits + 1)[1:]:
            sim.imu.advance(float(t))
            while sim.imu.port.pending:
                sim.imu.port.flush()
                out += client.read(client.in_waiting or 1)
        while chunk := client.read(65536):  # what is still in flight through the pty
            out += chunk
        client.close()
        return bytes(out), sim.imu
    finally:
        sim.stop()


def test_kvh_same_seed_same_bytes_with_or_without_empty_faults():
    plain, _ = _drive(None, splits=7)
    empty, _ = _drive([], splits=7)
    resplit, _ = _drive(Faults(), splits=41)
    assert len(plain) == 3000 * 36
    assert plain == empty == resplit
    other, _ = _drive(None, splits=7, seed=12)
    assert other != plain


def test_kvh_crc_and_drop_faults_only_touch_what_they_say():
    clean, _ = _drive(None, splits=5)
    crc, _ = _drive(["imu-crc-rate=0.2"], splits=5)
    ref, got = kvh.unpack_messages(clean), kvh.unpack_messages(crc)
    bad = ~got["crc_ok"]
    n = len(ref)
    # binomial(3000, 0.2): mean 600, σ ≈ 22
    assert abs(bad.sum() - 0.2 * n) < 5 * math.sqrt(n * 0.2 * 0.8)
    same = np.frombuffer(clean, np.uint8).reshape(n, 36) == np.frombuffer(crc, np.uint8).reshape(n, 36)
    assert same[:, :35].all() and (same[:, 35] == ~bad).all()
    dropped, imu = _drive(["imu-drop-byte-rate=0.1"], splits=5)
    lost = len(clean) - len(dropped)
    assert 0 < lost and abs(lost - 0.1 * n) < 5 * math.sqrt(n * 0.1 * 0.9)


def test_kvh_silence_fault_leaves_a_gap_of_its_duration():
    raw, imu = _drive(["imu-silence=1.0:0.5"], splits=6)
    msgs = kvh.unpack_messages(raw)
    assert msgs["crc_ok"].all() and len(msgs) == 3000 - 500
    jumps = np.diff(msgs["sequence"].astype(int)) % 128
    assert sorted(set(jumps.tolist())) == [1, 501 % 128]


def test_kvh_disconnect_fault_removes_then_repoints_the_symlink_and_cleans_up():
    # the port vanishes 40 device s (2 s wall) after start: after the client has opened it, even on a
    # loaded host (at 1 device s, 0.05 s wall, a late open found the pty already replaced)
    cfg = SimConfig(seed=2, time_scale=20.0, accel_enabled=False, faults=["imu-disconnect=40.0:20"])
    sim = Simulator(cfg)
    ep = sim.start()
    link = ep["imu"]
    try:
        assert os.path.islink(link)
        port = serial.Serial(link, 921600, timeout=0.5)
        with pytest.raises(serial.SerialException):  # the port vanishes under the client
            deadline = time.monotonic() + 30.0
            while time.monotonic() < deadline:
                port.read(65536)
        port.close()
        # while it is away the link is gone too, as a USB adapter's device node is: a link left on the
        # closed pty would name whichever pty the kernel hands out next under its number
        deadline = time.monotonic() + 0.5  # of the 1 s (wall) it is away
        while os.path.lexists(link) and time.monotonic() < deadline:
            time.sleep(0.002)
        assert not os.path.lexists(link)
        # it comes back behind the same link (a new pty; the kernel may reuse the number)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:
            try:
                port = serial.Serial(link, 921600, timeout=1.0)
                break
            except serial.SerialException:
                time.sleep(0.02)
        msgs = _messages(_read_exact(port, 36 * 101))
        port.close()
        assert msgs["crc_ok"].all() and (np.diff(msgs["sequence"].astype(int)) % 128 == 1).all()
    finally:
        sim.stop()
    assert not os.path.exists(os.path.dirname(link))


def test_fault_specs_are_checked():
    assert parse_faults([]) == Faults() == parse_faults(None)
    f = parse_faults(["imu-silence=10:2", "stage-stall=3", "imu-disconnect=4"])
    assert f.imu_silence == (10.0, 2.0) and f.stage_stall == 3 and f.imu_disconnect[0] == 4.0
    for bad in (["imu-crc-rate=1.5"], ["nope=1"], ["imu-silence=3"], ["stage-stall=0"], ["disturbance=1:2"]):
        with pytest.raises(FaultError):
            parse_faults(bad)


# ---------------------------------------------------------------------------------------------
# physics through the pty, and the time-scaled stream
# ---------------------------------------------------------------------------------------------
def _rz(a):
    return np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _rx(a):
    return np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])


def _ry(a):
    return np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])


def test_kvh_gyro_mean_is_earth_rate_projection_within_3_sigma():
    heading, pitch, roll, lat = 30.0, 1.0, -0.5, 40.0
    alpha_deg = -63.0  # the stage's power-on angle; not homed, so the table stands still
    cfg = SimConfig(seed=21, time_scale=50.0, heading_deg=heading, pitch_deg=pitch, roll_deg=roll,
                    latitude_deg=lat, grade="nav", accel_enabled=False, stage_power_on_deg=alpha_deg)
    n = 20000  # 20 s of device time at 1000 Hz
    with Simulator(cfg) as ep:
        port = serial.Serial(ep["imu"], 921600, timeout=1.0)
        try:
            msgs = _messages(_read_exact(port, 36 * (n + 1)))[:n]
        finally:
            port.close()
    assert msgs["crc_ok"].all()
    alpha = math.radians(alpha_deg)
    c_pn = _rz(-math.radians(heading)) @ _rx(math.radians(pitch)) @ _ry(math.radians(roll))
    c_bn = c_pn @ _rz(alpha)
    omega_b = c_bn.T @ earth_rate_enu_rad_s(lat)
    f_b = c_bn.T @ np.array([0.0, 0.0, normal_gravity_m_s2(lat)])
    dt = 1e-3
    gyro_mean = msgs["gyro"].astype(float).mean(axis=0) / dt
    g = GYRO_PRESETS["nav"]
    sigma_white = np.asarray(g.arw_deg_rt_h) * math.pi / 180.0 / 60.0 / math.sqrt(n * dt)
    # stated errors of the preset bound what is not white: constant bias, bias instability (3σ),
    # scale factor and misalignment acting on the Earth rate
    rrw = 3.0 * np.asarray(g.rrw_dph_rt_h) * math.sqrt(n * dt / 3600.0)
    systematic = (np.abs(g.bias_dph) + 3.0 * np.asarray(g.bias_instability_dph) + rrw) * DPH \
        + (np.abs(g.scale_factor_ppm) + np.abs(g.misalignment_urad).max()) * 1e-6 * np.linalg.norm(omega_b)
    assert np.all(np.abs(gyro_mean - omega_b) < 3.0 * sigma_white + systematic), (gyro_mean, omega_b)
    accel_g = msgs["accel"].astype(float).mean(axis=0)
    a = ACCEL_PRESETS["nav"]
    sigma_a = np.asarray(a.noise_ug_rt_hz) * 1e-6 / math.sqrt(n * dt)
    bound_a = 3.0 * sigma_a + (np.abs(a.bias_ug) + 3.0 * np.asarray(a.bias_instability_ug)) * 1e-6 \
        + (np.abs(a.scale_factor_ppm) + np.abs(a.misalignment_urad).max()) * 1e-6
    assert np.all(np.abs(accel_g - f_b / 9.80665) < bound_a)
    assert abs(np.linalg.norm(accel_g) - normal_gravity_m_s2(lat) / 9.80665) < np.linalg.norm(bound_a)


def test_time_scale_50_sixty_device_seconds_without_a_sequence_gap():
    # the reader may stall for 20 s of wall (a CI host beside the UML guest): the pty's backlog
    # holds it, as the default 1 s would not — this is about the stream, not about the host's pace
    n = 60000
    with Simulator(SimConfig(seed=3, time_scale=50.0, accel_enabled=False, client_stall_wall_s=20.0)) as ep:
        port = serial.Serial(ep["imu"], 921600, timeout=1.0)
        try:
            t0 = time.monotonic()
            raw = _read_exact(port, 36 * (n + 1), timeout_s=60.0)
            wall = time.monotonic() - t0
        finally:
            port.close()
    msgs = _messages(raw)
    assert len(msgs) >= n and msgs["crc_ok"].all()
    assert (np.diff(msgs["sequence"].astype(int)) % 128 == 1).all()
    print(f"\n60 s device time at 1000 Hz, time scale 50: {len(msgs)} messages in {wall:.2f} s wall")


# ---------------------------------------------------------------------------------------------
# the default bench's CAN accelerometer, through the slcan adapter's pty with python-can's slcan
# ---------------------------------------------------------------------------------------------
def test_default_bench_can_accelerometer_over_slcan():
    import can

    sim = Simulator(SimConfig(seed=4, time_scale=10.0, latitude_deg=40.0))
    ep = sim.start()
    try:
        assert ep["can"]["interface"] == "slcan" and ep["can"]["node_id"] == 0x10
        bus = can.Bus(interface="slcan", channel=ep["can"]["channel"], bitrate=ep["can"]["bitrate"],
                      sleep_after_open=0.0)
        try:
            first = bus.recv(timeout=5.0)  # the node powers on when the adapter's channel opens
            assert first is not None and (first.arbitration_id, bytes(first.data)) == (0x710, b"\x00")
            bus.send(can.Message(arbitration_id=0x000, data=[0x01, 0x10], is_extended_id=False))
            z_ug = [int.from_bytes(msg.data[:4], "little", signed=True)
                    for msg in recv_frames(bus, (0x290,), 50, timeout_s=10.0)]
        finally:
            bus.shutdown()
    finally:
        sim.stop()
    assert len(z_ug) == 50
    # level platform, table still: z reads local gravity in µg of standard g, within the nav
    # preset's bias and scale factor and 3σ of its noise at 100 Hz
    a = ACCEL_PRESETS["nav"]
    expected_ug = normal_gravity_m_s2(40.0) / 9.80665 * 1e6
    bound_ug = abs(a.bias_ug[2]) + 3 * a.bias_instability_ug[2] + abs(a.scale_factor_ppm[2]) \
        + 3 * a.noise_ug_rt_hz[2] * math.sqrt(100.0) / math.sqrt(len(z_ug)) + 1.0  # +1: µg rounding
    assert abs(np.mean(z_ug) - expected_ug) < bound_ug


def test_gyro_z_sum_across_a_90_deg_move_is_the_encoder_step_plus_earth_rate():
    """The gyro sees the table turn at the device time the stage reports: Σ dθz over a window
    holding a whole move = Δα (encoder) + Ωz·T, within the encoder steps and the gyro noise."""
    import threading

    # 10×: the reader thread shares the simulator's process; at 50× a loaded host fell more than the
    # pty's backlog behind and whole blocks of 128 frames were dropped, unseen by the 7-bit sequence
    lat, scale = 40.0, 10.0
    cfg = SimConfig(seed=8, time_scale=scale, latitude_deg=lat, heading_deg=10.0, pitch_deg=0.5,
                    roll_deg=0.3, grade="nav", accel_enabled=False)
    sim = Simulator(cfg)
    ep = sim.start()
    settle_wall_s = 10.0 * sim.world.table.decay_s / scale  # ringing down by e^-10
    raw = bytearray()
    stop = threading.Event()
    try:
        stage = Stage(ep["turntable"])
        stage.send("1OR")
        stage.wait_state((smc100.READY_FROM_HOMING,))
        time.sleep(settle_wall_s)
        imu = SerialKeepingInput(ep["imu"], 921600, timeout=0.05)

        def reader():
            while not stop.is_set():
                raw.extend(imu.read(65536))

        thread = threading.Thread(target=reader)
        thread.start()
        # the IMU delivers to a new client only after a short connect grace (docs/simulator.md):
        # the move must start after the first frames are here, or the sum misses its beginning
        deadline = time.monotonic() + 10.0
        while len(raw) < 100 * 36 and time.monotonic() < deadline:
            time.sleep(0.01)
        start_deg = stage.position_deg()
        stage.send("1PA90")
        stage.wait_state((smc100.READY_FROM_MOVING,))
        end_deg = stage.position_deg()
        # the window ends once the ringing is down by e^-10 in device time and the reader holds every
        # byte the IMU had handed over by then (a reader behind on a loaded host cut the ringing off)
        sim.run_for(10.0 * sim.world.table.decay_s)
        port = sim.imu.port
        handed = port.bytes_written + port.pending
        deadline = time.monotonic() + 20.0
        while len(raw) < handed and time.monotonic() < deadline:
            time.sleep(0.01)
        stop.set()
        thread.join()
        imu.close()
        stage.close()
        dropped = sim.imu.port.bytes_dropped
    finally:
        stop.set()
        sim.stop()
    assert dropped == 0, f"the host fell behind the IMU stream: {dropped} bytes dropped by the pty"
    msgs = _messages(bytes(raw))
    assert msgs["crc_ok"].all() and (np.diff(msgs["sequence"].astype(int)) % 128 == 1).all()
    n, dt = len(msgs), 1e-3
    total_deg = math.degrees(msgs["gyro"][:, 2].astype(float).sum())
    c_pn = _rz(-math.radians(cfg.heading_deg)) @ _rx(math.radians(cfg.pitch_deg)) \
        @ _ry(math.radians(cfg.roll_deg))
    earth_z_deg = math.degrees((c_pn.T @ earth_rate_enu_rad_s(lat))[2] * n * dt)  # b-z = p-z
    g = GYRO_PRESETS["nav"]
    step_deg = math.degrees(sim.world.table.encoder_step_rad)
    noise_deg = 3.0 * g.arw_deg_rt_h[2] / 60.0 * math.sqrt(n * dt)
    bias_deg = (abs(g.bias_dph[2]) + 3.0 * g.bias_instability_dph[2]) / 3600.0 * n * dt
    scale_deg = abs(g.scale_factor_ppm[2]) * 1e-6 * 90.0
    assert abs(end_deg - start_deg - 90.0) <= 2 * step_deg
    bound_deg = 2 * step_deg + noise_deg + bias_deg + scale_deg
    residual_deg = total_deg - (end_deg - start_deg) - earth_z_deg
    print(f"\nΣ gyro z {total_deg:.6f}°, encoder {end_deg - start_deg:.4f}°, Earth z {earth_z_deg:.6f}°, "
          f"residual {residual_deg:.2e}° (bound {bound_deg:.2e}°)")
    assert abs(residual_deg) < bound_deg


def test_virtual_can_interface_for_in_process_clients():
    import can

    client = can.Bus(interface="virtual", channel="test_sim_devices_vcan", receive_own_messages=False)
    sim = Simulator(SimConfig(seed=4, time_scale=10.0, can_interface="virtual",
                              can_channel="test_sim_devices_vcan", accel_rate_hz=50.0))
    try:
        ep = sim.start()
        assert ep["can"] == {"interface": "virtual", "channel": "test_sim_devices_vcan", "bitrate": 500000,
                             "node_id": 16}
        boot = client.recv(timeout=5.0)
        assert boot is not None and (boot.arbitration_id, bytes(boot.data)) == (0x710, b"\x00")
        client.send(can.Message(arbitration_id=0x000, data=[0x01, 0x00], is_extended_id=False))
        ids = [msg.arbitration_id for msg in recv_frames(client, (0x190, 0x290), 20, timeout_s=10.0)]
        assert len(ids) == 20 and ids[0] == 0x190  # TPDO1 then TPDO2, pair after pair
        assert ids == [0x190, 0x290] * 10
    finally:
        sim.stop()
        client.shutdown()


def test_a_client_that_stops_reading_never_blocks_the_bench():
    """The IMU overruns (bytes dropped and counted) while the turntable still answers at once."""
    sim = Simulator(SimConfig(seed=6, time_scale=10.0, accel_enabled=False))
    ep = sim.start()
    try:
        imu = serial.Serial(ep["imu"], 921600, timeout=1.0)  # connected, but does not read
        stage = Stage(ep["turntable"])
        backlog_device_s = sim.imu.port.backlog_bytes / (36 * 1000.0)
        deadline = time.monotonic() + 1.5 * backlog_device_s / 10.0 + 5.0
        while sim.imu.port.bytes_dropped == 0 and time.monotonic() < deadline:
            assert stage.ask("1TS") == "1TS00000A"
            time.sleep(0.05)
        assert sim.imu.port.bytes_dropped > 0
        assert stage.ask("1TS") == "1TS00000A"
        stage.close()
        imu.close()
    finally:
        sim.stop()


def test_loop_does_not_spin_on_ports_without_a_client():
    """A pty master with no client polls readable (hang-up): the loop must not watch it, or it
    spins a core while waiting. At time scale 1 the loop ticks a few hundred times a second."""
    import time as _time

    from firmware_sim.simulator import SimConfig, Simulator

    sim = Simulator(SimConfig(time_scale=1.0))
    sim.start()
    try:
        _time.sleep(1.0)  # past the start
        ticks0, t0 = sim.ticks, _time.monotonic()
        _time.sleep(0.5)
        rate = (sim.ticks - ticks0) / (_time.monotonic() - t0)
    finally:
        sim.stop()
    # one tick per select timeout (a few ms) when idle; a spinning loop does tens of thousands
    assert rate < 2000, f"{rate:.0f} loop ticks per second with no client"


def test_kvh_power_up_bit_message_comes_before_the_first_data_message():
    """KVH manual §3.4: at power-up the unit sends its BIT message, then the periodic data
    (with power_up_bit, or the imu-dialogue-rate fault; off by default: same bytes as before)."""
    from firmware_sim.devices.kvh import KvhImu

    sim = Simulator(SimConfig(seed=11, accel_enabled=False))
    sim._build()
    try:
        old = sim.imu
        unit = KvhImu(old.world, old.gyro_model, old.accel_model, power_up_bit=True)
        client = serial.Serial(unit.endpoint(), 921600, timeout=0.2)
        try:
            unit.advance(0.01)
            while unit.port.pending:
                unit.port.flush()
            out = client.read(11 + 36 * 10)
        finally:
            client.close()
            unit.close()
    finally:
        sim.stop()
    assert out[:11] == bytes.fromhex("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23")
    assert out[11:15] == b"\xfe\x81\xff\x55" and len(out) == 11 + 36 * 10
