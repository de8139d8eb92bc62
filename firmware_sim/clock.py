"""The device clock: one time for every device, running `time_scale` times faster than the wall."""

from __future__ import annotations

import time


class DeviceClock:
    """Device seconds = wall seconds elapsed since `start()` × `time_scale`, for every device alike.

    Devices never read the wall clock; the loop reads this once per tick and hands the value on,
    so the gyro sees the table move at the device time the stage reports.
    """

    def __init__(self, time_scale: float = 1.0) -> None:
        if not time_scale > 0.0:
            raise ValueError(f"time_scale must be > 0, got {time_scale!r}")
        self.time_scale = float(time_scale)
        self._t0_wall_s = time.monotonic()

    def start(self) -> None:
        """Make device time 0 now."""
        self._t0_wall_s = time.monotonic()

    def now(self) -> float:
        """Device seconds since start."""
        return (time.monotonic() - self._t0_wall_s) * self.time_scale

    def wall_s(self, device_s: float) -> float:
        """Wall seconds that a device-time interval takes."""
        return device_s / self.time_scale
