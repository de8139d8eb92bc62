"""Thorlabs APT binary messages for a KDC101 K-Cube driving a PRM1-Z8 rotation stage (pure codec).

Reference: Thorlabs Motion Controllers Host-Controller Communications Protocol, Issue 28
(21 September 2021), cited below as "APT" with its page numbers; docs/PROTOCOLS.md "Thorlabs APT"
is the project's copy. A message is a 6-byte header (APT §4, p. 33), little-endian throughout:

    header only:      msg_id (u16) | param1 (u8) | param2 (u8) | dest | source
    with data packet: msg_id (u16) | length (u16)               | dest | 0x80 | source

The host is source 0x01 and a single-USB-node controller such as the KDC101 is dest 0x50 (APT p. 34);
replies swap the two. There is no checksum: the stream decoder resynchronises on plausible headers
(known id, the documented data length, the documented source/dest) and counts what it skips.

Only what a rotation run needs: identify (HW_REQ_INFO/HW_GET_INFO), enable the channel, home /
homed, move absolute / completed, stop / stopped, position counter, status update (and its
"server alive" acknowledgement), velocity parameters. Units on the wire are encoder counts:
`counts_from_deg` etc. carry the PRM1-Z8 scaling of APT §8 (p. 38–39).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

# Message ids (APT pages in brackets)
HW_REQ_INFO = 0x0005  # [p. 51]
HW_GET_INFO = 0x0006
HW_START_UPDATEMSGS = 0x0011  # [p. 51]
HW_STOP_UPDATEMSGS = 0x0012
MOD_SET_CHANENABLESTATE = 0x0210  # [p. 46]
MOD_REQ_CHANENABLESTATE = 0x0211
MOD_GET_CHANENABLESTATE = 0x0212
MOT_REQ_POSCOUNTER = 0x0411  # [p. 62]
MOT_GET_POSCOUNTER = 0x0412
MOT_SET_VELPARAMS = 0x0413  # [p. 65]
MOT_REQ_VELPARAMS = 0x0414
MOT_GET_VELPARAMS = 0x0415
MOT_MOVE_HOME = 0x0443  # [p. 79]
MOT_MOVE_HOMED = 0x0444
MOT_MOVE_ABSOLUTE = 0x0453  # [p. 83]
MOT_MOVE_COMPLETED = 0x0464  # [p. 82]
MOT_MOVE_STOP = 0x0465  # [p. 87]
MOT_MOVE_STOPPED = 0x0466  # [p. 88]
MOT_REQ_STATUSUPDATE = 0x0490  # [p. 129] MGMSG_MOT_REQ_(D|U)STATUSUPDATE
MOT_GET_STATUSUPDATE = 0x0491  # [p. 124] MGMSG_MOT_GET_(D|U)STATUSUPDATE
MOT_ACK_STATUSUPDATE = 0x0492  # [p. 129] "server alive", USB only

HOST = 0x01
USB_UNIT = 0x50
CHANNEL_1 = 0x01
ENABLE = 0x01
DISABLE = 0x02
STOP_IMMEDIATE = 0x01
STOP_PROFILED = 0x02

DATA_LENGTHS: dict[int, int] = {
    HW_GET_INFO: 84,
    MOT_GET_POSCOUNTER: 6,
    MOT_SET_VELPARAMS: 14,
    MOT_GET_VELPARAMS: 14,
    MOT_MOVE_ABSOLUTE: 6,
    MOT_MOVE_COMPLETED: 14,
    MOT_MOVE_STOPPED: 14,
    MOT_GET_STATUSUPDATE: 14,
}
"""Data-packet length of each message that carries one (header-only messages are absent)."""
HEADER_ONLY: frozenset[int] = frozenset({
    HW_REQ_INFO, HW_START_UPDATEMSGS, HW_STOP_UPDATEMSGS, MOD_SET_CHANENABLESTATE,
    MOD_REQ_CHANENABLESTATE, MOD_GET_CHANENABLESTATE, MOT_REQ_POSCOUNTER, MOT_REQ_VELPARAMS,
    MOT_MOVE_HOME, MOT_MOVE_HOMED, MOT_MOVE_ABSOLUTE, MOT_MOVE_STOP, MOT_REQ_STATUSUPDATE,
    MOT_ACK_STATUSUPDATE,
})
"""Ids with a header-only form (MOVE_ABSOLUTE has both, APT p. 83)."""
ENDPOINTS = frozenset({HOST, USB_UNIT, 0x11, *range(0x21, 0x2B)})
"""Source/destination bytes APT §4 (p. 34–35) defines: host, USB unit, rack, bays 1–10."""

# Status bits of MOT_GET_STATUSUPDATE / MOVE_COMPLETED / MOVE_STOPPED (APT p. 125–127)
SB_CW_HARDLIMIT = 0x00000001
SB_CCW_HARDLIMIT = 0x00000002
SB_CW_SOFTLIMIT = 0x00000004
SB_CCW_SOFTLIMIT = 0x00000008
SB_IN_MOTION_CW = 0x00000010
SB_IN_MOTION_CCW = 0x00000020
SB_JOGGING_CW = 0x00000040
SB_JOGGING_CCW = 0x00000080
SB_CONNECTED = 0x00000100
SB_HOMING = 0x00000200
SB_HOMED = 0x00000400
SB_INITIALIZING = 0x00000800
SB_TRACKING = 0x00001000
SB_SETTLED = 0x00002000
SB_POSITION_ERROR = 0x00004000
SB_INSTR_ERROR = 0x00008000
SB_INTERLOCK = 0x00010000
SB_OVERTEMP = 0x00020000
SB_BUS_VOLT_FAULT = 0x00040000
SB_COMMUTATION_ERROR = 0x00080000
SB_OVERLOAD = 0x01000000
SB_ENCODER_FAULT = 0x02000000
SB_OVERCURRENT = 0x04000000
SB_BUS_CURRENT_FAULT = 0x08000000
SB_POWER_OK = 0x10000000
SB_ACTIVE = 0x20000000
SB_ERROR = 0x40000000
SB_ENABLED = 0x80000000

STATUS_BIT_NAMES: dict[int, str] = {
    SB_CW_HARDLIMIT: "CW hard limit", SB_CCW_HARDLIMIT: "CCW hard limit",
    SB_CW_SOFTLIMIT: "CW soft limit", SB_CCW_SOFTLIMIT: "CCW soft limit",
    SB_IN_MOTION_CW: "moving CW", SB_IN_MOTION_CCW: "moving CCW",
    SB_JOGGING_CW: "jogging CW", SB_JOGGING_CCW: "jogging CCW", SB_CONNECTED: "motor connected",
    SB_HOMING: "homing", SB_HOMED: "homed", SB_INITIALIZING: "initialising",
    SB_TRACKING: "tracking", SB_SETTLED: "settled", SB_POSITION_ERROR: "position error",
    SB_INSTR_ERROR: "instruction error", SB_INTERLOCK: "interlock", SB_OVERTEMP: "over temperature",
    SB_BUS_VOLT_FAULT: "bus voltage fault", SB_COMMUTATION_ERROR: "commutation error",
    SB_OVERLOAD: "overload", SB_ENCODER_FAULT: "encoder fault", SB_OVERCURRENT: "over current",
    SB_BUS_CURRENT_FAULT: "bus current fault", SB_POWER_OK: "power OK", SB_ACTIVE: "active",
    SB_ERROR: "error", SB_ENABLED: "enabled",
}
FAULT_BITS = (SB_POSITION_ERROR | SB_INSTR_ERROR | SB_OVERTEMP | SB_BUS_VOLT_FAULT | SB_COMMUTATION_ERROR
              | SB_OVERLOAD | SB_ENCODER_FAULT | SB_BUS_CURRENT_FAULT | SB_ERROR)
MOVING_BITS = SB_IN_MOTION_CW | SB_IN_MOTION_CCW | SB_JOGGING_CW | SB_JOGGING_CCW | SB_HOMING

# PRM1-Z8 on a brushed DC controller (KDC101), APT §8 p. 38–39
PRM1Z8_COUNTS_PER_DEG = 1919.6418578623391
KDC101_SAMPLE_PERIOD_S = 2048 / 6e6
"""T of APT §8: the KDC101's servo sampling interval."""


