"""Serial transports: open any pyserial URL and log its raw traffic in one place.

A :class:`SerialTransport` wraps a pyserial object the way a pymeasure adapter does: the serial
object is private, and the public ``write`` / ``read*`` methods are the only way bytes move,
so they are the one place where traffic is logged. Two logs are offered, both optional:

* ``raw_log`` — a binary file that receives every byte *read*, exactly as it arrived (what a
  replay needs: the IMU's raw stream); a path is truncated, so one file holds one session;
* ``transcript`` — a text file with one timestamped line per write (``>``) and per read
  (``<``), for a line protocol such as the SMC100's.

Ports are pyserial URLs: a device path (``/dev/ttyUSB0``, ``/dev/pts/3``), ``socket://host:port``,
``loop://`` or ``spy://PORT`` (pyserial's traffic tap). Local device paths are opened with
``exclusive=True`` so that a second program (or a second driver) cannot share the port silently.
A port that does not exist, is busy or cannot be opened raises
:class:`northfinder.errors.DeviceError` naming the port and saying what to do.

The CAN side of the transports is :func:`open_can_bus`: python-can's ``can.Bus`` except that an
``slcan`` bus is a :class:`ChunkedSlcanBus`, the stock client reading every waiting byte at once
(see its docstring; dropped when python-can releases the same change).

Example::

    with SerialTransport("/dev/pts/3", device="turntable", baudrate=57600,
                         transcript="stage.txt") as t:
        t.write(b"1VE\\r\\n")
        print(t.read_until(b"\\r\\n"))
"""

from __future__ import annotations

import errno
import io
import re
import select
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, BinaryIO, TextIO

import can
import serial
from can.exceptions import error_check
from can.interfaces.slcan import slcanBus

from northfinder.errors import DeviceError

__all__ = ["SLCAN_STOCK_READS_BYTEWISE", "ChunkedSlcanBus", "SerialTransport", "is_local_path",
           "open_can_bus", "open_serial"]


def is_local_path(url: str) -> bool:
    """True for a device path (``/dev/…``, ``COM3``), False for a ``scheme://`` URL."""
    return "://" not in url


def _explain_open_error(device: str, url: str, exc: Exception) -> DeviceError:
    """Turn a pyserial/OS error into one line that names the port and says what to do."""
    text = str(exc)
    err = getattr(exc, "errno", None)
    if "exclusively lock" in text or err in (errno.EAGAIN, errno.EBUSY, errno.EWOULDBLOCK):
        return DeviceError(
            device, url, f"port {url} is busy: another program (or another driver here) has it open "
            "— close that first"
        )
    if err == errno.ENOENT or "No such file" in text:
        return DeviceError(
            device, url, f"no such port {url} — check the path (ls /dev/tty* /dev/pts/*) or the bench config"
        )
    if err == errno.EACCES or "Permission denied" in text:
        return DeviceError(
            device, url, f"permission denied on {url} — add your user to the 'dialout' group or fix the "
            "device permissions"
        )
    if "ConnectionRefused" in type(exc).__name__ or "refused" in text.lower():
        return DeviceError(device, url, f"connection to {url} refused — is the server running on that port?")
    return DeviceError(device, url, f"cannot open {url} ({text}) — check the port and the bench config")


MIN_WRITE_TIMEOUT_S = 5.0
"""A write waits at least this long (host) for the line to take it: a streaming port reads with a
short timeout (the IMU's 0.05 s), but a command written to it must not fail because a loaded host
scheduled the other end late (seen as "Write timeout" on the IMU's pty under load: with 0.05 s, and
once with 1 s — a find's first `=CONFIG,1` in CI, 4 workers beside the UML guest on 2 cores). A
port that takes nothing for 5 s is still named at once after that."""


def open_serial(url: str, *, device: str, baudrate: int, timeout_s: float, **kwargs) -> serial.SerialBase:
    """Open `url` with pyserial (exclusive for local paths, also behind ``spy://``); DeviceError on
    any failure. Reads time out after `timeout_s`, writes after at least MIN_WRITE_TIMEOUT_S."""
    if not url:
        raise DeviceError(device, None, "no port given — set it in the bench config or on the command line")
    if is_local_path(url) or url.startswith("spy://"):
        kwargs.setdefault("exclusive", True)
    try:
        return serial.serial_for_url(url, baudrate=baudrate, timeout=timeout_s,
                                     write_timeout=max(timeout_s, MIN_WRITE_TIMEOUT_S), **kwargs)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise _explain_open_error(device, url, exc) from None


def _open_log(target, mode: str) -> tuple[IO | None, bool]:
    """A path opens a file we own (and close); a file object is used as is."""
    if target is None:
        return None, False
    if isinstance(target, (str, Path)):
        path = Path(target)
        path.parent.mkdir(parents=True, exist_ok=True)
        return open(path, mode), True  # noqa: SIM115 - closed in SerialTransport.close
    return target, False


