"""What the byte-streaming drivers (IMU, GNSS) share: one background read loop, one hand-off of
a reader error, one bounded wait — built once, python-can `BusABC` style, on a small surface.

A subclass calls ``StreamReader.__init__(port, timeout_s)`` (which owns the shared state: the
port, the Condition, the reader's error), opens its transport into `_t` (`read_available()` and
`close()`), implements :meth:`_on_bytes`, and calls :meth:`_start_reader`. :func:`wait_until` is
the one bounded wait on a Condition; the CAN accelerometer waits on it too.

No byte is interpreted here: the frames are the subclasses' codecs' (KVH format A per the 1775
ICD 56-0298 §5, the STIM datagrams per TS1524 §5, NMEA 0183 sentences). Host time only bounds
the waits; which samples were lost, and how many, the codecs decide from the devices' own
counters and the bytes that came (a pause of the device is a gap whose bytes never came).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from northfinder.errors import DeviceError
from northfinder.transport import ReadPacer


def wait_until(
    cond: threading.Condition,
    ready: Callable[[], bool],
    timeout_s: float,
    error: Callable[[], BaseException | None],
    on_timeout: Callable[[], BaseException],
) -> None:
    """With `cond` held: wait until `ready()`. `error()` (a reader's or a bus's error, or None) is
    raised as soon as it is set; after `timeout_s` host seconds, `on_timeout()` is raised. Host
    time only bounds the wait; `ready()` decides in device terms (samples, counters)."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        exc = error()
        if exc is not None:
            raise exc
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise on_timeout()
        cond.wait(remaining)


def read_bounds(n_samples: int, rate_hz: float, default_s: float,
                timeout_s: float | None) -> tuple[int, float]:
    """A `read(n_samples, timeout_s)`'s sample count (≥ 1, else ValueError) and its host bound: the
    given time-out, else the reader's own plus the samples' duration."""
    n = int(n_samples)
    if n < 1:
        raise ValueError("n_samples must be >= 1")
    return n, (default_s + n / rate_hz if timeout_s is None else float(timeout_s))


