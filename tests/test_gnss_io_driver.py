"""The Gnss driver on real ptys: golden sentences, firmware_sim's receiver on a driving vehicle
(decoded antenna positions and velocities against the trajectory's truth, at the noise the
receiver was given), faults counted and skipped, the replay path giving identical fixes, and
one-line errors that name the port."""

from __future__ import annotations

import time

import numpy as np
import pytest
from helpers import write_all

from firmware_sim.devices.gnss import GnssReceiver
from firmware_sim.physics.table import TableMotion
from firmware_sim.physics.vehicle import VehicleTrajectory
from firmware_sim.physics.world import Site, World
from northfinder.codecs.nmea import LocalEnu, fixes_to_arrays
from northfinder.drivers.gnss import Gnss, decode_nmea_log
from northfinder.errors import DeviceError

DURATION_S = 60.0
RATE_HZ = 10


def _run(rx: GnssReceiver, until_s: float, step_s: float = 1.0) -> None:
    """Advance the receiver's device time by hand, pushing its bytes into the pty as the client reads."""
    t = 0.0
    while t < until_s:
        t = min(t + step_s, until_s)
        rx.advance(t)
        deadline = time.monotonic() + 5.0
        while rx.port.pending and time.monotonic() < deadline:
            rx.port.flush()
            time.sleep(0.002)


def _drained(gnss: Gnss, rx: GnssReceiver, timeout_s: float = 5.0) -> None:
    """Wait until the driver has read every byte the receiver wrote."""
    deadline = time.monotonic() + timeout_s
    while gnss.stats.bytes < rx.port.bytes_written and time.monotonic() < deadline:
        time.sleep(0.005)
    assert gnss.stats.bytes == rx.port.bytes_written


@pytest.fixture(scope="module")
def drive():
    traj = VehicleTrajectory(duration_s=DURATION_S)
    world = World(Site(40.0, 100.0), traj, TableMotion(power_on_deg=0.0, ringing_amplitude_deg=None))
    return world, traj


def _truth_errors(rx: GnssReceiver, traj: VehicleTrajectory, fixes):
    ref = LocalEnu(rx.lat0_deg, rx.lon0_deg, rx.h0_m)
    a = fixes_to_arrays(fixes, ref)
    k = np.round((a.time_s - rx.start_utc.timestamp()) * RATE_HZ)  # epoch numbers from receiver UTC
    assert np.allclose(a.time_s - rx.start_utc.timestamp(), k / RATE_HZ, atol=1e-6)
    pos, vel = traj.antenna_enu(k / RATE_HZ, rx.lever_arm_b_m)  # the trajectory's own antenna truth
    return a.pos_enu_m - pos, a.vel_enu_m_s[:, :2] - vel[:, :2]


def _check_white(err: np.ndarray, sigma: np.ndarray) -> None:
    """Errors are white with the given σ: mean within 4σ/√n, sample σ within 4 standard errors
    (σ·4/√(2n)), and no single error beyond 6σ (no gross decoding error hides in the average)."""
    n = len(err)
    assert n > 100
    assert np.all(np.abs(err.mean(axis=0)) < 4 * sigma / np.sqrt(n)), err.mean(axis=0)
    assert np.all(np.abs(err.std(axis=0) / sigma - 1) < 4 / np.sqrt(2 * n)), err.std(axis=0)
    assert np.all(np.abs(err) < 6 * sigma)


def test_golden_sentences_over_a_real_pty(pty_pair, golden):
    master, path = pty_pair
    good = golden["nmea"]["good"]
    with Gnss(path, wait_for_data=False) as gnss:
        write_all(master, "".join(golden["nmea"]["bad"]).encode())
        write_all(master, "".join(v["sentence"] for v in good).encode())
        (fix,) = gnss.read_fixes(1, timeout_s=5)
        deadline = time.monotonic() + 5
        while gnss.stats.no_fix == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        s = gnss.stats
    assert abs(fix.lat_deg - good[0]["lat_deg"]) < 1e-9 and abs(fix.lon_deg - good[0]["lon_deg"]) < 1e-9
    assert fix.alt_m == good[0]["alt_m"] and fix.num_sv == good[0]["num_sv"]
    assert s.fixes == 1 and s.no_fix == 1 and s.bad_checksum + s.truncated == len(golden["nmea"]["bad"])


def test_receiver_on_a_pty_matches_the_trajectory_truth_and_replays_identically(drive, tmp_path):
    world, traj = drive
    rx = GnssReceiver(world, rng=np.random.default_rng(2024))
    raw = tmp_path / "gnss.nmea"
    try:
        with Gnss(rx.endpoint(), raw_log=raw, wait_for_data=False) as gnss:
            _run(rx, DURATION_S)
            n = int(DURATION_S * RATE_HZ) + 1
            fixes = gnss.read_fixes(n, timeout_s=10)
            stats = gnss.stats
    finally:
        rx.close()
    assert len(fixes) == n and stats.fixes == n and stats.missed_epochs == 0
    assert stats.bad_checksum == stats.truncated == stats.no_fix == stats.garbage_bytes == 0
    pos_err, vel_err = _truth_errors(rx, traj, fixes)
    _check_white(pos_err, np.array([0.5, 0.5, 1.0]))
    _check_white(vel_err, np.array([0.05, 0.05]))
    # replay: the raw log decodes to the very same fixes and counters
    replayed, replay_stats = decode_nmea_log(raw.read_bytes())
    assert replayed == fixes and replay_stats == stats
    assert decode_nmea_log(raw.read_text("latin-1"))[0] == fixes


