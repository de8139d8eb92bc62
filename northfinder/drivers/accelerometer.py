"""CANopen accelerometer driver (docs/PROTOCOLS.md §3, §3.1) on python-canopen over any python-can bus.

The bus comes from an interface/channel/bitrate (``virtual``, ``slcan`` on a serial port,
``socketcan`` on ``vcan0``/``can0``…) or is handed in; a ``canopen.Network`` runs over that same
bus object with a ``RemoteNode`` built from an EDS (the project's reference node,
``northfinder/data/accelerometer.eds``, or the user's own). NMT commands, heartbeat consumption,
the EMCY consumer, the SDO client (expedited and segmented) and reading the TPDO mapping are the
library's. One ``can.Notifier`` feeds the library and this driver's listener, which (in one place)
writes every frame to a python-can log (``.asc``/``.blf``, Tx frames marked) and assembles samples
from the TPDOs by the mapping the node reports (:class:`northfinder.codecs.canopen.AccelFrameDecoder`).

:meth:`Accelerometer.configure` is the start-of-run SDO configuration: NMT pre-operational,
identity (0x1018) and device name (0x1008), the TPDO mapping (0x1800/0x1A00…), the sample rate
(0x2100, or the object named by ``rate_object``, e.g. the TPDO event timer 1800:5) and the
heartbeat producer time (0x1017). What it writes is left as configured after the run (the node
keeps it until a reset-node or power cycle restores its defaults; nothing is stored with 0x1010);
the node itself is left stopped (NMT stop) by the run.

:func:`decode_can_log` is the pure replay path: the same decoder over the logged frames (with the
mapping the run used), so a log replays to bit-identical arrays.

Example::

    from northfinder.drivers.accelerometer import Accelerometer

    with Accelerometer("slcan", "/dev/ttyACM0", bitrate=500000, log_path="can.asc") as acc:
        acc.wait_heartbeat()                  # the node is there (boot-up 0x00 or its state)
        info = acc.configure(rate_hz=100)     # SDO: identity, mapping, rate, heartbeat time
        acc.start_node()                      # NMT start → operational
        block = acc.read(100)                 # one second at 100 Hz
        print(info["identity"], block.accel_g.mean(axis=0), acc.stats, acc.emergencies)
"""

from __future__ import annotations

import copy
import logging
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.objectdictionary import datatypes
from canopen.sdo.exceptions import SdoAbortedError, SdoError

from northfinder.codecs.canopen import (
    UNIT_SCALE,
    AccelBlock,
    AccelFrameDecoder,
    AccelStats,
    CanCodec,
    Emcy,
    MappedObject,
    PdoLayout,
    TpdoLayout,
    decode_accel_frames,
    node_frames,
    object_role,
    samples_to_block,
)
from northfinder.drivers._stream import read_bounds, wait_until
from northfinder.errors import DeviceError
from northfinder.transport import open_can_bus

__all__ = ["DEFAULT_EDS_PATH", "Accelerometer", "AccelBlock", "AccelStats", "Emcy", "decode_can_log",
           "samples_to_block"]

# python-canopen logs an SDO timeout at ERROR; with no logging set up, Python's last-resort handler
# would print it as a second line under our one-line error. The DeviceError says it already.
logging.getLogger("canopen").addHandler(logging.NullHandler())

DEFAULT_EDS_PATH = Path(__file__).resolve().parent.parent / "data" / "accelerometer.eds"
SDO_TIMEOUT_S = 5.0
"""Host seconds before an SDO request is given up (abort 0x05040000): CiA 301 leaves it to the
client; 1 s failed `check` on a loaded host while the node answered (docs/PROTOCOLS.md §3.1)."""
ABORT_MEANINGS = {
    0x05040000: "SDO protocol timed out",
    0x05040001: "command specifier not valid",
    0x06010001: "write-only object",
    0x06010002: "read-only object",
    0x06020000: "object does not exist",
    0x06070010: "length mismatch",
    0x06090011: "sub-index does not exist",
    0x06090030: "value range exceeded",
    0x08000022: "not allowed in the present device state",
}
DEVICE = "accelerometer"
NMT_STOPPED = 0x04
"""Heartbeat state byte of a stopped node (PROTOCOLS.md §3)."""


