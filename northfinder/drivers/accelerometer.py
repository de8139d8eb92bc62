"""CANopen-style accelerometer driver (docs/PROTOCOLS.md §3) on any python-can bus.

The bus comes from an interface/channel/bitrate (``virtual``, ``slcan`` on a serial port,
``socketcan`` on ``vcan0``/``can0``…); a ``can.Notifier`` hands every frame to one listener,
which (in one place) writes it to a python-can log (``.asc`` or ``.blf``, chosen by the suffix)
and decodes it with cantools through :class:`northfinder.codecs.canopen.AccelFrameDecoder`:
TPDO1/TPDO2 pairing, 8-bit counter unwrapping, lost samples, heartbeats and emergencies.
Frames this driver sends (NMT) are logged too, marked Tx.

:func:`decode_can_log` is the pure replay path: the same decoder over the logged frames, so a
log replays to bit-identical arrays.

Example::

    from northfinder.drivers.accelerometer import Accelerometer

    with Accelerometer("slcan", "/dev/ttyACM0", bitrate=500000, log_path="can.asc") as acc:
        acc.wait_heartbeat()                  # the node is there (boot-up 0x00 or its state)
        acc.start_node()                      # NMT start → operational
        acc.wait_heartbeat_state(0x05)        # its next heartbeats say operational
        block = acc.read(100)                 # one second at 100 Hz
        print(block.accel_g.mean(axis=0), acc.stats, acc.emergencies)
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import can
import numpy as np

from northfinder.codecs.canopen import AccelFrameDecoder, AccelStats, CanCodec, Emcy, RawAccelSamples
from northfinder.errors import DeviceError

__all__ = ["Accelerometer", "AccelBlock", "AccelStats", "Emcy", "decode_can_log", "samples_to_block"]

DEVICE = "accelerometer"


@dataclass(frozen=True)
class AccelBlock:
    """Consecutive paired samples. `lost_samples` counts gaps inside the block."""

    counter: np.ndarray  # int64 [n], unwrapped device counter
    accel_g: np.ndarray  # float64 [n, 3]
    temperature_c: np.ndarray  # float64 [n]
    status: np.ndarray  # uint8 [n]
    lost_samples: int

    def __len__(self) -> int:
        return len(self.counter)


def _divisor(scale: float) -> float:
    """1e-6 → 1e6: dividing by the exact integer rounds µg → g correctly."""
    inv = 1.0 / scale
    return float(round(inv)) if abs(inv - round(inv)) < 1e-9 * inv else inv


def samples_to_block(raw: RawAccelSamples, codec: CanCodec) -> AccelBlock:
    """Raw paired samples → an AccelBlock in g and °C, scaled by the DBC's factors."""
    accel_div = _divisor(codec.scale("TPDO1", "accel_x"))
    temp_div = _divisor(codec.scale("TPDO2", "temperature"))
    counter = np.asarray(raw.counter, dtype=np.int64)
    lost = int(counter[-1] - counter[0] + 1 - len(counter)) if len(counter) else 0
    return AccelBlock(
        counter=counter,
        accel_g=raw.accel_ug.astype(np.float64) / accel_div,
        temperature_c=raw.temperature_centi_c.astype(np.float64) / temp_div,
        status=raw.status.astype(np.uint8),
        lost_samples=lost,
    )


def decode_can_log(path: str | Path, node_id: int = 0x10, dbc_path: str | Path | None = None
                   ) -> tuple[AccelBlock, AccelStats]:
    """Decode a python-can log (.asc, .blf, …) of the node's traffic (replay)."""
    codec = CanCodec(node_id, dbc_path)
    decoder = AccelFrameDecoder(codec)
    for msg in can.LogReader(str(path)):
        if msg.is_error_frame or not msg.is_rx:
            continue
        decoder.feed(msg.arbitration_id, bytes(msg.data), msg.timestamp, msg.is_extended_id,
                     msg.is_remote_frame)
    return samples_to_block(decoder.drain(), codec), decoder.stats


class _Listener(can.Listener):
    """The one place frames are logged and decoded."""

    def __init__(self, owner: Accelerometer) -> None:
        self._owner = owner

    def on_message_received(self, msg: can.Message) -> None:
        self._owner._on_frame(msg)

    def on_error(self, exc: Exception) -> None:
        self._owner._on_error(exc)


