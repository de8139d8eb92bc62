"""The one surface every emulated device implements, so that one loop can run them all.

The simulator's loop (firmware_sim.simulator) reads the shared device clock, then for each
device: if its `fileno()` is readable, calls `on_readable(t)`; then calls `advance(t)`, which
must emit everything the device owes up to device time `t` (samples, heartbeats, end of a
move). Devices never sleep and never read the wall clock: device time is the only time.

This module holds no protocol: each device's bytes follow its own document, cited in its module
(SMC100 user manual §5, KVH 1775 ICD 56-0298, CiA 301/410, Thorlabs APT protocol issue 28,
STIM300 TS1524, NMEA 0183). `PtyDevice` is only the pty an RS-232/RS-422 device is reached on.
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from firmware_sim.pty import PtyPort


class Device(abc.ABC):
    """An emulated instrument. Subclasses implement `advance`; ports add `fileno`/`on_readable`."""

    name: str = "device"

    def fileno(self) -> int | None:
        """File descriptor the loop should watch for input, or None."""
        return None

    def on_readable(self, t_device_s: float) -> None:  # noqa: B027 - optional hook
        """Input is waiting on `fileno()`; read it without blocking and act on it at `t_device_s`."""

    @abc.abstractmethod
    def advance(self, t_device_s: float) -> None:
        """Emit everything due up to device time `t_device_s` (never beyond it)."""

    def endpoint(self) -> Any:
        """What clients connect to (a pty slave path, a CAN channel dict), for the JSON line."""
        return None

    def close(self) -> None:  # noqa: B027 - optional hook
        """Release ports and buses; must be idempotent."""


class PtyDevice(Device):
    """A serial instrument on a pty (`self.port`): the loop watches the port while a client has it
    open, clients connect to its slave path, and closing the device closes the port."""

    port: PtyPort

    def fileno(self) -> int | None:
        return self.port.watch_fileno()

    def endpoint(self) -> str:
        return self.port.path

    def close(self) -> None:
        self.port.close()
