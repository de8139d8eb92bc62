"""firmware_sim behaving like spec-conformant real units that differ from the default twin.

Each test talks to the simulator's real ptys with real pyserial and decodes the raw bytes with
firmware_sim's own KVH codec (never northfinder's): the KVH axes variants (--imu-axes), frames
flagged invalid by built-in test (--fault imu-invalid-rate) against the truth log, a USB link that
holds bytes back (--link-hold), link latency (--link-latency) and slow stage moves (--stage-speed).
"""

from __future__ import annotations

import json
import math
import threading
import time

import numpy as np
import pytest
import serial
from helpers import SerialKeepingInput

from firmware_sim.config import ConfigError, SimConfig
from firmware_sim.devices import kvh
from firmware_sim.simulator import TICK_WALL_S, Simulator

GYRO_BIT = {"x": 0x01, "y": 0x02, "z": 0x04}
ACCEL_BITS = 0x70


POWER_UP_BIT = bytes.fromhex("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23")


def _read_exact(port: serial.Serial, n: int, timeout_s: float = 30.0) -> bytes:
    out = bytearray()
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        out += port.read(n - len(out))
    assert len(out) == n, f"read {len(out)} of {n} bytes"
    return bytes(out)


def _read_from_connect(port: serial.Serial, n: int) -> bytes:
    """The first `n` bytes of data messages a client that has just opened the port gets (the
    simulator starts it on a frame boundary), without the power-up BIT message a client there at
    power-on hears first (KVH manual §3.4). The port must keep what came while it opened
    (SerialKeepingInput): pyserial's flush at open could cut a frame the simulator had begun."""
    data = _read_exact(port, n)
    if data.startswith(POWER_UP_BIT):
        data = data[len(POWER_UP_BIT):] + _read_exact(port, len(POWER_UP_BIT))
    return data


def _frames(data: bytes) -> np.ndarray:
    """Whole frames from a client that started on a frame boundary; every CRC checked."""
    assert data[:4] == kvh.HEADER
    msgs = kvh.unpack_messages(data)
    assert msgs["crc_ok"].all()
    return msgs


def _events(path) -> list[dict]:
    return [r for r in map(json.loads, open(path, encoding="utf-8")) if r.get("type") == "event"]


def _expected_status(axes: str) -> tuple[int, list[int], bool]:
    """From PROTOCOLS.md §2, independently of the simulator: valid bits, gyro axes, accel."""
    gyro, _, acc = axes.partition("+")
    bits = sum(GYRO_BIT[a] for a in gyro) | (ACCEL_BITS if acc else 0)
    return bits, ["xyz".index(a) for a in gyro], bool(acc)


@pytest.mark.parametrize("axes", ["xyz+acc", "xyz", "y", "xy", "xy+acc"])
def test_imu_axes_status_bits_and_zero_fields(axes):
    bits, gyro_axes, acc = _expected_status(axes)
    with Simulator(SimConfig(seed=1, time_scale=20.0, imu_axes=axes, accel_enabled=False)) as ep:
        port = SerialKeepingInput(ep["imu"], 921600, timeout=1.0)
        try:
            msgs = _frames(_read_from_connect(port, 36 * 400))
        finally:
            port.close()
    assert (msgs["status"] == bits).all()
    missing = [i for i in range(3) if i not in gyro_axes]
    assert (msgs["gyro"][:, missing] == 0.0).all()
    assert (msgs["gyro"][:, gyro_axes] != 0.0).all()  # sensor noise: a real axis is never exactly 0
    if acc:  # at rest, level: z near +1 g (local gravity in standard g), x and y near 0
        assert np.allclose(msgs["accel"].mean(axis=0), [0.0, 0.0, 1.0], atol=0.01)
    else:
        assert (msgs["accel"] == 0.0).all()


def test_imu_axes_old_variant_names_and_bad_values():
    assert SimConfig(imu_variant="gyro-1axis").imu_axes == "y"
    assert SimConfig(imu_variant="gyro-3axis").imu_axes == "xyz"
    assert SimConfig(imu_axes="gyro-accel").imu_axes == "xyz+acc"
    assert SimConfig(imu_axes="ZX").imu_axes == "xz"
    for bad in ("", "w", "xx", "xy+gps", "+acc"):
        with pytest.raises(ConfigError, match="imu_axes"):
            SimConfig(imu_axes=bad)
    with pytest.raises(ConfigError, match="disagree"):
        SimConfig(imu_axes="y", imu_variant="gyro-3axis")


