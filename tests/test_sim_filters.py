"""firmware_sim's Gauss-Markov filter before scipy.signal is loaded (physics/sensors.py).

The simulator starts device time at once and loads scipy.signal in a thread (0.9 s quiet, 3-5 s
on a loaded host: the IMU used to reach its first client that late, issue 27); meanwhile the
models filter their small blocks with `_first_order`, which must give lfilter's numbers bit for
bit, so that a run's samples do not depend on when the import finished.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from firmware_sim.physics import sensors
from firmware_sim.physics.sensors import GYRO_PRESETS, GyroModel


@pytest.mark.parametrize("phi", [0.0, 0.3, float(np.exp(-1e-3 / 100.0)), 0.999999])
def test_first_order_is_lfilter_bit_for_bit(phi):
    rng = np.random.default_rng(4)
    x = rng.standard_normal((3000, 3)) * 1e-7
    zi = (rng.standard_normal(3) * 1e-6)[None, :]
    want, want_zf = lfilter([1.0], [1.0, -phi], x, axis=0, zi=zi)
    got, got_zf = sensors._first_order(x, phi, zi)
    assert np.array_equal(got, want) and np.array_equal(got_zf, want_zf)


def test_a_gyro_gives_the_same_samples_before_and_after_scipy_is_loaded(monkeypatch):
    rng = np.random.default_rng(8)
    blocks = [rng.standard_normal((n, 3)) * 1e-6 for n in (1, 7, 250, 4096, 5000, 33)]
    assert sensors.load_filters() is lfilter  # every block through scipy's lfilter
    loaded = GyroModel(GYRO_PRESETS["nav"], 1000.0, 77)
    want = [loaded.apply(b) for b in blocks]
    monkeypatch.setattr(sensors, "_lfilter", None)  # as in the simulator's first ticks
    early = GyroModel(GYRO_PRESETS["nav"], 1000.0, 77)
    got = [early.apply(b) for b in blocks]
    assert all(np.array_equal(g, w) for g, w in zip(got, want, strict=True))
