"""firmware_sim scenarios (bench, ship, vehicle) and the truth log, through real ptys and pyserial.

The ship and vehicle runs are the simulator issues 5 and 6 build on; the truth log is how a
northfinder run (which cannot import firmware_sim) finds the truth at the device time of its
result, so its time alignment is tested to the sample: a client that opens the IMU port at a
random moment maps its first frame to the log's `imu_connect` k0, and the attitude the gyro
integrates to agrees with the logged truth at those device times — and not one sample off.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import math
import os
import random
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial
from helpers import advance_and_read

from firmware_sim.cli import build_parser, config_from_args, parse_sway
from firmware_sim.config import REFERENCE_SWAY, ConfigError, SimConfig
from firmware_sim.simulator import Simulator, build_world
from northfinder.codecs.kvh import HEADER, KvhDecoder
from northfinder.codecs.nmea import LocalEnu, NmeaDecoder, fixes_to_arrays
from northfinder.constants import OMEGA_EARTH_RAD_S, STANDARD_GRAVITY_M_S2, normal_gravity_m_s2
from northfinder.rotations import coning_corrected_rotvec, dcm_from_euler, euler_from_dcm, rotvec_to_dcm

ROOT = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def _run(*args: str) -> subprocess.Popen[bytes]:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-m", "firmware_sim", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _wait_device_time(sim: Simulator, timeout_s: float = 60.0) -> None:
    """Until the loop has started device time (the vehicle holds it at 0 until a client connects)."""
    deadline = time.monotonic() + timeout_s
    while sim.now() == 0.0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sim.now() > 0.0, "device time never started"


def _read_exact(port: serial.Serial, n_bytes: int, timeout_s: float = 60.0) -> bytes:
    out = bytearray()
    port.timeout = 0.5
    deadline = time.monotonic() + timeout_s
    while len(out) < n_bytes and time.monotonic() < deadline:
        out += port.read(min(n_bytes - len(out), 1 << 16))
    assert len(out) == n_bytes, f"read {len(out)} of {n_bytes} bytes"
    return bytes(out)


def _truth_log(path: Path) -> tuple[dict, list[dict], dict[str, np.ndarray]]:
    """(header, events, rows as arrays keyed by field) of a truth log."""
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert lines[0]["type"] == "header" and lines[0]["format"] == "firmware_sim truth log"
    events = [x for x in lines if x["type"] == "event"]
    rows = [x for x in lines if x["type"] == "truth"]
    t_all = [x["t_device_s"] for x in lines[1:]]
    assert t_all == sorted(t_all), "lines are in device-time order"
    cols = {k: np.array([r[k] for r in rows], dtype=float) for k in lines[0]["fields"]}
    return lines[0], events, cols


def _first_frame_k(events: list[dict], first_sequence: int) -> tuple[int, dict]:
    """docs/simulator.md: the client's first frame is k0 + ((its sequence − sequence0) mod 128)."""
    connects = [e for e in events if e["event"] == "imu_connect"]
    assert len(connects) == 1, connects
    e = connects[0]
    return e["k0"] + (first_sequence - e["sequence0"]) % 128, e