def test_invalid_frames_match_the_truth_log_and_carry_garbage_only_where_bits_are_clear(tmp_path):
    """imu-invalid-rate and the 2 messages after =DR: the frames a client sees with cleared bits are
    exactly the truth log's `imu_invalid` k's; fault frames carry |v| >= 100 in the unit's cleared
    fields (a delta angle per ms is under 1e-3 rad here, an accel under 2 g), CRC and sequence intact."""
    truth = tmp_path / "truth.jsonl"
    axes = "xy+acc"
    bits, gyro_axes, _ = _expected_status(axes)
    cfg = SimConfig(seed=5, time_scale=10.0, imu_axes=axes, accel_enabled=False, truth_log=str(truth),
                    faults=["imu-invalid-rate=0.02"])
    with Simulator(cfg) as ep:
        port = SerialKeepingInput(ep["imu"], 921600, timeout=1.0)
        try:
            data = _read_from_connect(port, 36 * 3000)
            port.write(b"=CONFIG,1\n=DR,500\n=CONFIG,0\n")  # =DR is answered in Configuration Mode only
            data += _read_exact(port, 36 * 3000 + 28)  # and the three echoes (§7)
        finally:
            port.close()
    for echo in (b"CONFIG,1\r\n", b"DR,500\r\n", b"CONFIG,0\r\n"):
        data = data.replace(echo, b"", 1)
    msgs = _frames(data)
    events = _events(truth)
    (connect,) = [e for e in events if e["event"] == "imu_connect"]
    assert (np.diff(msgs["sequence"].astype(int)) % 128 == 1).all()
    k = connect["k0"] + np.arange(len(msgs))
    flagged = {reason: {kk for e in events if e["event"] == "imu_invalid" and e["reason"] == reason
                        for kk in e["k"] if k[0] <= kk <= k[-1]} for reason in ("fault", "rate_change")}
    seen_invalid = set(k[msgs["status"] == 0].tolist())
    assert seen_invalid == flagged["fault"] | flagged["rate_change"]
    assert len(flagged["rate_change"]) == 2 and 30 <= len(flagged["fault"]) <= 130  # 0.02 × 5998 ≈ 120
    assert set(np.unique(msgs["status"])) == {0, bits}
    fields = np.concatenate([msgs["gyro"], msgs["accel"]], axis=1).astype(float)
    present = gyro_axes + [3, 4, 5]
    absent = [i for i in range(6) if i not in present]
    fault = np.isin(k, list(flagged["fault"]))
    assert (np.abs(fields[np.ix_(fault, present)]) >= 100.0).all() and np.isfinite(fields).all()
    assert (fields[:, absent] == 0.0).all()
    assert (np.abs(fields[~fault][:, gyro_axes]) < 1e-3).all()
    assert (np.abs(fields[~fault][:, 3:]) < 2.0).all()


def test_invalid_frames_are_deterministic_for_a_seed_whatever_the_batching():
    """The same seed gives the same bytes, flags and garbage, however the device time is split."""
    def drive(splits: int) -> bytes:
        sim = Simulator(SimConfig(seed=8, accel_enabled=False, faults=["imu-invalid-rate=0.05"]))
        sim._build()  # no loop thread: the test chooses the device times itself
        try:
            client = serial.Serial(sim.imu.endpoint(), 921600, timeout=0.2)
            out = bytearray()
            for t in np.linspace(0.0, 2.0, splits + 1)[1:]:
                sim.imu.advance(float(t))
                while sim.imu.port.pending or client.in_waiting:
                    out += client.read(client.in_waiting or 1)
                    sim.imu.port.flush()
            out += client.read(65536)
            client.close()
            return bytes(out)
        finally:
            sim._close_all()

    a, b = drive(3), drive(41)
    assert a == b and len(a) == 36 * 2000
    assert 50 <= int((_frames(a)["status"] == 0).sum()) <= 150  # 0.05 × 2000 = 100


