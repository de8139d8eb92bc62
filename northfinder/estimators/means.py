"""Statistics of a dwell: per-position means and spreads of the gyro and the accelerometer.

Pure numpy. The live run (the sequencer) and replay (northfinder.runs.find) compute the
per-position means through the same function (:func:`position_means`) from the same decoded
arrays, so replay reproduces the live numbers bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from northfinder.constants import DPH


@dataclass
class PositionMeans:
    """What one table position contributes to the fit: means, spreads and sample counts."""

    table_angle_deg: float
    gyro_dph: list[float]
    gyro_std_dph: list[float]
    """Sample standard deviation of each gyro axis over the dwell [deg/h]."""
    accel_g: list[float]
    accel_std_g: list[float]
    samples: int
    lost_samples: int
    accel_samples: int
    accel_lost_samples: int
    duration_device_s: float
    invalid_samples: dict[str, int] = field(default_factory=dict)
    """IMU gyro samples flagged not valid (status bit cleared) and left out, per gyro axis the unit
    has ("gx", "gy", "gz"); an axis the unit lacks has a NaN mean (None in JSON)."""


def _column_mean_std(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Contiguous per-axis rows: numpy's pairwise summation then runs in one fixed order whatever
    # the caller's memory layout, which is what makes live and replay means bit-identical.
    # NaN marks a sample flagged not valid: each axis is averaged over its own valid samples.
    rows = np.ascontiguousarray(np.asarray(values, dtype=np.float64).T)
    mean = np.full(rows.shape[0], np.nan)
    std = np.full(rows.shape[0], np.nan)
    for k, row in enumerate(rows):
        ok = row[~np.isnan(row)]
        if ok.size:
            mean[k] = ok.mean()
            std[k] = ok.std(ddof=1) if ok.size > 1 else 0.0
    return mean, std


def position_means(
    table_angle_deg: float,
    gyro_rad_s: np.ndarray,
    accel_g: np.ndarray,
    imu_lost: int,
    accel_lost: int,
    imu_rate_hz: float,
    gyro_axes: str = "xyz",
) -> PositionMeans:
    """Per-position means of the gyro [deg/h] and the accelerometer [g] from decoded samples.

    The one function both the live run and replay call. Duration is device time: samples
    (received and lost) over the IMU rate. Gyro samples flagged not valid are NaN and left out;
    they are counted per axis of `gyro_axes` (the axes the unit has, e.g. "y").
    """
    g_mean, g_std = _column_mean_std(gyro_rad_s)
    nan_count = np.isnan(np.asarray(gyro_rad_s, dtype=np.float64)).sum(axis=0)
    invalid = {f"g{a}": int(nan_count["xyz".index(a)]) for a in gyro_axes}
    a_mean, a_std = _column_mean_std(accel_g)
    n_imu = int(np.asarray(gyro_rad_s).shape[0])
    return PositionMeans(
        table_angle_deg=float(table_angle_deg),
        gyro_dph=(g_mean / DPH).tolist(),
        gyro_std_dph=(g_std / DPH).tolist(),
        accel_g=a_mean.tolist(),
        accel_std_g=a_std.tolist(),
        samples=n_imu,
        lost_samples=int(imu_lost),
        accel_samples=int(np.asarray(accel_g).shape[0]),
        accel_lost_samples=int(accel_lost),
        duration_device_s=(n_imu + int(imu_lost)) / float(imu_rate_hz),
        invalid_samples=invalid,
    )
