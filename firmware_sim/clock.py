"""The device clock: one time for every device, running `time_scale` times faster than the wall."""

from __future__ import annotations

import time


class DeviceClock:
    """Device seconds = wall seconds elapsed since `start()` × `time_scale`, for every device alike.

    Devices never read the wall clock; the loop reads this once per tick and hands the value on,
    so the gyro sees the table move at the device time the stage reports.
    """

    def __init__(self, time_scale: float = 1.0) -> None:
        self._anchor = (time.monotonic(), 0.0, _checked(time_scale))
        """(wall s, device s at that wall time, scale): one tuple, so that a reader on another
        thread never sees a new scale with an old anchor."""

    @property
    def time_scale(self) -> float:
        return self._anchor[2]

    def start(self) -> None:
        """Make device time 0 now."""
        self._anchor = (time.monotonic(), 0.0, self._anchor[2])

    def set_scale(self, time_scale: float) -> None:
        """Run `time_scale`× the wall clock from now on; device time goes on from where it is."""
        scale = _checked(time_scale)
        wall = time.monotonic()
        self._anchor = (wall, self._device_at(wall), scale)

    def now(self) -> float:
        """Device seconds since start."""
        return self._device_at(time.monotonic())

    def _device_at(self, wall_s: float) -> float:
        wall0, device0, scale = self._anchor
        return device0 + (wall_s - wall0) * scale

    def wall_s(self, device_s: float) -> float:
        """Wall seconds that a device-time interval takes (at the present scale)."""
        return device_s / self._anchor[2]


def _checked(time_scale: float) -> float:
    if not float(time_scale) > 0.0:
        raise ValueError(f"time_scale must be > 0, got {time_scale!r}")
    return float(time_scale)