class Accelerometer:
    """A CANopen-style accelerometer node on a python-can bus; a context manager."""

    def __init__(
        self,
        interface: str,
        channel: str | int | None,
        *,
        bitrate: int = 500000,
        node_id: int = 0x10,
        log_path: str | Path | None = None,
        dbc_path: str | Path | None = None,
        rate_hz: float = 100.0,
        timeout_s: float = 2.0,
        bus: can.BusABC | None = None,
        bus_options: dict | None = None,
    ) -> None:
        """`bus_options` go to `can.Bus` as they are (e.g. ``{"sleep_after_open": 0}`` for an slcan
        adapter that needs no settling time, such as firmware_sim's)."""
        self.interface = interface
        self.channel = channel
        self.port = f"{interface}:{channel}"
        self.bitrate = int(bitrate)
        self.rate_hz = float(rate_hz)
        self.timeout_s = float(timeout_s)
        try:
            self.codec = CanCodec(node_id, dbc_path)
        except ValueError as exc:
            raise DeviceError(DEVICE, self.port, f"{exc} — fix node_id in the bench config") from None
        except OSError as exc:
            raise DeviceError(DEVICE, self.port, f"cannot read the DBC file {dbc_path} ({exc})") from None
        self.node_id = self.codec.node_id
        self._own_bus = bus is None
        if bus is None:
            try:
                options = dict(bus_options or {})
                bus = can.Bus(interface=interface, channel=channel, bitrate=self.bitrate, **options)
            except Exception as exc:  # noqa: BLE001 - python-can raises many types; all are the user's setup
                raise DeviceError(
                    DEVICE, self.port,
                    f"cannot open CAN interface {interface!r} channel {channel!r} ({exc}) — check the "
                    "interface, channel and bitrate in the bench config"
                ) from None
        self._bus = bus
        self._lock = threading.Condition()
        self._decoder = AccelFrameDecoder(self.codec)
        self._error: BaseException | None = None
        self._last_heartbeat: float | None = None
        self._logger: can.Listener | None = None
        if log_path is not None:
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            self._logger = can.Logger(str(log_path))
        self._notifier = can.Notifier(self._bus, [_Listener(self)], timeout=0.05)

    # -- frames ------------------------------------------------------------------------------
    def _log(self, msg: can.Message) -> None:
        if self._logger is not None:
            # BLF stores the channel as the number that ends the channel's name; a name such as
            # "rig-1234567" gives one above 65535, which the writer cannot pack. Log such
            # frames without a channel rather than lose the log (and the bus thread) to it.
            channel = can.util.channel2int(msg.channel)
            if channel is not None and not 0 <= channel <= 0xFFFF:
                msg = copy.copy(msg)
                msg.channel = None
            self._logger.on_message_received(msg)

    def _on_frame(self, msg: can.Message) -> None:
        with self._lock:
            self._log(msg)
            if not msg.is_error_frame:
                name = self._decoder.feed(msg.arbitration_id, bytes(msg.data), msg.timestamp,
                                          msg.is_extended_id, msg.is_remote_frame)
                if name == "HEARTBEAT":
                    self._last_heartbeat = time.monotonic()
            self._lock.notify_all()

    def _on_error(self, exc: Exception) -> None:
        with self._lock:
            self._error = exc
            self._lock.notify_all()

    def _send(self, can_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=can_id, data=data, is_extended_id=False, timestamp=time.time(),
                          is_rx=False)
        try:
            self._bus.send(msg, timeout=self.timeout_s)
        except can.CanError as exc:
            raise DeviceError(DEVICE, self.port, f"cannot send on {self.port} ({exc}) — is the bus up and "
                              "another node acknowledging?") from None
        with self._lock:
            self._log(msg)

    def start_node(self) -> None:
        """NMT start: the node becomes operational and sends TPDO1/TPDO2 at its rate."""
        self._send(*self.codec.encode_nmt("start"))

    def stop_node(self) -> None:
        """NMT stop: the node stops sending data (heartbeats go on)."""
        self._send(*self.codec.encode_nmt("stop"))

    def wait_heartbeat(self, timeout_s: float = 3.0, fresh: bool = True) -> int:
        """Wait for the node's next heartbeat (or, with ``fresh=False``, any seen) → its state byte."""
        with self._lock:
            seen = self._decoder.stats.heartbeats if fresh else 0
            self._wait_locked(
                lambda: self._decoder.stats.heartbeats > seen,
                timeout_s,
                lambda: f"no heartbeat from node 0x{self.node_id:02X} on {self.port} within {timeout_s:g} s "
                f"— is the node powered, on this bus, node ID {self.node_id}, {self.bitrate} bit/s?",
            )
            return int(self._decoder.heartbeat_state)

    def _wait_locked(
        self, ready: Callable[[], bool], timeout_s: float, timeout_message: Callable[[], str]
    ) -> None:
        """With the lock held: wait until `ready()`; DeviceError on a bus error or after `timeout_s`
        (the message from `timeout_message()`)."""
        deadline = time.monotonic() + timeout_s
        while not ready():
            if self._error is not None:
                raise DeviceError(DEVICE, self.port, f"bus error on {self.port}: {self._error}")
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceError(DEVICE, self.port, timeout_message())
            self._lock.wait(remaining)

    def wait_heartbeat_state(self, state: int, timeout_s: float = 3.0) -> int:
        """Wait until a heartbeat reports `state` (e.g. 0x05 after :meth:`start_node`)."""
        deadline = time.monotonic() + timeout_s
        last = None
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceError(
                    DEVICE, self.port,
                    f"node 0x{self.node_id:02X} on {self.port} did not report state 0x{state:02X} within "
                    f"{timeout_s:g} s (last heartbeat: {last if last is None else hex(last)})"
                )
            try:
                last = self.wait_heartbeat(remaining)
            except DeviceError:
                last = self.heartbeat_state
                continue
            if last == state:
                return last

    @property
    def heartbeat_age_s(self) -> float | None:
        """Host seconds since the last heartbeat (None before the first): the node watch — more
        than ~2 heartbeat periods means the node or the bus is gone."""
        with self._lock:
            return None if self._last_heartbeat is None else time.monotonic() - self._last_heartbeat

    @property
    def heartbeat_state(self) -> int | None:
        """The state byte of the last heartbeat (None before the first)."""
        with self._lock:
            return self._decoder.heartbeat_state

    def read(self, n_samples: int, timeout_s: float | None = None) -> AccelBlock:
        """The next `n_samples` paired samples, blocking; DeviceError naming the channel on timeout."""
        n = int(n_samples)
        if n < 1:
            raise ValueError("n_samples must be >= 1")
        wait_s = self.timeout_s + n / self.rate_hz if timeout_s is None else float(timeout_s)
        with self._lock:
            self._wait_locked(
                lambda: self._decoder.pending() >= n,
                wait_s,
                lambda: f"only {self._decoder.pending()} of {n} samples from node 0x{self.node_id:02X} "
                f"within {wait_s:g} s on {self.port} — is the node operational (start_node) and the "
                "bitrate right?",
            )
            raw = self._decoder.drain(n)
        return samples_to_block(raw, self.codec)

    def discard_pending(self) -> int:
        """Drop paired samples not read yet; returns how many."""
        with self._lock:
            return len(self._decoder.drain())

    @property
    def emergencies(self) -> list[Emcy]:
        """Every EMCY frame received so far (code, register, meaning)."""
        with self._lock:
            return list(self._decoder.emergencies)

    @property
    def stats(self) -> AccelStats:
        """A snapshot of the counters (pairs, unpaired, counter_gaps, lost_samples, emcy)."""
        with self._lock:
            return replace(self._decoder.stats)

    # -- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the notifier, shut the bus down (if the driver opened it) and close the log."""
        notifier, self._notifier = getattr(self, "_notifier", None), None
        if notifier is not None:
            notifier.stop(timeout=1.0)
            if self._own_bus:
                self._bus.shutdown()
            with self._lock:
                if self._logger is not None:
                    self._logger.stop()
                    self._logger = None

    def __enter__(self) -> Accelerometer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Accelerometer({self.interface!r}, {self.channel!r}, node_id=0x{self.node_id:02X})"
