"""What the byte-streaming drivers (IMU, GNSS) share: one background read loop, one hand-off of
a reader error, one bounded wait — built once, python-can `BusABC` style, on a small surface.

A subclass sets `port`, `timeout_s`, `_t` (a transport with `read_available()` and `close()`),
`_cond` (a Condition) and `_error`, implements :meth:`_on_bytes`, and calls
:meth:`_start_reader`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from northfinder.errors import DeviceError


class StreamReader:
    """Background reader over a byte transport; a context manager."""

    device = "device"
    port: str
    timeout_s: float
    _t: Any
    _cond: threading.Condition
    _error: BaseException | None

    def _on_bytes(self, data: bytes, idle_s: float) -> None:
        """New bytes from the port, called with `_cond` held. `idle_s`: host seconds the port was
        silent before them (0 when bytes kept coming)."""
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
        last_data = time.monotonic()
        silent = False
        while not stop.is_set():
            try:
                data = self._t.read_available()
            except BaseException as exc:  # noqa: BLE001 - handed to the reading thread
                with self._cond:
                    self._error = exc
                    self._cond.notify_all()
                return
            now = time.monotonic()
            if not data:
                silent = True
                continue
            idle_s = now - last_data if silent else 0.0
            last_data, silent = now, False
            with self._cond:
                self._on_bytes(data, idle_s)
                self._cond.notify_all()

    def _wait_locked(
        self, ready: Callable[[], bool], timeout_s: float, timeout_message: Callable[[], str]
    ) -> None:
        """With `_cond` held: wait until `ready()`. The reader's error (port gone, I/O error) is
        raised as it is; after `timeout_s` a DeviceError naming the port with `timeout_message()`."""
        deadline = time.monotonic() + timeout_s
        while not ready():
            if self._error is not None:
                raise self._error
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceError(self.device, self.port, timeout_message())
            self._cond.wait(remaining)

    # -- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the reader thread and close the port."""
        self._stop_reader()
        self._t.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
