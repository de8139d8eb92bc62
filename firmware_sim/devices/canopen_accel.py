"""CANopen-style 3-axis accelerometer node on any python-can bus (docs/PROTOCOLS.md §3).

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

import logging
import math
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import can
import numpy as np

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
# Faults
# ---------------------------------------------------------------------------------------------
@dataclass
class AccelFaults:
    """The CAN accelerometer's fault hooks (times in device seconds); all absent by default."""

    loss_rate: float = 0.0  # accel-loss-rate=P: drop each TPDO frame with probability P
    emcy: list[tuple[float, int]] = field(default_factory=list)  # accel-emcy=AT_S[:CODE]
    heartbeat_loss_at_s: float | None = None  # accel-heartbeat-loss=AT_S: no heartbeat from then

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


class CanAccelNode(Device):
    """A CANopen-style accelerometer on `bus`, measuring `world` through `accel_model`.

    `rng` (a numpy Generator or a seed) drives only the `accel-loss-rate` fault, so that a
    faulted run is repeatable; it is not drawn from when the fault is absent.
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
    ) -> None:
        if not 1 <= node_id <= 127:
            raise ValueError(f"CAN accelerometer node_id={node_id}: give a node ID in 1…127")
        if not rate_hz > 0:
            raise ValueError(f"CAN accelerometer rate_hz={rate_hz}: give a positive sample rate")
        self.bus = bus
        self.world = world
        self.accel_model = accel_model
        self.node_id = node_id
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.lever_arm_b_m = np.asarray(tuple(lever_arm_b_m), dtype=float)
        self.faults = AccelFaults.from_spec(faults)
        self.temperature_c = float(temperature_c)
        self.full_scale_g = float(full_scale_g)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng or 0)
        self.stats = NodeStats()

        self.state: int | None = None  # None until powered on
        self.power_on_s: float | None = None  # device time of the first `advance`
        self._next_sample = 0  # index k of the next sample (interval t_on + [k·dt, (k+1)·dt])
        self._next_heartbeat_s = math.inf
        self._counter = 0
        self._emcy_index = 0
        self._closed = False

    # -- Device surface --------------------------------------------------------------------
    def fileno(self) -> int | None:
        """The loop drives the node through `advance`; its bus is polled there."""
        return None

    def endpoint(self) -> dict[str, Any]:
        """The node as a client sees it (the bus channel itself is the adapter's endpoint)."""
        return {"node_id": self.node_id}

    def advance(self, t_device_s: float) -> None:
        """Act on received NMT commands at `t_device_s`, then send every frame due up to it."""
        if self._closed:
            return
        if self.state is None:
            self.power_on_s = float(t_device_s)
            self._boot(t_device_s)
        while (msg := self.bus.recv(timeout=0)) is not None:
            self._on_frame(msg, t_device_s)
        self._emit_until(t_device_s)

    def close(self) -> None:
        """Stop sending; the bus belongs to whoever made it (the simulator shuts it down)."""
        self._closed = True

    # -- NMT ---------------------------------------------------------------------------------
    def _boot(self, t_s: float) -> None:
        """Power-on or reset node: boot-up heartbeat, then pre-operational."""
        self._counter = 0
        self.state = STATE_PRE_OPERATIONAL
        self._next_heartbeat_s = t_s + HEARTBEAT_PERIOD_S
        self._send_heartbeat(t_s, STATE_BOOTUP)

    def _on_frame(self, msg: can.Message, t_s: float) -> None:
        if msg.arbitration_id != NMT_ID or msg.is_extended_id or msg.is_remote_frame or msg.dlc != 2:
            return
        command, node = decode_nmt(bytes(msg.data))
        if node not in (0, self.node_id):
            return
        self.stats.nmt_received += 1
        # Everything due before the command arrived goes out under the old state.
        self._emit_until(t_s)
        if command == NMT_START:
            self.state = STATE_OPERATIONAL
        elif command == NMT_STOP:
            self.state = STATE_STOPPED
        elif command == NMT_PRE_OPERATIONAL:
            self.state = STATE_PRE_OPERATIONAL
        elif command == NMT_RESET_NODE:
            self._boot(t_s)
        log.debug("node 0x%02X: NMT 0x%02X at %.6f s -> state 0x%02X", self.node_id, command, t_s, self.state)

    # -- output ------------------------------------------------------------------------------
    def _emit_until(self, t_s: float) -> None:
        """Send heartbeats, EMCYs and samples due up to `t_s`, in device-time order."""
        eps = 1e-9
        t_on = self.power_on_s if self.power_on_s is not None else t_s
        k_end = int(math.floor((t_s - t_on) * self.rate_hz + eps))  # samples k < k_end ended by t_s
        n = k_end - self._next_sample
        events: list[tuple[float, int, Any]] = []
        while self._next_heartbeat_s <= t_s + eps:
            events.append((self._next_heartbeat_s, 0, None))
            self._next_heartbeat_s += HEARTBEAT_PERIOD_S
        while self._emcy_index < len(self.faults.emcy) and self.faults.emcy[self._emcy_index][0] <= t_s + eps:
            events.append((self.faults.emcy[self._emcy_index][0], 1, self.faults.emcy[self._emcy_index][1]))
            self._emcy_index += 1
        if n <= 0 and not events:
            return
        if n > 0:
            frames = self._sample_frames(self._next_sample, n)
            self._next_sample = k_end
            if frames is not None:
                events.extend(frames)
        events.sort(key=lambda e: (e[0], e[1]))
        for t_event, kind, payload in events:
            if kind == 0:
                self._send_heartbeat(t_event, self.state)
            elif kind == 1:
                self._send_emcy(t_event, payload)
            else:
                self.stats.tpdo_sent += 1
                self._send(t_event, *payload)

    def _sample_frames(self, k0: int, n: int) -> list[tuple[float, int, Any]] | None:
        """Measure samples k0…k0+n−1; TPDO events if operational (the sensor runs regardless)."""
        t0_s = self.power_on_s + k0 * self.dt_s
        _, dv_true = self.world.increments(t0_s, n, self.dt_s, self.lever_arm_b_m)
        dv_meas = self.accel_model.apply(np.asarray(dv_true, dtype=float))
        if self.state != STATE_OPERATIONAL:
            return None
        ug, over = specific_force_to_ug(dv_meas, self.dt_s, self.full_scale_g)
        counters = (self._counter + np.arange(n)) & 0xFF
        self._counter = (self._counter + n) & 0xFF
        status = np.where(over, STATUS_OVER_RANGE, 0) | (STATUS_X_VALID | STATUS_Y_VALID | STATUS_Z_VALID)
        temp_centi = int(round(self.temperature_c * 100.0))
        p1, p2 = encode_samples(ug, temp_centi, counters, status)
        keep = np.ones((n, 2), dtype=bool)
        if self.faults.loss_rate > 0.0:
            keep = self.rng.random((n, 2)) >= self.faults.loss_rate
        self.stats.samples += n
        self.stats.tpdo_dropped += int(2 * n - keep.sum())
        t_end = self.power_on_s + (k0 + 1 + np.arange(n)) * self.dt_s
        id1, id2 = TPDO1_BASE + self.node_id, TPDO2_BASE + self.node_id
        events: list[tuple[float, int, Any]] = []
        for i in range(n):
            t = float(t_end[i])
            if keep[i, 0]:
                events.append((t, 2, (id1, p1[i])))
            if keep[i, 1]:
                events.append((t, 3, (id2, p2[i])))
        return events

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
