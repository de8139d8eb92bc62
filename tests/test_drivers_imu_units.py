"""What real KVH units do that our simulator did not (issue 11), at the driver level: real ptys,
real pyserial, crafted format-A frames.

- the status byte: the unit's axes are learned from it, fields flagged not valid are excluded
  (NaN, never averaged) and counted per axis, live and in replay alike;
- late bytes: a link that holds bytes back and bursts them loses nothing and is not a pause; only a
  silence longer than the link timeout is.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from helpers import write_all

from northfinder.codecs import kvh
from northfinder.drivers.imu import Imu, decode_imu_stream
from northfinder.errors import InputError
from northfinder.estimators.heading import solve_heading
from northfinder.estimators.means import PositionMeans, position_means
from northfinder.runs.find import _solve

GARBAGE = 3.0e4  # what a unit leaves in a field it flags not valid (built-in test, rate change)


def _stream(n: int, status: int, invalid_at: tuple[int, ...] | np.ndarray = (), seed: int = 5):
    """n frames of one unit (`status` = its valid bits), those at `invalid_at` flagged not valid
    (bits cleared) with garbage in every field → bytes, the true gyro [rad/s] and accel [g]."""
    rng = np.random.default_rng(seed)
    gyro = rng.normal(1e-7, 1e-8, size=(n, 3))
    accel = np.tile([0.01, -0.02, 1.0], (n, 1)) + rng.normal(0, 1e-4, size=(n, 3))
    st = np.full(n, status, dtype=np.uint8)
    sent_g, sent_a = gyro.copy(), accel.copy()
    invalid_at = np.asarray(invalid_at, dtype=int)
    st[invalid_at] = 0
    sent_g[invalid_at] = GARBAGE
    sent_a[invalid_at] = -GARBAGE
    data = kvh.encode_frames(sent_g / 1000.0, sent_a, st, np.arange(n), np.full(n, 25))  # DELTA at 1 kHz
    return data, gyro.astype(np.float32).astype(np.float64), accel.astype(np.float32).astype(np.float64)


@pytest.mark.parametrize(
    "status, described, gyro_axes",
    [
        (0x77, "gyro x y z, accel x y z", "xyz"),
        (0x07, "gyro x y z, no accel", "xyz"),
        (0x03, "gyro x y, no accel", "xy"),
        (0x02, "gyro y only", "y"),
    ],
)
def test_the_units_axes_are_learned_from_its_status_bits(pty_pair, status, described, gyro_axes):
    master, path = pty_pair
    data, _, _ = _stream(200, status, invalid_at=np.array([3, 70]))  # flagged frames keep the axes
    with Imu(path, wait_for_data=False) as imu:
        write_all(master, data)
        axes = imu.axes
        block = imu.read(200, timeout_s=5)
        invalid = imu.invalid_samples()
    assert axes.describe() == described and axes.gyro == gyro_axes
    # fields of an axis the unit lacks are NaN in every frame; the flagged frames' in every field
    valid = kvh.valid_mask(block.status)
    assert np.array_equal(np.isnan(block.gyro_rad_s), ~valid[:, :3])
    assert np.array_equal(np.isnan(block.accel_g), ~valid[:, 3:])
    assert invalid == {a: 2 for a, p in zip(kvh.AXIS_NAMES, axes.present, strict=True) if p}


def test_frames_flagged_not_valid_are_left_out_of_the_means_and_counted(pty_pair):
    master, path = pty_pair
    n = 5000
    flagged = np.sort(np.random.default_rng(8).choice(n, size=5, replace=False))  # 1 in 1000
    data, gyro, _ = _stream(n, 0x77, flagged)
    with Imu(path, wait_for_data=False) as imu:
        write_all(master, data)
        block = imu.read(n, timeout_s=10)
        stats = imu.stats
    means = position_means(0.0, block.gyro_rad_s, np.zeros((10, 3)), 0, 0, 1000.0, "xyz")
    keep = np.ones(n, bool)
    keep[flagged] = False
    # the mean is over the valid samples only, the flagged ones counted per axis
    scale = kvh.gyro_scale_to_rad_s(1000.0, "DELTA", "RAD")
    expected = (np.float32(gyro / 1000.0).astype(np.float64) * scale)[keep].mean(axis=0)
    assert np.allclose(np.array(means.gyro_dph) * np.pi / 180 / 3600, expected, rtol=1e-12)
    assert means.invalid_samples == {"gx": 5, "gy": 5, "gz": 5}
    assert stats.invalid_samples(kvh.ImuAxes((True,) * 6)) == dict.fromkeys(kvh.AXIS_NAMES, 5)
    # a plain mean would have been ruined by the garbage: the exclusion is what makes it right
    assert abs(means.gyro_dph[1]) < 1.0
    # replay decodes the same bytes to the same NaN-marked arrays, bit for bit
    replayed, rstats = decode_imu_stream(data)
    assert np.array_equal(replayed.gyro_rad_s, block.gyro_rad_s, equal_nan=True)
    assert rstats.invalid_gx == stats.invalid_gx == 5


def test_a_single_gyro_on_y_feeds_the_estimator_with_its_one_axis():
    # positions of a y-only unit: x and z means are NaN (the unit lacks them); the fit takes (n,)
    alpha = np.arange(8) * 45.0
    omega_h = 15.041 * np.cos(np.radians(40.0))
    gy = omega_h * np.cos(np.radians(37.0 + alpha))  # b-y toward the heading at α = 0
    pos = [
        PositionMeans(a, [np.nan, g, np.nan], [np.nan, 0.01, np.nan], [0.0, 0.0, 1.0], [1e-5] * 3,
                      30000, 0, 3000, 0, 30.0, {"gy": 0})
        for a, g in zip(alpha, gy, strict=True)
    ]
    sol = _solve(pos, 40.0, "exact")
    accel = np.tile([0.0, 0.0, 1.0], (8, 1))
    direct = solve_heading(alpha, gy, accel, 40.0, gyro_std_dph=np.full(8, 0.01 / np.sqrt(30000)),
                           accel_std_g=np.full((8, 3), 1e-5 / np.sqrt(3000)))
    assert sol.heading_deg == direct.heading_deg and sol.heading_std_deg == direct.heading_std_deg
    # an x-only unit cannot find north: said in one line, not a NaN heading
    for p in pos:
        p.gyro_dph = [p.gyro_dph[1], np.nan, np.nan]
    with pytest.raises(InputError, match=r"gyro axes \(x\)"):
        _solve(pos, 40.0, "exact")


def _paced_writer(master: int, data: bytes, hold_every_s: float, hold_s: float, rate_hz: float) -> None:
    """Write frames at `rate_hz` (host time), holding everything back for `hold_s` every
    `hold_every_s` and then bursting what was held — a busy USB-serial adapter; nothing lost."""
    t0 = time.monotonic()
    sent, held_until, next_hold = 0, 0.0, hold_every_s
    n = len(data) // kvh.FRAME_SIZE
    while sent < n:
        now = time.monotonic() - t0
        if now >= next_hold:
            held_until, next_hold = now + hold_s, next_hold + hold_every_s
        if now < held_until:
            time.sleep(0.005)
            continue
        due = min(n, int(now * rate_hz) + 1)
        if due > sent:
            write_all(master, data[sent * kvh.FRAME_SIZE:due * kvh.FRAME_SIZE])
            sent = due
        time.sleep(0.002)


def test_bytes_held_back_and_burst_are_no_pause_and_lose_nothing(pty_pair):
    master, path = pty_pair
    n = 1500  # 1.5 s at 1 kHz with a 0.3 s hold every 0.5 s
    data, _, _ = _stream(n, 0x77)
    with Imu(path, wait_for_data=False) as imu:  # default link timeout (1 s host)
        _paced_writer(master, data, hold_every_s=0.5, hold_s=0.3, rate_hz=1000.0)
        block = imu.read(n, timeout_s=10)
        stalls, stats = imu.stall_indices, imu.stats
    assert stalls == []
    assert stats.lost_samples == 0 and block.lost_samples == 0
    assert block.sample_index.tolist() == list(range(n))


def test_a_device_pause_is_a_gap_of_unknown_length_and_a_host_silence_none(pty_pair):
    """The device silent for 300 samples (their bytes never sent), written without a host pause:
    a pause at the first frame after it, decided from the bytes (the sequence says 44 lost, the
    missing bytes say it may be 128·k more). Then 0.6 s of host silence with the sequence
    continuous: no pause — host time decides no loss."""
    master, path = pty_pair
    data, _, _ = _stream(900, 0x77)
    f = kvh.FRAME_SIZE
    with Imu(path, wait_for_data=False) as imu:
        write_all(master, data[: 200 * f] + data[500 * f : 700 * f])
        block = imu.read(400, timeout_s=5)
        time.sleep(0.6)
        write_all(master, data[700 * f :])
        imu.read(200, timeout_s=5)
        stalls, stats = imu.stall_indices, imu.stats
    assert block.sample_index[200] - block.sample_index[199] == 1 + 300 % 128
    assert stalls == [int(block.sample_index[200])]
    assert stats.lost_samples == 300 % 128


class _StarvedTransport:
    """Frames in two halves with the reader kept away 1.5 s between them (as a loaded host or the
    GIL does): one empty read, then a read that only returns after 1.5 s — the second half was
    waiting at the port all along, which the reader never saw empty for that long."""

    timeout_s = 0.05

    def __init__(self, halves: list[bytes]) -> None:
        self.reads = [halves[0], b"", "starve", halves[1]]

    def write(self, data: bytes) -> None:
        raise AssertionError(f"unexpected write {data!r}")

    def read_available(self, max_bytes: int = 1 << 16) -> bytes:
        if not self.reads:
            time.sleep(0.01)
            return b""
        item = self.reads.pop(0)
        if item == "starve":
            time.sleep(1.5)
            return self.reads.pop(0)
        return item

    def close(self) -> None:
        pass


def test_a_reader_kept_off_the_cpu_is_no_pause():
    data, _, _ = _stream(400, 0x77)
    half = 200 * kvh.FRAME_SIZE
    with Imu("starved://kvh", transport=_StarvedTransport([data[:half], data[half:]]),
             wait_for_data=False) as imu:
        block = imu.read(400, timeout_s=10)
        stalls = imu.stall_indices
    assert stalls == [] and block.lost_samples == 0
