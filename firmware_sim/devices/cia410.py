"""A two-axis CiA 410 inclinometer node on any python-can bus (docs/PROTOCOLS.md "CiA 410").

Written from CiA DS 410 v1.2 (2 August 2006): 0x6000 resolution (UNSIGNED16, 0.001° units),
0x6010/0x6020 slope long16 / lateral16 (INTEGER16) with their operating parameter (bit 0 inversion,
bit 1 scaling), preset value, offset and differential offset (0x6011–0x6014, 0x6021–0x6024), and
the default TPDO1 mapping 0x6010, 0x6020. CiA 301 (NMT, heartbeat, SDO) comes from the same
server the project's accelerometer node uses (firmware_sim.devices.canopen_accel.SdoServer).
The dictionary is the one described by firmware_sim/data/cia410.eds.

Sample rate the profile's way: TPDO1 is event-driven (transmission type 0xFE) with its event
timer 0x1800:05 in ms (10 ms → 100 Hz); a write of the event timer in pre-operational sets a new
sample grid. Each sample is the mean specific force over its interval (the one physical world,
through the accelerometer error model), turned into each axis's angle against the horizontal,
β = asin(f_axis / |f|), then rounded to the resolution and saturated to INTEGER16.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import can
import numpy as np

from firmware_sim.devices.canopen_accel import (
    NMT_ID,
    STATE_BOOTUP,
    STATE_OPERATIONAL,
    STATE_PRE_OPERATIONAL,
    STATE_STOPPED,
    CanopenNode,
    OdEntry,
    SdoServer,
    check_mapping_entry,
    encode_mapped,
    mapping_layout,
)

log = logging.getLogger(__name__)

SDO_RX_BASE, SDO_TX_BASE = 0x600, 0x580
DEVICE_TYPE = 0x0000019A  # profile 410 in the low word (CiA 301: 0x1000)
DEVICE_NAME = "NF-INC2 inclinometer (CiA 410)"
SOFTWARE_VERSION = "1.0.0"
VENDOR_ID = 0x000004E2  # the project's made-up vendor, as for the accelerometer node
PRODUCT_CODE = 0x00410002
REVISION = 0x00010000
SERIAL_NUMBER = 0x00004101
RESOLUTIONS_MDEG = (1, 10, 100, 1000)


def build_od(node_id: int, event_ms: int = 10, resolution_mdeg: int = 1) -> dict[tuple[int, int], OdEntry]:
    """The object dictionary at power-on (what firmware_sim/data/cia410.eds describes)."""
    od: dict[tuple[int, int], OdEntry] = {
        (0x1000, 0): OdEntry("u32", "ro", DEVICE_TYPE),
        (0x1001, 0): OdEntry("u8", "ro", 0),
        (0x1008, 0): OdEntry("vs", "ro", DEVICE_NAME),
        (0x100A, 0): OdEntry("vs", "ro", SOFTWARE_VERSION),
        (0x1017, 0): OdEntry("u16", "rw", 1000, 0, 0xFFFF),
        (0x1018, 0): OdEntry("u8", "ro", 4),
        (0x1018, 1): OdEntry("u32", "ro", VENDOR_ID),
        (0x1018, 2): OdEntry("u32", "ro", PRODUCT_CODE),
        (0x1018, 3): OdEntry("u32", "ro", REVISION),
        (0x1018, 4): OdEntry("u32", "ro", SERIAL_NUMBER),
        (0x1800, 0): OdEntry("u8", "ro", 5),
        (0x1800, 1): OdEntry("u32", "ro", 0x180 + node_id),
        (0x1800, 2): OdEntry("u8", "rw-preop", 0xFE, 0xFE, 0xFE),
        (0x1800, 3): OdEntry("u16", "rw-preop", 0, 0, 0xFFFF),
        (0x1800, 5): OdEntry("u16", "rw-preop", event_ms, 1, 1000),
        (0x1A00, 0): OdEntry("u8", "rw-preop", 2, 0, 4),
        (0x1A00, 1): OdEntry("u32", "rw-preop", 0x60100010),
        (0x1A00, 2): OdEntry("u32", "rw-preop", 0x60200010),
        (0x1A00, 3): OdEntry("u32", "rw-preop", 0),
        (0x1A00, 4): OdEntry("u32", "rw-preop", 0),
        (0x6000, 0): OdEntry("u16", "rw-preop", resolution_mdeg, 1, 1000),
    }
    for base in (0x6010, 0x6020):
        od[(base, 0)] = OdEntry("i16", "ro", 0, mappable=True)
        od[(base + 1, 0)] = OdEntry("u8", "rw", 0, 0, 3)
        for k in (2, 3, 4):
            od[(base + k, 0)] = OdEntry("i16", "rw", 0, -32768, 32767)
    return od


class Cia410Node(CanopenNode):
    """A CiA 410 inclinometer on `bus`, measuring `world` through `accel_model` (may be None)."""

    name = "tilt"

    def __init__(self, bus: can.BusABC, world: Any, accel_model: Any = None, *, node_id: int = 0x20,
                 event_ms: int = 10, lever_arm_b_m: Any = (0.0, 0.0, 0.0), make_model: Any = None) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CiA 410 node_id={node_id}: give a node ID in 1…127")
        self.bus = bus
        self.world = world
        self.accel_model = accel_model
        self.make_model = make_model
        self.node_id = node_id
        self.lever_arm_b_m = np.asarray(lever_arm_b_m, dtype=float)
        self._power_on_event_ms = int(event_ms)
        self.od = build_od(node_id, event_ms)
        self.sdo = SdoServer(self.od, self._on_write)
        self.state: int | None = None
        self._grid_t0_s = 0.0
        self._next_sample = 0
        self._next_heartbeat_s = math.inf
        self._t_now_s = 0.0
        self._physical = (0, 0)
        self.samples_sent = 0
        self._closed = False

    @property
    def dt_s(self) -> float:
        return int(self.od[(0x1800, 5)].value) / 1000.0

    @property
    def resolution_mdeg(self) -> int:
        return int(self.od[(0x6000, 0)].value)

    # -- Device surface -----------------------------------------------------------------------
    def endpoint(self) -> dict[str, Any]:
        return {"node_id": self.node_id, "profile": "CiA 410"}

    # -- CiA 301 ------------------------------------------------------------------------------
    def _boot(self, t_s: float) -> None:
        self._emit_until(t_s)
        self._restart_grid(t_s)
        self.od.update(build_od(self.node_id, self._power_on_event_ms))
        self.state = STATE_PRE_OPERATIONAL
        self._next_heartbeat_s = t_s + 1.0
        self._send(t_s, 0x700 + self.node_id, bytes((STATE_BOOTUP,)))

    def _on_frame(self, msg: can.Message, t_s: float) -> None:
        if msg.is_extended_id or msg.is_remote_frame:
            return
        if msg.arbitration_id == SDO_RX_BASE + self.node_id:
            if self.state == STATE_STOPPED:
                return
            self._emit_until(t_s)
            reply = self.sdo.handle(bytes(msg.data), self.state)
            if reply:
                self._send(t_s, SDO_TX_BASE + self.node_id, reply)
            return
        if msg.arbitration_id != NMT_ID or msg.dlc != 2 or msg.data[1] not in (0, self.node_id):
            return
        self._emit_until(t_s)
        self._nmt_state_command(msg.data[0], t_s)

    def _on_write(self, index: int, sub: int, value: Any) -> None:
        """The profile's rules for writes the dictionary allowed (ValueError → SDO abort)."""
        if index == 0x6000 and int(value) not in RESOLUTIONS_MDEG:
            raise ValueError("resolution")
        if index == 0x1A00 and sub > 0:
            check_mapping_entry(self.od, int(value))
        if index == 0x1800 and sub == 5:
            self._emit_until(self._t_now_s)
            self._restart_grid(self._t_now_s)
            if self.make_model is not None:
                self.accel_model = self.make_model(1000.0 / int(value))
        if index == 0x1017:
            self._next_heartbeat_s = self._t_now_s + int(value) / 1000.0 if int(value) else math.inf
        if index in (0x6012, 0x6022):  # preset: offset = preset − physical − differential offset
            axis = 0 if index == 0x6012 else 1
            base = index - 2
            diff = int(self.od[(base + 4, 0)].value)
            self.od[(base + 3, 0)].value = int(value) - self._physical[axis] - diff

    def _restart_grid(self, t_s: float) -> None:
        self._grid_t0_s = t_s
        self._next_sample = 0

    # -- samples ------------------------------------------------------------------------------
    def _emit_until(self, t_s: float) -> None:
        dt = self.dt_s
        k_end = int(math.floor((t_s - self._grid_t0_s) / dt + 1e-9))
        n = k_end - self._next_sample
        period = int(self.od[(0x1017, 0)].value) / 1000.0
        while self._next_heartbeat_s <= t_s and self.state is not None:
            self._send(self._next_heartbeat_s, 0x700 + self.node_id, bytes((self.state,)))
            self._next_heartbeat_s = self._next_heartbeat_s + period if period > 0 else math.inf
        if n <= 0:
            return
        t0 = self._grid_t0_s + self._next_sample * dt
        self._next_sample = k_end
        _, dv = self.world.increments(t0, n, dt, self.lever_arm_b_m)
        dv = np.asarray(self.accel_model.apply(np.asarray(dv, dtype=float)) if self.accel_model else dv)
        values = self._slopes(dv)
        if self.state != STATE_OPERATIONAL:
            return
        layout = mapping_layout(self.od, 0)
        payloads = encode_mapped(layout, values, n) or []
        t_end = self._grid_t0_s + (k_end - n + 1 + np.arange(n)) * dt
        for t, payload in zip(t_end, payloads, strict=False):
            self._send(float(t), int(self.od[(0x1800, 1)].value), payload)
            self.samples_sent += 1

    def _slopes(self, dv: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
        norm = np.linalg.norm(dv, axis=1)
        norm = np.where(norm > 0, norm, 1.0)
        lsb_deg = self.resolution_mdeg * 1e-3
        values: dict[tuple[int, int], np.ndarray] = {}
        physical = []
        for axis, base in enumerate((0x6010, 0x6020)):
            beta_deg = np.degrees(np.arcsin(np.clip(dv[:, axis] / norm, -1.0, 1.0)))
            counts = np.clip(np.rint(beta_deg / lsb_deg), -32768, 32767).astype(np.int64)
            physical.append(int(counts[-1]))
            op = int(self.od[(base + 1, 0)].value)
            shown = -counts if op & 0x01 else counts
            if op & 0x02:
                shown = shown + int(self.od[(base + 3, 0)].value) + int(self.od[(base + 4, 0)].value)
            shown = (shown + 0x8000) % 0x10000 - 0x8000
            values[(base, 0)] = shown
            self.od[(base, 0)].value = int(shown[-1])
        self._physical = (physical[0], physical[1])
        return values

    def _send(self, t_s: float, arbitration_id: int, data: bytes) -> None:
        msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False, timestamp=t_s)
        try:
            self.bus.send(msg)
        except can.CanError as exc:
            log.warning("node 0x%02X: frame 0x%03X not sent: %s", self.node_id, arbitration_id, exc)