# ---------------------------------------------------------------------------------------------
# the command
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("argv, keys", [
    (["--scenario", "ship", "--sway", "roll=10:8,pitch=5:6,yaw=3:10,heave=0.5:7", "--lever-arm", "1,2,1.5"],
     {"imu"}),
    (["--scenario", "vehicle", "--lever-arm", "0.5,1.5,1.2", "--imu-rate", "250"],
     {"imu", "gnss", "gnss_start_utc"}),
])
def test_scenario_starts_from_the_command_prints_endpoints_and_writes_a_truth_log(argv, keys, tmp_path):
    log_path = tmp_path / "truth.jsonl"
    proc = _run(*argv, "--seed", "3", "--time-scale", "5", "--truth-log", str(log_path))
    try:
        ready, _, _ = select.select([proc.stdout], [], [], 30.0)
        assert ready, "firmware-sim printed nothing"
        ep = json.loads(proc.stdout.readline())
        assert set(ep) == keys and all(os.path.exists(ep[k]) for k in keys if k != "gnss_start_utc")
        if "gnss_start_utc" in ep:
            assert ep["gnss_start_utc"] == "2026-11-22T12:00:00Z"
        header = json.loads(log_path.read_text().splitlines()[0])  # written before the endpoints
        assert header["scenario"] == argv[1] and header["seed"] == 3 and header["endpoints"] == ep
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=20) == 0
        assert proc.stderr.read() == b""
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    lines = [json.loads(x) for x in log_path.read_text().splitlines()]
    assert lines[-1]["type"] == "event" and lines[-1]["event"] == "end"  # closed at exit


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------
def test_scenario_defaults_flags_and_toml():
    ship = SimConfig(scenario="ship")
    assert ship.sway == REFERENCE_SWAY and ship.imu_lever_arm_m == (1.0, 2.0, 1.5)
    assert ship.latitude_deg == 40.0 and ship.imu_rate_hz == 1000
    vehicle = SimConfig(scenario="vehicle")
    assert vehicle.imu_rate_hz == 250 and vehicle.gnss_lever_arm_m == (0.5, 1.5, 1.2)
    bench = SimConfig()
    assert (bench.scenario, bench.latitude_deg, bench.imu_rate_hz, bench.imu_lever_arm_m, bench.sway) == \
        ("bench", 45.0, 1000, (0.0, 0.0, 0.0), None)
    args = build_parser().parse_args(["--scenario", "vehicle", "--lever-arm", "0.4,1,1.3", "--imu-rate",
                                      "100", "--truth-log", "t.jsonl", "--truth-rate", "200"])
    cfg = config_from_args(args)
    assert cfg.gnss_lever_arm_m == (0.4, 1.0, 1.3) and cfg.imu_lever_arm_m == (0.0, 0.0, 0.0)
    assert (cfg.imu_rate_hz, cfg.truth_log, cfg.truth_rate_hz) == (100, "t.jsonl", 200.0)
    cfg = config_from_args(build_parser().parse_args(["--scenario", "ship", "--lever-arm", "0,1,2"]))
    assert cfg.imu_lever_arm_m == (0.0, 1.0, 2.0)
    assert parse_sway("roll=2:8:30, roll=1:3,heave=0.2:7") == {"roll": [[2, 8, 30], [1, 3]],
                                                                "heave": [[0.2, 7]]}
    assert parse_sway("none") == {} and SimConfig(scenario="ship", sway={}).sway == {}
    for bad in ("roll=abc", "roll=1", "roll=1:0", "wobble=1:2", "roll=1:2:3:4"):
        with pytest.raises(ConfigError, match="--sway"):
            parse_sway(bad)
    with pytest.raises(ConfigError, match="scenario"):
        SimConfig(scenario="boat")
    with pytest.raises(ConfigError, match="gnss_start_utc"):
        SimConfig(scenario="vehicle", gnss_start_utc="noon")
    with pytest.raises(ConfigError, match="gnss_rate_hz"):
        SimConfig(scenario="vehicle", gnss_rate_hz=3)


def test_ship_phases_come_from_the_seed_unless_given():
    def phases(**kw):
        world = build_world(SimConfig(scenario="ship", **kw))
        return [t.phase_deg for axis in ("roll", "pitch", "yaw", "heave")
                for t in getattr(world.platform, axis)]

    a, b, c = phases(seed=1), phases(seed=1), phases(seed=2)
    assert a == b and a != c and all(0.0 <= p < 360.0 for p in a)
    given = phases(seed=1, sway={"roll": [[10.0, 8.0, 33.0]], "heave": [[0.5, 7.0]]})
    assert given[0] == 33.0 and 0.0 <= given[1] < 360.0
    # the bench keeps its old behaviour: phase 0 unless given
    bench = build_world(SimConfig(sway={"roll": [[2.0, 8.0]]}))
    assert bench.platform.roll[0].phase_deg == 0.0


def test_gnss_faults_reach_the_receiver():
    faults = ["gnss-bad-checksum-rate=0.1", "gnss-truncate-rate=0.05", "gnss-nofix=30:5"]
    sim = Simulator(SimConfig(scenario="vehicle", faults=faults))
    sim._build()
    try:
        gnss = sim.gnss
        assert (gnss.bad_checksum_rate, gnss.truncate_rate, gnss.nofix) == (0.1, 0.05, (30.0, 5.0))
        assert sim.turntable is None and sim.accelerometer is None
        assert set(sim.endpoints) == {"imu", "gnss", "gnss_start_utc"}
    finally:
        sim.stop()