def counts_from_deg(angle_deg: float) -> int:
    """POS_APT = EncCnt × Pos, rounded to the nearest count (APT §8)."""
    return int(round(angle_deg * PRM1Z8_COUNTS_PER_DEG))


def deg_from_counts(counts: int) -> float:
    return counts / PRM1Z8_COUNTS_PER_DEG


def velocity_from_deg_s(velocity_deg_s: float) -> int:
    """VEL_APT = EncCnt × T × 65536 × Vel (42941.66 per °/s for the PRM1-Z8, APT §8)."""
    return int(round(PRM1Z8_COUNTS_PER_DEG * KDC101_SAMPLE_PERIOD_S * 65536 * velocity_deg_s))


def acceleration_from_deg_s2(accel_deg_s2: float) -> int:
    """ACC_APT = EncCnt × T² × 65536 × Acc (14.66 per °/s² for the PRM1-Z8, APT §8)."""
    return int(round(PRM1Z8_COUNTS_PER_DEG * KDC101_SAMPLE_PERIOD_S**2 * 65536 * accel_deg_s2))


def deg_s_from_velocity(vel_apt: int) -> float:
    return vel_apt / (PRM1Z8_COUNTS_PER_DEG * KDC101_SAMPLE_PERIOD_S * 65536)


def deg_s2_from_acceleration(acc_apt: int) -> float:
    return acc_apt / (PRM1Z8_COUNTS_PER_DEG * KDC101_SAMPLE_PERIOD_S**2 * 65536)