class SerialTransport:
    """A pyserial port whose reads and writes are logged in one place.

    `device` is the short name used in error messages ("imu", "turntable"). Reads return
    whatever arrived (possibly fewer bytes than asked) after `timeout_s`; a pyserial error
    while the port is open becomes a DeviceError naming the port.
    """

    def __init__(
        self,
        url: str,
        *,
        device: str,
        baudrate: int,
        timeout_s: float = 1.0,
        raw_log: str | Path | BinaryIO | None = None,
        transcript: str | Path | TextIO | None = None,
        **serial_kwargs,
    ) -> None:
        self.url = url
        self.device = device
        self.timeout_s = timeout_s
        self.drained = False
        """Whether the last read_available found nothing waiting (all the port had sent was read)."""
        self._serial = open_serial(url, device=device, baudrate=baudrate, timeout_s=timeout_s,
                                   **serial_kwargs)
        self._raw_log, self._own_raw = _open_log(raw_log, "wb")  # one session per raw log: replayable
        self._transcript, self._own_transcript = _open_log(transcript, "a")
        self._log_lock = threading.Lock()
        self._t0 = time.monotonic()
        self.bytes_read = 0
        self.bytes_written = 0

    # -- the one logging place -------------------------------------------------------------
    def _log(self, direction: str, data: bytes) -> None:
        if not data:
            return
        with self._log_lock:
            if direction == "<" and self._raw_log is not None:
                self._raw_log.write(data)
                self._raw_log.flush()
            if self._transcript is not None:
                stamp = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime())
                frac = f"{time.time() % 1:.6f}"[1:]
                text = data.decode("ascii", errors="backslashreplace")
                text = text.replace("\r", "\\r").replace("\n", "\\n")
                self._transcript.write(f"{stamp}{frac}Z {direction} {text}\n")
                self._transcript.flush()

    def note(self, text: str) -> None:
        """Write a comment line (``#``) to the transcript, e.g. what a poll loop is waiting for."""
        if self._transcript is not None:
            with self._log_lock:
                self._transcript.write(f"# {text}\n")
                self._transcript.flush()

    def _wrap(self, exc: Exception) -> DeviceError:
        return DeviceError(self.device, self.url,
                           f"I/O error on {self.url} ({exc}) — was the device unplugged?")

    # -- public I/O ------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        """Send all of `data`."""
        try:
            self._serial.write(data)
            self._serial.flush()
        except (serial.SerialException, OSError) as exc:
            raise self._wrap(exc) from None
        self.bytes_written += len(data)
        self._log(">", data)

    def read(self, size: int) -> bytes:
        """Up to `size` bytes, waiting at most the port timeout."""
        try:
            data = self._serial.read(size)
        except (serial.SerialException, OSError, TypeError) as exc:
            raise self._wrap(exc) from None
        self.bytes_read += len(data)
        self._log("<", data)
        return data

    def read_available(self, max_bytes: int = 1 << 16) -> bytes:
        """Whatever is waiting; if nothing is, wait up to the timeout for the first byte and then
        take everything that came with it (one log entry, few small chunks). `drained` then says
        whether nothing was waiting: every byte that came before had been read."""
        try:
            if type(self._serial).__module__ == "serial.urlhandler.protocol_socket":  # its in_waiting: 0 or 1
                return self._logged(self._read_socket(self._serial._socket, max_bytes))
            waiting = self._serial.in_waiting
            self.drained = not waiting
            if waiting:
                data = self._serial.read(min(waiting, max_bytes))
            else:
                data = self._serial.read(1)
                if data:
                    more = self._serial.in_waiting
                    if more:
                        data += self._serial.read(min(more, max_bytes - 1))
        except (serial.SerialException, OSError, TypeError) as exc:
            raise self._wrap(exc) from None
        return self._logged(data)

    def _logged(self, data: bytes) -> bytes:
        self.bytes_read += len(data)
        self._log("<", data)
        return data

    def _read_socket(self, sock: Any, max_bytes: int) -> bytes:
        """read_available on pyserial's socket:// (whose in_waiting says 1 for any number of bytes
        waiting, so the generic path read a stream one byte per call): one recv of all that is
        there, after waiting up to the timeout for the first."""
        ready, _, _ = select.select([sock], [], [], 0)
        self.drained = not ready
        if not ready and not select.select([sock], [], [], self.timeout_s)[0]:
            return b""
        try:
            data = sock.recv(max_bytes)
        except BlockingIOError:
            return b""
        if not data:
            raise serial.SerialException("socket disconnected")
        return data

    def read_until(self, terminator: bytes = b"\r\n", size: int | None = 256) -> bytes:
        """Bytes up to and including `terminator`, or what came before the timeout / `size`."""
        try:
            data = self._serial.read_until(terminator, size)
        except (serial.SerialException, OSError, TypeError) as exc:
            raise self._wrap(exc) from None
        self.bytes_read += len(data)
        self._log("<", data)
        return data

    def reset_input_buffer(self) -> None:
        """Drop unread input (logged: the dropped bytes are read first, so nothing is lost silently)."""
        try:
            waiting = self._serial.in_waiting
        except (serial.SerialException, OSError, TypeError) as exc:
            raise self._wrap(exc) from None
        if waiting:
            old = self._serial.timeout
            self._serial.timeout = 0
            try:
                self.read(waiting)
            finally:
                self._serial.timeout = old

    @property
    def timeout(self) -> float:
        return self._serial.timeout

    @timeout.setter
    def timeout(self, value_s: float) -> None:
        self._serial.timeout = value_s

    @property
    def is_open(self) -> bool:
        return bool(self._serial.is_open)

    def close(self) -> None:
        """Close the port and any log file this transport opened itself. Idempotent."""
        try:
            self._serial.close()
        except (serial.SerialException, OSError):
            pass
        with self._log_lock:
            for handle, own in ((self._raw_log, self._own_raw), (self._transcript, self._own_transcript)):
                if handle is None:
                    continue
                try:
                    handle.close() if own else handle.flush()
                except (OSError, ValueError, io.UnsupportedOperation):
                    pass
            self._raw_log = self._transcript = None

    def __enter__(self) -> SerialTransport:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"SerialTransport({self.url!r}, device={self.device!r})"