# ---------------------------------------------------------------------------------------------
# the bench is unchanged by all this
# ---------------------------------------------------------------------------------------------
BENCH_DIGESTS = {
    # sha256 of the IMU bytes a client connected from power-on receives, computed with the code of
    # commit 9ea6fec (before the scenarios existed) by this same harness
    "default": ({}, "485caf310360087d0cd807d9b96e404ec25a9b1e0183cdc261ff379dd25e723e", 95328),
    "kvh1760_tilt": (dict(grade="kvh1760", heading_deg=30.0, pitch_deg=1.0, roll_deg=-2.0, latitude_deg=40.0,
                          seed=7), "3203153eef800675b9de8b6bd3d33a243705ac6f90cbfe6fa5ec4752a72f36b9", 95328),
    "rate250_lever": (dict(imu_rate_hz=250, imu_lever_arm_m=(0.1, 0.2, 0.3), seed=3),
                      "49031bcbf28b791a36a09275e940e1428589dd0921199695f0047b44fe9a0b47", 23832),
}


MOTION_TERMS_OFF = dict(stage_ripple_pct=0.0, stage_wobble_urad=0.0, gyro_sf_asymmetry_ppm=0.0,
                        gyro_g_sensitivity_dph_g=0.0)
"""Issue 13's motion terms (on by default since) switched off: the bytes are those from before."""


@pytest.mark.parametrize("name", sorted(BENCH_DIGESTS))
def test_bench_without_the_new_flags_sends_the_same_bytes_as_before(name):
    kw, digest, n_bytes = BENCH_DIGESTS[name]
    sim = Simulator(SimConfig(accel_enabled=False, **MOTION_TERMS_OFF, **kw))
    sim._build()  # no loop thread: the device times are chosen here, with a table move in between
    try:
        client = serial.Serial(sim.imu.endpoint(), 921600, timeout=0.2)
        out = bytearray()
        t = 0.0
        for k, dt in enumerate(np.tile([0.0137, 0.05, 0.0011, 0.2], 10)):
            t += dt
            if k == 12:
                sim.world.table.command_move(t, np.deg2rad(90.0))
            advance_and_read(sim, client, t, out)
        while chunk := client.read(65536):
            out += chunk
        client.close()
    finally:
        sim.stop()
    assert len(out) == n_bytes and hashlib.sha256(bytes(out)).hexdigest() == digest


# ---------------------------------------------------------------------------------------------
# ship: reference sway through the pty, and the truth log's time alignment
# ---------------------------------------------------------------------------------------------
SHIP_RATE_HZ = 1000
SHIP_SECONDS = 24.0  # three roll periods, four pitch periods


@pytest.fixture(scope="module")
def ship_run(tmp_path_factory):
    """The reference ship (nav grade), a pyserial client that opens the IMU at a random moment."""
    log_path = tmp_path_factory.mktemp("ship") / "truth.jsonl"
    # the whole run fits the IMU's backlog (by default the simulator keeps 1 s of wall time for a
    # client that stops reading): this reader shares its process with the simulator, and at load
    # 5-10 on 2 cores it stalled longer and lost bytes — an overrun, which these tests are not about
    cfg = SimConfig(scenario="ship", seed=5, heading_deg=57.0, time_scale=10.0, truth_log=str(log_path),
                    truth_rate_hz=SHIP_RATE_HZ, client_stall_wall_s=1.0 + SHIP_SECONDS / 10.0)
    n = int(SHIP_SECONDS * SHIP_RATE_HZ)
    with Simulator(cfg) as ep:
        time.sleep(random.Random(20261122).uniform(0.3, 1.2))  # some moment after the endpoints
        port = serial.Serial(ep["imu"], 921600)
        try:
            raw = _read_exact(port, 36 * n)
        finally:
            port.close()
    decoder = KvhDecoder()
    frames = decoder.feed(raw)
    header, events, rows = _truth_log(log_path)
    return cfg, raw, frames, decoder.stats, header, events, rows


