"""CANopen 3-axis accelerometer node on any python-can bus (docs/PROTOCOLS.md §3, CiA 301).

Reference: CiA 301 v4.2 "CANopen application layer and communication profile": §7.2.2 PDO
(transmission types, inhibit time, event timer, SYNC-driven transmission), §7.2.5 SYNC,
§7.5.2.5 COB-ID SYNC (1005h), §7.5.2.37 TPDO communication parameter (1800h+n: COB-ID with its
valid bit 31 and RTR bit 30, transmission type, inhibit time, sub-index 4 reserved, event timer,
SYNC start value), §7.5.2.38 TPDO mapping parameter (1A00h+n) with the mapping procedure
(invalidate the PDO, count 0, entries, count, validate), §7.2.4.3.17 SDO abort codes.
docs/conformance/canopen.md (tools/conformance_canopen.py) lists every object against the standard.

The node boots on its first `advance`, sends the boot-up heartbeat (state 0x00), then a
heartbeat every 1000 ms of device time with its NMT state. While operational it sends one
TPDO1 (x, y) + TPDO2 (z, temperature, counter, status) pair per sample at `rate_hz` in device
time. The samples come from the simulator's world (integrated specific force over each sample
interval) through the accelerometer's error model, so the node measures what a real sensor on
the table would. Codecs are written here from the protocol sheet (firmware_sim never imports
northfinder).

The sensor itself runs from power-on (the first `advance`) whatever the NMT state is (its error
model's state moves on in pre-operational too); NMT only gates what goes onto the bus. The sample
clock is a fixed grid t_power_on + k / rate_hz, each sample sent at the end of its interval; a
reset-node command restarts the application (boot-up, counter 0) but not the sampling.
"""

from __future__ import annotations

import abc
import logging
import math
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import can
import numpy as np

from firmware_sim.can_wire import arrival_s
from firmware_sim.devices.base import Device

log = logging.getLogger(__name__)

STANDARD_GRAVITY_M_S2 = 9.80665  # 1 g as a unit (docs/CONVENTIONS.md project notes)

# NMT commands (ID 0x000, [cmd, node]; node 0 = all nodes)
NMT_ID = 0x000
NMT_START = 0x01
NMT_STOP = 0x02
NMT_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81

# Heartbeat states (ID 0x700 + node)
STATE_BOOTUP = 0x00
STATE_STOPPED = 0x04
STATE_OPERATIONAL = 0x05
STATE_PRE_OPERATIONAL = 0x7F

HEARTBEAT_BASE = 0x700
TPDO1_BASE = 0x180
TPDO2_BASE = 0x280
EMCY_BASE = 0x080

EMCY_NO_ERROR = 0x0000
EMCY_DEVICE_HARDWARE = 0x5000
EMCY_CAN_OVERRUN = 0x8110
EMCY_HEARTBEAT = 0x8130

STATUS_X_VALID = 0x01
STATUS_Y_VALID = 0x02
STATUS_Z_VALID = 0x04
STATUS_OVER_RANGE = 0x80

HEARTBEAT_PERIOD_S = 1.0

_TPDO1_DTYPE = np.dtype([("x", "<i4"), ("y", "<i4")])
_TPDO2_DTYPE = np.dtype([("z", "<i4"), ("temp", "<i2"), ("counter", "u1"), ("status", "u1")])
_INT32_MAX = 2**31 - 1


# ---------------------------------------------------------------------------------------------
# Codecs: (arbitration id, payload bytes), pure, byte-exact to PROTOCOLS.md §3
# ---------------------------------------------------------------------------------------------
def encode_nmt(command: int, node_id: int) -> tuple[int, bytes]:
    """NMT command frame: ID 0x000, [cmd, node] (node 0 addresses every node)."""
    return NMT_ID, bytes((command & 0xFF, node_id & 0x7F))


def decode_nmt(data: bytes) -> tuple[int, int]:
    """NMT payload -> (command, node id); ValueError if it is not 2 bytes."""
    if len(data) != 2:
        raise ValueError(f"NMT frame must have 2 data bytes, got {len(data)}")
    return data[0], data[1]


def encode_heartbeat(node_id: int, state: int) -> tuple[int, bytes]:
    """Heartbeat frame: ID 0x700 + node, 1 byte NMT state."""
    return HEARTBEAT_BASE + node_id, bytes((state & 0xFF,))


def encode_tpdo1(node_id: int, x_ug: int, y_ug: int) -> tuple[int, bytes]:
    """TPDO1: accel x, y as int32 little-endian in µg."""
    return TPDO1_BASE + node_id, struct.pack("<ii", x_ug, y_ug)


def encode_tpdo2(
    node_id: int, z_ug: int, temperature_centi_c: int, counter: int, status: int
) -> tuple[int, bytes]:
    """TPDO2: accel z int32 LE µg, temperature int16 LE 0.01 °C, counter uint8, status uint8."""
    return TPDO2_BASE + node_id, struct.pack("<ihBB", z_ug, temperature_centi_c, counter & 0xFF, status)


def encode_emcy(node_id: int, code: int, register: int, vendor: bytes = bytes(5)) -> tuple[int, bytes]:
    """EMCY: error code uint16 LE, error register uint8, 5 vendor-specific bytes."""
    if len(vendor) != 5:
        raise ValueError(f"EMCY vendor field must be 5 bytes, got {len(vendor)}")
    return EMCY_BASE + node_id, struct.pack("<HB", code, register) + bytes(vendor)


def encode_samples(
    accel_ug: np.ndarray, temperature_centi_c: int, counters: np.ndarray, status: np.ndarray
) -> tuple[list[bytes], list[bytes]]:
    """Vectorized TPDO1/TPDO2 payloads for a block of samples (accel_ug int [n,3])."""
    n = accel_ug.shape[0]
    t1 = np.empty(n, _TPDO1_DTYPE)
    t1["x"] = accel_ug[:, 0]
    t1["y"] = accel_ug[:, 1]
    t2 = np.empty(n, _TPDO2_DTYPE)
    t2["z"] = accel_ug[:, 2]
    t2["temp"] = temperature_centi_c
    t2["counter"] = counters
    t2["status"] = status
    b1, b2 = t1.tobytes(), t2.tobytes()
    return [b1[8 * i : 8 * i + 8] for i in range(n)], [b2[8 * i : 8 * i + 8] for i in range(n)]