class StampedTransport:
    """A SerialTransport whose every received chunk is stamped with the host's monotonic clock (the
    GNSS alignment's host time alignment of two ports, northfinder.runs.gnss.time_alignment).

    Appends "host_s total_bytes" to `stamp_path` (flushed every `flush_s`, and at close), so the
    arrival time of any byte of the raw log can be looked up afterwards.
    """

    def __init__(self, inner: Any, stamp_path: str | Path, flush_s: float = 0.5):
        self._inner = inner
        self.url = inner.url
        self._fh = open(stamp_path, "w", encoding="ascii")  # noqa: SIM115 - closed in close()
        self._total = 0
        self._flush_s = flush_s
        self._last_flush = time.monotonic()

    def write(self, data: bytes) -> None:
        self._inner.write(data)

    @property
    def drained(self) -> bool:
        return bool(getattr(self._inner, "drained", False))

    def read_available(self, max_bytes: int = 1 << 16) -> bytes:
        data = self._inner.read_available(max_bytes)
        if data:
            now = time.monotonic()
            self._total += len(data)
            self._fh.write(f"{now:.6f} {self._total}\n")
            if now - self._last_flush >= self._flush_s:
                self._fh.flush()
                self._last_flush = now
        return data

    def close(self) -> None:
        try:
            self._inner.close()
        finally:
            if not self._fh.closed:
                self._fh.close()


# --------------------------------------------------------------------------------------------
# CAN: the slcan client read in chunks


def _release(version: str) -> tuple[int, ...]:
    """``"4.6.1"`` → ``(4, 6, 1)``; a suffix is dropped (``"4.7.0rc1"`` → ``(4, 7, 0)``)."""
    head = re.match(r"\d+(?:\.\d+)*", version)
    return tuple(int(p) for p in head.group(0).split(".")) if head else ()


LAST_BYTEWISE_PYTHON_CAN = (4, 6, 1)
"""The newest python-can release whose slcan client reads one byte per pyserial call (issue #2027;
fixed on python-can's main branch by pull request #2028, merged 2026-02, in no release yet)."""

SLCAN_STOCK_READS_BYTEWISE = _release(can.__version__) <= LAST_BYTEWISE_PYTHON_CAN
"""True while the installed python-can needs :class:`ChunkedSlcanBus`. tests/test_slcan_chunked.py
measures the stock client's reads per frame and fails, saying "drop ChunkedSlcanBus", once a
release reads in chunks."""


