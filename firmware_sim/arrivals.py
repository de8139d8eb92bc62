"""Client input stamped with the device time it arrived, not the time the busy loop got to it.

The simulator's loop works one tick at a time; at high time scales a tick takes about as long as it
covers (~1 ms of wall time at 120×), so a command that came while the loop worked was taken at the
next tick: a move command started the stage ~1 ms of wall time — 0.12 device s at 120×, 0.005 s at
10× — after the host had sent it. A real unit acts on a command when its last byte is in.

`ArrivalStamper` is a thread that waits on the ports the loop gives it, reads what arrives at once,
and stamps it with the device clock under a lock the loop also takes to read the clock: so every
chunk the loop takes at a tick was stamped at or before that tick's time, and after the previous
one's. The loop hands each chunk to its device with its own time (Device.on_input).

How soon the thread runs after its bytes arrive depends on the interpreter's switch interval while
the loop holds the GIL: the firmware-sim command sets it short (firmware_sim.cli); a simulator
started inside another program keeps that program's setting and stamps no later than before.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
from collections.abc import Callable, Mapping

from firmware_sim.pty import PtyPort

QUIET_RECHECK_S = 0.005
"""How often a hung-up port is looked at again (wall): a client that closes the port and opens it
again is read at once, even if the loop never saw it gone (both within one of its ticks)."""


class ArrivalStamper:
    """Reads the watched ports as input arrives; `take()` returns it with the device time it came."""

    def __init__(self, now: Callable[[], float]) -> None:
        self._now = now
        self._lock = threading.Lock()
        self._arrived: list[tuple[float, PtyPort, bytes]] = []
        self._ports: dict[int, PtyPort] = {}
        self._wake_r, self._wake_w = os.pipe()  # readable for the loop when something arrived
        self._ctl_r, self._ctl_w = os.pipe()  # tells the thread: new ports to watch, or stop
        for fd in (self._wake_r, self._wake_w, self._ctl_r, self._ctl_w):
            os.set_blocking(fd, False)
        self._stopping = False
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="firmware_sim-arrivals", daemon=True)
        self._thread.start()

    def fileno(self) -> int:
        """Readable while stamped input waits for `take()` (the loop selects on it)."""
        return self._wake_r

    def watch(self, ports: Mapping[int, PtyPort]) -> None:
        """The ports to read (fd → port: those a client has open), given by the loop every tick;
        the thread starts on a new set at once."""
        if ports != self._ports:
            self._ports = dict(ports)
            _poke(self._ctl_w)

    def take(self) -> tuple[float, list[tuple[float, PtyPort, bytes]]]:
        """The device time now, and every chunk stamped before it, in the order it came. Raises
        what stopped the thread, if something did (the loop then fails, not goes deaf)."""
        if self.error is not None:
            raise RuntimeError("the arrival thread stopped") from self.error
        _drain(self._wake_r)  # first: a chunk stamped after the take below pokes again
        with self._lock:
            t = self._now()
            arrived, self._arrived = self._arrived, []
        return t, arrived

    def close(self) -> None:
        """End the thread, then close its pipes. Idempotent."""
        if self._stopping:
            return
        self._stopping = True
        _poke(self._ctl_w)
        self._thread.join(timeout=5.0)
        for fd in (self._wake_r, self._wake_w, self._ctl_r, self._ctl_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _run(self) -> None:
        try:
            self._watch_ports()
        except BaseException as exc:  # noqa: BLE001 - handed to the loop by take()
            self.error = exc
            _poke(self._wake_w)

    def _watch_ports(self) -> None:
        quiet: set[int] = set()  # hung up (no client): left out while it stays so
        ports = self._ports
        while not self._stopping:
            quiet = {fd for fd in quiet if not ports[fd].connected}  # a client may be back
            fds = [fd for fd in ports if fd not in quiet]
            try:
                wait_s = QUIET_RECHECK_S if quiet else None
                readable, _, _ = select.select([*fds, self._ctl_r], [], [], wait_s)
            except OSError:  # a port was closed under us: read the loop's set again shortly
                readable = select.select([self._ctl_r], [], [], QUIET_RECHECK_S)[0]
                ports, quiet = self._ports, set()
            if self._ctl_r in readable:
                _drain(self._ctl_r)
                ports, quiet = self._ports, set()
                continue
            if self._stamp(readable, ports, quiet):
                _poke(self._wake_w)

    def _stamp(self, readable: list[int], ports: Mapping[int, PtyPort], quiet: set[int]) -> bool:
        got = False
        with self._lock:
            t = self._now()
            for fd in readable:
                port = ports[fd]
                try:
                    data = port.read()
                except OSError:  # closed under us (a device replaced its port): the loop says so next
                    data = b""
                if data:
                    self._arrived.append((t, port, data))
                    got = True
                elif not port.connected:
                    quiet.add(fd)
        return got


def _poke(fd: int) -> None:
    with contextlib.suppress(BlockingIOError, OSError):
        os.write(fd, b"\0")


def _drain(fd: int) -> None:
    with contextlib.suppress(BlockingIOError, OSError):
        while os.read(fd, 4096):
            pass
