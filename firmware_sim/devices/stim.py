"""Safran Sensonor STIM300/STIM318 IMU in Normal Mode on a pty, with the service-mode identity.

Written from the STIM300 datasheet TS1524 rev.31 (February 2024), independently of northfinder's
codec: the datagram of Table 5-20 in the reduced forms of Table 5-21 (default 0x93: rate,
acceleration and inclination), 24-bit big-endian two's complement values (§7.5.2.2), STATUS bytes
(Table 5-23), the counter of internal 2000 Hz samples (§7.5.2.2.18), the latency word, and the
CRC-32 (polynomial 0x04C11DB7, seed 0xFFFFFFFF) over the datagram padded with the zero dummy
bytes of Table 5-22, sent most significant byte first (§5.5.7).

The data come from the one physical world: each datagram k covers [(k−1)/rate, k/rate] of device
time; the gyros give the integrated angle through the gyro error model, the accelerometers and
inclinometers the integrated specific force through their error models. Output units are the
unit's configuration: gyro incremental angle [°] (default) or angular rate [°/s]; accelerometer
incremental velocity [m/s] (default) or acceleration [g]; inclinometer acceleration [g].

Commands (TS1524 §8, §9): `SERVICEMODE<CR>` stops the datagrams and lists the identity and
configuration (Figure 8-1 layout); in Service Mode `i<CR>` lists it again and `x N<CR>` returns to
Normal Mode at once (the sample grid goes on, datagrams due meanwhile are lost, §7.5.3). In Normal
Mode `N<CR>` / `I<CR>` send one Part Number / Serial Number datagram in place of the next sample.
While the start-up bit time runs (`startup_s` from power-on) every STATUS has bit 6 set.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from firmware_sim.devices.base import PtyDevice
from firmware_sim.pty import PtyPort

log = logging.getLogger("firmware_sim.stim")

G0 = 9.80665  # k0 of TS1524 Table 7-2
RATES_HZ = (125, 250, 500, 1000, 2000)
INTERNAL_HZ = 2000
# identifier → (accelerometers, inclinometers) in the datagram; temperature/PPS forms not emitted
CONTENT = {0x90: (False, False), 0x91: (True, False), 0x92: (False, True), 0x93: (True, True)}
GYRO_SCALE = {"rate": 2.0**14, "increment": 2.0**21}  # LSB per °/s, per °
ACC10_SCALE = {"acceleration": 2.0**19, "increment": 2.0**22}  # 10 g range: LSB per g, per m/s
INCL_SCALE = 2.0**22  # LSB per g
STARTUP_BIT = 0x40
CHANNEL_ERROR = 0x08
LATENCY_US = 500
SERIAL = "N25582405002002"
PART_NUMBER = "84167-4400003-321 REV K"


def _crc_table() -> list[int]:
    table = []
    for byte in range(256):
        c = byte << 24
        for _ in range(8):
            c = ((c << 1) ^ 0x04C11DB7) if c & 0x80000000 else (c << 1)
        table.append(c & 0xFFFFFFFF)
    return table


_TABLE = _crc_table()


def crc32(data: bytes) -> int:
    """MSB-first CRC-32, poly 0x04C11DB7, seed 0xFFFFFFFF, no final XOR (TS1524 §5.5.7)."""
    c = 0xFFFFFFFF
    for b in data:
        c = ((c << 8) & 0xFFFFFFFF) ^ _TABLE[(c >> 24) ^ b]
    return c


def seal(body: bytes) -> bytes:
    """Body + its CRC over the body and the Table 5-22 dummy bytes."""
    return body + crc32(body + bytes(-len(body) % 4)).to_bytes(4, "big")


def pack24(values: np.ndarray) -> np.ndarray:
    """(n, 3) integers → (n, 9) bytes, big-endian 24-bit two's complement, saturated."""
    v = np.clip(np.rint(values), -(2**23), 2**23 - 1).astype(np.int64) & 0xFFFFFF
    return np.stack([v >> 16, (v >> 8) & 0xFF, v & 0xFF], axis=-1).astype(np.uint8).reshape(len(v), 9)