# ---------------------------------------------------------------------------------------------
# Encoding
# ---------------------------------------------------------------------------------------------
def header_only(msg_id: int, param1: int = 0, param2: int = 0, dest: int = USB_UNIT,
                source: int = HOST) -> bytes:
    """A 6-byte header-only message (APT §4)."""
    return struct.pack("<HBBBB", msg_id, param1 & 0xFF, param2 & 0xFF, dest & 0x7F, source & 0xFF)


def with_data(msg_id: int, data: bytes, dest: int = USB_UNIT, source: int = HOST) -> bytes:
    """A header announcing `len(data)` bytes (dest | 0x80), then the data (APT §4)."""
    return struct.pack("<HHBB", msg_id, len(data), (dest | 0x80) & 0xFF, source & 0xFF) + bytes(data)


def hw_req_info(dest: int = USB_UNIT) -> bytes:
    return header_only(HW_REQ_INFO, dest=dest)


def set_channel_enable(enable: bool, channel: int = CHANNEL_1, dest: int = USB_UNIT) -> bytes:
    return header_only(MOD_SET_CHANENABLESTATE, channel, ENABLE if enable else DISABLE, dest=dest)


def move_home(channel: int = CHANNEL_1, dest: int = USB_UNIT) -> bytes:
    return header_only(MOT_MOVE_HOME, channel, 0, dest=dest)


def move_absolute(position_counts: int, channel: int = CHANNEL_1, dest: int = USB_UNIT) -> bytes:
    """The long form of MOVE_ABSOLUTE: channel word + signed 32-bit position (APT p. 83)."""
    return with_data(MOT_MOVE_ABSOLUTE, struct.pack("<Hi", channel, position_counts), dest=dest)


def move_stop(mode: int = STOP_PROFILED, channel: int = CHANNEL_1, dest: int = USB_UNIT) -> bytes:
    return header_only(MOT_MOVE_STOP, channel, mode, dest=dest)


def req_position(channel: int = CHANNEL_1, dest: int = USB_UNIT) -> bytes:
    return header_only(MOT_REQ_POSCOUNTER, channel, 0, dest=dest)


def req_status(channel: int = CHANNEL_1, dest: int = USB_UNIT) -> bytes:
    return header_only(MOT_REQ_STATUSUPDATE, channel, 0, dest=dest)


def ack_status(dest: int = USB_UNIT) -> bytes:
    """MOT_ACK_(D|U)STATUSUPDATE, "server alive": at least once a second over USB (APT p. 129)."""
    return header_only(MOT_ACK_STATUSUPDATE, dest=dest)


def set_velocity_params(accel_apt: int, max_vel_apt: int, channel: int = CHANNEL_1,
                        dest: int = USB_UNIT) -> bytes:
    """MOT_SET_VELPARAMS: channel, min velocity (always 0), acceleration, max velocity (APT p. 65)."""
    return with_data(MOT_SET_VELPARAMS, struct.pack("<Hiii", channel, 0, accel_apt, max_vel_apt), dest=dest)


def req_velocity_params(channel: int = CHANNEL_1, dest: int = USB_UNIT) -> bytes:
    return header_only(MOT_REQ_VELPARAMS, channel, 0, dest=dest)


# ---------------------------------------------------------------------------------------------
# Decoding
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class AptMessage:
    """One message as received: header fields and the data packet (b'' for header-only)."""

    msg_id: int
    param1: int
    param2: int
    dest: int
    source: int
    data: bytes = b""

    @property
    def raw(self) -> bytes:
        if self.data:
            return with_data(self.msg_id, self.data, self.dest, self.source)
        return header_only(self.msg_id, self.param1, self.param2, self.dest, self.source)


@dataclass(frozen=True)
class HwInfo:
    """HW_GET_INFO data (APT p. 52): the unit's identity."""

    serial_number: int
    model: str
    hw_type: int
    firmware: tuple[int, int, int]
    """(major, interim, minor) from firmware bytes 22, 21, 20."""
    hw_version: int
    mod_state: int
    channels: int

    def describe(self) -> str:
        major, interim, minor = self.firmware
        fw = f"{major}.{interim}.{minor}"
        return f"Thorlabs {self.model} s/n {self.serial_number} fw {fw} hw {self.hw_version}"


