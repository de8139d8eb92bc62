"""GNSS receiver driver: NMEA 0183 over serial (docs/PROTOCOLS.md §5), one GnssFix per epoch.

A background thread reads whatever the port delivers, writes it to the raw log as it arrives
(through :class:`northfinder.transport.SerialTransport`, the one logging place: the log is the
NMEA text exactly as received), and feeds it to :class:`northfinder.codecs.nmea.NmeaDecoder`,
which checks checksums, counts bad/truncated/no-fix sentences and assembles GGA+RMC+VTG into a
:class:`~northfinder.codecs.nmea.GnssFix` of the antenna per epoch. :func:`decode_nmea_log` is
the pure replay path: the same decoder on the whole log, so replay gives identical fixes.

Fix times are the receiver's UTC (``GnssFix.time_s``, POSIX seconds), not host time.

Example::

    from northfinder.codecs.nmea import LocalEnu, fixes_to_arrays
    from northfinder.drivers.gnss import Gnss

    with Gnss("/dev/ttyUSB2", raw_log="gnss.nmea") as gnss:
        fixes = gnss.read_fixes(100)                  # 10 s at 10 Hz
        arrays = fixes_to_arrays(fixes)               # ENU about the first fix
        print(arrays.pos_enu_m[-1], gnss.stats)
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import BinaryIO, Protocol

from northfinder.codecs.nmea import GnssFix, NmeaDecoder, NmeaStats
from northfinder.drivers._stream import StreamReader
from northfinder.transport import SerialTransport

__all__ = ["Gnss", "GnssFix", "NmeaStats", "decode_nmea_log"]

DEVICE = "gnss"


def decode_nmea_log(text_or_bytes: str | bytes) -> tuple[list[GnssFix], NmeaStats]:
    """Decode a whole raw NMEA log (replay): every fix and the stream's counters.

    An epoch still open at the end of the log (its VTG not received) is left out, exactly as the
    live driver had not delivered it yet. NMEA is ASCII: text is taken as Latin-1 (a character
    outside it becomes '?', garbage either way); pass the log's bytes for an exact replay.
    """
    if isinstance(text_or_bytes, str):
        data = text_or_bytes.encode("latin-1", errors="replace")
    else:
        data = bytes(text_or_bytes)
    decoder = NmeaDecoder()
    fixes = decoder.feed(data)
    return fixes, decoder.stats


class _ByteTransport(Protocol):  # what the driver needs from SerialTransport (tests may pass their own)
    url: str

    def read_available(self, max_bytes: int = ...) -> bytes: ...
    def close(self) -> None: ...


class Gnss(StreamReader):
    """A GNSS receiver streaming NMEA on a pyserial URL; a context manager with a background reader.

    On open it waits up to `timeout_s` for one good NMEA sentence (any type, checksum right) and
    raises DeviceError naming the port if none comes: the wrong port, or the receiver is off.
    """

    device = DEVICE

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        raw_log: str | Path | BinaryIO | None = None,
        timeout_s: float = 2.0,
        wait_for_data: bool = True,
        transport: _ByteTransport | None = None,
    ) -> None:
        super().__init__(port, timeout_s)
        self._t = transport if transport is not None else SerialTransport(
            port, device=DEVICE, baudrate=baudrate, timeout_s=0.05, raw_log=raw_log
        )
        self._decoder = NmeaDecoder()
        self._pending: list[GnssFix] = []
        self._start_reader()
        if wait_for_data:
            try:
                self._wait_for_first_sentence()
            except BaseException:
                self.close()
                raise

    # -- background reader -------------------------------------------------------------------
    def _on_bytes(self, data: bytes) -> None:
        self._pending.extend(self._decoder.feed(data))

    def _good_sentences(self) -> int:
        s = self._decoder.stats
        return s.sentences + s.unknown + s.malformed

    def _wait_for_first_sentence(self) -> None:
        def message() -> str:
            s = self._decoder.stats
            what = (f"{s.bytes} bytes, {s.bad_checksum} with a bad checksum, {s.truncated} truncated"
                    if s.bytes else "no bytes at all")
            return (f"no NMEA sentences on {self.port} within {self.timeout_s:g} s ({what}) — is it the "
                    "GNSS receiver's port, at 115200 baud?")

        with self._cond:
            self._wait_locked(lambda: self._good_sentences() > 0, self.timeout_s, message)

    def _wait(self, ready: Callable[[], bool], wait_s: float, what: Callable[[], str]) -> None:
        """Wait (holding the condition) until `ready()`; DeviceError naming the port on timeout."""

        def message() -> str:
            s = self._decoder.stats
            return (f"{what()} within {wait_s:g} s on {self.port} ({s.fixes} fixes so far, {s.no_fix} "
                    "no-fix sentences) — has the receiver a fix (antenna, sky view) and is it still "
                    "streaming?")

        self._wait_locked(ready, wait_s, message)

    # -- fixes -------------------------------------------------------------------------------
    def read_fixes(self, n: int, timeout_s: float | None = None) -> list[GnssFix]:
        """The next `n` fixes, blocking (default wait: timeout_s + n seconds, enough at 1 Hz)."""
        n = int(n)
        if n < 1:
            raise ValueError("n must be >= 1")
        wait_s = self.timeout_s + n if timeout_s is None else float(timeout_s)
        with self._cond:
            self._wait(lambda: len(self._pending) >= n, wait_s,
                       lambda: f"only {len(self._pending)} of {n} fixes arrived")
            out, self._pending = self._pending[:n], self._pending[n:]
        return out

    def fixes_until(self, t_s: float, timeout_s: float | None = None) -> list[GnssFix]:
        """Every pending fix with ``time_s <= t_s``, once a fix at or past `t_s` has arrived (so none
        up to `t_s` is still on its way). `t_s` is receiver UTC in POSIX seconds, as ``GnssFix.time_s``."""
        t_s = float(t_s)
        with self._cond:
            last = self._pending[-1].time_s if self._pending else None
            wait_s = self.timeout_s if timeout_s is None else float(timeout_s)
            if timeout_s is None and last is not None and t_s > last:
                wait_s += t_s - last
            self._wait(lambda: bool(self._pending) and self._pending[-1].time_s >= t_s, wait_s,
                       lambda: f"no fix at or after t = {t_s:.2f} s")
            k = next((i for i, f in enumerate(self._pending) if f.time_s > t_s), len(self._pending))
            out, self._pending = self._pending[:k], self._pending[k:]
        return out

    def discard_pending(self) -> int:
        """Drop fixes decoded but not read yet; returns how many."""
        with self._cond:
            n, self._pending = len(self._pending), []
        return n

    @property
    def pending(self) -> int:
        """Fixes decoded and not read yet."""
        with self._cond:
            return len(self._pending)

    @property
    def stats(self) -> NmeaStats:
        """A snapshot of the stream counters."""
        with self._cond:
            return replace(self._decoder.stats)

    # -- lifetime ----------------------------------------------------------------------------
    def __repr__(self) -> str:
        return f"Gnss({self.port!r})"