def specific_force_to_ug(
    dv_m_s: np.ndarray, dt_s: float, full_scale_g: float
) -> tuple[np.ndarray, np.ndarray]:
    """Velocity increments [n,3] over dt -> (µg int64 [n,3] clipped to full scale, over-range bool [n]).

    Mean specific force over the interval is dv/dt; 1 g = 9.80665 m/s² (standard gravity).
    """
    accel_g = np.asarray(dv_m_s, dtype=float) / (dt_s * STANDARD_GRAVITY_M_S2)
    over = np.any(np.abs(accel_g) > full_scale_g, axis=1)
    limit_ug = min(full_scale_g * 1e6, _INT32_MAX)
    ug = np.clip(np.rint(accel_g * 1e6), -limit_ug, limit_ug).astype(np.int64)
    return ug, over


# ---------------------------------------------------------------------------------------------
# SDO server and object dictionary (CiA 301, docs/PROTOCOLS.md §3.1), device side
# ---------------------------------------------------------------------------------------------
SDO_RX_BASE = 0x600  # client -> server
SDO_TX_BASE = 0x580  # server -> client

ABORT_TOGGLE = 0x05030000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED = 0x06010000
ABORT_WRITE_ONLY = 0x06010001
ABORT_READ_ONLY = 0x06010002
ABORT_NO_OBJECT = 0x06020000
ABORT_NOT_MAPPABLE = 0x06040041
ABORT_PDO_LENGTH = 0x06040042
ABORT_LENGTH = 0x06070010
ABORT_NO_SUBINDEX = 0x06090011
ABORT_RANGE = 0x06090030
ABORT_STATE = 0x08000022

SYNC_ID = 0x080  # CiA 301 default COB-ID SYNC (1005h)
NMT_RESET_COMMUNICATION = 0x82
PDO_NOT_VALID = 1 << 31  # 1800h+n sub 1 bit 31: 1 = PDO does not exist / is not valid
PDO_NO_RTR = 1 << 30  # bit 30: 1 = no RTR allowed on this PDO
PDO_EXTENDED = 1 << 29  # bit 29: 1 = 29-bit CAN-ID (this node: 11-bit only)
TRANSMISSION_SYNC_ACYCLIC = 0
TRANSMISSION_SYNC_RTR = 252
TRANSMISSION_RTR = 253
TRANSMISSION_EVENT_MANUFACTURER = 254
TRANSMISSION_EVENT_PROFILE = 255

DEVICE_NAME = "NF-ACC3 accelerometer"
SOFTWARE_VERSION = "firmware-sim 1.0"
VENDOR_ID = 0x000004E2  # a made-up vendor of the project's reference node
PRODUCT_CODE = 0x00ACC003
REVISION = 0x00010000
SERIAL_NUMBER = 0x00001010

# Mapping entries: index << 16 | sub << 8 | bits (PROTOCOLS.md §3.1 defaults).
MAPPINGS: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "default": ((0x20000120, 0x20000220), (0x20000320, 0x20010010, 0x20020008, 0x20030008)),
    # axes in another order and another scale (0x2004, 0.1 µg per count), other fields reordered
    "swapped": ((0x20040320, 0x20040120), (0x20040220, 0x20030008, 0x20020008, 0x20010010)),
}

_SIZES = {"u8": 1, "u16": 2, "u32": 4, "i16": 2, "i32": 4}
_STRUCT = {"u8": "B", "u16": "H", "u32": "I", "i16": "h", "i32": "i"}
_NUMPY = {"u8": "u1", "u16": "<u2", "u32": "<u4", "i16": "<i2", "i32": "<i4"}


@dataclass
class OdEntry:
    """One sub-object: its type, access (`ro`, `rw`, `rw-preop` = writable in pre-operational
    only), value, and the writable range."""

    kind: str  # u8 u16 u32 i16 i32 vs (visible string)
    access: str
    value: Any
    low: int | None = None
    high: int | None = None
    mappable: bool = False

    def encode(self) -> bytes:
        if self.kind == "vs":
            return str(self.value).encode("ascii")
        return struct.pack("<" + _STRUCT[self.kind], int(self.value))


def build_object_dictionary(node_id: int, mapping: str, rate_hz: float,
                            heartbeat_ms: int = 1000) -> dict[tuple[int, int], OdEntry]:
    """The node's object dictionary (the shipped EDS describes the `default` variant)."""
    if mapping not in MAPPINGS:
        raise ValueError(f"accel mapping {mapping!r}: use one of {', '.join(MAPPINGS)}")
    t1, t2 = MAPPINGS[mapping]
    od: dict[tuple[int, int], OdEntry] = {
        (0x1000, 0): OdEntry("u32", "ro", 0),
        (0x1001, 0): OdEntry("u8", "ro", 0),
        (0x1008, 0): OdEntry("vs", "ro", DEVICE_NAME),
        (0x100A, 0): OdEntry("vs", "ro", SOFTWARE_VERSION),
        (0x1017, 0): OdEntry("u16", "rw", heartbeat_ms, 0, 0xFFFF),
        (0x1018, 0): OdEntry("u8", "ro", 4),
        (0x1018, 1): OdEntry("u32", "ro", VENDOR_ID),
        (0x1018, 2): OdEntry("u32", "ro", PRODUCT_CODE),
        (0x1018, 3): OdEntry("u32", "ro", REVISION),
        (0x1018, 4): OdEntry("u32", "ro", SERIAL_NUMBER),
        (0x2001, 0): OdEntry("i16", "ro", 0, mappable=True),
        (0x2002, 0): OdEntry("u8", "ro", 0, mappable=True),
        (0x2003, 0): OdEntry("u8", "ro", 0, mappable=True),
        (0x2100, 0): OdEntry("u16", "rw-preop", int(round(rate_hz)), 1, 1000),
    }
    od[(0x1005, 0)] = OdEntry("u32", "rw", SYNC_ID)
    for k, (base, entries) in enumerate(((TPDO1_BASE, t1), (TPDO2_BASE, t2))):
        # CiA 301 §7.5.2.37: sub 4 is reserved and not implemented (abort 0x06090011)
        od[(0x1800 + k, 0)] = OdEntry("u8", "ro", 6)
        od[(0x1800 + k, 1)] = OdEntry("u32", "rw", base + node_id)
        od[(0x1800 + k, 2)] = OdEntry("u8", "rw", TRANSMISSION_EVENT_MANUFACTURER)
        od[(0x1800 + k, 3)] = OdEntry("u16", "rw", 0)
        od[(0x1800 + k, 5)] = OdEntry("u16", "rw", 0)
        od[(0x1800 + k, 6)] = OdEntry("u8", "rw", 0, 0, 240)
        od[(0x1A00 + k, 0)] = OdEntry("u8", "rw", len(entries), 0, 8)
        for s in range(1, 9):
            od[(0x1A00 + k, s)] = OdEntry("u32", "rw", entries[s - 1] if s <= len(entries) else 0)
    axes_index = 0x2004 if mapping == "swapped" else 0x2000
    od[(axes_index, 0)] = OdEntry("u8", "ro", 3)
    for s in (1, 2, 3):
        od[(axes_index, s)] = OdEntry("i32", "ro", 0, mappable=True)
    return od