@dataclass(frozen=True)
class MotorStatus:
    """The 14-byte status structure of GET_STATUSUPDATE, MOVE_COMPLETED and MOVE_STOPPED (APT p. 124)."""

    channel: int
    position_counts: int
    velocity: int
    motor_current_ma: int
    status_bits: int

    @property
    def homed(self) -> bool:
        return bool(self.status_bits & SB_HOMED)

    @property
    def moving(self) -> bool:
        return bool(self.status_bits & MOVING_BITS)

    @property
    def enabled(self) -> bool:
        return bool(self.status_bits & SB_ENABLED)

    @property
    def fault(self) -> bool:
        return bool(self.status_bits & FAULT_BITS)


def parse_hw_info(data: bytes) -> HwInfo:
    """84 data bytes of HW_GET_INFO → HwInfo; ValueError on any other length."""
    if len(data) != 84:
        raise ValueError(f"HW_GET_INFO carries 84 bytes, not {len(data)}")
    serial, model, hw_type, minor, interim, major = struct.unpack_from("<i8sHBBB", data, 0)
    hw_version, mod_state, channels = struct.unpack_from("<HHH", data, 78)
    name = model.split(b"\0", 1)[0].decode("ascii", "replace").strip()
    return HwInfo(serial, name, hw_type, (major, interim, minor), hw_version, mod_state, channels)


def encode_hw_info(info: HwInfo) -> bytes:
    """The 84-byte data packet of HW_GET_INFO (the 60 internal-use bytes are zero)."""
    major, interim, minor = info.firmware
    head = struct.pack("<i8sHBBBB", info.serial_number, info.model.encode("ascii")[:8].ljust(8, b"\0"),
                       info.hw_type, minor, interim, major, 0)
    return head + bytes(60) + struct.pack("<HHH", info.hw_version, info.mod_state, info.channels)


def parse_status(data: bytes) -> MotorStatus:
    """14 data bytes: channel u16, position i32, velocity u16, motor current i16, status bits u32."""
    if len(data) != 14:
        raise ValueError(f"a status structure is 14 bytes, not {len(data)}")
    return MotorStatus(*struct.unpack("<HiHhI", data))


def encode_status(status: MotorStatus) -> bytes:
    return struct.pack("<HiHhI", status.channel, status.position_counts, status.velocity & 0xFFFF,
                       status.motor_current_ma, status.status_bits & 0xFFFFFFFF)


def parse_position(data: bytes) -> tuple[int, int]:
    """MOT_GET_POSCOUNTER data → (channel, position counts)."""
    if len(data) != 6:
        raise ValueError(f"a position counter is 6 bytes, not {len(data)}")
    channel, position = struct.unpack("<Hi", data)
    return channel, position


def parse_velocity_params(data: bytes) -> tuple[int, int, int, int]:
    """MOT_GET/SET_VELPARAMS data → (channel, min velocity, acceleration, max velocity) in APT units."""
    if len(data) != 14:
        raise ValueError(f"velocity parameters are 14 bytes, not {len(data)}")
    return struct.unpack("<Hiii", data)


def describe_status(bits: int) -> str:
    """The set bits by their APT names, e.g. 'homed, settled, enabled'."""
    names = [name for bit, name in STATUS_BIT_NAMES.items() if bits & bit]
    return ", ".join(names) if names else "none"


def _header_plausible(buf: bytes | bytearray, i: int) -> int | None:
    """Total length of a message starting at buf[i] if its header is plausible, else None."""
    msg_id, = struct.unpack_from("<H", buf, i)
    dest, source = buf[i + 4], buf[i + 5]
    if source not in ENDPOINTS or (dest & 0x7F) not in ENDPOINTS:
        return None
    if dest & 0x80:
        length, = struct.unpack_from("<H", buf, i + 2)
        return 6 + length if DATA_LENGTHS.get(msg_id) == length else None
    return 6 if msg_id in HEADER_ONLY else None


@dataclass
class AptStats:
    """What the decoder saw: messages, bytes skipped while resynchronising."""

    messages: int = 0
    skipped_bytes: int = 0
    by_id: dict[int, int] = field(default_factory=dict)


class AptDecoder:
    """Incremental stream decoder: `feed(bytes)` → complete messages; never raises on bad bytes."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.stats = AptStats()

    @property
    def pending_bytes(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes) -> list[AptMessage]:
        self._buf += data
        out: list[AptMessage] = []
        buf = self._buf
        i = 0
        while len(buf) - i >= 6:
            total = _header_plausible(buf, i)
            if total is None:
                i += 1
                self.stats.skipped_bytes += 1
                continue
            if len(buf) - i < total:
                break
            msg_id, p1, p2, dest, source = struct.unpack_from("<HBBBB", buf, i)
            data = bytes(buf[i + 6 : i + total])
            out.append(AptMessage(msg_id, 0 if data else p1, 0 if data else p2, dest & 0x7F, source, data))
            self.stats.messages += 1
            self.stats.by_id[msg_id] = self.stats.by_id.get(msg_id, 0) + 1
            i += total
        del buf[:i]
        return out