def test_faults_are_counted_and_skipped_on_the_wire(drive, tmp_path):
    world, traj = drive
    faults = {"gnss-bad-checksum-rate": 0.03, "gnss-truncate-rate": 0.03, "gnss-nofix": "10:3"}
    rx = GnssReceiver(world, rng=7, faults=faults, fault_seed=11, sigma_h_m=0.0, sigma_v_m=0.0,
                      sigma_vel_m_s=0.0)
    raw = tmp_path / "faulty.nmea"
    try:
        with Gnss(rx.endpoint(), raw_log=raw, wait_for_data=False) as gnss:
            _run(rx, 30.0, step_s=2.0)
            _drained(gnss, rx)
            fixes = gnss.read_fixes(gnss.pending)
            s = gnss.stats
    finally:
        rx.close()
    assert s.bytes == rx.port.bytes_written
    assert s.bad_checksum == rx.sentences_corrupted > 0 and s.truncated == rx.sentences_truncated > 0
    assert s.no_fix > 0 and s.fixes + s.missed_epochs == 301 and s.missed_epochs >= 30
    t = np.array([f.time_s for f in fixes]) - rx.start_utc.timestamp()
    assert not np.any((t > 10.0 - 1e-3) & (t < 13.0 - 1e-3))  # nothing from the no-fix window
    pos_err, vel_err = _truth_errors(rx, traj, [f for f in fixes if f.vel_enu_m_s is not None])
    assert np.max(np.abs(pos_err)) < 2e-3 and np.max(np.abs(vel_err)) < 2e-3  # no noise: formatting only
    assert decode_nmea_log(raw.read_bytes()) == (fixes, s)


def test_fixes_until_and_discard_pending(drive):
    world, _ = drive
    rx = GnssReceiver(world, rng=3)
    try:
        with Gnss(rx.endpoint(), wait_for_data=False) as gnss:
            _run(rx, 5.0)
            _drained(gnss, rx)
            t0 = rx.start_utc.timestamp()
            first = gnss.fixes_until(t0 + 2.0, timeout_s=5)
            assert [round(f.time_s - t0, 1) for f in first] == [k / 10 for k in range(21)]
            assert round(gnss.read_fixes(1, timeout_s=5)[0].time_s - t0, 1) == 2.1
            assert gnss.discard_pending() == 29 and gnss.pending == 0
            with pytest.raises(DeviceError, match="no fix at or after") as exc:
                gnss.fixes_until(t0 + 60.0, timeout_s=0.2)
            assert rx.endpoint() in str(exc.value) and "\n" not in str(exc.value)
    finally:
        rx.close()


def test_wait_for_data_sees_the_receiver(drive):
    world, _ = drive
    rx = GnssReceiver(world, rng=3)
    import threading

    stop = threading.Event()

    def loop():  # the bench keeps sending while the driver opens (pyserial flushes input on open)
        t = 0.0
        while not stop.is_set() and t < DURATION_S:
            t += 0.1
            rx.advance(t)
            rx.port.flush()
            time.sleep(0.01)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    try:
        with Gnss(rx.endpoint(), timeout_s=5.0) as gnss:
            assert len(gnss.read_fixes(3, timeout_s=5)) == 3
    finally:
        stop.set()
        th.join()
        rx.close()


# -- user mistakes: one line naming the port ---------------------------------------------------
def test_missing_port_is_named():
    with pytest.raises(DeviceError) as exc:
        Gnss("/dev/does-not-exist-gnss")
    msg = str(exc.value)
    assert "/dev/does-not-exist-gnss" in msg and "\n" not in msg and msg.startswith("gnss on ")


def test_a_port_without_nmea_is_named(pty_pair):
    master, path = pty_pair
    write_all(master, bytes(range(256)) * 4)  # something binary, e.g. an IMU
    with pytest.raises(DeviceError, match="no NMEA sentences on") as exc:
        Gnss(path, timeout_s=0.5)
    msg = str(exc.value)
    assert path in msg and "GNSS receiver's port" in msg and "\n" not in msg


def test_a_silent_port_is_named(pty_pair):
    _, path = pty_pair
    with pytest.raises(DeviceError, match="no bytes at all") as exc:
        Gnss(path, timeout_s=0.3)
    assert path in str(exc.value)


def test_a_busy_port_is_named(pty_pair):
    _, path = pty_pair
    with Gnss(path, wait_for_data=False), pytest.raises(DeviceError, match="busy") as exc:
        Gnss(path, wait_for_data=False)
    assert path in str(exc.value)