def test_ship_client_starts_on_a_frame_boundary_and_maps_to_k0(ship_run):
    cfg, raw, frames, stats, header, events, rows = ship_run
    assert raw[:4] == HEADER and stats.skipped_bytes == 0 and stats.lost_samples == 0
    assert len(frames) == int(SHIP_SECONDS * SHIP_RATE_HZ) and (frames.frames["status"] == 0x77).all()
    k_first, e = _first_frame_k(events, int(frames.frames["sequence"][0]))
    assert k_first == e["k0"]  # nothing lost between the connect and the client's first read
    assert e["sequence0"] == (e["k0"] - 1) % 128 and e["t0_device_s"] == pytest.approx(e["k0"] / SHIP_RATE_HZ)
    assert header["imu"]["lever_arm_b_m"] == [1.0, 2.0, 1.5] and set(header["sway"]) == set(REFERENCE_SWAY)


def _strapdown(c0: np.ndarray, dtheta: np.ndarray, latitude_deg: float) -> np.ndarray:
    """C_b^n after each interval: C_k = Rz(Ωe·dt about the Earth axis)ᵀ-corrected C_{k−1}·exp(φ_k),
    φ_k the coning-corrected rotation vector (northfinder's own rotations, not firmware_sim's)."""
    lat = math.radians(latitude_deg)
    w_ie = OMEGA_EARTH_RAD_S * np.array([0.0, math.cos(lat), math.sin(lat)])
    c_nn = rotvec_to_dcm(-w_ie / SHIP_RATE_HZ)  # the n frame turns with the Earth
    steps = rotvec_to_dcm(coning_corrected_rotvec(dtheta))
    out = np.empty((len(dtheta), 3, 3))
    c = c0
    for k in range(len(dtheta)):
        c = c_nn @ c @ steps[k]
        out[k] = c
    return out


def test_ship_truth_log_alignment_is_exact_to_the_sample(ship_run):
    """Integrated gyro attitude vs the logged truth at t(k) = t0 + (k − k0)/rate: agreement far
    inside what a one-sample shift of the time axis would cost, and that shift visibly worse."""
    cfg, raw, frames, stats, header, events, rows = ship_run
    k_first, e = _first_frame_k(events, int(frames.frames["sequence"][0]))
    index = frames.sample_index - frames.sample_index[0]  # the driver's numbering, from 0
    dtheta = frames.frames["gyro"].astype(float)
    t_row = np.round(rows["t_device_s"] * SHIP_RATE_HZ).astype(int)  # truth rows at every sample
    assert (np.diff(t_row) == 1).all()

    def truth_at(k: np.ndarray) -> np.ndarray:  # rows at the end times of samples k
        i = e["t0_device_s"] * SHIP_RATE_HZ + (k - e["k0"]) - t_row[0]
        i = np.round(i).astype(int)
        return np.stack([rows["heading_deg"][i], rows["pitch_deg"][i], rows["roll_deg"][i]], axis=-1)

    def error_deg(shift: int) -> float:
        k = k_first + index + shift
        start = truth_at(np.array([k[0] - 1]))[0]  # attitude at the start of the first interval
        c0 = dcm_from_euler(*np.radians(start))
        c = _strapdown(c0, dtheta, cfg.latitude_deg)
        hpr = np.degrees(np.stack(euler_from_dcm(c), axis=-1))
        d = hpr - truth_at(k)
        d[:, 0] = (d[:, 0] + 180.0) % 360.0 - 180.0
        return float(np.sqrt(np.mean(d**2)))

    # what one sample of misalignment costs: the rms change of the truth attitude in one sample
    k_all = k_first + index[1:]
    step = truth_at(k_all) - truth_at(k_all - 1)
    step[:, 0] = (step[:, 0] + 180.0) % 360.0 - 180.0
    one_sample_deg = float(np.sqrt(np.mean(step**2)))
    errors = {s: error_deg(s) for s in (-1, 0, 1)}
    print(f"\nship alignment: rms attitude error {errors} deg; one sample of motion {one_sample_deg:.5f} deg")
    assert errors[0] < 0.25 * one_sample_deg
    assert errors[-1] > 0.5 * one_sample_deg and errors[1] > 0.5 * one_sample_deg

    # the gyro's integrated roll follows the configured sway: 10° at 8 s (and its logged phase)
    k = k_first + index
    t = e["t0_device_s"] + (k - e["k0"]) / SHIP_RATE_HZ
    c = _strapdown(dcm_from_euler(*np.radians(truth_at(np.array([k[0] - 1]))[0])), dtheta, cfg.latitude_deg)
    roll = np.degrees(euler_from_dcm(c)[2])
    amp, period, phase = header["sway"]["roll"][0]
    w = 2.0 * math.pi / period
    a = np.column_stack([np.sin(w * t), np.cos(w * t), np.ones_like(t)])
    s, co, mean = np.linalg.lstsq(a, roll, rcond=None)[0]
    print(f"ship roll from the gyro: amplitude {math.hypot(s, co):.4f} deg (configured {amp}), phase "
          f"{math.degrees(math.atan2(co, s)) % 360.0:.3f} deg (logged {phase:.3f}), mean {mean:+.4f} deg")
    assert amp == 10.0 and period == 8.0
    assert math.hypot(s, co) == pytest.approx(amp, abs=0.01)  # 0.1 % of it: far above the errors above
    assert (math.degrees(math.atan2(co, s)) - phase + 180.0) % 360.0 - 180.0 == pytest.approx(0.0, abs=0.06)