class StreamReader:
    """Background reader over a byte transport; a context manager."""

    _newest_index: int | None = None
    """Device index of the newest sample decoded (a sample stream's `_on_bytes` sets it)."""

    device = "device"
    read_pace_below_bytes_s = 0.0
    """transport.ReadPacer's rate: under it the reader pauses 10 ms after each read (0: never).
    SampleQueue sets it for the sample streams; a GNSS receiver's few sentences a second are not
    worth the latency."""

    def __init__(self, port: str, timeout_s: float) -> None:
        self.port = port
        self.timeout_s = float(timeout_s)
        self._t: Any = None
        """The byte transport (set by the subclass once it is open)."""
        self._cond = threading.Condition()
        self._error: BaseException | None = None
        """The reader thread's error, handed to the next waiting call."""
        self._caught_up: tuple[int, int | None] = (0, None)
        """(times the reader found the link drained, the newest sample index decoded then)."""

    def _on_bytes(self, data: bytes) -> None:
        """New bytes from the port, called with `_cond` held."""
        raise NotImplementedError

    # -- the reader thread -------------------------------------------------------------------
    def _start_reader(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._read_loop, name=f"{self.device}-reader {self.port}", daemon=True
        )
        self._thread.start()

    def _stop_reader(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def _read_loop(self) -> None:
        stop = self._stop  # a reconnect replaces the event; this thread answers to its own
        pacer = ReadPacer(self.read_pace_below_bytes_s) if self.read_pace_below_bytes_s else None
        while not stop.is_set():
            newest = self._newest_index  # only this thread changes it
            try:
                data = self._t.read_available()
            except BaseException as exc:  # noqa: BLE001 - handed to the reading thread
                with self._cond:
                    self._error = exc
                    self._cond.notify_all()
                return
            if not data:
                continue
            with self._cond:
                if getattr(self._t, "drained", False):
                    self._caught_up = (self._caught_up[0] + 1, newest)
                self._on_bytes(data)
                self._cond.notify_all()
            if pacer is not None:
                pacer.after_read(len(data))

    def _wait_locked(
        self, ready: Callable[[], bool], timeout_s: float, timeout_message: Callable[[], str]
    ) -> None:
        """With `_cond` held: wait until `ready()`. The reader's error (port gone, I/O error) is
        raised as it is; after `timeout_s` a DeviceError naming the port with `timeout_message()`."""
        wait_until(self._cond, ready, timeout_s, lambda: self._error,
                   lambda: DeviceError(self.device, self.port, timeout_message()))

    # -- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the reader thread and close the port."""
        self._stop_reader()
        self._t.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SampleQueue:
    """The queue of decoded samples a sample stream's reader (a StreamReader subclass) keeps for
    `read`, under the reader's Condition `_cond`: `_pending`, chunks of (device indices, the model's
    samples), `_pending_n` samples in them, and `_newest_index`, the device index of the newest
    decoded."""

    read_pace_below_bytes_s = 100_000.0
    """StreamReader's ReadPacer rate for a sample stream: a KVH at 1 kHz is 36 kB/s, a STIM300 tens
    of kB/s; a time-scaled stream above it is never paused."""

    port: str
    _cond: threading.Condition
    _error: BaseException | None
    _wait_locked: Callable[..., None]
    _pending: list[tuple[Any, Any]]
    _pending_n: int
    _newest_index: int | None

    def _take_pending(self, n: int, cut: Callable[[Any, int, int], Any]) -> list[tuple[Any, Any]]:
        """With `_cond` held and n samples queued: the first n as (indices, samples) chunks, in
        order; only the chunks needed (a long backlog is not copied on every read). `cut(samples,
        lo, hi)` slices a chunk's samples."""
        taken, got = [], 0
        while got < n:
            index, samples = self._pending.pop(0)
            k = min(len(index), n - got)
            taken.append((index[:k], cut(samples, 0, k)))
            if k < len(index):
                self._pending.insert(0, (index[k:], cut(samples, k, len(index))))
            got += k
        self._pending_n -= n
        return taken

    def next_index(self, timeout_s: float) -> int:
        """Device index of the sample the next read returns, once one is decoded (at most
        `timeout_s` host seconds; DeviceError naming the port after that). Reads nothing."""
        with self._cond:
            self._wait_locked(
                lambda: self._pending_n >= 1, timeout_s,
                lambda: f"no sample arrived within {timeout_s:g} s on {self.port} "
                "— is the IMU still streaming (cable, rate, not left in config mode)?")
            return int(self._pending[0][0][0])

    def discard_pending(self) -> int:
        """Drop samples decoded but not read yet (e.g. those from before a move); returns how many."""
        with self._cond:
            n, self._pending, self._pending_n = self._pending_n, [], 0
        return n

    def newest_index(self) -> int | None:
        """Device index of the newest sample decoded (read or not); None before the first."""
        with self._cond:
            return self._newest_index

    def caught_up_index(self, timeout_s: float) -> int | None:
        """The newest sample index decoded when the reader next finds the link drained (every byte
        the device had sent read and decoded): at that host moment the device clock is at least
        there, and — unlike :meth:`newest_index` behind a backlog — not far ahead of it. After
        `timeout_s` host seconds without that (a link that never drains), the newest index."""
        with self._cond:
            seen = self._caught_up[0]
            if self._cond.wait_for(lambda: self._caught_up[0] > seen or self._error is not None, timeout_s) \
                    and self._error is None and self._caught_up[1] is not None:
                return self._caught_up[1]
            return self._newest_index

    def wait_decoded(self, n: int, timeout_s: float) -> bool:
        """Wait until `n` more samples have been decoded, at most `timeout_s` host seconds."""
        with self._cond:
            target = self._pending_n + int(n)
            return self._cond.wait_for(lambda: self._pending_n >= target or self._error is not None,
                                       timeout_s) and self._error is None