def decode_can_log(path: str | Path, node_id: int = 0x10, dbc_path: str | Path | None = None,
                   layout: PdoLayout | dict | None = None) -> tuple[AccelBlock, AccelStats]:
    """Decode a python-can log (.asc, .blf, …) of the node's traffic (replay): python-can reads the
    file, :func:`northfinder.codecs.canopen.decode_accel_frames` decodes it; `layout` is the
    mapping the run read from the node (its events' `accel_config`), default the reference one.
    The node's frames are taken by COB-ID (:func:`northfinder.codecs.canopen.node_frames`), whatever
    direction the log marks them with."""
    frames = ((m.arbitration_id, bytes(m.data), m.timestamp, m.is_extended_id, m.is_remote_frame)
              for m in can.LogReader(str(path)) if not m.is_error_frame)
    return decode_accel_frames(node_frames(frames, node_id, layout), node_id, dbc_path, layout)


SO_RXQ_OVFL = getattr(socket, "SO_RXQ_OVFL", 40)  # Linux socket(7); Python's socket module lacks it
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
RECEIVE_BUFFER_BYTES = 4 * 1024 * 1024
"""The socketcan receive buffer asked for: the default (net.core.rmem_default, 208 KiB) holds ~300
frames, 0.15 s of the node at 100 Hz × 10 time scale; 4 MiB holds seconds of it. Above
net.core.rmem_max only with CAP_NET_ADMIN (SO_RCVBUFFORCE); otherwise the kernel caps it."""


class _DropCountingSocket:
    """A socketcan socket whose `recvmsg` also takes the kernel's drop counter (SO_RXQ_OVFL: frames
    dropped because the socket's receive buffer was full) out of the ancillary data, leaving python-can
    the timestamp it asked for. Everything else goes to the socket as it is."""

    def __init__(self, sock: socket.socket) -> None:
        self._sock = sock
        self.kernel_drops = 0
        sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, RECEIVE_BUFFER_BYTES)
        except OSError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        self.receive_buffer_bytes = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)

    def fileno(self) -> int:
        return self._sock.fileno()

    def recvmsg(self, bufsize: int, ancbufsize: int = 0, flags: int = 0) -> tuple:
        data, ancillary, msg_flags, address = self._sock.recvmsg(bufsize, ancbufsize + socket.CMSG_SPACE(4),
                                                                 flags)
        kept = []
        for level, kind, payload in ancillary:
            if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL:
                self.kernel_drops = struct.unpack_from("=I", payload)[0]  # the socket's total so far
            else:
                kept.append((level, kind, payload))
        return data, kept, msg_flags, address


def _count_kernel_drops(bus: can.BusABC) -> _DropCountingSocket | None:
    """On python-can's socketcan bus: a bigger receive buffer and the kernel's drop counter."""
    sock = getattr(bus, "socket", None)
    if type(bus).__name__ != "SocketcanBus" or not isinstance(sock, socket.socket):
        return None
    try:
        counting = _DropCountingSocket(sock)
    except OSError:
        return None
    bus.socket = counting
    return counting


def layout_from_node(node: canopen.RemoteNode) -> PdoLayout:
    """The enabled TPDOs of `node.tpdo` (read from the node) as a PdoLayout, roles, scale and
    units from the EDS entries of the mapped objects."""
    tpdos = []
    for number, pdo_map in sorted(node.tpdo.map.items()):
        if not pdo_map.enabled or not len(pdo_map.map):
            continue
        objects = []
        for var in pdo_map.map:
            od = var.od
            unit = str(getattr(od, "unit", "") or "")
            role = object_role(od.name)
            scale = float(getattr(od, "factor", 1) or 1) * UNIT_SCALE.get(unit.lower(), 1.0)
            objects.append(MappedObject(var.index, var.subindex, int(var.length),
                                        od.data_type in datatypes.SIGNED_TYPES, od.name, role, scale, unit))
        tpdos.append(TpdoLayout(number, int(pdo_map.cob_id), tuple(objects)))
    return PdoLayout(tuple(tpdos))


