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
started inside another program keeps that program's setting and stamps no later than before. And it
needs a CPU: on a busy 2-core host a woken thread waited up to ~6 ms for one (0.7 device s at 120×).
So the loop also reads and stamps what has come itself once its devices have worked (`poll`): a
command then waits at most for one tick's work (mostly the IMU's, ~0.5 ms at 120×).
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
from collections.abc import Callable, Mapping
from typing import Generic, TypeVar

from firmware_sim.pty import PtyPort

Owner = TypeVar("Owner")

QUIET_RECHECK_S = 0.005
"""How often a hung-up port is looked at again (wall): a client that closes the port and opens it
again is read at once, even if the loop never saw it gone (both within one of its ticks)."""


class ArrivalStamper(Generic[Owner]):
    """Reads the watched ports as input arrives; `take()` returns it with the device time it came
    and the port's owner (the device the loop hands it to)."""

    def __init__(self, now: Callable[[], float]) -> None:
        self._now = now
        self._lock = threading.Lock()
        self._arrived: list[tuple[float, Owner, bytes]] = []
        self._owners: dict[PtyPort, Owner] = {}
        self._by_fd: dict[int, tuple[PtyPort, Owner]] = {}
        self._wake_r, self._wake_w = os.pipe()  # readable for the loop when something arrived
        self._ctl_r, self._ctl_w = os.pipe()  # wakes the thread: new ports to watch, or stop
        for fd in (self._wake_r, self._wake_w, self._ctl_r, self._ctl_w):
            os.set_blocking(fd, False)
        self._stopping = False
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="firmware_sim-arrivals", daemon=True)
        self._thread.start()

    def fileno(self) -> int:
        """Readable while stamped input waits for `take()` (the loop selects on it)."""
        return self._wake_r

    def watch(self, owners: Mapping[PtyPort, Owner]) -> None:
        """The ports to read (those a client has open) and whose input each is, given by the loop
        every tick; the thread starts on a new set at once."""
        if owners != self._owners:
            self._owners = dict(owners)
            self._by_fd = {port.master_fd: (port, owner) for port, owner in owners.items()}
            _poke(self._ctl_w)

    def take(self) -> tuple[float, list[tuple[float, Owner, bytes]]]:
        """The device time now, and every chunk stamped before it (time, owner, bytes), in the
        order it came. Raises what stopped the thread, if something did (the loop then fails, not
        goes deaf)."""
        if self.error is not None:
            raise RuntimeError("the arrival thread stopped") from self.error
        _drain(self._wake_r)  # first: a chunk stamped after the take below pokes again
        with self._lock:
            t = self._now()
            arrived, self._arrived = self._arrived, []
        return t, arrived

    def poll(self) -> None:
        """Read and stamp what has arrived, from the calling thread, without waiting: the loop calls
        this after its devices' work each tick, so input that came meanwhile is stamped then even
        when the thread waits for a CPU (a busy 2-core host can keep it off one for milliseconds)."""
        by_fd = self._by_fd  # the ports the loop's watch() gave this tick: a client has each open
        if not by_fd:
            return
        try:
            readable = select.select(list(by_fd), [], [], 0)[0]
        except OSError:  # a port closed under us: the thread and the loop's next set see to it
            return
        if readable and self._stamp(readable, by_fd, set()):
            _poke(self._wake_w)

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
        while not self._stopping:
            by_fd = self._by_fd  # the loop's newest set (it pokes _ctl_r when it changes)
            quiet = {fd for fd in quiet if fd in by_fd and not by_fd[fd][0].connected}
            fds = [fd for fd in by_fd if fd not in quiet]
            try:
                wait_s = QUIET_RECHECK_S if quiet else None
                readable, _, _ = select.select([*fds, self._ctl_r], [], [], wait_s)
            except OSError:  # a port was closed under us: the loop's next set leaves it out
                readable = select.select([self._ctl_r], [], [], QUIET_RECHECK_S)[0]
            if self._ctl_r in readable:
                _drain(self._ctl_r)
            elif readable and self._stamp(readable, by_fd, quiet):
                _poke(self._wake_w)

    def _stamp(self, readable: list[int], by_fd: Mapping[int, tuple[PtyPort, Owner]],
               quiet: set[int]) -> bool:
        chunks: list[tuple[Owner, bytes]] = []
        with self._lock:
            for fd in readable:
                port, owner = by_fd[fd]
                try:
                    data = port.read()
                except OSError:  # closed under us (a device replaced its port): the loop says so next
                    data = b""
                if data:
                    chunks.append((owner, data))
                elif not port.connected:
                    quiet.add(fd)
            # the clock after the reads: a byte that came while they ran is not stamped before it came
            t = self._now()
            self._arrived += [(t, owner, data) for owner, data in chunks]
        return bool(chunks)


def _poke(fd: int) -> None:
    with contextlib.suppress(BlockingIOError, OSError):
        os.write(fd, b"\0")


def _drain(fd: int) -> None:
    with contextlib.suppress(BlockingIOError, OSError):
        while os.read(fd, 4096):
            pass