def test_ship_mean_specific_force_over_whole_sway_periods_is_gravity(ship_run):
    """|f| = |a − g| for the IMU point; its mean over the window is normal gravity up to the
    window's mean vertical acceleration (≤ 2·v_max/T) and the second-order a²/(2g) term; and it
    is what the logged motion of the IMU point gives, to within the accelerometer's own errors."""
    cfg, raw, frames, stats, header, events, rows = ship_run
    accel_m_s2 = frames.frames["accel"].astype(float) * STANDARD_GRAVITY_M_S2
    g = float(normal_gravity_m_s2(cfg.latitude_deg))
    mag = np.linalg.norm(accel_m_s2, axis=1)
    # bounds of the motion from the configured sway (amplitudes × ω, × ω²) and the lever arm
    ang = [(math.radians(a), 2 * math.pi / p) for axis in ("roll", "pitch", "yaw")
           for a, p, _ in header["sway"][axis]]
    heave = [(a, 2 * math.pi / p) for a, p, _ in header["sway"]["heave"]]
    r = float(np.linalg.norm(header["imu"]["lever_arm_b_m"]))
    w_max = sum(a * w for a, w in ang)
    v_max = sum(a * w for a, w in heave) + w_max * r
    a_max = sum(a * w * w for a, w in heave) + sum(a * w * w for a, w in ang) * r + w_max**2 * r
    t_window = len(mag) / SHIP_RATE_HZ
    bound = 2.0 * v_max / t_window + a_max**2 / (2.0 * g)
    print(f"\nship: mean |f| {mag.mean():.5f} m/s², normal gravity {g:.5f}, bound {bound:.4f} "
          f"(sway makes |f| swing by {np.ptp(mag):.3f})")
    assert np.ptp(mag) > 0.3  # the ship does move the accelerometer
    assert abs(mag.mean() - g) < bound

    # sharper: |a^n + 2ω_ie × v^n − g^n| from the logged IMU velocity at the aligned device times
    k_first, e = _first_frame_k(events, int(frames.frames["sequence"][0]))
    k = k_first + frames.sample_index - frames.sample_index[0]
    t_row = np.round(rows["t_device_s"] * SHIP_RATE_HZ).astype(int)
    i = np.round(e["t0_device_s"] * SHIP_RATE_HZ + (k - e["k0"])).astype(int) - t_row[0]
    vel = rows["imu_vel_enu_m_s"]
    acc = np.gradient(vel, 1.0 / SHIP_RATE_HZ, axis=0)
    lat = math.radians(cfg.latitude_deg)
    w_ie = OMEGA_EARTH_RAD_S * np.array([0.0, math.cos(lat), math.sin(lat)])
    f_n = acc + 2.0 * np.cross(w_ie, vel) + np.array([0.0, 0.0, g])
    # each message is the mean over its interval, the rows are at its end: use the interval's mid
    f_mid = 0.5 * (np.linalg.norm(f_n[i], axis=1) + np.linalg.norm(f_n[i - 1], axis=1))
    from firmware_sim.physics.sensors import ACCEL_PRESETS

    a = ACCEL_PRESETS[cfg.grade]
    ug = 1e-6 * STANDARD_GRAVITY_M_S2
    budget = (np.linalg.norm(a.bias_ug) + 3.0 * max(a.bias_instability_ug)) * ug \
        + max(np.abs(a.scale_factor_ppm)) * 1e-6 * g + 3.0 * max(a.noise_ug_rt_hz) * ug / math.sqrt(t_window)
    print(f"ship: mean |f| from the logged motion {f_mid.mean():.6f} m/s², measured {mag.mean():.6f}, "
          f"accelerometer error budget {budget:.6f}")
    assert abs(mag.mean() - f_mid.mean()) < budget


