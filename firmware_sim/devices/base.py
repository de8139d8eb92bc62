"""The one surface every emulated device implements, so that one loop can run them all.

The simulator's loop (firmware_sim.simulator) reads the shared device clock, hands each device
the bytes its client sent with the device time they arrived (`on_input(data, t)`: the loop's
arrival thread reads each `input_port()` as bytes come), then calls `advance(t)`, which must emit
everything the device owes up to device time `t` (samples, heartbeats, end of a move). Devices
never sleep and never read the wall clock: device time is the only time.

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
    """An emulated instrument. Subclasses implement `advance`; ports add `input_port`/`on_input`."""

    name: str = "device"

    def input_port(self) -> PtyPort | None:
        """The pty whose client input the device takes, while a client has it open; else None
        (a master without a client polls readable — hang-up — all the time)."""
        return None

    def fileno(self) -> int | None:
        """The input port's descriptor, for a loop that polls devices itself (tests, tools)."""
        port = self.input_port()
        return None if port is None else port.master_fd

    def on_input(self, data: bytes, t_device_s: float) -> None:  # noqa: B027 - optional hook
        """Act on bytes the client sent, which arrived at device time `t_device_s`."""

    def on_readable(self, t_device_s: float) -> None:
        """Read all that waits on the input port without blocking and act on it at `t_device_s`."""
        port = self.input_port()
        while port is not None and (data := port.read()):
            self.on_input(data, t_device_s)

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

    def input_port(self) -> PtyPort | None:
        return None if self.port.watch_fileno() is None else self.port

    def endpoint(self) -> str:
        return self.port.path

    def close(self) -> None:
        self.port.close()
