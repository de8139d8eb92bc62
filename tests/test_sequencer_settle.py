"""The settle rule and the one mean function that live runs and replay share."""

from __future__ import annotations

import numpy as np
import pytest

from northfinder.config import RunConfig
from northfinder.estimators.means import position_means
from northfinder.sequencer import after_motion_s, settle_reached

RATE_HZ = 1000.0
WINDOW = 200  # 0.2 s


def _ringing_z_dph(t_s: np.ndarray, amp_deg: float, freq_hz: float, decay_s: float, noise_dph: float, rng):
    """Gyro z of a table top ringing after a stop: d/dt of A·e^(−t/τ)·sin(2πft), plus white noise."""
    w = 2 * np.pi * freq_hz
    rate_deg_s = amp_deg * np.exp(-t_s / decay_s) * (w * np.cos(w * t_s) - np.sin(w * t_s) / decay_s)
    return rate_deg_s * 3600.0 + 9.6 + rng.normal(0.0, noise_dph, t_s.size)


def _first_settled_window(z: np.ndarray, cfg: RunConfig) -> int | None:
    windows = [z[k : k + WINDOW] for k in range(0, z.size - WINDOW + 1, WINDOW)]
    for k in range(1, len(windows)):
        if settle_reached(windows[: k + 1], cfg.settle_ratio, cfg.settle_rest_dph):
            return k
    return None


@pytest.mark.parametrize("seed", range(5))
def test_settle_waits_until_the_ringing_is_below_the_noise(seed):
    rng = np.random.default_rng(seed)
    cfg = RunConfig()
    t = np.arange(int(6.0 * RATE_HZ)) / RATE_HZ
    noise = 3.8  # nav grade at 1 kHz: 0.002 °/√h · 60 · √1000 ≈ 3.8 °/h per sample
    z = _ringing_z_dph(t, amp_deg=0.005, freq_hz=10.0, decay_s=0.3, noise_dph=noise, rng=rng)
    k = _first_settled_window(z, cfg)
    assert k is not None
    t_settled = (k + 1) * WINDOW / RATE_HZ
    # ringing rate amplitude 0.005°·2π·10 Hz = 1131 °/h; it reaches the per-sample noise after
    # τ·ln(1131/3.8) ≈ 1.7 s. The rule must not stop before the envelope is near the noise.
    envelope = 0.005 * 2 * np.pi * 10.0 * 3600.0 * np.exp(-t_settled / 0.3)
    assert envelope < 2.0 * noise
    assert t_settled < 4.0


def test_a_steady_slew_is_not_settled():
    rng = np.random.default_rng(1)
    cfg = RunConfig()
    slew = 20.0 * 3600.0 + rng.normal(0.0, 3.8, 2 * WINDOW)  # 20 °/s, steady
    assert not settle_reached([slew[:WINDOW], slew[WINDOW:]], cfg.settle_ratio, cfg.settle_rest_dph)
    rest = 9.6 + rng.normal(0.0, 3.8, 2 * WINDOW)
    assert settle_reached([rest[:WINDOW], rest[WINDOW:]], cfg.settle_ratio, cfg.settle_rest_dph)


def test_position_means_do_not_depend_on_memory_layout():
    rng = np.random.default_rng(7)
    gyro = rng.normal(0.0, 1e-5, (30000, 3))
    accel = rng.normal(0.0, 1e-3, (3000, 3)) + [0.0, 0.0, 1.0]
    a = position_means(45.0, gyro, accel, 0, 0, 1000.0)
    b = position_means(45.0, np.asfortranarray(gyro), accel[::1].copy(order="F"), 0, 0, 1000.0)
    c = position_means(45.0, np.concatenate([gyro[:7000], gyro[7000:]]), accel, 0, 0, 1000.0)
    assert a == b == c  # bit for bit
    assert a.samples == 30000 and a.accel_samples == 3000 and a.duration_device_s == 30.0


@pytest.mark.parametrize("move_deg", [45.0, 480.0])
def test_the_rest_after_the_motion_starts_no_earlier_than_the_planned_move_ends(move_deg):
    """A stream started at READY (the planned move's end) skips `after_motion_s` of samples: it must
    then start at or after the settle's end, and not more than two windows later. Trapezoid at 20 °/s and
    80 °/s², then a stop ringing 10× harder than firmware_sim's default (0.05°, 10 Hz, τ 0.3 s)."""
    rng = np.random.default_rng(3)
    v, a, dt = 20.0, 80.0, 1.0 / RATE_HZ
    t_ramp, t_end = v / a, move_deg / v + v / a
    t = np.arange(0.0, t_end + 8.0, dt)
    rate_dps = np.clip(np.minimum(t / t_ramp, (t_end - t) / t_ramp), 0.0, 1.0) * v
    z = rate_dps * 3600.0 + rng.normal(0.0, 0.5, t.size)
    after = t > t_end
    z[after] += _ringing_z_dph(t[after] - t_end, 0.05, 10.0, 0.3, 0.0, rng) - 9.6
    cfg = RunConfig()
    windows = [z[k : k + WINDOW] for k in range(0, z.size - WINDOW + 1, WINDOW)]
    settled = next(k for k in range(1, len(windows))
                   if k * WINDOW * dt > t_end and settle_reached(windows[: k + 1], cfg.settle_ratio,
                                                                 cfg.settle_rest_dph))  # fmt: skip
    means = [float(np.mean(w)) for w in windows[: settled + 1]]
    skip_s = after_motion_s(means, WINDOW * dt, 0.0)
    settle_end_s = (settled + 1) * WINDOW * dt
    assert t_end + skip_s >= settle_end_s - 1e-9
    assert t_end + skip_s <= settle_end_s + 2 * WINDOW * dt
    assert after_motion_s([0.0, 0.0], WINDOW * dt, 0.0) is None