# ---------------------------------------------------------------------------------------------
# vehicle: NMEA from the GNSS pty follows the trajectory
# ---------------------------------------------------------------------------------------------
def test_vehicle_gnss_sentences_parse_and_follow_the_trajectory(tmp_path):
    log_path = tmp_path / "truth.jsonl"
    cfg = SimConfig(scenario="vehicle", seed=4, heading_deg=30.0, time_scale=20.0, truth_log=str(log_path))
    n_fixes = 260  # 26 s: still start, a speed-up to 10 m/s and the first S-turn
    with Simulator(cfg) as ep:
        port = serial.Serial(ep["gnss"], 115200, timeout=0.2)
        decoder = NmeaDecoder()
        fixes = []
        deadline = time.monotonic() + 60.0
        while len(fixes) < n_fixes and time.monotonic() < deadline:
            fixes += decoder.feed(port.read(4096))
        port.close()
    assert len(fixes) >= n_fixes, f"only {len(fixes)} fixes"
    assert decoder.stats.bad_checksum == decoder.stats.truncated == decoder.stats.no_fix == 0
    header, events, rows = _truth_log(log_path)
    ref = LocalEnu(header["enu_origin"]["latitude_deg"], header["enu_origin"]["longitude_deg"],
                   header["enu_origin"]["height_m"])
    arr = fixes_to_arrays(fixes, ref)
    t_dev = arr.time_s - dt.datetime.fromisoformat(header["gnss"]["start_utc"]).timestamp()  # UTC → device
    assert np.allclose(t_dev * 10, np.round(t_dev * 10), atol=1e-5)  # epochs on the 10 Hz grid
    t_dev = np.round(t_dev * 10) / 10  # (POSIX seconds as floats are only good to ~0.2 µs)
    # the trajectory, from the physics, at those device times
    from firmware_sim.physics.vehicle import VehicleTrajectory

    traj = VehicleTrajectory(heading0_deg=30.0)
    pos_truth, vel_truth = traj.antenna_enu(t_dev, header["gnss"]["lever_arm_b_m"])
    err = arr.pos_enu_m - pos_truth
    n = len(err)
    moved = float(np.ptp(pos_truth[:, 1]) + np.ptp(pos_truth[:, 0]))
    print(f"\nvehicle: {n} fixes over device {t_dev[0]:.1f}-{t_dev[-1]:.1f} s, moved {moved:.1f} m; "
          f"position error mean {err.mean(axis=0).round(3)} m, std {err.std(axis=0).round(3)} m")
    sigma = np.array([0.5, 0.5, 1.0])  # the receiver's white noise (issue 6)
    assert (np.abs(err) < 5.0 * sigma).all()
    assert (np.abs(err.mean(axis=0)) < 4.0 * sigma / math.sqrt(n)).all()
    assert (err.std(axis=0) < 1.5 * sigma).all() and (err.std(axis=0) > 0.5 * sigma).all()
    vel_err = arr.vel_enu_m_s[:, :2] - vel_truth[:, :2]  # NMEA has no vertical speed
    assert (np.abs(vel_err) < 5.0 * 0.05).all()
    # the truth log's antenna is the same point (what northfinder compares its result with)
    t_rows = rows["t_device_s"]
    i = np.minimum(np.searchsorted(t_rows, t_dev - 1e-9), len(t_rows) - 1)
    both = np.isclose(t_rows[i], t_dev, atol=1e-9, rtol=0.0)
    assert both.sum() > 0.9 * n  # the rows run at 50 Hz: every epoch has one
    assert np.allclose(rows["antenna_pos_enu_m"][i[both]], pos_truth[both], atol=1e-6)
    assert np.allclose(rows["antenna_vel_enu_m_s"][i[both]], vel_truth[both], atol=1e-6)