class ReadPacer:
    """A short pause after each read while a stream runs slowly, so that a real-time stream is read
    in forty calls a second, not in one per simulator tick or USB packet.

    Why: at real time a read brings a few frames, and the wake-up costs more than the frames do
    (measured, KVH at 1 kHz: the reader 2.4 % of a core with a 10 ms pause, 1.0 % with 25 ms; 3–4 %
    without). The CAN reader did not gain from it (its cost is per frame, in python-can's Notifier
    and canopen), so only the IMU drivers pace their reads. The pause adds `pause_s` of latency
    (25 ms: a fortieth of the sequencer's 1 s dwell grid), nothing at the rates where latency counts:
    the rate is measured over each `window_s` of wall time, and the pause stops as soon as it is at
    or above `below_bytes_s` (a time-scaled simulator). Nor is there a pause after a read of
    `small_bytes` or more (default: two pauses' worth of bytes at `below_bytes_s`): bytes were
    waiting, the reader is behind. (The rate is what the reader took, so on a starved host paused
    reads could measure "slow" again and again while the backlog grew until the simulator dropped
    bytes.) The clock and the sleep are parameters for tests."""

    def __init__(self, below_bytes_s: float, pause_s: float = 0.025, window_s: float = 0.25,
                 small_bytes: int | None = None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep):
        self.below_bytes_s, self.pause_s = float(below_bytes_s), float(pause_s)
        self.window_s = float(window_s)
        two_pauses = int(2 * self.below_bytes_s * self.pause_s)
        self.small_bytes = two_pauses if small_bytes is None else int(small_bytes)
        self._clock, self._sleep = clock, sleep
        self._t0, self._bytes = clock(), 0
        self.slow = False
        """The last window's rate was under below_bytes_s (False until a window has passed)."""

    def after_read(self, n_bytes: int) -> None:
        """Called after each read that brought `n_bytes` (> 0): pause if the stream is slow and the
        read took all there was."""
        self._bytes += n_bytes
        now = self._clock()
        if now - self._t0 >= self.window_s:
            self.slow = self._bytes / (now - self._t0) < self.below_bytes_s
            self._t0, self._bytes = now, 0
        if self.slow and n_bytes < self.small_bytes:
            self._sleep(self.pause_s)


class ChunkedSlcanBus(slcanBus):
    """python-can's slcan client with its receive path reading every waiting byte in one call.

    The stock ``_read`` (python-can ≤ 4.6.1) calls ``serial.read(1)`` once per byte — about 22
    calls for a 22-byte TPDO line, each a syscall, which caps the client at ~8 k frames/s and was
    most of the find's CPU at high time scales (issue 27). This override does what python-can's
    pull request #2028 does upstream: read ``max(1, in_waiting)`` bytes at once into the same
    ``_buffer`` and hand back one line at a time, up to and including its first terminator
    (``\\r`` for a frame or an OK, ``\\a`` for an error, as in the Lawicel protocol), keeping the
    rest for the next call. Lines, and so frames, are the same as the stock client's on the same
    bytes (tests/test_slcan_chunked.py). Everything else (open, bitrate, send, shutdown,
    get_version, the line parser in ``_recv_internal``) is the stock class's.
    """

    _fd: int | None = None
    _fd_looked_up = False

    def _take_line(self) -> str | None:
        """The first whole line in the buffer (terminator included), removed from it; or None."""
        buf = self._buffer
        end = buf.find(self._OK)
        error = buf.find(self._ERROR, 0, end if end >= 0 else len(buf))
        if error >= 0:
            end = error
        if end < 0:
            return None
        line = buf[: end + 1].decode()
        del buf[: end + 1]
        return line

    def _read(self, timeout: float | None) -> str | None:
        deadline = serial.Timeout(timeout)
        port = self.serialPortOrig
        if not self._fd_looked_up:  # once: the read path runs per frame
            self._fd, self._fd_looked_up = _select_fd(port), True
        fd = self._fd
        while True:
            line = self._take_line()
            if line is not None:
                return line
            with error_check("Could not read from serial device"):
                waiting = port.in_waiting
                if not waiting and fd is not None:
                    # nothing there: sleep in select until bytes come or the caller's time is up —
                    # not in read(1)'s 1 ms port time-out, which woke this thread 1000 times a second
                    # and cost ~3 % of a core at real time with the node sending 200 frames/s
                    if not select.select([fd], [], [], deadline.time_left())[0]:
                        return None
                    waiting = port.in_waiting
                # bytes waiting: read returns them at once; none (a port without a file
                # descriptor): read(1) blocks up to the port's own time-out, as the stock client does
                chunk = port.read(max(1, waiting))
            if chunk:
                self._buffer.extend(chunk)
            elif deadline.expired():
                return None


def _select_fd(port: Any) -> int | None:
    """The port's file descriptor when select() can wait on it (a device or pty); None for
    pyserial URL transports without one (loop://, socket:// wrap theirs)."""
    try:
        fd = port.fileno()
    except (AttributeError, OSError, ValueError, serial.SerialException):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


def open_can_bus(interface: str, channel: str | int | None, *, bitrate: int, **options: Any) -> can.BusABC:
    """``can.Bus(interface=…, channel=…, bitrate=…, **options)``, except that ``slcan`` opens a
    :class:`ChunkedSlcanBus` while the installed python-can reads slcan one byte at a time."""
    if interface == "slcan" and SLCAN_STOCK_READS_BYTEWISE:
        return ChunkedSlcanBus(channel=channel, bitrate=bitrate, **options)
    return can.Bus(interface=interface, channel=channel, bitrate=bitrate, **options)