class _Reader(threading.Thread):
    """Reads a pty with pyserial as fast as it can, noting each chunk's arrival (host monotonic
    time and the simulator's device time)."""

    def __init__(self, path: str, sim: Simulator) -> None:
        super().__init__(daemon=True)
        self.port = SerialKeepingInput(path, 921600, timeout=0.005)
        self.sim = sim
        self.chunks: list[tuple[float, float, bytes]] = []
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set():
            data = self.port.read(65536)
            if data:
                self.chunks.append((time.monotonic(), self.sim.now(), data))

    def quiet_s(self) -> float:
        """Wall seconds since the last chunk arrived."""
        return time.monotonic() - self.chunks[-1][0] if self.chunks else math.inf

    def finish(self) -> bytes:
        self.stop.set()
        self.join(5.0)
        self.port.close()
        return b"".join(c for _, _, c in self.chunks)


def test_link_hold_delays_every_byte_without_loss_and_shows_host_gaps(tmp_path):
    """--link-hold 2,250 at time scale 5: every 2 device s the IMU link holds its bytes for 250 ms of
    wall time. Every frame arrives (CRC good, sequence continuous, as many as the truth says were
    sent); each hold is released later in device time (the simulator's own events), and the holds
    show on the host as gaps between chunks. The
    gaps are host time: a loaded host may read the bytes before a hold late (shortening that gap)
    or stall the reader as long as a hold, so the test asks for one gap of at least half a hold,
    not one per hold."""
    hold_ms, truth = 250.0, tmp_path / "truth.jsonl"
    cfg = SimConfig(seed=2, time_scale=5.0, accel_enabled=False, truth_log=str(truth),
                    link_hold_period_s=2.0, link_hold_ms=hold_ms)
    sim = Simulator(cfg)
    try:
        ep = sim.start()
        reader = _Reader(ep["imu"], sim)
        reader.start()
        sim.run_for(9.0)
        sim._stop.set()  # the loop ends, the ports stay: the test now drains the link itself
        sim._thread.join(5.0)
        link, port = sim.imu.link, sim.imu.port
        deadline = time.monotonic() + 10.0
        while (link.queued_bytes or port.pending or reader.quiet_s() < 0.3) and time.monotonic() < deadline:
            link.pump(sim.last_t, port)  # (an unfinished hold still holds until its wall time is up)
            port.flush()
            time.sleep(0.01)
        data = reader.finish()
        sent_bytes, dropped = link.bytes_in, port.bytes_dropped
        k_last = sim.imu.k_last_delivered
    finally:
        sim.stop()
    msgs = _frames(data)
    events = _events(truth)
    (connect,) = [e for e in events if e["event"] == "imu_connect"]
    holds = [e for e in events if e["event"] == "link_hold" and e["link"] == "imu"]
    releases = [e for e in events if e["event"] == "link_release" and e["link"] == "imu"]
    assert (np.diff(msgs["sequence"].astype(int)) % 128 == 1).all()
    assert dropped == 0 and msgs["sequence"][0] == connect["sequence0"]
    assert len(data) == sent_bytes == 36 * (k_last - connect["k0"] + 1)  # every frame, none twice
    arrivals = np.array([w for w, _, _ in reader.chunks])
    gaps = np.diff(arrivals)
    assert len(holds) >= 3
    # each hold: a host gap of the hold's length; the reader may see the last bytes before a hold
    # up to one loop tick late, so a gap is at least hold − a tick; and the longest is the full hold
    long_gaps = gaps[gaps >= hold_ms / 1e3 - TICK_WALL_S]
    print(f"link hold: {len(msgs)} frames, {len(holds)} holds, host gaps >= hold - tick: "
          f"{np.round(long_gaps * 1e3, 1).tolist()} ms")
    # every hold but perhaps the last (the stop) is released, later in device time (the hold's length
    # is wall time inside the simulator's loop: its device-time span shrinks by the loop's own work)
    assert len(releases) >= len(holds) - 1
    for hold, release in zip(holds, releases, strict=False):
        assert hold["t_device_s"] < release["t_device_s"] < hold["t_device_s"] + 10.0 * cfg.time_scale
    assert gaps.max() >= 0.5 * hold_ms / 1e3  # and the host saw one