class _Network(canopen.Network):
    """python-canopen's network over a bus we opened; every frame it sends is also logged."""

    def __init__(self, bus: can.BusABC, on_tx: Callable[[can.Message], None]) -> None:
        super().__init__(bus)
        self._on_tx = on_tx

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        msg = can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=can_id > 0x7FF,
                          is_remote_frame=remote, is_rx=False, timestamp=time.time())
        with self.send_lock:
            self.bus.send(msg)
        self._on_tx(msg)


class _Listener(can.Listener):
    """The one place frames are logged and decoded."""

    def __init__(self, owner: Accelerometer) -> None:
        self._owner = owner

    def on_message_received(self, msg: can.Message) -> None:
        self._owner._on_frame(msg)

    def on_error(self, exc: Exception) -> None:
        self._owner._on_error(exc)


class Accelerometer:
    """A CANopen accelerometer node on a python-can bus, through python-canopen; a context manager."""

    def __init__(
        self,
        interface: str,
        channel: str | int | None,
        *,
        bitrate: int = 500000,
        node_id: int = 0x10,
        log_path: str | Path | None = None,
        dbc_path: str | Path | None = None,
        eds_path: str | Path | None = None,
        rate_hz: float = 100.0,
        timeout_s: float = 2.0,
        sdo_timeout_s: float = SDO_TIMEOUT_S,
        bus: can.BusABC | None = None,
        bus_options: dict | None = None,
    ) -> None:
        """`bus_options` go to `can.Bus` as they are (e.g. ``{"sleep_after_open": 0}`` for an slcan
        adapter that needs no settling time, such as firmware_sim's). `rate_hz` is the rate assumed
        until :meth:`configure` reads the node's own; `eds_path` the node's EDS (default: ours)."""
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
        self.eds_path = Path(eds_path) if eds_path else DEFAULT_EDS_PATH
        node = self._remote_node(self.eds_path)
        self._own_bus = bus is None
        if bus is None:
            try:
                options = dict(bus_options or {})
                bus = open_can_bus(interface, channel, bitrate=self.bitrate, **options)
            except Exception as exc:  # noqa: BLE001 - python-can raises many types; all are the user's setup
                raise DeviceError(
                    DEVICE, self.port,
                    f"cannot open CAN interface {interface!r} channel {channel!r} ({exc}) — check the "
                    "interface, channel and bitrate in the bench config"
                ) from None
        self._bus = bus
        self._drops = _count_kernel_drops(bus)
        self._lock = threading.Condition()
        self._want = 1
        """Paired samples the reading thread waits for: the bus thread notifies it only once they are
        there (a notify per sample made both threads trade the GIL 12 000 times a second at 120×)."""
        self._decoder = AccelFrameDecoder(self.codec)
        self._error: BaseException | None = None
        self._last_heartbeat: float | None = None
        self._stopped_reports = 0
        """Heartbeats that reported NMT state stopped (0x04), counted in bus order."""
        self._stop_mark = 0
        self._stopping = False
        """Stopped by stop_node, not started again since."""
        self._logger: can.Listener | None = None
        if log_path is not None:
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            self._logger = can.Logger(str(log_path))
        self.network = _Network(bus, self._log_tx)
        self.node = node
        self.network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = float(sdo_timeout_s)
        node.sdo.MAX_RETRIES = 1
        node.nmt.add_heartbeat_callback(self._on_heartbeat)
        node.emcy.add_callback(self._on_emcy)
        self._notifier = can.Notifier(self._bus, [_Listener(self), *self.network.listeners], timeout=0.05)
        self.network.notifier = self._notifier

    def _remote_node(self, eds: Path) -> canopen.RemoteNode:
        """The RemoteNode from the EDS; a missing or unreadable EDS is one line naming the file."""
        if not eds.is_file():
            raise DeviceError(DEVICE, self.port, f"EDS file {eds} not found — fix [accelerometer] eds")
        try:
            return canopen.RemoteNode(self.node_id, str(eds))
        except Exception as exc:  # noqa: BLE001 - the EDS parser raises many types; all mean a bad file
            raise DeviceError(DEVICE, self.port, f"cannot parse the EDS file {eds} ({exc})") from None

    @property
    def layout(self) -> PdoLayout:
        """The TPDO mapping samples are decoded by (the node's, once :meth:`read_mapping` ran)."""
        with self._lock:
            return self._decoder.layout

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

    def _log_tx(self, msg: can.Message) -> None:
        with self._lock:
            self._log(msg)

    def _on_frame(self, msg: can.Message) -> None:
        with self._lock:
            self._log(msg)
            if self._drops is not None:
                self._decoder.stats.kernel_drops = self._drops.kernel_drops
            if not msg.is_error_frame:
                can_id, data = msg.arbitration_id, msg.data
                if can_id == 0x700 + self.node_id and len(data) < 1 or can_id == 0x080 + self.node_id and (
                        len(data) < 8):
                    self._decoder.stats.malformed += 1  # python-canopen would drop it (and log an error)
                elif self._decoder.feed(can_id, bytes(data), msg.timestamp, msg.is_extended_id,
                                        msg.is_remote_frame, node_frames=False) and (
                        self._decoder.pending() >= self._want):
                    self._lock.notify_all()

    def _on_heartbeat(self, state: int) -> None:
        with self._lock:
            self._decoder.on_heartbeat(state)
            if int(state) == NMT_STOPPED:
                self._stopped_reports += 1
            self._last_heartbeat = time.monotonic()
            self._lock.notify_all()

    def _on_emcy(self, err: canopen.emcy.EmcyError) -> None:
        with self._lock:
            self._decoder.on_emcy(err.code, err.register, bytes(err.data), err.timestamp)
            self._lock.notify_all()

    def _on_error(self, exc: Exception) -> None:
        with self._lock:
            self._error = exc
            self._lock.notify_all()

    def _nmt(self, command: int) -> None:
        try:
            self.node.nmt.send_command(command)
        except can.CanError as exc:
            raise DeviceError(DEVICE, self.port, f"cannot send on {self.port} ({exc}) — is the bus up and "
                              "another node acknowledging?") from None

    def start_node(self) -> None:
        """NMT start: the node becomes operational and sends its TPDOs at its rate."""
        with self._lock:
            self._stopping = False
        self._nmt(0x01)

    def stop_node(self) -> None:
        """NMT stop: the node stops sending data (heartbeats go on)."""
        with self._lock:
            self._stop_mark = self._stopped_reports
            self._stopping = True
        self._nmt(0x02)

    def _stop_proven(self) -> bool:
        """With `_lock` held: a heartbeat since the last stop_node (no start since) reported stopped —
        every TPDO the node sent before it stopped is here (bus order)."""
        return self._stopping and self._stopped_reports > self._stop_mark

    def wait_stopped_report(self, timeout_s: float) -> bool:
        """Wait until a heartbeat received after the last :meth:`stop_node` reports state stopped.

        The bus delivers a node's frames in the order it sent them, so once that heartbeat is here
        every TPDO the node sent before it stopped has arrived too: what is pending then is all from
        before the stop (device order, not host quiet). False after `timeout_s` (heartbeat off or lost).
        """
        with self._lock:
            try:
                self._wait_locked(lambda: self._stopped_reports > self._stop_mark, timeout_s, lambda: "")
            except DeviceError:
                return False
            return True

    def enter_pre_operational(self) -> None:
        """NMT enter pre-operational: SDO works, mapping and rate may be written, no TPDOs."""
        self._nmt(0x80)

    # -- SDO ---------------------------------------------------------------------------------
    def _what(self, index: int, sub: int) -> str:
        try:
            obj = self.node.object_dictionary[index]
            name = obj.name if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[sub].name
        except KeyError:
            name = ""
        return f"object {index:04X}:{sub}" + (f" ({name})" if name else "")

    def _sdo_error(self, verb: str, index: int, sub: int, exc: Exception) -> DeviceError:
        where = f"node 0x{self.node_id:02X}"  # the DeviceError's prefix names the port
        if isinstance(exc, KeyError):
            return DeviceError(DEVICE, self.port, f"the EDS {self.eds_path} has no object {index:04X}:{sub}, "
                               f"which the run needs ({verb}) — use the node's own EDS ([accelerometer] eds)")
        if isinstance(exc, SdoAbortedError):
            code = int(exc.code)
            return DeviceError(DEVICE, self.port, f"{where}: SDO {verb} of {self._what(index, sub)} aborted "
                               f"with 0x{code:08X} ({ABORT_MEANINGS.get(code, 'abort code')})")
        return DeviceError(DEVICE, self.port, f"{where}: no SDO answer to the {verb} of "
                           f"{self._what(index, sub)} within {self.node.sdo.RESPONSE_TIMEOUT:g} s (abort "
                           "0x05040000, SDO timeout) — is the node pre-operational or operational?")

    def sdo_read(self, index: int, sub: int = 0, need_eds: bool = True) -> Any:
        """One object's value through the EDS's type (segmented when longer than 4 bytes); with
        `need_eds=False` an object the EDS lacks is still asked for (its raw bytes)."""
        try:
            try:
                obj = self.node.sdo[index]
                var = obj if isinstance(obj, canopen.sdo.Variable) else obj[sub]
            except KeyError:
                if need_eds:
                    raise
                return self.node.sdo.upload(index, sub)
            return var.raw
        except (KeyError, SdoError) as exc:
            raise self._sdo_error("read", index, sub, exc) from None

    def sdo_write(self, index: int, sub: int, value: Any) -> None:
        """Write one object (expedited) through the EDS's type."""
        try:
            obj = self.node.sdo[index]
            (obj if isinstance(obj, canopen.sdo.Variable) else obj[sub]).raw = value
        except (KeyError, SdoError) as exc:
            raise self._sdo_error("write", index, sub, exc) from None

    def identity(self) -> dict[str, Any]:
        """Vendor ID, product code, revision, serial number (0x1018) and device name (0x1008)."""
        keys = ("vendor_id", "product_code", "revision", "serial_number")
        out: dict[str, Any] = {k: int(self.sdo_read(0x1018, s)) for s, k in enumerate(keys, start=1)}
        out["device_name"] = str(self.sdo_read(0x1008, 0)).rstrip("\x00")
        return out

    def read_mapping(self) -> PdoLayout:
        """Read the TPDO communication and mapping parameters from the node (python-canopen's
        TPDO maps) and decode samples by that mapping from now on."""
        for number, pdo_map in sorted(self.node.tpdo.map.items()):
            try:
                pdo_map.read()
            except (KeyError, SdoError) as exc:
                what = f"read of the TPDO{number} mapping"
                raise self._sdo_error(what, 0x1A00 + number - 1, 0, exc) from None
            if pdo_map.cob_id:
                self.network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)  # decoded here, not twice
        layout = layout_from_node(self.node)
        problems = layout.problems()
        if problems:
            raise DeviceError(DEVICE, self.port, f"node 0x{self.node_id:02X}: cannot decode its TPDO mapping "
                              f"({layout.describe() or 'nothing mapped'}): {problems[0]}")
        with self._lock:
            self._decoder.drain()
            self._decoder.set_layout(layout)
        return layout

    def _rate_object(self, rate_object: str | None) -> tuple[int, int]:
        text = rate_object or "2100:0"
        index, _, sub = text.partition(":")
        return int(index, 16), int(sub or "0", 16)

    def read_rate(self, rate_object: str | None = None) -> float:
        """The node's sample rate [Hz]: the rate object (Hz), or an event timer 18xx:5 (ms)."""
        index, sub = self._rate_object(rate_object)
        value = float(self.sdo_read(index, sub))
        if 0x1800 <= index < 0x1A00 and sub == 5:
            return 1000.0 / value if value else 0.0
        return value

    def configure(self, rate_hz: float | None = None, heartbeat_ms: int | None = 1000,
                  rate_object: str | None = None,
                  log: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
        """Start-of-run SDO configuration, each step passed to `log` (the run's events): NMT
        pre-operational; identity and device name; the TPDO mapping; the rate (written if
        `rate_hz` is given, else left as the node has it) and the heartbeat producer time.
        Returns what the node reported. DeviceError (one line: node, object, abort code) on an
        SDO abort or timeout, or an EDS without an object the run needs."""
        log = log or (lambda event: None)
        self.enter_pre_operational()
        log({"event": "accel_config", "step": "nmt", "state": "pre-operational"})
        ident = self.identity()
        log({"event": "accel_config", "step": "identity", **ident})
        layout = self.read_mapping()
        log({"event": "accel_config", "step": "mapping", "mapping": layout.describe(),
             "layout": layout.to_dict()})
        index, sub = self._rate_object(rate_object)
        if rate_hz is not None:
            value = round(1000.0 / rate_hz) if 0x1800 <= index < 0x1A00 and sub == 5 else round(rate_hz)
            self.sdo_write(index, sub, int(value))
        self.rate_hz = self.read_rate(rate_object)
        log({"event": "accel_config", "step": "rate", "object": f"{index:04X}:{sub}", "rate_hz": self.rate_hz,
             "written": rate_hz is not None, "after_run": "left as configured (a reset node restores it)"})
        if heartbeat_ms is not None:
            self.sdo_write(0x1017, 0, int(heartbeat_ms))
        hb = int(self.sdo_read(0x1017, 0))
        log({"event": "accel_config", "step": "heartbeat", "producer_ms": hb,
             "written": heartbeat_ms is not None, "after_run": "left as configured"})
        return {"identity": ident, "mapping": layout.describe(), "rate_hz": self.rate_hz, "heartbeat_ms": hb}

    # -- waiting -----------------------------------------------------------------------------
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
        (the message from `timeout_message()`). The byte streams' wait (drivers._stream)."""

        def bus_error() -> DeviceError | None:
            if self._error is None:
                return None
            return DeviceError(DEVICE, self.port, f"bus error on {self.port}: {self._error}")

        wait_until(self._lock, ready, timeout_s, bus_error,
                   lambda: DeviceError(DEVICE, self.port, timeout_message()))

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

    # what a node's samples are, for read (the CiA 410 inclinometer's are slopes)
    _noun = "samples"
    _silent_hint = "is the node operational (start_node) and the bitrate right?"

    def _queued(self) -> int:
        """With `_lock` held: samples received and not read yet."""
        return self._decoder.pending()

    def _drain(self, k: int) -> Any:
        """With `_lock` held: the oldest `k` queued samples, raw."""
        return self._decoder.drain(k)

    def _block(self, raw: Any) -> AccelBlock:
        """Drained samples as an AccelBlock (outside the lock: the bus thread goes on meanwhile)."""
        return samples_to_block(raw, self._decoder.layout)

    def read(self, n_samples: int, timeout_s: float | None = None, until_stopped: bool = False) -> AccelBlock:
        """The next `n_samples` samples, blocking; DeviceError naming the channel on timeout.
        `until_stopped`: fewer once the node has proven its stop (:meth:`_stop_proven`) — all it sent."""
        n, wait_s = read_bounds(n_samples, self.rate_hz, self.timeout_s, timeout_s)
        with self._lock:
            self._want = n  # the bus thread wakes this one when n are there, not at every sample
            try:
                self._wait_locked(
                    lambda: self._queued() >= n or until_stopped and self._stop_proven(),
                    wait_s,
                    lambda: f"only {self._queued()} of {n} {self._noun} from node 0x{self.node_id:02X} "
                    f"within {wait_s:g} s on {self.port} — {self._silent_hint}",
                )
            finally:
                self._want = 1
            raw = self._drain(min(n, self._queued()))
        return self._block(raw)

    def pending_samples(self) -> int:
        """Samples received and not read yet."""
        with self._lock:
            return self._queued()

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

    def flush_log(self) -> None:
        """Push the CAN log to disk (python-can's writer buffers; the notifier thread writes to it)."""
        with self._lock:
            handle = getattr(self._logger, "file", None)
            if handle is not None and not handle.closed:
                handle.flush()

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
