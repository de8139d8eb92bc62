"""firmware_sim without scipy: the Gauss–Markov recursion in numpy, and the vehicle's held start.

`FirstOrderRecursion` (firmware_sim/physics/sensors.py) replaces scipy.signal.lfilter for the
sensor models' Gauss–Markov bias, so a simulator start no longer imports scipy (~1 s of CPU). It
is compared here with lfilter itself (scipy is a dependency of the project, not of the simulator)
to a tolerance from float64 rounding: both compute y[n] = φ·y[n−1] + x[n] with a few correctly
rounded operations per sample whose errors are carried on with a factor |φ| ≤ 1, so each is
within (n + 4) · c · u · scale of the exact value (u = 2⁻⁵³; c = 4 covers the ≤ 4 roundings per
sample of either; scale = max|y| + max|x| + |zi|), and the two within twice that.

The vehicle scenario holds device time at 0 until a client has a data port open
(`Simulator.holds_for_client`): a client that comes long after the still start would have ended,
were device time running, still gets the vehicle from device time 0.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import serial
from scipy.signal import lfilter

from firmware_sim.config import SimConfig
from firmware_sim.devices.kvh import HEADER, MESSAGE_BYTES, unpack_messages
from firmware_sim.physics.sensors import GM_BLOCK_MAX, FirstOrderRecursion, first_order_filter
from firmware_sim.simulator import Simulator

ROOT = Path(__file__).resolve().parent.parent
UNIT_ROUNDOFF = 2.0**-53
ROUNDINGS_PER_SAMPLE = 4

PHIS = (0.0, 0.5, 1.0 - 1e-6, math.exp(-1e-3 / 0.3))
LENGTHS = (1, 7, 1000, 100_000)


def _rounding_bound(n: int, x: np.ndarray, y: np.ndarray, zi: np.ndarray) -> float:
    """|numpy − lfilter| allowed: twice each one's worst-case float64 error over n samples."""
    scale = np.abs(y).max() + np.abs(x).max() + np.abs(zi).max()
    return 2.0 * (n + 4) * ROUNDINGS_PER_SAMPLE * UNIT_ROUNDOFF * scale


def _cuts(n: int, rng: np.random.Generator) -> list[int]:
    """Split points: single samples at the start, a block boundary when n reaches it, random ones."""
    inner = {1, 2, GM_BLOCK_MAX - 1, GM_BLOCK_MAX, GM_BLOCK_MAX + 3}
    inner |= set(rng.integers(1, max(n, 2), 5).tolist())
    return [0, *sorted(c for c in inner if 0 < c < n), n]


@pytest.mark.parametrize("n", LENGTHS)
@pytest.mark.parametrize("phi", PHIS)
def test_recursion_matches_lfilter_in_one_call_and_in_pieces(phi, n):
    rng = np.random.default_rng(n + int(phi * 1000))
    x = rng.standard_normal((n, 3)) * [1.0, 1e-9, 3e4]  # three scales: the error is relative to each
    zi = rng.standard_normal((1, 3)) * [1.0, 1e-9, 3e4] * 10.0
    y_ref, zf_ref = lfilter([1.0], [1.0, -phi], x, axis=0, zi=zi)
    y_one, zf_one = first_order_filter(x, phi, zi)
    assert y_one.shape == y_ref.shape and zf_one.shape == zf_ref.shape == (1, 3)
    # lfilter in pieces, each given the last one's zf (its own split is exact: it is sequential)
    cuts = _cuts(n, rng)
    pieces, z = [], zi
    for i, j in zip(cuts[:-1], cuts[1:], strict=True):
        y_piece, z = first_order_filter(x[i:j], phi, z)
        pieces.append(y_piece)
    y_pieces = np.concatenate(pieces)
    worst = []
    for axis in range(3):
        bound = _rounding_bound(n, x[:, axis], y_ref[:, axis], zi[:, axis])
        for y, zf in ((y_one, zf_one), (y_pieces, z)):
            err = max(np.abs(y[:, axis] - y_ref[:, axis]).max(), abs(zf[0, axis] - zf_ref[0, axis]))
            assert err <= bound, f"axis {axis}: |numpy − lfilter| {err:.3g} > rounding bound {bound:.3g}"
            worst.append(err / bound if bound else 0.0)
    print(f"φ={phi:.9g} n={n}: worst error {max(worst):.2g} of the rounding bound")


@pytest.mark.parametrize("phi", PHIS)
def test_the_model_state_gives_one_calls_bits_in_any_pieces(phi):
    """The sensor models' form: one recursion object carried across calls of any length gives
    exactly (bit for bit) what one call gives — the simulator's bytes must not depend on its ticks."""
    rng = np.random.default_rng(5)
    n = 3 * GM_BLOCK_MAX + 123
    x = rng.standard_normal((n, 3))
    zi = rng.standard_normal(3)
    one = FirstOrderRecursion(phi, zi)
    y_one = one.apply(x)
    parts = FirstOrderRecursion(phi, zi)
    cuts = [0, 1, 2, 3, 50, GM_BLOCK_MAX - 1, GM_BLOCK_MAX + 1, 2 * GM_BLOCK_MAX, 2 * GM_BLOCK_MAX, n - 1, n]
    y_parts = np.concatenate([parts.apply(x[i:j]) for i, j in zip(cuts[:-1], cuts[1:], strict=True)])
    assert np.array_equal(y_one, y_parts)
    assert np.array_equal(one.zf, parts.zf)
    y_ref, zf_ref = lfilter([1.0], [1.0, -phi], x, axis=0, zi=zi[None, :])
    bound = _rounding_bound(n, x, y_ref, zi)
    assert np.abs(y_one - y_ref).max() <= bound and np.abs(one.zf - zf_ref).max() <= bound


