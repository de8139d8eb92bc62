"""KVH 1750/1760/1775 IMU driver, format A (docs/PROTOCOLS.md §2).

The dialogue follows the KVH 1775 technical manual §7: every configuration command is confirmed
by its echo (``=DR,100`` → ``DR,100``), and an ``INVALID,…`` or ``USAGE,…`` answer is a
DeviceError naming the command the unit refused. Echoes, query replies and BIT messages (§5.3)
that arrive between data messages are skipped by the decoder like any non-frame bytes (no sample
is counted lost for them); BIT messages are kept (:meth:`Imu.built_in_test`: the power-up one, or
``?BIT``, which the manual allows in Normal Mode, §8.5).

A background thread reads whatever the port delivers, writes it to the raw log as it arrives
(through :class:`northfinder.transport.SerialTransport`, the one logging place), and feeds it to
:class:`northfinder.codecs.kvh.KvhDecoder`, which finds headers, checks CRCs, resyncs, decodes
all complete frames of the chunk at once and unwraps the 7-bit sequence into a monotonic device
sample index. :meth:`Imu.read` blocks until the next n samples are there. Gyro fields become
rad/s whatever the device's ``ROTFMT`` (delta angle or rate) and ``ROTUNITS`` (rad or deg);
``time_s = sample_index / rate_hz`` is device time.

:func:`northfinder.codecs.kvh.decode_imu_stream` (re-exported here) is the pure replay path: the
same decoder and conversion, so a raw log replays to bit-identical arrays.

Example::

    from northfinder.drivers.imu import Imu

    with Imu("/dev/ttyUSB1", raw_log="imu.raw") as imu:
        imu.configure(rate_hz=1000, rot_format="DELTA", rot_units="RAD")
        block = imu.read(1000)                       # one second of samples
        print(block.gyro_rad_s.mean(axis=0), imu.stats)
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import replace
from pathlib import Path
from typing import BinaryIO, Protocol

import numpy as np

from northfinder.codecs import kvh
from northfinder.codecs.kvh import ImuBlock, ImuStats, KvhDecoder, decode_imu_stream, frames_to_block
from northfinder.drivers._stream import SampleQueue, StreamReader, read_bounds
from northfinder.errors import ConfigError, DeviceError
from northfinder.transport import SerialTransport

__all__ = ["Imu", "ImuBlock", "ImuStats", "decode_imu_stream", "frames_to_block"]

DEVICE = "imu"
INVALID_AFTER_RATE_CHANGE = 2  # PROTOCOLS.md §2: the next 2 messages after =DR are not valid data


class _ByteTransport(Protocol):  # what the driver needs from SerialTransport (tests pass their own)
    url: str

    def write(self, data: bytes) -> None: ...
    def read_available(self, max_bytes: int = ...) -> bytes: ...
    def close(self) -> None: ...


class Imu(SampleQueue, StreamReader):
    """A KVH format-A IMU on a pyserial URL; a context manager with a background reader."""

    device = DEVICE

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 921600,
        raw_log: str | Path | BinaryIO | None = None,
        timeout_s: float = 2.0,
        rate_hz: float = 1000.0,
        rot_format: str = "DELTA",
        rot_units: str = "RAD",
        wait_for_data: bool = True,
        transport: _ByteTransport | None = None,
    ) -> None:
        super().__init__(port, timeout_s)
        self.rate_hz = float(rate_hz)
        self.rot_format = rot_format.upper()
        self.rot_units = rot_units.upper()
        try:
            kvh.gyro_scale_to_rad_s(self.rate_hz, self.rot_format, self.rot_units)
        except ValueError as exc:
            raise ConfigError(f"imu: {exc}") from None
        self._baudrate = int(baudrate)
        # The driver owns the raw log (not the transport), so a reconnect appends to the same one.
        self._own_raw = isinstance(raw_log, str | Path)
        if isinstance(raw_log, str | Path):
            Path(raw_log).parent.mkdir(parents=True, exist_ok=True)
            raw_log = open(raw_log, "wb")  # noqa: SIM115 - closed in close()
        self._raw_log = raw_log
        self.reconnects = 0
        self._stalls: list[int] = []
        self._mark_stall = False
        self._unknown_seen = 0
        try:
            self._t = transport if transport is not None else self._open_transport()
        except BaseException:
            if self._own_raw:
                self._raw_log.close()
            raise
        self._decoder = KvhDecoder()
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending_n = 0
        self._tap: list[tuple[np.ndarray, np.ndarray]] | None = None  # every decoded chunk (start_tap)
        self._first_index: int | None = None
        self._config_mode = False
        self._text = bytearray()
        self._listening = False  # collect text in `_text` (config mode, and while awaiting an echo)
        self._discard_next = 0
        self._bit_messages: list[kvh.BitMessage] = []
        self._bit_first_frame: list[bool] = []  # each BIT message: came before the first data frame
        self._bit_carry = b""
        self._bit_seen_until = 0  # stream offset after the last BIT message found
        self._start_reader()
        if wait_for_data:
            try:
                self._wait_for_first_frame()
            except BaseException:
                self.close()
                raise

    def _open_transport(self) -> SerialTransport:
        return SerialTransport(self.port, device=DEVICE, baudrate=self._baudrate, timeout_s=0.05,
                               raw_log=self._raw_log)

    # -- background reader -------------------------------------------------------------------
    @property
    def failed(self) -> BaseException | None:
        """The error that stopped the reader (port gone, I/O error), or None while it runs."""
        with self._cond:
            return self._error

    def reconnect(self, timeout_s: float = 10.0, first_wait_s: float = 0.05, max_wait_s: float = 1.0) -> int:
        """Re-open the same port after it vanished (USB unplug, a symlink re-pointed), retrying with
        exponential backoff until a format-A frame arrives or `timeout_s` (host) passes; returns
        the number of attempts. The decoder and the raw log carry on, so the sample index stays
        monotonic and replay of the raw log decodes exactly what was decoded live.
        Raises the last DeviceError (naming the port) when the device does not come back."""
        self._stop_reader()
        with contextlib.suppress(Exception):
            self._t.close()
        deadline = time.monotonic() + timeout_s
        backoff_s = first_wait_s
        attempts = 0
        last: BaseException | None = None
        while True:
            attempts += 1
            try:
                self._t = self._open_transport()
            except DeviceError as exc:
                last = exc
            else:
                with self._cond:
                    self._error = None
                    self._pending, self._pending_n = [], 0
                    self._mark_stall = True  # the samples missed while the link was down
                    frames0 = self._decoder.stats.frames
                self._start_reader()

                def arrived(frames0: int = frames0) -> bool:
                    return self._decoder.stats.frames > frames0 or self._error is not None

                with self._cond:
                    wait_s = max(0.0, min(self.timeout_s, deadline - time.monotonic()))
                    ok = self._cond.wait_for(arrived, wait_s)
                    ok = ok and self._error is None
                    last = self._error
                if ok:
                    self.reconnects += 1
                    return attempts
                self._stop_reader()
                with contextlib.suppress(Exception):
                    self._t.close()
            if time.monotonic() + backoff_s > deadline:
                if isinstance(last, DeviceError):
                    raise last
                raise DeviceError(DEVICE, self.port, f"did not come back within {timeout_s:g} s after the "
                                  f"link was lost ({last}) — check the cable")
            time.sleep(backoff_s)
            backoff_s = min(2.0 * backoff_s, max_wait_s)

    @property
    def stall_indices(self) -> list[int]:
        """Device sample index of the first frame after each gap whose bytes never arrived (a pause
        of the device, a line overrun: ImuBlock.unknown_gaps) and after each reconnect. Such a gap
        cannot be counted from the 7-bit sequence number (it aliases every 128 samples), so a sample
        range that contains one of these indices has an unknown gap: the caller measures it again.
        Decided from the bytes alone, so replay finds the same gaps; host time plays no part (bytes a
        USB adapter holds back and bursts, or a reader kept off the CPU, are no pause)."""
        with self._cond:
            return list(self._stalls)

    def _on_bytes(self, data: bytes) -> None:
        if self._listening:
            self._text += data
        self._find_bit_messages(data)
        out = self._decoder.feed(data)
        if len(out) and self._mark_stall:
            self._stalls.append(int(out.sample_index[0]))
            self._mark_stall = False
        unknown = self._decoder.unknown_gap_indices
        if len(unknown) > self._unknown_seen:  # bytes lost on the line: as unknown as a pause
            self._stalls.extend(k for k in unknown[self._unknown_seen:] if k not in self._stalls)
            self._unknown_seen = len(unknown)
        if len(out):
            index, frames = out.sample_index, out.frames
            self._newest_index = int(index[-1])
            if self._first_index is None:
                self._first_index = int(index[0])
            if self._tap is not None:  # before the discard: the tap sees what a decode of imu.raw sees
                self._tap.append((index, frames))
            if self._discard_next:
                k = min(self._discard_next, len(index))
                self._discard_next -= k
                self._decoder.stats.discarded_frames += k
                index, frames = index[k:], frames[k:]
            if len(index):
                self._pending.append((index, frames))
                self._pending_n += len(index)

    def _find_bit_messages(self, data: bytes) -> None:
        """BIT messages (manual §5.3) between the data frames: kept for :meth:`built_in_test`. The
        decoder skips their bytes as it skips any non-frame bytes, so they cost no sample."""
        buf = self._bit_carry + data
        if kvh.BIT_HEADER[:3] not in buf:  # FE 81 00: both BIT headers; a data header is FE 81 FF
            self._bit_carry = buf[-12:]
            return
        base = self._decoder.stats.bytes - len(self._bit_carry)  # stream offset of buf[0] (before feed)
        for message, start in kvh.find_bit_messages(buf):
            if base + start >= self._bit_seen_until:
                self._bit_messages.append(message)
                self._bit_first_frame.append(self._decoder.stats.frames == 0)
                self._bit_seen_until = base + start + 1
        self._bit_carry = buf[-12:]

    @property
    def bit_messages(self) -> list[kvh.BitMessage]:
        """Every BIT message the unit sent so far (power-up, `?BIT` answers)."""
        with self._cond:
            return list(self._bit_messages)

    def built_in_test(self, timeout_s: float | None = None) -> tuple[kvh.BitMessage, str]:
        """The unit's BIT result → (message, "power-up" | "?BIT"). The power-up BIT message (sent
        before the periodic data, manual §3.4) when the driver heard it; otherwise it asks with
        ``?BIT``, which the manual allows in Normal Mode (§8.5: the answer follows the next data
        message, typically within 100 ms)."""
        with self._cond:
            if self._bit_first_frame and self._bit_first_frame[0]:
                return self._bit_messages[0], "power-up"
            seen = len(self._bit_messages)
        self._t.write(kvh.encode_query("BIT"))
        wait_s = self.timeout_s if timeout_s is None else float(timeout_s)
        with self._cond:
            self._wait_locked(lambda: len(self._bit_messages) > seen, wait_s,
                              lambda: f"no BIT message within {wait_s:g} s of ?BIT — is it a KVH 1750/1775?")
            return self._bit_messages[seen], "?BIT"

    def _wait_for_first_frame(self) -> None:
        with self._cond:
            self._wait_locked(
                lambda: self._decoder.stats.frames > 0,
                self.timeout_s,
                lambda: f"no KVH format-A data on {self.port} within {self.timeout_s:g} s "
                f"({self._decoder.stats.bytes} bytes of something else) — is it the IMU's port?",
            )

    # -- samples -----------------------------------------------------------------------------
    def read(self, n_samples: int, timeout_s: float | None = None) -> ImuBlock:
        """The next `n_samples` samples, blocking; DeviceError naming the port on timeout."""
        n, wait_s = read_bounds(n_samples, self.rate_hz, self.timeout_s, timeout_s)
        with self._cond:
            self._wait_locked(
                lambda: self._pending_n >= n,
                wait_s,
                lambda: f"only {self._pending_n} of {n} samples arrived within {wait_s:g} s on {self.port} "
                "— is the IMU still streaming (cable, rate, not left in config mode)?",
            )
            taken = self._take_pending(n, lambda frames, lo, hi: frames[lo:hi])
            rate, fmt, units = self.rate_hz, self.rot_format, self.rot_units
            first, last = int(taken[0][0][0]), int(taken[-1][0][-1])
            gaps = tuple(k for k in self._decoder.unknown_gap_indices if first <= k <= last)
        index = np.concatenate([c[0] for c in taken])
        frames = np.concatenate([c[1] for c in taken])
        block = frames_to_block(index, frames, rate, fmt, units)
        return replace(block, unknown_gaps=gaps) if gaps else block

    def start_tap(self) -> bool:
        """From now on keep every decoded sample, read or not, for :meth:`take_tapped`."""
        with self._cond:
            self._tap = []
        return True

    @property
    def first_sample_index(self) -> int | None:
        with self._cond:
            return self._first_index

    def take_tapped(self) -> ImuBlock | None:
        """Every sample decoded since the last call (or start_tap), in stream order, as a decode of
        imu.raw gives them (the same conversion: bit-identical); None without start_tap."""
        with self._cond:
            if self._tap is None:
                return None
            chunks, self._tap = self._tap, []
            rate, fmt, units = self.rate_hz, self.rot_format, self.rot_units
        if not chunks:
            return frames_to_block(np.zeros(0, np.int64), np.zeros(0, kvh.FRAME_DTYPE), rate, fmt, units)
        return frames_to_block(np.concatenate([c[0] for c in chunks]), np.concatenate([c[1] for c in chunks]),
                               rate, fmt, units)

    @property
    def stats(self) -> ImuStats:
        """A snapshot of the stream counters."""
        with self._cond:
            return replace(self._decoder.stats)

    @property
    def axes(self) -> kvh.ImuAxes:
        """The axes the unit has, from the status bits of its first frames (waits for them)."""
        n = kvh.AXES_LEARN_FRAMES
        with self._cond:
            self._wait_locked(
                lambda: self._decoder.axes is not None,
                self.timeout_s + n / self.rate_hz,
                lambda: f"only {self._decoder.stats.frames} of the first {n} frames arrived on {self.port} "
                "— is the IMU still streaming?",
            )
            assert self._decoder.axes is not None
            return self._decoder.axes

    def invalid_samples(self) -> dict[str, int]:
        """Frames flagged not valid so far, per axis the unit has ({} until its axes are known)."""
        with self._cond:
            return self._decoder.stats.invalid_samples(self._decoder.axes)

    # -- configuration -----------------------------------------------------------------------
    def _await_reply(self, key: str, timeout_s: float) -> str:
        found: list[tuple[str, int]] = []

        def answered() -> bool:
            reply = kvh.find_config_reply(bytes(self._text), key)
            if reply is not None:
                found.append(reply)
            return reply is not None

        with self._cond:
            self._wait_locked(
                answered,
                timeout_s,
                lambda: f"no answer to ?{key} on {self.port} within {timeout_s:g} s — is it a KVH IMU "
                "in format A on this port?",
            )
            value, end = found[0]
            del self._text[:end]
            return value

    def _command(self, key: str, value: object) -> None:
        """Send ``=KEY,VALUE`` and wait for its echo (manual §7: "a positive feedback mechanism");
        an ``INVALID,…`` or ``USAGE,…`` answer instead is a DeviceError saying which command the
        unit refused and what it answered."""
        with self._cond:
            self._listening = True
        self._t.write(kvh.encode_set(key, value))
        found: list[tuple[int, str | None]] = []

        def answered() -> bool:
            text = bytes(self._text)
            end = kvh.find_echo(text, key, value)
            refusal = kvh.find_refusal(text, key)
            # <=: 'INVALID,=DR,1\r\n' ends where the echo 'DR,1\r\n' would
            if refusal is not None and (end is None or refusal[1] <= end):
                found.append((refusal[1], refusal[0]))
            elif end is not None:
                found.append((end, None))
            return bool(found)

        with self._cond:
            self._wait_locked(answered, self.timeout_s,
                              lambda: f"no echo of ={key},{value} within {self.timeout_s:g} s — is it a "
                              "KVH IMU in format A on this port?")
            end, refusal = found[0]
            del self._text[:end]
        if refusal is not None:
            raise DeviceError(DEVICE, self.port, f"the IMU refused ={key},{value} (it answered {refusal!r})")

    def _enter_config(self) -> None:
        with self._cond:
            self._config_mode = True
            self._text.clear()
        try:
            self._command("CONFIG", 1)
        except BaseException:
            with self._cond:
                self._config_mode = self._listening = False
            raise

    def _leave_config(self, invalid_next: int = 0) -> None:
        with self._cond:
            self._pending, self._pending_n = [], 0
            self._discard_next = invalid_next
            self._config_mode = False
        try:
            self._command("CONFIG", 0)  # data resumes right after the echo
        finally:
            with self._cond:
                self._listening = False
                self._text.clear()

    def query(self, key: str) -> str:
        """``?KEY`` → its value ("DR" → "1000").

        Outside config mode this enters and leaves it (data pauses; samples pending are dropped).
        A DR/ROTFMT/ROTUNITS answer also updates :attr:`rate_hz` / :attr:`rot_format` /
        :attr:`rot_units`, so the conversion to rad/s follows what the device says.
        """
        key = key.upper()
        inside = self._config_mode
        if not inside:
            self._enter_config()
        try:
            self._t.write(kvh.encode_query(key))
            value = self._await_reply(key, self.timeout_s)
        finally:
            if not inside:
                self._leave_config()
        self._adopt(key, value)
        return value

    def _adopt(self, key: str, value: str) -> None:
        """Follow the device's own DR / ROTFMT / ROTUNITS when it reports a valid one."""
        with self._cond:
            try:
                if key == "DR" and float(value) in kvh.RATES_HZ:
                    self.rate_hz = float(value)
                elif key == "ROTFMT" and value.upper() in kvh.ROT_FORMATS:
                    self.rot_format = value.upper()
                elif key == "ROTUNITS" and value.upper() in kvh.ROT_UNITS:
                    self.rot_units = value.upper()
            except ValueError:
                pass

    def configure(self, rate_hz: float | None = None, rot_format: str | None = None,
                  rot_units: str | None = None) -> dict[str, str]:
        """Set what is given inside ``=CONFIG,1`` … ``=CONFIG,0`` and read all three back.

        Samples pending before the change are dropped, and after a rate change the 2 invalid
        messages the device sends are discarded (counted in ``stats.discarded_frames``).
        """
        if rate_hz is not None and int(rate_hz) not in kvh.RATES_HZ:
            raise ConfigError(f"imu rate_hz {rate_hz} is not one the KVH supports: {kvh.RATES_HZ}")
        if rot_format is not None and rot_format.upper() not in kvh.ROT_FORMATS:
            raise ConfigError(f"imu rot_format {rot_format!r} must be one of {kvh.ROT_FORMATS}")
        if rot_units is not None and rot_units.upper() not in kvh.ROT_UNITS:
            raise ConfigError(f"imu rot_units {rot_units!r} must be one of {kvh.ROT_UNITS}")
        old_rate = self.rate_hz
        self._enter_config()
        rate_changed = False
        try:
            if rate_hz is not None:
                rate_changed = True  # the unit restarts its sample clock once it echoes
                self._command("DR", int(rate_hz))
            if rot_format is not None:
                self._command("ROTFMT", rot_format.upper())
            if rot_units is not None:
                self._command("ROTUNITS", rot_units.upper())
            values = {key: self.query(key) for key in ("DR", "ROTFMT", "ROTUNITS")}
            try:
                new_rate = float(values["DR"])
                kvh.gyro_scale_to_rad_s(new_rate, values["ROTFMT"], values["ROTUNITS"])
            except ValueError:
                raise DeviceError(DEVICE, self.port, f"unexpected configuration reply {values} — is it a "
                                  "KVH IMU in format A?") from None
            for asked, key in ((rate_hz, "DR"), (rot_format, "ROTFMT"), (rot_units, "ROTUNITS")):
                if asked is not None and str(asked).upper() != values[key].upper() and not (
                        key == "DR" and float(asked) == float(values[key])):
                    raise DeviceError(DEVICE, self.port, f"the IMU did not accept {key}={asked} "
                                      f"(it reports {values[key]})")
            rate_changed = new_rate != old_rate or rate_hz is not None
            with self._cond:
                self.rate_hz = new_rate
                self.rot_format = values["ROTFMT"].upper()
                self.rot_units = values["ROTUNITS"].upper()
        finally:
            self._leave_config(INVALID_AFTER_RATE_CHANGE if rate_changed else 0)
        return values

    # -- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the reader thread and close the port (and the raw log if the driver opened it)."""
        super().close()
        if self._own_raw and self._raw_log is not None and not self._raw_log.closed:
            self._raw_log.close()

    def __repr__(self) -> str:
        return f"Imu({self.port!r}, rate_hz={self.rate_hz:g}, {self.rot_format}/{self.rot_units})"
