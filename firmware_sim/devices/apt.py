"""Thorlabs KDC101 K-Cube with a PRM1-Z8 rotation stage, speaking APT binary messages on a pty.

Written from the Thorlabs Host-Controller Communications Protocol, Issue 28 (21 Sep 2021), the
same document docs/PROTOCOLS.md "Thorlabs APT" summarises; firmware_sim never imports northfinder,
so the message layouts are written again here (APT §4 p. 33: 6-byte header, little-endian, a data
packet when bit 7 of the destination byte is set; the unit answers as source 0x50 to host 0x01).

The controller drives `world.table` (one physical world for every stage model): MOVE_HOME plans a
homing move to α = 0 and sends MOVE_HOMED when the planned move ends; MOVE_ABSOLUTE plans a move to
the position in encoder counts and sends MOVE_COMPLETED with the status structure; MOVE_STOP stops
(profiled or at once) and sends MOVE_STOPPED. The position counter is the motor-side angle of the
physics rounded to the PRM1-Z8's 1919.6418578623391 counts per degree (APT §8 p. 39). Motion needs
the channel enabled (MOD_SET_CHANENABLESTATE); a move before homing is carried out but HOMED stays
clear, so the counter means nothing until the client homes (docs/PROTOCOLS.md, start-up dialogue).
Both stop modes decelerate at the table's configured rate. Fault `stage-stall` (its move number):
the stage jams half-way, the servo trips (POSITION_ERROR, disabled) and MOVE_STOPPED is sent.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import Any

from firmware_sim.devices.base import PtyDevice
from firmware_sim.pty import PtyPort

log = logging.getLogger("firmware_sim.apt")

HOST, UNIT = 0x01, 0x50
COUNTS_PER_DEG = 1919.6418578623391  # PRM1-Z8 on a brushed DC controller (APT §8, p. 39)
SAMPLE_PERIOD_S = 2048 / 6e6  # KDC101 T of APT §8
VEL_SCALE = COUNTS_PER_DEG * SAMPLE_PERIOD_S * 65536  # APT units per °/s (42941.66)
ACC_SCALE = COUNTS_PER_DEG * SAMPLE_PERIOD_S**2 * 65536  # APT units per °/s² (14.66)

# message ids (APT p. 46–130)
REQ_INFO, GET_INFO = 0x0005, 0x0006
START_UPDATES, STOP_UPDATES = 0x0011, 0x0012
SET_ENABLE, REQ_ENABLE, GET_ENABLE = 0x0210, 0x0211, 0x0212
REQ_POS, GET_POS = 0x0411, 0x0412
SET_VEL, REQ_VEL, GET_VEL = 0x0413, 0x0414, 0x0415
HOME, HOMED = 0x0443, 0x0444
MOVE_ABS, COMPLETED = 0x0453, 0x0464
STOP, STOPPED = 0x0465, 0x0466
REQ_STATUS, GET_STATUS, ACK_STATUS = 0x0490, 0x0491, 0x0492

DATA_LEN = {SET_VEL: 14, MOVE_ABS: 6}
"""Host → unit messages that carry a data packet, and its length."""

# status bits (APT p. 125–127)
MOVING_CW, MOVING_CCW = 0x10, 0x20
CONNECTED, HOMING_BIT, HOMED_BIT, SETTLED = 0x100, 0x200, 0x400, 0x2000
POSITION_ERROR, POWER_OK, ACTIVE, ERROR, ENABLED = 0x4000, 0x10000000, 0x20000000, 0x40000000, 0x80000000

SERIAL_NUMBER = 27000001  # 27xxxxxx: K-Cube brushed DC servo driver (APT §2.2, p. 31)
MODEL = b"KDC101\0\0"
HW_TYPE = 16  # not listed in Issue 28 (only 44 and 45 are); a driver must not rely on it
FIRMWARE = (3, 0, 10)  # major, interim, minor
STATUS_PERIOD_S = 0.1
"""Status updates every 100 ms once HW_START_UPDATEMSGS is received (APT §5 (c), p. 36)."""
ACK_WINDOW = 50
"""USB: without MOT_ACK_STATUSUPDATE the unit stops its status messages after ~50 (APT p. 129)."""


def header(msg_id: int, p1: int = 0, p2: int = 0, dest: int = HOST, source: int = UNIT) -> bytes:
    return struct.pack("<HBBBB", msg_id, p1 & 0xFF, p2 & 0xFF, dest, source)


def packet(msg_id: int, data: bytes, dest: int = HOST, source: int = UNIT) -> bytes:
    return struct.pack("<HHBB", msg_id, len(data), dest | 0x80, source) + data


class AptStage(PtyDevice):
    """A KDC101 + PRM1-Z8 on its own pty, driving `world.table`."""

    name = "turntable"

    def __init__(self, world: Any, *, stall_move: int | None = None, port: PtyPort | None = None,
                 on_event: Any = None, usb: bool = True) -> None:
        self.world = world
        self.table = world.table
        self.port = port if port is not None else PtyPort("turntable")
        self.on_event = on_event
        self.stall_move = stall_move
        self.usb = usb
        self._rx = bytearray()
        self.enabled = False
        self.homed = False
        self.homing = False
        self.position_error = False
        self.moves = 0
        self._pending: int | None = None  # HOMED / COMPLETED / STOPPED owed when the plan ends
        self._end_s: float | None = None
        self.accel_apt = int(round(self.table.accel_rad_s2 / math.pi * 180 * ACC_SCALE))
        self.max_vel_apt = int(round(self.table.speed_rad_s / math.pi * 180 * VEL_SCALE))
        self._updates = False
        self._next_update_s = 0.0
        self._unacked = 0
        self.messages_in = 0
        self.bad_bytes = 0

    # -- Device surface -------------------------------------------------------------------------
    def on_input(self, data: bytes, t_device_s: float) -> None:
        self._rx += data
        while len(self._rx) >= 6:
            msg_id, length = struct.unpack_from("<HH", self._rx, 0)
            dest, source = self._rx[4], self._rx[5]
            if source != HOST or (dest & 0x7F) != UNIT:
                del self._rx[0]  # not a header meant for us: resynchronise byte by byte
                self.bad_bytes += 1
                continue
            size = 6 + (length if dest & 0x80 else 0)
            if dest & 0x80 and DATA_LEN.get(msg_id) != length:
                del self._rx[0]
                self.bad_bytes += 1
                continue
            if len(self._rx) < size:
                return
            msg = bytes(self._rx[:size])
            del self._rx[:size]
            self.advance(t_device_s)
            self.messages_in += 1
            self.handle(msg, t_device_s)

    def advance(self, t_device_s: float) -> None:
        if self._end_s is not None and t_device_s >= self._end_s:
            self._finish_motion(self._end_s)
        if self._updates:
            while self._next_update_s <= t_device_s:
                if not self.usb or self._unacked < ACK_WINDOW:
                    self._send(packet(GET_STATUS, self._status_data(self._next_update_s)))
                    self._unacked += 1
                self._next_update_s += STATUS_PERIOD_S

    # -- commands ---------------------------------------------------------------------------------
    def handle(self, msg: bytes, t: float) -> None:
        msg_id, p1, p2 = struct.unpack_from("<HBB", msg, 0)
        data = msg[6:]
        if msg_id == REQ_INFO:
            self._send(packet(GET_INFO, self._info_data()))
        elif msg_id == SET_ENABLE:
            self._set_enable(p2 == 0x01, t)
        elif msg_id == REQ_ENABLE:
            self._send(header(GET_ENABLE, 0x01, 0x01 if self.enabled else 0x02))
        elif msg_id == REQ_POS:
            self._send(packet(GET_POS, struct.pack("<Hi", 1, self._counts(t))))
        elif msg_id == REQ_STATUS:
            self._send(packet(GET_STATUS, self._status_data(t)))
        elif msg_id == ACK_STATUS:
            self._unacked = 0
        elif msg_id == START_UPDATES:
            self._updates, self._next_update_s = True, t
        elif msg_id == STOP_UPDATES:
            self._updates = False
        elif msg_id == SET_VEL:
            _, _min, accel, vmax = struct.unpack("<Hiii", data)
            if accel > 0 and vmax > 0:
                self.accel_apt, self.max_vel_apt = accel, vmax
                self.table.accel_rad_s2 = math.radians(accel / ACC_SCALE)
                self.table.speed_rad_s = math.radians(vmax / VEL_SCALE)
        elif msg_id == REQ_VEL:
            self._send(packet(GET_VEL, struct.pack("<Hiii", 1, 0, self.accel_apt, self.max_vel_apt)))
        elif msg_id == HOME:
            self._home(t)
        elif msg_id == MOVE_ABS:
            if len(data) == 6:
                _, counts = struct.unpack("<Hi", data)
                self._move(counts / COUNTS_PER_DEG, t)
        elif msg_id == STOP:
            self._stop(t, immediate=p2 == 0x01)
        else:
            log.info("apt: message 0x%04X ignored", msg_id)

    def _set_enable(self, enable: bool, t: float) -> None:
        if not enable and self._end_s is not None:
            self.table.stop(t)  # the drive lets go: the table coasts down (here: stops at once)
            self._end_s = None
            self._pending = None
            self.homing = False
        self.enabled = enable
        if enable:
            self.position_error = False

    def _home(self, t: float) -> None:
        if not self.enabled:
            log.info("apt: home while disabled ignored")
            return
        start = self._motor_deg(t)
        self._end_s = float(self.table.home(t))
        self.homing, self.homed, self._pending = True, False, HOMED
        self._event("home", t, start)

    def _move(self, target_deg: float, t: float) -> None:
        if not self.enabled:
            log.info("apt: move while disabled ignored")
            return
        self.moves += 1
        stall = 0.5 if self.stall_move is not None and self.moves == self.stall_move else None
        start = self._motor_deg(t)
        self._end_s = float(self.table.command_move(t, math.radians(target_deg), stall_fraction=stall))
        self._pending = COMPLETED
        self._event("move", t, start)

    def _stop(self, t: float, immediate: bool) -> None:
        if self._end_s is None:
            self._send(packet(STOPPED, self._status_data(t)))
            return
        start = self._motor_deg(t)
        self._end_s = float(self.table.stop(t))
        self.homing = False
        self._pending = STOPPED
        self._event("stop", t, start)

    def _finish_motion(self, t: float) -> None:
        pending, self._end_s, self._pending = self._pending, None, None
        if pending == HOMED:
            self.homing, self.homed = False, True
            self._send(header(HOMED, 0x01, 0x00))
        elif pending == COMPLETED and self.table.stalled:
            self.position_error, self.enabled = True, False  # the servo trips and lets go
            self._send(packet(STOPPED, self._status_data(t)))
        elif pending is not None:
            self._send(packet(pending, self._status_data(t)))

    # -- data -------------------------------------------------------------------------------------
    def _motor_deg(self, t: float) -> float:
        return math.degrees(float(self.table.motor_kinematics(t)[0]))

    def _counts(self, t: float) -> int:
        return int(round(self._motor_deg(t) * COUNTS_PER_DEG))

    def _status_data(self, t: float) -> bytes:
        _, rate, _ = self.table.motor_kinematics(t)
        rate_deg_s = math.degrees(float(rate))
        bits = CONNECTED | POWER_OK
        if self.enabled:
            bits |= ENABLED
        if self.homed:
            bits |= HOMED_BIT
        if self.homing:
            bits |= HOMING_BIT
        if self._end_s is not None and t < self._end_s:
            bits |= ACTIVE | (MOVING_CW if rate_deg_s < 0 else MOVING_CCW if rate_deg_s > 0 else 0)
        elif self.enabled and not self.position_error:
            bits |= SETTLED
        if self.position_error:
            bits |= POSITION_ERROR | ERROR
        velocity = int(round(abs(rate_deg_s) * VEL_SCALE / 65536)) & 0xFFFF
        return struct.pack("<HiHhI", 1, self._counts(t), velocity, 0, bits)

    def _info_data(self) -> bytes:
        major, interim, minor = FIRMWARE
        return (struct.pack("<i8sHBBBB", SERIAL_NUMBER, MODEL, HW_TYPE, minor, interim, major, 0)
                + bytes(60) + struct.pack("<HHH", 1, 0, 1))

    def _send(self, data: bytes) -> None:
        self.port.write(data)

    def _event(self, kind: str, t: float, from_deg: float) -> None:
        if self.on_event is None:
            return
        self.on_event("move", t, {
            "kind": kind, "t_start_s": float(t), "t_end_s": float(self.table.move_end_s),
            "t_rest_s": float(self.table.rest_s(math.radians(1e-6))),
            "from_deg": from_deg, "to_deg": self._motor_deg(float(self.table.move_end_s)),
            "rest_threshold_deg": 1e-6,
        })
