"""Each driver against the real emulator (firmware_sim's Simulator, in this process, over real
ptys and the slcan pty). Physics checks use tolerances derived from the `nav` preset's errors."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_sim.config import SimConfig
from firmware_sim.physics.sensors import ACCEL_PRESETS, GYRO_PRESETS
from firmware_sim.simulator import Simulator
from northfinder.constants import DPH, OMEGA_EARTH_RAD_S, STANDARD_GRAVITY_M_S2, normal_gravity_m_s2
from northfinder.drivers.accelerometer import Accelerometer, decode_can_log
from northfinder.drivers.imu import Imu, decode_imu_stream
from northfinder.drivers.turntable import StageError, Turntable

LAT_DEG = 40.0


def _gyro_tolerance_rad_s(n: int, rate_hz: float) -> float:
    """Norm of the mean of n samples vs Ωe: constant bias + 5σ of white noise (ARW) on 3 axes."""
    g = GYRO_PRESETS["nav"]
    bias = np.linalg.norm(np.atleast_1d(g.bias_dph) * np.ones(3)) + np.max(g.bias_instability_dph)
    arw_rad_rt_s = np.max(g.arw_deg_rt_h) * np.pi / 180 / 60  # °/√h → rad/√s
    sigma = arw_rad_rt_s / np.sqrt(n / rate_hz)
    return bias * DPH + 5 * np.sqrt(3) * sigma


def _accel_tolerance_g(n: int, rate_hz: float) -> float:
    """Norm of the mean vs local gravity: constant bias + instability + 5σ of white noise."""
    a = ACCEL_PRESETS["nav"]
    bias = np.linalg.norm(np.atleast_1d(a.bias_ug) * np.ones(3)) + np.max(a.bias_instability_ug)
    sigma = np.max(a.noise_ug_rt_hz) * np.sqrt(rate_hz / 2) / np.sqrt(n)  # white noise, Nyquist band
    return (bias + 5 * np.sqrt(3) * sigma) * 1e-6


@pytest.fixture(scope="module")
def bench():
    sim = Simulator(SimConfig(seed=11, time_scale=20.0, latitude_deg=LAT_DEG, heading_deg=30.0,
                              pitch_deg=2.0, roll_deg=-1.0, grade="nav", can_interface="slcan"))
    endpoints = sim.start()
    yield sim, endpoints
    sim.stop()
    assert sim.error is None


def test_turntable_against_the_emulator(bench, tmp_path):
    sim, ep = bench
    log = tmp_path / "stage.log"
    with Turntable(ep["turntable"], transcript=log) as stage:
        assert stage.version()
        assert stage.soft_limits_deg() == (-360.0, 360.0)
        st = stage.ensure_referenced()
        assert st.is_ready and st.is_referenced
        assert stage.move_absolute_deg(90.0, timeout_s=30).is_ready
        assert stage.position_deg() == pytest.approx(90.0, abs=0.01)
        assert stage.move_relative_deg(-45.5, timeout_s=30).state_name == "READY from MOVING"
        assert stage.position_deg() == pytest.approx(44.5, abs=0.01)
        with pytest.raises(StageError) as exc:
            stage.move_absolute_deg(400)
        assert exc.value.letter == "G" and exc.value.state_name.startswith("READY")
        stage.move_absolute_deg(0.0, wait=False)
        assert stage.stop().is_moving is False
    text = log.read_text()
    assert "> 1PA90\\r\\n" in text and "< 1TEG\\r\\n" in text


def test_imu_against_the_emulator(bench, tmp_path):
    sim, ep = bench
    raw = tmp_path / "imu.raw"
    with Imu(ep["imu"], raw_log=raw) as imu:
        assert imu.query("DR") == "1000"
        imu.configure(rate_hz=250, rot_format="RATE", rot_units="DEG")
        n = 1000  # 4 s of device time
        block = imu.read(n, timeout_s=20)
        stats = imu.stats
    assert (stats.bad_crc, stats.discarded_frames) == (0, 2)
    assert block.lost_samples == 0 and np.all(np.diff(block.sample_index) == 1)
    w = np.linalg.norm(block.gyro_rad_s.mean(axis=0))
    assert abs(w - OMEGA_EARTH_RAD_S) < _gyro_tolerance_rad_s(n, 250.0)
    f = np.linalg.norm(block.accel_g.mean(axis=0))
    g_local = normal_gravity_m_s2(LAT_DEG) / STANDARD_GRAVITY_M_S2
    assert abs(f - g_local) < _accel_tolerance_g(n, 250.0)
    # replay from the raw log: the block's samples come back bit-identical at its indices
    replayed, _ = decode_imu_stream(raw.read_bytes(), 250.0, "RATE", "DEG")
    sel = np.isin(replayed.sample_index, block.sample_index)
    assert np.array_equal(replayed.sample_index[sel], block.sample_index)
    assert np.array_equal(replayed.gyro_rad_s[sel], block.gyro_rad_s)
    assert np.array_equal(replayed.accel_g[sel], block.accel_g)


def test_accelerometer_against_the_emulator_over_slcan(bench, tmp_path):
    sim, ep = bench
    can_ep = ep["can"]
    log = tmp_path / "can.asc"
    with Accelerometer(can_ep["interface"], can_ep["channel"], bitrate=can_ep["bitrate"],
                       node_id=can_ep["node_id"], log_path=log) as acc:
        assert acc.wait_heartbeat(timeout_s=5) in (0x00, 0x7F)  # boot-up, then pre-operational
        acc.start_node()
        assert acc.wait_heartbeat_state(0x05, timeout_s=5) == 0x05
        n = 200  # 2 s of device time at 100 Hz
        block = acc.read(n, timeout_s=20)
        stats = acc.stats
    assert stats.pairs >= n and block.lost_samples == 0
    f = np.linalg.norm(block.accel_g.mean(axis=0))
    g_local = normal_gravity_m_s2(LAT_DEG) / STANDARD_GRAVITY_M_S2
    assert abs(f - g_local) < _accel_tolerance_g(n, 100.0)
    replayed, rstats = decode_can_log(log, node_id=can_ep["node_id"])
    sel = np.isin(replayed.counter, block.counter)
    assert np.array_equal(replayed.accel_g[sel], block.accel_g)
    assert rstats.pairs >= stats.pairs  # the log also holds frames that came after the snapshot
