"""A pseudo-terminal a device speaks on: raw mode, non-blocking master, clients get the slave path.

The simulator closes its own slave descriptor, so it can tell whether a client has the port
open (the master polls POLLHUP when nobody does): with no client, output goes nowhere, as
bytes sent down an unplugged cable, and a client that opens the port later gets fresh data.
Output never blocks the loop: what the kernel does not take at once (about 12 kB on Linux)
waits in a bounded backlog; what does not fit there is dropped and counted, as a host-side
UART overrun loses bytes while the device keeps transmitting.

This is the one place that logs the raw traffic of every pty (logger `firmware_sim.pty`,
DEBUG; `firmware-sim -vv`), at most 200 bytes per read or write.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import termios
import threading
import tty

log = logging.getLogger("firmware_sim.pty")

DEFAULT_BACKLOG_BYTES = 512 * 1024
"""Bytes held for a connected but slow client before new ones are dropped (≈ 14 s of KVH data)."""


def make_raw(fd: int) -> None:
    """cfmakeraw: no echo, no line editing, no signals, no CR/NL translation, 8-bit bytes."""
    attrs = termios.tcgetattr(fd)
    attrs[0] &= ~(
        termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP
        | termios.INLCR | termios.IGNCR | termios.ICRNL | termios.IXON
    )
    attrs[1] &= ~termios.OPOST
    attrs[3] &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    attrs[2] &= ~(termios.CSIZE | termios.PARENB)
    attrs[2] |= termios.CS8
    attrs[6][termios.VMIN] = 1
    attrs[6][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


class PtyPort:
    """One pty pair. `path` is what a client opens; the device reads and writes the master."""

    def __init__(self, name: str = "pty", backlog_bytes: int = DEFAULT_BACKLOG_BYTES) -> None:
        self.name = name
        self.backlog_bytes = int(backlog_bytes)
        self.master_fd, slave_fd = os.openpty()
        try:
            make_raw(slave_fd)
            tty.setraw(self.master_fd)
            self.path = os.ttyname(slave_fd)
        finally:
            os.close(slave_fd)
        os.set_blocking(self.master_fd, False)
        self._poll = select.poll()
        self._poll.register(self.master_fd, select.POLLOUT)
        self._poll_lock = threading.Lock()  # one poll object: concurrent poll() calls raise
        self._pending = bytearray()
        self.bytes_written = 0
        self.bytes_dropped = 0
        """Overrun: bytes a connected client was too slow to take."""
        self.bytes_unheard = 0
        """Bytes sent while no client had the port open."""
        self.bytes_read = 0
        self.closed = False
        log.debug("%s: opened %s", name, self.path)

    def fileno(self) -> int:
        return self.master_fd

    def read(self, max_bytes: int = 65536) -> bytes:
        """What the client sent, without blocking (b'' if nothing waits)."""
        if self.closed:
            return b""
        try:
            data = os.read(self.master_fd, max_bytes)
        except BlockingIOError:
            return b""
        except OSError as exc:
            if exc.errno == errno.EIO:  # no client has the slave open
                return b""
            raise
        self.bytes_read += len(data)
        if data:
            log.debug("%s <- %r", self.name, data[:200])
        return data

    @property
    def connected(self) -> bool:
        """True while some client has the slave open."""
        if self.closed:
            return False
        with self._poll_lock:  # the loop and the arrival thread (firmware_sim.arrivals) both ask
            events = self._poll.poll(0)
        return not any(ev & select.POLLHUP for _, ev in events)

    def watch_fileno(self) -> int | None:
        """The master fd for a loop to watch for input; None while closed or while no client has
        the slave open (a client-less master polls readable — hang-up — all the time, which would
        make the loop spin)."""
        return None if self.closed or not self.connected else self.master_fd

    def write(self, data: bytes) -> None:
        """Queue bytes for the client and push what the kernel takes now; overflow is dropped."""
        if self.closed or not data:
            return
        if log.isEnabledFor(logging.DEBUG):
            log.debug("%s -> %r", self.name, bytes(data[:200]))
        if not self.connected:
            self.bytes_unheard += len(data) + len(self._pending)
            self._pending.clear()
            return
        room = self.backlog_bytes - len(self._pending)
        if len(data) > room:
            self.bytes_dropped += len(data) - max(room, 0)
            data = data[: max(room, 0)]
        self._pending += data
        self.flush()

    def flush(self) -> int:
        """Push pending bytes into the pty until the kernel refuses more; returns how many went."""
        sent = 0
        while self._pending and not self.closed:
            try:
                n = os.write(self.master_fd, self._pending)
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno in (errno.EIO, errno.EAGAIN):
                    break
                raise
            if n <= 0:
                break
            self.bytes_written += n
            sent += n
            del self._pending[:n]
        return sent

    @property
    def pending(self) -> int:
        """Bytes waiting in the backlog for the client to read."""
        return len(self._pending)

    def discard(self) -> None:
        """Forget every byte the client has not read yet: the backlog and the kernel's queue."""
        if self.closed:
            return
        self._pending.clear()
        try:
            termios.tcflush(self.master_fd, termios.TCOFLUSH)  # what the old client left unread
        except termios.error:
            pass

    def close(self) -> None:
        """Close both ends; a connected client sees the port vanish. Idempotent."""
        if self.closed:
            return
        self.closed = True
        self._pending.clear()
        try:
            os.close(self.master_fd)
        except OSError:
            pass
        log.debug("%s: closed %s (written %d, dropped %d)", self.name, self.path,
                  self.bytes_written, self.bytes_dropped)

    def __enter__(self) -> PtyPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