# ---------------------------------------------------------------------------------------------
# reconnects and configuration mode: the k ↔ device-time anchors
# ---------------------------------------------------------------------------------------------
def device_time_s(events: list[dict], k: np.ndarray) -> np.ndarray:
    """docs/simulator.md: sample k's interval ends at t_a + (k − k_a)/rate_a for the anchor
    (imu_connect: k0, t0_device_s; imu_grid: k_next, t_next_device_s) with the largest k_a ≤ k
    (the later one in the file on a tie)."""
    anchors = [(e["k0"], e["t0_device_s"], e["rate_hz"]) if e["event"] == "imu_connect"
               else (e["k_next"], e["t_next_device_s"], e["rate_hz"])
               for e in events if e["event"] in ("imu_connect", "imu_grid")]
    k = np.asarray(k)
    out = np.full(k.shape, np.nan)
    best = np.full(k.shape, -1)
    for ka, ta, rate in anchors:  # file order: a later anchor with the same k_a wins
        use = (ka <= k) & (ka >= best)
        out[use] = ta + (k[use] - ka) / rate
        best[use] = ka
    return out


def test_reconnect_and_config_mode_keep_the_time_map_exact(tmp_path):
    """Client A reads, puts the IMU in configuration mode for a while (the grid moves on without
    samples), reads again and leaves; client B connects later. Every frame's gyro increment equals
    the world's over the interval the anchors give — and not over the interval next to it."""
    log_path = tmp_path / "truth.jsonl"
    cfg = SimConfig(scenario="ship", seed=8, time_scale=10.0, truth_log=str(log_path))
    with Simulator(cfg) as ep:
        _ = time.sleep(0.2)
        a = serial.Serial(ep["imu"], 921600)
        raw_a = _read_exact(a, 36 * 1500)
        a.write(b"=CONFIG,1\n")
        time.sleep(0.3)  # about 3 s of device time without samples
        a.write(b"=CONFIG,0\n")
        raw_a += a.read(a.in_waiting)  # what was on its way before the configuration mode
        raw_a += _read_exact(a, 36 * 1500)
        a.close()
        time.sleep(0.3)
        b = serial.Serial(ep["imu"], 921600)
        raw_b = _read_exact(b, 36 * 1000)
        b.close()
    header, events, rows = _truth_log(log_path)
    names = [e["event"] for e in events]
    links = [n for n in names if n in ("imu_connect", "imu_disconnect")]
    assert links[:3] == ["imu_connect", "imu_disconnect", "imu_connect"] and len(links) <= 4  # B's close too
    assert names.count("imu_grid") == 1 and names[-1] == "end"
    connect_a, connect_b = (e for e in events if e["event"] == "imu_connect")
    world = build_world(cfg)
    dt_s = 1.0 / SHIP_RATE_HZ
    lever = header["imu"]["lever_arm_b_m"]
    residual, shifted = [], []
    for raw, connect in ((raw_a, connect_a), (raw_b, connect_b)):
        decoder = KvhDecoder()
        frames = decoder.feed(raw)
        echoes = len(b"CONFIG,1\r\nCONFIG,0\r\n") if raw is raw_a else 0  # =CONFIG echoed (KVH manual §7)
        assert raw[:4] == HEADER and decoder.stats.skipped_bytes == echoes and decoder.pending_bytes < 36
        k = connect["k0"] + (int(frames.frames["sequence"][0]) - connect["sequence0"]) % 128 \
            + frames.sample_index - frames.sample_index[0]
        t_end = device_time_s(events, k)
        measured = frames.frames["gyro"].astype(float)
        # contiguous runs of device time → one World.increments call each
        cut = np.flatnonzero(np.abs(np.diff(t_end) - dt_s) > 1e-9) + 1
        for lo, hi in zip(np.r_[0, cut], np.r_[cut, len(t_end)], strict=True):
            n = hi - lo
            truth, _ = world.increments(t_end[lo] - 2 * dt_s, n + 2, dt_s, lever)  # one extra each side
            residual.append(measured[lo:hi] - truth[1:-1])
            shifted.append(measured[lo:hi] - truth[2:])
        if connect is connect_a:
            assert len(cut) == 1 and t_end[cut[0]] - t_end[cut[0] - 1] > 1.0  # the configuration gap
    disconnect = next(e for e in events if e["event"] == "imu_disconnect")
    assert disconnect["k_last"] >= connect_a["k0"] + 3000 - 1 and connect_b["k0"] > disconnect["k_last"]
    rms = float(np.sqrt(np.mean(np.concatenate(residual) ** 2)))
    rms_shift = float(np.sqrt(np.mean(np.concatenate(shifted) ** 2)))
    from firmware_sim.physics.sensors import GYRO_PRESETS

    # the residual is the gyro's white noise, σ = N·√dt (ARW in rad/√s); the other errors of the
    # grade are far below it per sample (bias 0.004 °/h·1 ms ≈ 2e-11 rad, 1 ppm of 1e-4 rad)
    sigma = max(GYRO_PRESETS[cfg.grade].arw_deg_rt_h) * math.pi / 180.0 / 60.0 * math.sqrt(dt_s)
    print(f"\nreconnect/config: gyro increment vs world rms {rms:.3e} rad (white noise σ {sigma:.3e}); "
          f"one sample off {rms_shift:.3e} rad")
    assert rms < 1.1 * sigma and rms_shift > 2.0 * sigma