class StimImu(PtyDevice):
    """A STIM300 (or STIM318) on a pty. `product` names it in the identity listing."""

    name = "imu"

    def __init__(self, world: Any, gyro_model: Any = None, accel_model: Any = None, *,
                 incl_model: Any = None, rate_hz: int = 500, datagram_id: int = 0x93,
                 gyro_unit: str = "increment", accel_unit: str = "increment", product: str = "STIM300",
                 lever_arm_b_m: Any = (0.0, 0.0, 0.0), startup_s: float = 0.0, faults: Any = None,
                 fault_seed: Any = 0, port: PtyPort | None = None) -> None:
        if int(rate_hz) not in RATES_HZ:
            raise ValueError(f"STIM sample rate {rate_hz} not one of {RATES_HZ} (TS1524 Table 5-11)")
        if datagram_id not in CONTENT:
            raise ValueError(f"datagram 0x{datagram_id:02X}: this simulator sends 0x90–0x93")
        if gyro_unit not in GYRO_SCALE or accel_unit not in ACC10_SCALE:
            raise ValueError("gyro unit: rate|increment; accelerometer unit: acceleration|increment")
        self.world = world
        self.gyro_model, self.accel_model, self.incl_model = gyro_model, accel_model, incl_model
        self.rate_hz = int(rate_hz)
        self.datagram_id = datagram_id
        self.has_acc, self.has_incl = CONTENT[datagram_id]
        self.axes = "xyz+acc" if self.has_acc else "xyz"
        """The unit's axes in the KVH device's notation (the truth log's header names them)."""
        self.gyro_unit, self.accel_unit = gyro_unit, accel_unit
        self.product = product
        self.lever_arm_b_m = np.asarray(lever_arm_b_m, dtype=float)
        self.startup_s = float(startup_s)
        self.port = port if port is not None else PtyPort("imu")
        self.crc_rate = float(getattr(faults, "imu_crc_rate", 0.0) or 0.0)
        self.invalid_rate = float(getattr(faults, "imu_invalid_rate", 0.0) or 0.0)
        self.fault_rng = np.random.default_rng(fault_seed)
        self.emitted = 0
        """Samples produced since power-on (sent or not): datagram k covers ((k−1)/rate, k/rate]."""
        self.sent = 0
        self.service_mode = False
        self._special: list[bytes] = []
        self._rx = bytearray()

    # -- Device surface -------------------------------------------------------------------------
    def on_input(self, data: bytes, t_device_s: float) -> None:
        self._rx += data
        while (cut := self._rx.find(b"\r")) >= 0:
            line = bytes(self._rx[:cut]).strip(b"\n ").decode("ascii", "replace")
            del self._rx[: cut + 1]
            self.advance(t_device_s)
            self.handle_command(line)
        if len(self._rx) > 256:
            self._rx.clear()

    def advance(self, t_device_s: float) -> None:
        n = int(math.floor(t_device_s * self.rate_hz + 1e-9)) - self.emitted
        if n > 0:
            self._emit(n)

    # -- commands ---------------------------------------------------------------------------------
    def handle_command(self, line: str) -> None:
        if self.service_mode:
            if line == "x N":
                self.service_mode = False
            elif line == "i":
                self.port.write(self.listing())
            elif line:
                self.port.write(b"E001 UNKNOWN COMMAND\r\n")
        elif line == "SERVICEMODE":
            self.service_mode = True
            self.port.write(self.listing())
        elif line == "N":
            self._special.append(self.part_number_datagram())
        elif line == "I":
            self._special.append(self.serial_datagram())
        elif line:
            log.info("stim: normal-mode command %r ignored", line)

    def listing(self) -> bytes:
        """The identity and configuration lines of TS1524 Figure 8-1 (the subset a driver reads)."""
        gyro = "[°] – INCREMENTAL ANGLE" if self.gyro_unit == "increment" else "[°/s] – ANGULAR RATE"
        acc = "[m/s] – INCREMENTAL VELOCITY" if self.accel_unit == "increment" else "[g] – ACCELERATION"
        lines = [f"SERIAL NUMBER = {SERIAL}", f"PRODUCT = {self.product}", f"PART NUMBER = {PART_NUMBER}",
                 "FW CONFIG = SWD12404 REV 0", f"GYRO OUTPUT UNIT = {gyro}",
                 f"ACCELEROMETER OUTPUT UNIT = {acc}", "INCLINOMETER OUTPUT UNIT = [g] – ACCELERATION",
                 f"SAMPLE RATE [samples/s] = {self.rate_hz}", "ACCELEROMETER RANGE:", " X-AXIS: ± 10g",
                 f"DATAGRAM = 0x{self.datagram_id:02X}", ""]
        return "\r\n".join(lines).encode("utf-8")

    def serial_datagram(self) -> bytes:
        digits = SERIAL[1:]
        body = bytes([0xB5, ord(SERIAL[0])]) + bytes(int(digits[k]) << 4 | int(digits[k + 1])
                                                     for k in range(0, 14, 2)) + bytes(7)
        return seal(body)

    def part_number_datagram(self) -> bytes:
        """0xB1 with the part number's digits in nibbles (Table 5-13), revision byte 'K'."""
        d = [int(c) for c in PART_NUMBER.split()[0] if c.isdigit()]  # 84167 4400003 321
        body = bytes([0xB1, d[0], d[1] << 4 | d[2], d[3] << 4 | d[4], 0x2D, d[5] << 4 | d[6],
                      d[7] << 4 | d[8],
                      d[9] << 4 | d[10], 0x2D, d[12] << 4 | d[13], d[14] << 4, d[11], 0, 0, 0, ord("K")])
        return seal(body)

    # -- data -------------------------------------------------------------------------------------
    def _emit(self, n: int) -> None:
        dt = 1.0 / self.rate_hz
        t0 = self.emitted * dt
        dtheta, dv = self.world.increments(t0, n, dt, self.lever_arm_b_m)
        dv_true = np.asarray(dv, dtype=float)
        gyro = np.asarray(self.gyro_model.apply(dtheta, dv_true) if self.gyro_model else dtheta, dtype=float)
        acc = np.asarray(self.accel_model.apply(dv_true) if self.accel_model else dv_true, dtype=float)
        incl = np.asarray(self.incl_model.apply(dv_true) if self.incl_model else dv_true, dtype=float)
        k = self.emitted + 1 + np.arange(n)
        self.emitted += n
        if self.service_mode or not self.port.connected:
            return
        gyro_deg = np.degrees(gyro) if self.gyro_unit == "increment" else np.degrees(gyro) / dt
        acc_out = acc if self.accel_unit == "increment" else acc / (dt * G0)
        status = np.where(k * dt <= self.startup_s + 1e-12, STARTUP_BIT, 0).astype(np.uint8)
        if self.invalid_rate:
            hit = self.fault_rng.random(n) < self.invalid_rate
            status[hit] |= CHANNEL_ERROR | 0x07
        counter = (k * (INTERNAL_HZ // self.rate_hz)) & 0xFF
        rows = [np.full((n, 1), self.datagram_id, np.uint8), pack24(gyro_deg * GYRO_SCALE[self.gyro_unit]),
                status[:, None]]
        if self.has_acc:
            rows += [pack24(acc_out * ACC10_SCALE[self.accel_unit]), status[:, None]]
        if self.has_incl:
            rows += [pack24(incl / (dt * G0) * INCL_SCALE), status[:, None]]
        latency = np.full((n, 2), (LATENCY_US >> 8, LATENCY_US & 0xFF), np.uint8)
        rows += [counter.astype(np.uint8)[:, None], latency]
        bodies = np.concatenate(rows, axis=1)
        out = bytearray()
        for body in bodies:
            if self._special:
                out += self._special.pop(0)  # a special datagram replaces this sample (TS1524 §8.1)
                continue
            dg = seal(body.tobytes())
            if self.crc_rate and self.fault_rng.random() < self.crc_rate:
                dg = dg[:-1] + bytes([dg[-1] ^ 0x5A])
            out += dg
            self.sent += 1
        self.port.write(bytes(out))