def sdo_abort(index: int, sub: int, code: int) -> bytes:
    """Abort frame payload: 0x80, index LE, sub-index, code uint32 LE."""
    return struct.pack("<BHBI", 0x80, index, sub, code)


def sdo_upload_request(index: int, sub: int) -> bytes:
    """Initiate upload (read) request payload (client side; tests and golden vectors)."""
    return struct.pack("<BHB4x", 0x40, index, sub)


def sdo_download_request(index: int, sub: int, data: bytes) -> bytes:
    """Expedited download (write) request payload, 1–4 data bytes."""
    if not 1 <= len(data) <= 4:
        raise ValueError("an expedited download carries 1..4 bytes")
    return struct.pack("<BHB", 0x23 | (4 - len(data)) << 2, index, sub) + bytes(data).ljust(4, b"\0")


class _SdoAbort(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


class SdoServer:
    """CiA 301 SDO server over an object dictionary: expedited and segmented upload, expedited and
    segmented download, aborts. `on_write(index, sub, value)` lets the node act on (or refuse, by
    raising ValueError) a write after the dictionary's own checks."""

    def __init__(self, od: dict[tuple[int, int], OdEntry], on_write: Callable[[int, int, Any], None]) -> None:
        self.od = od
        self.on_write = on_write
        self._upload: tuple[int, int, bytes, int, int] | None = None  # index, sub, data, offset, toggle
        self._download: tuple[int, int, bytearray, int] | None = None  # index, sub, data, toggle

    def handle(self, req: bytes, state: int) -> bytes:
        """One request payload (8 bytes) in NMT `state` -> the response payload."""
        if len(req) != 8:
            return sdo_abort(0, 0, ABORT_COMMAND)
        ccs = req[0] >> 5
        index, sub = struct.unpack_from("<HB", req, 1)
        ongoing = self._upload if ccs == 3 else self._download if ccs == 0 else None
        if ongoing is not None:  # a segment carries data where the index was: abort on the transfer's
            index, sub = ongoing[0], ongoing[1]
        try:
            if ccs == 2:  # initiate upload
                return self._initiate_upload(index, sub)
            if ccs == 3:  # upload segment
                return self._upload_segment(req)
            if ccs == 1:  # initiate download
                return self._initiate_download(req, index, sub, state)
            if ccs == 0:  # download segment
                return self._download_segment(req, state)
            if ccs == 4:  # abort from the client: forget the transfer, no answer is owed
                self._upload = self._download = None
                return b""
            raise _SdoAbort(ABORT_COMMAND)
        except _SdoAbort as exc:
            self._upload = self._download = None
            return sdo_abort(index, sub, exc.code)

    def _entry(self, index: int, sub: int) -> OdEntry:
        if (index, sub) in self.od:
            return self.od[(index, sub)]
        if any(i == index for i, _ in self.od):
            raise _SdoAbort(ABORT_NO_SUBINDEX)
        raise _SdoAbort(ABORT_NO_OBJECT)

    def _initiate_upload(self, index: int, sub: int) -> bytes:
        data = self._entry(index, sub).encode()
        self._upload = None
        if len(data) <= 4:
            return struct.pack("<BHB", 0x43 | (4 - len(data)) << 2, index, sub) + data.ljust(4, b"\0")
        self._upload = (index, sub, data, 0, 0)
        return struct.pack("<BHBI", 0x41, index, sub, len(data))

    def _upload_segment(self, req: bytes) -> bytes:
        if self._upload is None:
            raise _SdoAbort(ABORT_COMMAND)
        index, sub, data, offset, toggle = self._upload
        if (req[0] >> 4) & 1 != toggle:
            raise _SdoAbort(ABORT_TOGGLE)
        chunk = data[offset : offset + 7]
        last = offset + len(chunk) >= len(data)
        self._upload = None if last else (index, sub, data, offset + len(chunk), toggle ^ 1)
        return bytes((toggle << 4 | (7 - len(chunk)) << 1 | int(last),)) + chunk.ljust(7, b"\0")

    def _check_writable(self, entry: OdEntry, state: int) -> None:
        if entry.access == "ro":
            raise _SdoAbort(ABORT_READ_ONLY)
        if entry.access == "rw-preop" and state != STATE_PRE_OPERATIONAL:
            raise _SdoAbort(ABORT_STATE)

    def _initiate_download(self, req: bytes, index: int, sub: int, state: int) -> bytes:
        entry = self._entry(index, sub)
        self._check_writable(entry, state)
        expedited, sized = bool(req[0] & 0x02), bool(req[0] & 0x01)
        if not expedited:  # segmented: the size (if given) in bytes 4–7, data follows
            self._download = (index, sub, bytearray(), 0)
            return struct.pack("<BHB4x", 0x60, index, sub)
        n = 4 - ((req[0] >> 2) & 3) if sized else _SIZES.get(entry.kind, 4)
        self._write(index, sub, entry, bytes(req[4 : 4 + n]))
        return struct.pack("<BHB4x", 0x60, index, sub)

    def _download_segment(self, req: bytes, state: int) -> bytes:
        if self._download is None:
            raise _SdoAbort(ABORT_COMMAND)
        index, sub, buf, toggle = self._download
        if (req[0] >> 4) & 1 != toggle:
            raise _SdoAbort(ABORT_TOGGLE)
        buf += req[1 : 1 + 7 - ((req[0] >> 1) & 7)]
        if req[0] & 1:  # last segment
            self._download = None
            entry = self._entry(index, sub)
            self._check_writable(entry, state)
            self._write(index, sub, entry, bytes(buf))
        else:
            self._download = (index, sub, buf, toggle ^ 1)
        return bytes((0x20 | toggle << 4,)) + bytes(7)

    def _write(self, index: int, sub: int, entry: OdEntry, data: bytes) -> None:
        if entry.kind == "vs":
            value: Any = data.decode("ascii", errors="replace")
        else:
            if len(data) != _SIZES[entry.kind]:
                raise _SdoAbort(ABORT_LENGTH)
            (value,) = struct.unpack("<" + _STRUCT[entry.kind], data)
            low, high = entry.low, entry.high
            if (low is not None and value < low) or (high is not None and value > high):
                raise _SdoAbort(ABORT_RANGE)
        try:
            self.on_write(index, sub, value)
        except _SdoAbort:
            raise
        except ValueError:
            raise _SdoAbort(ABORT_RANGE) from None
        entry.value = value


def mapping_layout(od: dict[tuple[int, int], OdEntry], pdo: int) -> list[tuple[int, int, str]]:
    """TPDO `pdo` (0 or 1) as [(index, sub, kind)] from its mapping object."""
    count = int(od[(0x1A00 + pdo, 0)].value)
    out = []
    for s in range(1, count + 1):
        entry = int(od[(0x1A00 + pdo, s)].value)
        out.append((entry >> 16, (entry >> 8) & 0xFF, od[(entry >> 16, (entry >> 8) & 0xFF)].kind))
    return out


def pdo_valid(od: dict[tuple[int, int], OdEntry], pdo: int) -> bool:
    """CiA 301 §7.5.2.37: bit 31 of the COB-ID clear = the PDO exists (is valid)."""
    return not int(od[(0x1800 + pdo, 1)].value) & PDO_NOT_VALID


def check_mapping_entry(od: dict[tuple[int, int], OdEntry], entry: int) -> None:
    """A mapping entry names an existing (0x06020000), mappable object with its exact bit length
    (0x06040041, object cannot be mapped); 0 clears the entry."""
    if entry == 0:
        return
    key = (entry >> 16, (entry >> 8) & 0xFF)
    target = od.get(key)
    if target is None:
        if any(i == key[0] for i, _ in od):
            raise _SdoAbort(ABORT_NO_SUBINDEX)
        raise _SdoAbort(ABORT_NO_OBJECT)
    if not target.mappable or _SIZES[target.kind] * 8 != entry & 0xFF:
        raise _SdoAbort(ABORT_NOT_MAPPABLE)


def check_mapping_write(od: dict[tuple[int, int], OdEntry], pdo: int, sub: int, value: int) -> None:
    """CiA 301 §7.5.2.38, the mapping procedure: the mapping changes only while the PDO is not
    valid (0x06010000); an entry only while the count (sub 0) is 0 (0x06010000); a new count
    checks every entry it takes in (0x06040041) and their length against 64 bits (0x06040042)."""
    if pdo_valid(od, pdo):
        raise _SdoAbort(ABORT_UNSUPPORTED)
    if sub == 0:
        for s in range(1, value + 1):
            entry = int(od[(0x1A00 + pdo, s)].value)
            if entry == 0:
                raise _SdoAbort(ABORT_NOT_MAPPABLE)
            check_mapping_entry(od, entry)
        if mapping_bits(od, pdo, value) > 64:
            raise _SdoAbort(ABORT_PDO_LENGTH)
        return
    if int(od[(0x1A00 + pdo, 0)].value) != 0:
        raise _SdoAbort(ABORT_UNSUPPORTED)
    check_mapping_entry(od, value)


def check_communication_write(od: dict[tuple[int, int], OdEntry], pdo: int, sub: int, value: int) -> None:
    """CiA 301 §7.5.2.37: while the PDO is valid its CAN-ID (bits 0–29), inhibit time and SYNC
    start value do not change (0x06090030); transmission types 241…251 are reserved (0x06090030);
    this node has 11-bit CAN-IDs only (bit 29 set, or ID bits above 0x7FF: 0x06090030)."""
    valid = pdo_valid(od, pdo)
    if sub == 1:
        if value & PDO_EXTENDED or value & 0x1FFFF800:
            raise _SdoAbort(ABORT_RANGE)
        old = int(od[(0x1800 + pdo, 1)].value)
        if valid and not value & PDO_NOT_VALID and (value ^ old) & 0x3FFFFFFF:
            raise _SdoAbort(ABORT_RANGE)
    elif sub == 2:
        if 241 <= value <= 251:
            raise _SdoAbort(ABORT_RANGE)
    elif sub in (3, 6) and valid:
        raise _SdoAbort(ABORT_RANGE)


def mapping_bits(od: dict[tuple[int, int], OdEntry], pdo: int, count: int) -> int:
    """Bits of the first `count` entries of TPDO `pdo`'s mapping."""
    return sum(int(od[(0x1A00 + pdo, s)].value) & 0xFF for s in range(1, count + 1))


@dataclass
class TpdoTx:
    """One TPDO's transmission state (CiA 301 §7.2.2.2): when it last went out, what is pending
    behind the inhibit time, the latest payload for SYNC/RTR/timer-driven types, the SYNC count."""

    last_sent_s: float = -math.inf
    pending: tuple[bytes, bool] | None = None  # (payload, keep) waiting for the inhibit time
    latest: tuple[bytes, bool] | None = None  # the newest sample's (payload, keep)
    fresh: bool = False  # a sample came since the last transmission (type 0)
    next_timer_s: float = math.inf
    sync_count: int = 0
    sync_started: bool = False
    at_sync: tuple[bytes, bool] | None = None  # type 252: the sample taken at the last SYNC
    timer_s: float = 0.0

    def restart(self, t_s: float, timer_ms: int | None = None) -> None:
        if timer_ms is not None:
            self.timer_s = timer_ms / 1000.0
        self.next_timer_s = t_s + self.timer_s if self.timer_s > 0 else math.inf
        self.pending = None


# ---------------------------------------------------------------------------------------------
# Faults
# ---------------------------------------------------------------------------------------------
@dataclass
class AccelFaults:
    """The CAN accelerometer's fault hooks (times in device seconds); all absent by default."""

    loss_rate: float = 0.0  # accel-loss-rate=P: drop each TPDO frame with probability P
    emcy: list[tuple[float, int]] = field(default_factory=list)  # accel-emcy=AT_S[:CODE]
    heartbeat_loss_at_s: float | None = None  # accel-heartbeat-loss=AT_S: no heartbeat from then
    sdo_silent_at_s: float | None = None  # accel-sdo-silent=AT_S: no SDO answer from then
    start_lag_s: float = 0.0  # accel-start-lag=LAG_S: the first sample LAG_S after each NMT start

    @classmethod
    def from_spec(cls, faults: Any) -> AccelFaults:
        """Build from None, an AccelFaults, or a mapping of fault names (`accel-*`) to values.

        Values may be numbers or the strings of `--fault NAME=VALUE`; other names are ignored
        (they belong to other devices). `accel-emcy` may be one value or a list of them, each
        `AT_S` (code 0x5000 device hardware), `AT_S:CODE` (CODE in hex or decimal) or a tuple
        (at_s, code). A `firmware_sim.faults.Faults` (or its `for_accel()` mapping) works too.
        """
        if faults is None:
            return cls()
        if isinstance(faults, AccelFaults):
            return faults
        if not isinstance(faults, Mapping):
            faults = {k: v for k, v in vars(faults).items() if not k.startswith("_")}
        out = cls()
        for key, value in faults.items():
            name = str(key).replace("_", "-")
            if value is None:
                continue
            if name == "accel-loss-rate":
                out.loss_rate = float(value)
                if not 0.0 <= out.loss_rate <= 1.0:
                    raise ValueError(f"fault accel-loss-rate={value}: give a probability in [0, 1]")
            elif name == "accel-emcy":
                # a tuple is one (at_s, code) as in firmware_sim.faults.Faults; a list is several
                values = [value] if isinstance(value, tuple) or not isinstance(value, list) else value
                for v in values:
                    out.emcy.append(_parse_emcy(v))
                out.emcy.sort()
            elif name == "accel-heartbeat-loss":
                out.heartbeat_loss_at_s = float(value)
            elif name == "accel-sdo-silent":
                out.sdo_silent_at_s = float(value)
            elif name == "accel-start-lag":
                out.start_lag_s = float(value)
        return out


def _parse_emcy(value: Any) -> tuple[float, int]:
    if isinstance(value, tuple) and len(value) == 2:
        return float(value[0]), int(value[1])
    if isinstance(value, int | float):
        return float(value), EMCY_DEVICE_HARDWARE
    text = str(value)
    at, _, code = text.partition(":")
    try:
        return float(at), (int(code, 0) if code else EMCY_DEVICE_HARDWARE)
    except ValueError:
        raise ValueError(f"fault accel-emcy={text}: give AT_S or AT_S:CODE, e.g. 12.5:0x5000") from None


# ---------------------------------------------------------------------------------------------
# The node
# ---------------------------------------------------------------------------------------------
class _World(Protocol):
    def increments(
        self, t0_s: float, n: int, dt_s: float, lever_arm_b_m: Any
    ) -> tuple[np.ndarray, np.ndarray]: ...


class _AccelModel(Protocol):
    def apply(self, dv_true_m_s: np.ndarray) -> np.ndarray: ...


@dataclass
class NodeStats:
    """What the node put on the bus (and what the loss fault swallowed)."""

    samples: int = 0  # samples taken while operational (each one counter step)
    tpdo_sent: int = 0
    tpdo_dropped: int = 0
    heartbeats: int = 0
    emcy: int = 0
    nmt_received: int = 0
    tx_errors: int = 0
    sdo_requests: int = 0
    sdo_aborts: int = 0
    sdo_ignored: int = 0  # requests not answered (stopped state, or the accel-sdo-silent fault)


class CanopenNode(Device):
    """What every emulated CANopen node on a python-can bus shares (CiA 301): the loop drives it
    through `advance` (frames received up to `t`, then every frame due up to it), the NMT state
    commands, and `close`. Subclasses set `bus`, `state` (None until powered on), `_closed`,
    `_t_now_s`, `_grid_t0_s` and implement `_boot`, `_on_frame` and `_emit_until`."""

    bus: can.BusABC
    state: int | None
    _closed: bool
    _t_now_s: float
    _grid_t0_s: float | None

    @abc.abstractmethod
    def _boot(self, t_s: float) -> None:
        """Power-on or NMT reset node at `t_s`: boot-up heartbeat, then pre-operational."""

    @abc.abstractmethod
    def _on_frame(self, msg: can.Message, t_s: float) -> None:
        """Act on one received frame at device time `t_s`."""

    @abc.abstractmethod
    def _emit_until(self, t_s: float) -> None:
        """Send every frame due up to device time `t_s`."""

    def _power_on(self, t_s: float) -> None:
        """The first `advance`: the sample grid starts here, then the node boots."""
        self._grid_t0_s = float(t_s)
        self._boot(t_s)

    def advance(self, t_device_s: float) -> None:
        """Act on each received NMT/SDO frame at the device time it came in (`can_wire.arrival_s`:
        on firmware_sim's own wire, when its slcan line reached the adapter; on another bus, now),
        then send every frame due up to `t_device_s`."""
        if self._closed:
            return
        if self.state is None:
            self._power_on(t_device_s)
            self._t_now_s = float(t_device_s)
        while (msg := self.bus.recv(timeout=0)) is not None:  # _t_now_s: the last frame's time
            self._t_now_s = arrival_s(self.bus, msg, self._t_now_s, t_device_s)
            self._on_frame(msg, self._t_now_s)
        self._t_now_s = float(t_device_s)
        self._emit_until(t_device_s)

    def close(self) -> None:
        """Stop sending; the bus belongs to whoever made it (the simulator shuts it down)."""
        self._closed = True

    def _nmt_state_command(self, command: int, t_s: float) -> bool:
        """Start, stop, enter pre-operational or reset node (CiA 301 NMT node control); False for any
        other command."""
        if command == NMT_START:
            self.state = STATE_OPERATIONAL
        elif command == NMT_STOP:
            self.state = STATE_STOPPED
        elif command == NMT_PRE_OPERATIONAL:
            self.state = STATE_PRE_OPERATIONAL
        elif command == NMT_RESET_NODE:
            self._boot(t_s)
        else:
            return False
        return True


class CanAccelNode(CanopenNode):
    """A CANopen accelerometer on `bus`, measuring `world` through `accel_model`, with a CiA 301 SDO
    server over its object dictionary (PROTOCOLS.md §3.1).

    `mapping` picks the TPDO mapping variant (`default`, or `swapped`: axes in another order and
    another scale); `make_model(rate_hz)` rebuilds the error model when the rate is changed over
    SDO (0x2100), so that the noise per sample follows the rate. `rng` (a numpy Generator or a
    seed) drives only the faults, so that a faulted run is repeatable.
    """

    name = "accelerometer"

    def __init__(
        self,
        bus: can.BusABC,
        world: _World,
        accel_model: _AccelModel,
        *,
        node_id: int = 0x10,
        rate_hz: float = 100.0,
        lever_arm_b_m: Iterable[float] = (0, 0, 0),
        faults: Any = None,
        temperature_c: float = 25.0,
        full_scale_g: float = 8.0,
        rng: np.random.Generator | int | None = None,
        mapping: str = "default",
        make_model: Callable[[float], _AccelModel] | None = None,
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CAN accelerometer node_id={node_id}: give a node ID in 1…127")
        if not rate_hz > 0:
            raise ValueError(f"CAN accelerometer rate_hz={rate_hz}: give a positive sample rate")
        self.bus = bus
        self.world = world
        self.accel_model = accel_model
        self.make_model = make_model
        self.node_id = node_id
        self.mapping = mapping
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.lever_arm_b_m = np.asarray(tuple(lever_arm_b_m), dtype=float)
        self.faults = AccelFaults.from_spec(faults)
        self.temperature_c = float(temperature_c)
        self.full_scale_g = float(full_scale_g)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng or 0)
        self.stats = NodeStats()
        self._power_on_rate_hz = self.rate_hz
        self.od = build_object_dictionary(node_id, mapping, self.rate_hz)
        self.sdo = SdoServer(self.od, self._on_sdo_write)
        self._tx = [TpdoTx(), TpdoTx()]

        self.state: int | None = None  # None until powered on
        self.power_on_s: float | None = None  # device time of the first `advance`
        self._grid_t0_s: float | None = None  # sample k covers grid_t0 + [k·dt, (k+1)·dt]
        self._next_sample = 0
        self._next_heartbeat_s = math.inf
        self._counter = 0
        self._emcy_index = 0
        self._closed = False
        self._t_now_s = 0.0
        self._send_from_s: float | None = None  # accel-start-lag: no sample ends before this

    @property
    def heartbeat_period_s(self) -> float:
        """0x1017 in seconds (0: no heartbeat)."""
        return int(self.od[(0x1017, 0)].value) / 1000.0

    # -- Device surface --------------------------------------------------------------------
    def endpoint(self) -> dict[str, Any]:
        """The node as a client sees it (the bus channel itself is the adapter's endpoint)."""
        return {"node_id": self.node_id}

    def _power_on(self, t_s: float) -> None:
        self.power_on_s = float(t_s)
        super()._power_on(t_s)

    # -- NMT ---------------------------------------------------------------------------------
    def _boot(self, t_s: float) -> None:
        """Power-on or reset node: the dictionary back to its defaults (rate, mapping, heartbeat
        time), boot-up heartbeat, then pre-operational."""
        self._counter = 0
        if self.power_on_s is not None and self.power_on_s != t_s:
            self._set_rate(self._power_on_rate_hz, t_s)
        self.od.update(build_object_dictionary(self.node_id, self.mapping, self._power_on_rate_hz))
        self._tx = [TpdoTx(), TpdoTx()]
        self.state = STATE_PRE_OPERATIONAL
        period = self.heartbeat_period_s
        self._next_heartbeat_s = t_s + period if period > 0 else math.inf
        self._send_heartbeat(t_s, STATE_BOOTUP)

    def _on_frame(self, msg: can.Message, t_s: float) -> None:
        if msg.is_extended_id:
            return
        if msg.is_remote_frame:
            self._on_remote(msg.arbitration_id, t_s)
            return
        if msg.arbitration_id == SDO_RX_BASE + self.node_id:
            self._on_sdo(bytes(msg.data), t_s)
            return
        if msg.arbitration_id == int(self.od[(0x1005, 0)].value) & 0x7FF and msg.dlc <= 1:
            self._on_sync(bytes(msg.data), t_s)
            return
        if msg.arbitration_id != NMT_ID or msg.dlc != 2:
            return
        command, node = decode_nmt(bytes(msg.data))
        if node not in (0, self.node_id):
            return
        self.stats.nmt_received += 1
        # Everything due before the command arrived goes out under the old state.
        self._emit_until(t_s)
        if not self._nmt_state_command(command, t_s) and command == NMT_RESET_COMMUNICATION:
            self._reset_communication(t_s)
        log.debug("node 0x%02X: NMT 0x%02X at %.6f s -> state 0x%02X", self.node_id, command, t_s, self.state)

    def _reset_communication(self, t_s: float) -> None:
        """NMT reset communication: the communication objects (1000h–1FFFh) back to their
        defaults, boot-up, pre-operational; the application (rate, counter) goes on."""
        defaults = build_object_dictionary(self.node_id, self.mapping, self.rate_hz)
        self.od.update({key: entry for key, entry in defaults.items() if key[0] < 0x2000})
        self._tx = [TpdoTx(), TpdoTx()]
        self.state = STATE_PRE_OPERATIONAL
        period = self.heartbeat_period_s
        self._next_heartbeat_s = t_s + period if period > 0 else math.inf
        self._send_heartbeat(t_s, STATE_BOOTUP)

    # -- SYNC and RTR (CiA 301 §7.2.5, §7.2.2.2) ----------------------------------------------
    def _on_sync(self, data: bytes, t_s: float) -> None:
        """A SYNC: synchronous TPDOs (types 0…240) go out now with the newest sample; type 252
        takes its sample for the next RTR. The optional counter byte meets the SYNC start value."""
        self._emit_until(t_s)
        if self.state != STATE_OPERATIONAL:
            return
        counter = data[0] if data else None
        for pdo, tx in enumerate(self._tx):
            if not pdo_valid(self.od, pdo) or tx.latest is None:
                continue
            ttype = int(self.od[(0x1800 + pdo, 2)].value)
            if ttype == TRANSMISSION_SYNC_RTR:
                tx.at_sync = tx.latest
            elif ttype == TRANSMISSION_SYNC_ACYCLIC:
                if tx.fresh:
                    self._transmit(pdo, t_s, tx.latest)
            elif ttype <= 240:
                start = int(self.od[(0x1800 + pdo, 6)].value)
                if start and counter is not None and not tx.sync_started:
                    if counter != start:
                        continue
                    tx.sync_started, tx.sync_count = True, ttype - 1  # this SYNC is the first one
                tx.sync_count += 1
                if tx.sync_count >= ttype:
                    tx.sync_count = 0
                    self._transmit(pdo, t_s, tx.latest)

    def _on_remote(self, cob_id: int, t_s: float) -> None:
        """An RTR for a TPDO of type 252 (sample of the last SYNC) or 253 (the newest sample)."""
        self._emit_until(t_s)
        if self.state != STATE_OPERATIONAL:
            return
        for pdo, tx in enumerate(self._tx):
            value = int(self.od[(0x1800 + pdo, 1)].value)
            if value & (PDO_NOT_VALID | PDO_NO_RTR) or value & 0x7FF != cob_id:
                continue
            ttype = int(self.od[(0x1800 + pdo, 2)].value)
            frames = {TRANSMISSION_SYNC_RTR: tx.at_sync, TRANSMISSION_RTR: tx.latest}
            frame = frames.get(ttype)
            if frame is not None:
                self._transmit(pdo, t_s, frame)

    def _transmit(self, pdo: int, t_s: float, frame: tuple[bytes, bool]) -> None:
        """Send one TPDO now (SYNC/RTR answers), through the loss fault like every TPDO."""
        tx = self._tx[pdo]
        tx.last_sent_s, tx.fresh = t_s, False
        payload, keep = frame
        if not keep:
            self.stats.tpdo_dropped += 1
            return
        self.stats.tpdo_sent += 1
        self._send(t_s, int(self.od[(0x1800 + pdo, 1)].value) & 0x7FF, payload)

    # -- SDO ---------------------------------------------------------------------------------
    def _on_sdo(self, request: bytes, t_s: float) -> None:
        """Answer at once (well inside the 10 ms of §3.1); no SDO in stopped (CiA 301), none
        either once the accel-sdo-silent fault is on."""
        silent_at = self.faults.sdo_silent_at_s
        if self.state == STATE_STOPPED or (silent_at is not None and t_s >= silent_at):
            self.stats.sdo_ignored += 1
            return
        self._emit_until(t_s)  # a write (rate, mapping) acts from now on, not on earlier samples
        self.stats.sdo_requests += 1
        reply = self.sdo.handle(request, self.state)
        if reply:
            self.stats.sdo_aborts += int(reply[0] == 0x80)
            self._send(t_s, SDO_TX_BASE + self.node_id, reply)

    def _on_sdo_write(self, index: int, sub: int, value: Any) -> None:
        """The node's own rules for a write the dictionary allowed (CiA 301 §7.5.2.37/38 for the
        PDO parameters, §7.5.2.5 for COB-ID SYNC)."""
        if index in (0x1A00, 0x1A01):
            check_mapping_write(self.od, index - 0x1A00, sub, int(value))
        elif index in (0x1800, 0x1801):
            check_communication_write(self.od, index - 0x1800, sub, int(value))
            self._on_communication_write(index - 0x1800, sub, int(value))
        elif index == 0x1005:
            if int(value) & (PDO_EXTENDED | 1 << 30) or int(value) & 0x1FFFF800:
                raise _SdoAbort(ABORT_RANGE)  # 11-bit SYNC consumer only: no 29-bit ID, no producing
        elif index == 0x2100:
            self._set_rate(float(value), self._t_now_s)
        elif index == 0x1017:
            period = int(value) / 1000.0
            self._next_heartbeat_s = self._t_now_s + period if period > 0 else math.inf

    def _on_communication_write(self, pdo: int, sub: int, value: int) -> None:
        """A TPDO becoming valid, or its event timer changed, starts its timer from now."""
        self._emit_until(self._t_now_s)
        tx = self._tx[pdo]
        if sub == 1 and not value & PDO_NOT_VALID:
            tx.restart(self._t_now_s)
        elif sub in (2, 5):
            tx.next_timer_s = math.inf  # re-armed below with the new figures
            tx.sync_count = 0
            tx.restart(self._t_now_s, timer_ms=value if sub == 5 else None)

    def _set_rate(self, rate_hz: float, t_s: float) -> None:
        """A new sample rate from `t_s`: the grid restarts where the last sample sent ended."""
        if rate_hz == self.rate_hz:
            return
        self._emit_until(t_s)
        self._grid_t0_s = self._grid_t0_s + self._next_sample * self.dt_s
        self._next_sample = 0
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        if self.make_model is not None:
            self.accel_model = self.make_model(self.rate_hz)

    # -- output ------------------------------------------------------------------------------
    def _emit_until(self, t_s: float) -> None:
        """Send heartbeats, EMCYs and samples due up to `t_s`, in device-time order."""
        eps = 1e-9
        t0 = self._grid_t0_s if self._grid_t0_s is not None else t_s
        k_end = int(math.floor((t_s - t0) * self.rate_hz + eps))  # samples k < k_end ended by t_s
        n = k_end - self._next_sample
        events: list[tuple[float, int, Any]] = []
        period = self.heartbeat_period_s
        while period > 0 and self._next_heartbeat_s <= t_s + eps:
            events.append((self._next_heartbeat_s, 0, None))
            self._next_heartbeat_s += period
        while self._emcy_index < len(self.faults.emcy) and self.faults.emcy[self._emcy_index][0] <= t_s + eps:
            events.append((self.faults.emcy[self._emcy_index][0], 1, self.faults.emcy[self._emcy_index][1]))
            self._emcy_index += 1
        if n > 0:
            frames = self._sample_frames(self._next_sample, n)
            self._next_sample = k_end
            if frames is not None:
                events.extend(frames)
        events.extend(self._due_tpdos(t_s))
        if not events:
            return
        events.sort(key=lambda e: (e[0], e[1]))
        for t_event, kind, payload in events:
            if kind == 0:
                self._send_heartbeat(t_event, self.state)
            elif kind == 1:
                self._send_emcy(t_event, payload)
            else:
                self.stats.tpdo_sent += 1
                self._send(t_event, *payload)

    def _due_tpdos(self, t_s: float) -> list[tuple[float, int, Any]]:
        """Event-timer ticks and inhibit-delayed TPDOs due by `t_s` (after the samples up to it)."""
        out: list[tuple[float, int, Any]] = []
        for pdo, tx in enumerate(self._tx):
            if self.state != STATE_OPERATIONAL or not pdo_valid(self.od, pdo):  # nothing goes out
                if tx.next_timer_s <= t_s + 1e-9:
                    tx.next_timer_s += math.ceil((t_s - tx.next_timer_s) / tx.timer_s + 1e-12) * tx.timer_s
                tx.pending = None
                continue
            while tx.next_timer_s <= t_s + 1e-9:
                if tx.latest is not None:
                    self._tx_event(pdo, tx.next_timer_s, tx.latest, out)
                tx.next_timer_s += tx.timer_s
            inhibit_s = int(self.od[(0x1800 + pdo, 3)].value) * 1e-4
            if tx.pending is not None and tx.last_sent_s + inhibit_s <= t_s:
                self._tx_event(pdo, tx.last_sent_s + inhibit_s, tx.pending, out)
                tx.pending = None
        return out

    def _tx_event(self, pdo: int, t_s: float, frame: tuple[bytes, bool], out: list) -> None:
        tx = self._tx[pdo]
        tx.last_sent_s, tx.fresh = t_s, False
        payload, keep = frame
        if keep:
            out.append((t_s, 2 + pdo, (int(self.od[(0x1800 + pdo, 1)].value) & 0x7FF, payload)))
        else:
            self.stats.tpdo_dropped += 1

    def _tpdo_events(self, pdo: int, t_end: np.ndarray, payloads: list[bytes],
                     keep: np.ndarray) -> list[tuple[float, int, Any]]:
        """CiA 301 §7.2.2.2 for one TPDO over a block of samples: event-driven types (254, 255)
        send each sample (no sooner than the inhibit time after the last one: then the newest
        sample goes out when it has passed) or, with an event timer, the newest sample at each
        tick (the manufacturer-specific event of this node); the other types keep the newest
        sample for the SYNC or RTR that sends it."""
        tx = self._tx[pdo]
        ttype = int(self.od[(0x1800 + pdo, 2)].value)
        out: list[tuple[float, int, Any]] = []
        if ttype < TRANSMISSION_EVENT_MANUFACTURER:
            tx.latest, tx.fresh = (payloads[-1], bool(keep[-1])), True
            return out
        inhibit_s = int(self.od[(0x1800 + pdo, 3)].value) * 1e-4
        for i, t in enumerate(t_end.tolist()):
            frame = (payloads[i], bool(keep[i]))
            if tx.timer_s > 0:
                while tx.next_timer_s < t - 1e-9:
                    if tx.latest is not None:
                        self._tx_event(pdo, tx.next_timer_s, tx.latest, out)
                    tx.next_timer_s += tx.timer_s
            elif inhibit_s > 0 and tx.pending is not None and tx.last_sent_s + inhibit_s <= t:
                self._tx_event(pdo, tx.last_sent_s + inhibit_s, tx.pending, out)
                tx.pending = None
            if tx.timer_s <= 0:
                if t >= tx.last_sent_s + inhibit_s:
                    self._tx_event(pdo, t, frame, out)
                else:
                    tx.pending = frame
            tx.latest = frame
        return out

    def _sample_frames(self, k0: int, n: int) -> list[tuple[float, int, Any]] | None:
        """Measure samples k0…k0+n−1; TPDO events if operational (the sensor runs regardless)."""
        t0_s = self._grid_t0_s + k0 * self.dt_s
        _, dv_true = self.world.increments(t0_s, n, self.dt_s, self.lever_arm_b_m)
        dv_meas = self.accel_model.apply(np.asarray(dv_true, dtype=float))
        ug, over = specific_force_to_ug(dv_meas, self.dt_s, self.full_scale_g)
        status = np.where(over, STATUS_OVER_RANGE, 0) | (STATUS_X_VALID | STATUS_Y_VALID | STATUS_Z_VALID)
        temp_centi = int(round(self.temperature_c * 100.0))
        values = self._object_values(dv_meas, ug, temp_centi, status, n)
        if self.state != STATE_OPERATIONAL:
            return None
        held = self._held_after_start(k0, n)
        if held >= n:
            return None
        if held:  # the start lag: these are measured (the noise stream goes on) but not sent
            k0, n = k0 + held, n - held
            dv_meas, ug, status = dv_meas[held:], ug[held:], status[held:]
            values = self._object_values(dv_meas, ug, temp_centi, status, n)
        self._counter = (self._counter + n) & 0xFF
        payloads = [encode_mapped(mapping_layout(self.od, pdo), values, n) for pdo in (0, 1)]
        keep = np.ones((n, 2), dtype=bool)
        if self.faults.loss_rate > 0.0:
            keep = self.rng.random((n, 2)) >= self.faults.loss_rate
        self.stats.samples += n
        t_end = self._grid_t0_s + (k0 + 1 + np.arange(n)) * self.dt_s
        events: list[tuple[float, int, Any]] = []
        for pdo in (0, 1):
            if payloads[pdo] is not None and pdo_valid(self.od, pdo):
                events.extend(self._tpdo_events(pdo, t_end, payloads[pdo], keep[:, pdo]))
        events.sort(key=lambda e: (e[0], e[1]))
        return events

    def _held_after_start(self, k0: int, n: int) -> int:
        """How many of samples k0…k0+n−1 end before the start lag after the last NMT start is over."""
        if self._send_from_s is None:
            return 0
        first = math.ceil((self._send_from_s - self._grid_t0_s) / self.dt_s - 1.0 - 1e-9)
        return int(min(max(first - k0, 0), n))

    def _nmt_state_command(self, command: int, t_s: float) -> bool:
        if command == NMT_START and self.state != STATE_OPERATIONAL and self.faults.start_lag_s > 0.0:
            self._send_from_s = t_s + self.faults.start_lag_s
        return super()._nmt_state_command(command, t_s)

    def _object_values(self, dv_meas: np.ndarray, ug: np.ndarray, temp_centi: int, status: np.ndarray,
                       n: int) -> dict[tuple[int, int], np.ndarray]:
        """Every mappable object's value per sample; the last one also into the dictionary."""
        accel_g = dv_meas / (self.dt_s * STANDARD_GRAVITY_M_S2)
        limit = min(self.full_scale_g * 1e7, _INT32_MAX)
        tenth_ug = np.clip(np.rint(accel_g * 1e7), -limit, limit).astype(np.int64)
        values = {
            (0x2000, 1): ug[:, 0], (0x2000, 2): ug[:, 1], (0x2000, 3): ug[:, 2],
            (0x2004, 1): tenth_ug[:, 0], (0x2004, 2): tenth_ug[:, 1], (0x2004, 3): tenth_ug[:, 2],
            (0x2001, 0): np.full(n, temp_centi), (0x2002, 0): (self._counter + np.arange(n)) & 0xFF,
            (0x2003, 0): status,
        }
        for key, v in values.items():
            if key in self.od:
                self.od[key].value = int(v[-1])
        return values

    def _send_heartbeat(self, t_s: float, state: int) -> None:
        loss_at = self.faults.heartbeat_loss_at_s
        if loss_at is not None and t_s >= loss_at:
            return
        self.stats.heartbeats += 1
        self._send(t_s, *encode_heartbeat(self.node_id, state))

    def _send_emcy(self, t_s: float, code: int) -> None:
        if self.state == STATE_STOPPED:  # CiA 301: no EMCY in stopped
            return
        self.stats.emcy += 1
        register = 0x00 if code == EMCY_NO_ERROR else 0x01  # bit0 generic error
        self._send(t_s, *encode_emcy(self.node_id, code, register))

    def _send(self, t_s: float, arbitration_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, timestamp=t_s)
        try:
            self.bus.send(msg)
        except can.CanError as exc:  # a full TX queue on a real bus: the frame is lost, as on hardware
            self.stats.tx_errors += 1
            log.warning("node 0x%02X: frame 0x%03X not sent: %s", self.node_id, arbitration_id, exc)


def encode_mapped(layout: list[tuple[int, int, str]], values: dict[tuple[int, int], np.ndarray],
                  n: int) -> list[bytes] | None:
    """n TPDO payloads by a mapping [(index, sub, kind)] (None for an empty mapping)."""
    if not layout:
        return None
    dtype = np.dtype([(f"f{j}", _NUMPY[kind]) for j, (_, _, kind) in enumerate(layout)])
    rec = np.empty(n, dtype)
    for j, (index, sub, _) in enumerate(layout):
        rec[f"f{j}"] = values[(index, sub)]
    raw, size = rec.tobytes(), dtype.itemsize
    return [raw[size * i : size * i + size] for i in range(n)]