def test_link_latency_shifts_arrival_by_the_latency(tmp_path):
    """--link-latency 200,50 at time scale 1 against the same bench without it: each frame's lag
    (device time at arrival − device time it was produced) is never below 150 ms, and the median
    lag grows by 200 ms. Tolerance: the jitter is a process with knots every 4·50 ms uniform in
    ±50 ms, so over 5 s (25 knots) the median's σ is at most 1.25·(50/√3)/√25 ≈ 7.2 ms; 3σ plus
    one loop tick (5 ms of device time at scale 1) for where each run's frames land in a tick."""
    latency_ms, jitter_ms, run_s = 200.0, 50.0, 5.0

    def lags(name: str, **kw) -> np.ndarray:
        truth = tmp_path / f"{name}.jsonl"
        sim = Simulator(SimConfig(seed=4, time_scale=1.0, accel_enabled=False, imu_rate_hz=100,
                                  truth_log=str(truth), **kw))
        try:
            ep = sim.start()
            reader = _Reader(ep["imu"], sim)
            reader.start()
            sim.run_for(run_s + 1.0)
            reader.finish()
        finally:
            sim.stop()
        (connect,) = [e for e in _events(truth) if e["event"] == "imu_connect"]
        out, n_bytes = [], 0
        for _, t_arrival, chunk in reader.chunks:  # a chunk may end inside a frame
            done_before, n_bytes = n_bytes // 36, n_bytes + len(chunk)
            n = np.arange(done_before, n_bytes // 36)  # frames completed by this chunk
            out.append(t_arrival - (connect["t0_device_s"] + n / 100.0))
        assert _frames(b"".join(c for _, _, c in reader.chunks)[:36 * 100]) is not None
        return np.concatenate(out)[50:]  # after the first half second

    base = lags("base")
    shifted = lags("shifted", imu_link_latency_ms=latency_ms, imu_link_jitter_ms=jitter_ms)
    assert shifted.min() >= (latency_ms - jitter_ms) / 1e3
    sigma_median_s = 1.25 * (jitter_ms / math.sqrt(3.0)) / math.sqrt(run_s / (4 * jitter_ms / 1e3)) / 1e3
    tolerance_s = 3.0 * sigma_median_s + TICK_WALL_S * 1.0
    shift = float(np.median(shifted) - np.median(base))
    print(f"link latency: min lag {shifted.min() * 1e3:.1f} ms, median shift {shift * 1e3:.1f} ms "
          f"(want {latency_ms} ± {tolerance_s * 1e3:.1f} ms)")
    assert abs(shift - latency_ms / 1e3) <= tolerance_s, (shift, tolerance_s)


def test_slow_stage_move_takes_its_planned_device_time(tmp_path):
    """--stage-speed 5 --stage-accel 10: a 90° move takes 90/5 + 5/10 = 18.5 s of device time
    (trapezoid: cruise 17.5 s and the two ramps of 0.5 s); the SMC100 says MOVING (28) until the
    plan ends, then READY from MOVING (33); TP follows the encoder in between; the truth log's
    move event gives the start, end and rest times.

    The encoder reads the motor side: the plan plus the bench's speed ripple (0.5 % of the speed,
    4° period: up to 3.2e-3° off the plan at cruise). Each TP is checked against that path between
    the device times before asking and after the reply, so a reply answered within microseconds
    (a quiet host) meets the same bound as a slow one."""
    truth = tmp_path / "truth.jsonl"
    ripple_pct, ripple_period_deg = 0.5, 4.0
    cfg = SimConfig(seed=1, time_scale=10.0, accel_enabled=False, truth_log=str(truth), stage_speed_dps=5.0,
                    stage_accel_dps2=10.0, stage_power_on_deg=10.0, stage_ripple_pct=ripple_pct,
                    stage_ripple_period_deg=ripple_period_deg)
    sim = Simulator(cfg)
    try:
        ep = sim.start()
        stage = serial.Serial(ep["turntable"], 57600, timeout=30.0)  # host bound only: a reply comes

        def ask(cmd: bytes) -> bytes:
            stage.write(b"1" + cmd + b"\r\n")
            return stage.readline().strip()

        stage.write(b"1OR\r\n")  # homing at the same slow speed: 10° → 2 s + 0.5 s
        while ask(b"TS") != b"1TS000032":
            time.sleep(0.02)
        stage.write(b"1PA90\r\n")
        states, positions = [], []
        while True:
            t_before = sim.now()
            status = ask(b"TS")
            states.append((t_before, status[-2:], sim.now()))
            t_before = sim.now()
            tp_deg = float(ask(b"TP")[3:])
            positions.append((t_before, sim.now(), tp_deg))
            if status.endswith(b"33"):
                break
            time.sleep(0.01)
        stage.close()
        # the truth rows through the ringing after the stop: until the loop has ticked 4 s (device)
        # past READY — its ticks, not a wall-clock sleep that a loaded host's loop may not fill
        until_s, deadline = states[-1][2] + 4.0, time.monotonic() + 60.0
        while sim.last_t < until_s and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        sim.stop()
    moves = [e for e in _events(truth) if e["event"] == "move"]
    home, move = moves
    assert home["kind"] == "home" and home["to_deg"] == 0.0 and home["from_deg"] == pytest.approx(10.0)
    assert home["t_end_s"] - home["t_start_s"] == pytest.approx(10.0 / 5.0 + 5.0 / 10.0, abs=1e-9)
    assert move["kind"] == "move" and move["from_deg"] == pytest.approx(0.0)
    assert move["to_deg"] == pytest.approx(90.0, abs=1e-9)
    assert move["t_end_s"] - move["t_start_s"] == pytest.approx(90.0 / 5.0 + 5.0 / 10.0, abs=1e-9)
    assert move["t_end_s"] < move["t_rest_s"] < move["t_end_s"] + 3.0
    rows = [r for r in map(json.loads, open(truth, encoding="utf-8")) if r.get("type") == "truth"]
    after = [r for r in rows if move["t_end_s"] <= r["t_device_s"]]
    assert after[-1]["t_device_s"] > move["t_rest_s"] + 0.5
    deviation = {r["t_device_s"]: abs(r["table_deg"] - move["to_deg"]) for r in after}
    # at rest from t_rest_s on (the true top angle, ringing included); still ringing at the stop
    assert max(d for t, d in deviation.items() if t >= move["t_rest_s"]) <= move["rest_threshold_deg"]
    ringing = [d for t, d in deviation.items() if t < move["t_end_s"] + 0.2]
    assert max(ringing) > 100 * move["rest_threshold_deg"]
    assert [s for _, s, _ in states] == [b"28"] * (len(states) - 1) + [b"33"]  # MOVING, then READY
    # each answer was made between the device times before asking and after the reply
    assert states[0][0] <= move["t_start_s"] + 1.0 and states[-2][0] < move["t_end_s"] <= states[-1][2]
    def planned_deg(t: float) -> float:  # the trapezoid from the flags, written out here
        tau = min(max(t - move["t_start_s"], 0.0), 18.5)
        ramp = min(tau, 0.5)
        out = 0.5 * 10.0 * ramp**2 + 5.0 * max(0.0, min(tau, 18.0) - 0.5)
        return out + max(0.0, tau - 18.0) * 5.0 - 0.5 * 10.0 * max(0.0, tau - 18.0) ** 2

    def planned_rate_dps(t: float) -> float:
        tau = min(max(t - move["t_start_s"], 0.0), 18.5)
        return min(10.0 * tau, 5.0, 10.0 * (18.5 - tau))

    def encoder_deg(t: float) -> float:  # motor side: plan + ripple e = A·sin(2π·p/λ)·v/V, A = r·λ/2π
        p = planned_deg(t)
        amplitude_deg = ripple_pct / 100.0 * ripple_period_deg / (2.0 * np.pi)
        return p + amplitude_deg * np.sin(2.0 * np.pi * p / ripple_period_deg) * planned_rate_dps(t) / 5.0

    during = [(a, b, p) for a, b, p in positions if move["t_start_s"] < a and b < move["t_end_s"]]
    # how many replies fall inside the 18.5 device s is host time (1.85 s wall at 10×: ~100 on a quiet
    # host, a few at load 15 on 2 cores); two suffice to see TP advance
    assert len(during) >= 2 and (np.diff([p for _, _, p in during]) > 0).all()
    for a, b, p in during:  # TP is the encoder (1e-4° steps) at a device time between a and b
        assert encoder_deg(a) - 1e-4 <= p <= encoder_deg(b) + 1e-4, (a, b, p, planned_deg(a))
    assert positions[-1][2] == pytest.approx(90.0, abs=1e-4)


def test_one_degree_per_second_homing_and_move(tmp_path):
    """--stage-speed 1 (default acceleration 80 °/s²): homing from the default power-on angle
    137.2345° takes 137.2345 + 1/80 s, a 45° move 45 + 1/80 s of device time; the controller stays
    HOMING (1E) / MOVING (28) until then."""
    truth = tmp_path / "truth.jsonl"
    cfg = SimConfig(seed=1, time_scale=50.0, accel_enabled=False, truth_log=str(truth), stage_speed_dps=1.0)
    sim = Simulator(cfg)
    try:
        ep = sim.start()
        stage = serial.Serial(ep["turntable"], 57600, timeout=30.0)  # host bound only: a reply comes

        def state() -> tuple[float, bytes, float]:  # device time before asking, state, after the reply
            t_before = sim.now()
            stage.write(b"1TS\r\n")
            return t_before, stage.readline().strip()[-2:], sim.now()

        def wait_ready() -> list[tuple[float, bytes]]:
            seen = [state()]
            while seen[-1][1] not in (b"32", b"33"):
                time.sleep(0.02)
                seen.append(state())
            return seen

        stage.write(b"1OR\r\n")
        homing = wait_ready()
        stage.write(b"1PA45\r\n")
        moving = wait_ready()
        stage.close()
    finally:
        sim.stop()
    home, move = [e for e in _events(truth) if e["event"] == "move"]
    assert home["t_end_s"] - home["t_start_s"] == pytest.approx(137.2345 + 1.0 / 80.0, abs=1e-9)
    assert move["t_end_s"] - move["t_start_s"] == pytest.approx(45.0 + 1.0 / 80.0, abs=1e-9)
    for seen, busy, ready, plan in ((homing, b"1E", b"32", home), (moving, b"28", b"33", move)):
        assert [s for _, s, _ in seen] == [busy] * (len(seen) - 1) + [ready]
        # the controller answered at a device time between before and after: busy before the
        # plan's end, ready at or after it
        assert seen[-2][0] < plan["t_end_s"] <= seen[-1][2]
        assert len(seen) >= 2  # polled while busy (how often is host time: ~every 20 ms when quiet)


def test_gnss_link_latency_and_hold_never_lose_or_reorder_epochs():
    """--link-latency gnss=300:0 --link-hold 3,150 on the vehicle: every epoch arrives whole and in
    order (GGA, RMC, VTG; UTC steps of 0.1 s, checksums good) and none before 300 ms of device time
    after its own UTC (the epoch's device time is its UTC minus gnss_start_utc)."""
    cfg = SimConfig(scenario="vehicle", seed=3, time_scale=2.0, gnss_link_latency_ms=300.0,
                    link_hold_period_s=3.0, link_hold_ms=150.0)
    sim = Simulator(cfg)
    try:
        ep = sim.start()
        reader = _Reader(ep["gnss"], sim)
        reader.start()
        sim.run_for(8.0)
        reader.finish()
    finally:
        sim.stop()
    lines, t_arrival, buf = [], [], b""
    for _, t_dev, chunk in reader.chunks:
        buf += chunk
        *done, buf = buf.split(b"\r\n")
        lines += done
        t_arrival += [t_dev] * len(done)
    assert len(lines) >= 3 * 50
    for line in lines:
        body, star, checksum = line[1:].partition(b"*")
        assert line[:1] == b"$" and star and int(checksum, 16) == _xor(body)
    kinds = [line[3:6] for line in lines]
    first = kinds.index(b"GGA")
    whole = len(kinds[first:]) // 3 * 3
    assert kinds[first:first + whole] == [b"GGA", b"RMC", b"VTG"] * (whole // 3)
    gga = [(line, t) for line, t in zip(lines, t_arrival, strict=True) if line[3:6] == b"GGA"]
    t_utc = np.array([_hhmmss_s(line.split(b",")[1]) - 12 * 3600.0 for line, _ in gga])  # start 12:00:00
    assert np.allclose(np.diff(t_utc), 0.1, atol=1e-6)
    assert (np.array([t for _, t in gga]) - t_utc >= 0.3).all()


def _xor(body: bytes) -> int:
    out = 0
    for b in body:
        out ^= b
    return out


def _hhmmss_s(field: bytes) -> float:
    text = field.decode()
    return int(text[:2]) * 3600.0 + int(text[2:4]) * 60.0 + float(text[4:])


def test_new_flags_refuse_bad_values_in_one_line(capsys):
    from firmware_sim.cli import main

    for argv, names in ((["--imu-axes", "xw"], "imu_axes"), (["--link-hold", "5"], "--link-hold"),
                        (["--link-latency", "10,20"], "--link-latency"),
                        (["--link-latency", "imu=1:0,can=2"], "--link-latency"),
                        (["--stage-speed", "0"], "stage_speed_dps"),
                        (["--stage-accel", "-3"], "stage_accel_dps2"),
                        (["--fault", "imu-invalid-rate=1.5"], "imu-invalid-rate")):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and names in err and "Traceback" not in err, err
    with pytest.raises(ConfigError, match="link_hold_ms"):
        SimConfig(link_hold_ms=100.0)
    with pytest.raises(ConfigError, match="jitter"):
        SimConfig(imu_link_latency_ms=5.0, imu_link_jitter_ms=6.0)


class _Sink:
    """A port stand-in for the link's own unit test: records what is written."""

    def __init__(self) -> None:
        self.data = bytearray()

    def write(self, data: bytes) -> None:
        self.data += data


def test_link_shaper_keeps_order_loses_nothing_and_holds_on_the_wall_clock():
    """The link alone, with a fake wall clock: latency 50 ± 20 ms at 1000 messages/s never
    reorders and never releases a message before t + 30 ms or after t + 70 ms (plus the pump step);
    a hold of 0.3 wall s every 1 device s releases nothing until the wall clock has moved on."""
    from firmware_sim.link import LinkShaper, LinkSpec

    wall = [0.0]
    link = LinkShaper(LinkSpec(latency_s=0.05, jitter_s=0.02, hold_period_s=1.0, hold_wall_s=0.3),
                      np.random.default_rng(0), wall_clock=lambda: wall[0])
    sink, step_s = _Sink(), 0.005
    released_at: dict[int, float] = {}
    for i in range(1, 800):  # to 3.995 device s in pump steps of 5 ms; 5 messages per step
        t = i * step_s
        k = np.arange((i - 1) * 5, i * 5)
        link.send_many(b"".join(int(v).to_bytes(4, "big") for v in k), np.full(5, 4), (k + 1) / 1000.0)
        before = len(sink.data)
        link.pump(t, sink)
        for j in range(before // 4, len(sink.data) // 4):
            released_at[j] = t
        wall[0] += step_s / 2.0  # the wall runs at half device speed (time scale 2)
    got = np.frombuffer(bytes(sink.data), dtype=">u4")
    assert (got == np.arange(len(got))).all()  # in order, none lost or doubled
    assert link.queued_bytes == 4 * (3995 - len(got)) and len(got) > 3900
    t_made = (np.arange(len(got)) + 1) / 1000.0
    lag = np.array([released_at[j] for j in range(len(got))]) - t_made
    assert link.holds == 3  # at 1, 2 and 3 device s; each 0.3 wall s = 0.6 device s here
    clear = np.ones(len(got), dtype=bool)  # due (t + 30…70 ms) outside every hold
    for start in (1.0, 2.0, 3.0):
        clear &= (t_made + 0.07 + step_s < start) | (t_made + 0.03 > start + 0.6 + step_s)
    assert lag.min() >= 0.03 and lag[clear].max() <= 0.07 + step_s
    assert lag.max() >= 0.6 - 0.07  # a held message waited out the hold