def test_phi_zero_passes_the_input_through_and_phi_beyond_one_is_refused():
    x = np.arange(12.0).reshape(4, 3)
    y, zf = first_order_filter(x, 0.0, np.ones((1, 3)))
    assert np.array_equal(y[1:], x[1:]) and np.array_equal(y[0], x[0] + 1.0) and not zf.any()
    with pytest.raises(ValueError, match="φ"):
        FirstOrderRecursion(1.5, np.zeros(3))


def test_a_simulator_start_does_not_import_scipy():
    """A bench started in a fresh interpreter runs device time (no hold) and never loads scipy."""
    code = ("import sys, time\n"
            "from firmware_sim.simulator import Simulator, SimConfig\n"
            "sim = Simulator(SimConfig(time_scale=20.0, seed=3))\n"
            "sim.start()\n"
            "deadline = time.monotonic() + 30.0\n"
            "while sim.now() < 2.0 and time.monotonic() < deadline and not sim.failed.is_set():\n"
            "    time.sleep(0.01)\n"
            "sim.stop()\n"
            "scipy = any(m.split('.')[0] == 'scipy' for m in sys.modules)\n"
            "print(sim.now() >= 2.0, sim.imu.emitted, scipy)\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    ran, emitted, scipy_loaded = out.stdout.split()
    assert ran == "True" and int(emitted) > 0, out.stdout  # device time ran and the IMU produced
    assert scipy_loaded == "False"


def test_vehicle_holds_device_time_for_a_late_client_who_then_reads_the_still_start(tmp_path):
    """At 120× the vehicle's 10 s still start is 83 ms of wall time. The client opens the IMU a
    full second (120 device seconds, were time running) after the endpoints: device time is
    still 0, the IMU hands it every sample from k = 1 (device time 1/rate), and the 5 s of samples
    the GNSS/INS alignment levels on are of a vehicle standing still. (pyserial flushes its input
    right after opening; should a starved host flush the first frames too, the first frame read
    is still one of the first 128, its k known from the 7-bit sequence.)"""
    scale, wait_wall_s = 120.0, 1.0
    log_path = tmp_path / "truth.jsonl"
    sim = Simulator(SimConfig(scenario="vehicle", seed=2, time_scale=scale, truth_log=str(log_path)))
    try:
        ep = sim.start()
        assert sim.holds_for_client
        time.sleep(wait_wall_s)
        held_at = sim.now()
        emitted_while_held = sim.imu.emitted
        rate = sim.imu.rate_hz
        n_level = int(5.0 * rate)  # the alignment's levelling window, in samples
        port = serial.Serial(ep["imu"], 921600, timeout=0.5)
        raw = bytearray()
        deadline = time.monotonic() + 60.0  # host time only bounds the wait; counts decide
        while len(raw) < MESSAGE_BYTES * (n_level + 2) and time.monotonic() < deadline:
            raw += port.read(1 << 16)
        port.close()
    finally:
        sim.stop()
    assert held_at == 0.0 and emitted_while_held == 0
    lines = [json.loads(line) for line in log_path.read_text().splitlines()]
    connects = [e for e in lines if e.get("event") == "imu_connect"]
    assert connects and connects[0]["k0"] == 1 and connects[0]["t0_device_s"] == pytest.approx(1.0 / rate)
    start = bytes(raw).find(HEADER)
    msgs = unpack_messages(bytes(raw[start:]))[:n_level]
    assert 0 <= start < MESSAGE_BYTES and len(msgs) == n_level and msgs["crc_ok"].all()
    k_first = int(msgs["sequence"][0]) + 1  # one of the first 128 samples
    k = np.arange(k_first, k_first + n_level)
    assert np.array_equal(msgs["sequence"], (k - 1) % 128)  # no gap
    print(f"\nvehicle at {scale:g}x, IMU opened {wait_wall_s:g} s late: device time {held_at} then, "
          f"first sample read k = {k_first} (t = {k_first / rate:.3f} s)")
    # the vehicle stood still over those samples (its truth, from the same run's log)
    t_end = k[-1] / rate
    rows = [r for r in lines if r["type"] == "truth" and r["t_device_s"] <= t_end + 1e-9]
    assert rows and rows[-1]["t_device_s"] >= t_end - 1.0 / sim.config.truth_rate_hz
    assert max(np.abs(r["imu_vel_enu_m_s"]).max() for r in rows) == 0.0