def test_bench_truth_rows_follow_the_table_while_it_homes(tmp_path):
    """Bench rows: the stator's attitude as configured, the top's heading = ψ − α (level stator,
    C_b^n = Rz(−ψ)·Rz(α)), α from the power-on angle to 0 while the stage homes over its pty."""
    log_path = tmp_path / "truth.jsonl"
    cfg = SimConfig(heading_deg=37.0, accel_enabled=False, time_scale=20.0, truth_log=str(log_path),
                    stage_power_on_deg=100.0)
    with Simulator(cfg) as ep:
        stage = serial.Serial(ep["turntable"], 57600, timeout=2.0)
        stage.write(b"1OR\r\n")
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline:  # until READY from homing (32)
            stage.write(b"1TS\r\n")
            if stage.readline().strip().endswith(b"32"):
                break
            time.sleep(0.05)
        stage.close()
    header, events, rows = _truth_log(log_path)
    assert header["fields"][-5:] == ["platform_heading_deg", "platform_pitch_deg", "platform_roll_deg",
                                     "table_deg", "table_encoder_deg"]
    assert np.allclose(rows["platform_heading_deg"], 37.0) and np.allclose(rows["platform_pitch_deg"], 0.0)
    alpha = rows["table_deg"]
    assert alpha[0] == pytest.approx(100.0) and abs(alpha[-1]) < 0.05  # homed (ringing dies out)
    assert np.ptp(alpha) > 99.0
    # the stage's default wobble (a1, a2 µrad once and twice per turn) tilts the top by
    # |a1·e^{iα} + a2·e^{2iα}| and moves its heading only to second order in that tilt
    from firmware_sim.config import STAGE_WOBBLE_URAD

    a1, a2 = np.asarray(STAGE_WOBBLE_URAD) * 1e-6
    tilt_rad = np.sqrt(a1**2 + a2**2 + 2 * a1 * a2 * np.cos(np.radians(alpha)))
    row_tilt_rad = np.arccos(np.cos(np.radians(rows["pitch_deg"])) * np.cos(np.radians(rows["roll_deg"])))
    assert np.allclose(row_tilt_rad, tilt_rad, rtol=1e-3, atol=1e-9)
    atol_deg = 1e-9 + np.degrees(float(np.max(tilt_rad)) ** 2)
    assert np.allclose((rows["heading_deg"] - (37.0 - alpha) + 180.0) % 360.0 - 180.0, 0.0, atol=atol_deg)
    encoder = rows["table_encoder_deg"]
    assert encoder[0] == pytest.approx(100.0, abs=1e-4)  # the homing began at t = 0 (sent at start)
    assert abs(encoder[-1] - alpha[-1]) < 0.01  # the top rings about the motor (≤ 0.005° here) then settles
    assert np.allclose(rows["imu_pos_enu_m"], 0.0) and np.allclose(rows["imu_vel_enu_m_s"], 0.0)
