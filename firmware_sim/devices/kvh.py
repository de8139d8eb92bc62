"""KVH 1750/1760/1775 IMU speaking "format A" (docs/PROTOCOLS.md §2) on a pty.

Reference: KVH "1775 IMU Technical Manual" 54-0938 and its Appendix C, the ICD 56-0298 Rev. B
("Page n of 77"; read at easymanua.ls/kvh-industries/1775-imu, which shows the technical manual
then the ICD). Data messages: ICD Tables 5-1, 5-2 (format A), 5-8 (status), 5-9 (CRC), §5.2.1 (a
sample message). The dialogue: ICD §7 "Commands and Queries" (p. 24: echo without the `=`,
`KEY,value` replies, `INVALID,` + the line in Configuration Mode, a prompt for bad parameters —
the copy breaks off before that prompt's first word; §7.1 p. 25 calls it "a usage response"),
§8 (one entry per command: the COMMANDS table below, section numbers where the entry was read),
§3.3 and §5.1 (Normal vs Configuration Mode, the Normal Mode subset), §3.4, §5.1 and §5.3 (the
BIT message: one at power-up before the data, one per `?BIT`/`?BIT,2`), §8.25 (`?LOGS`), Table 8-4
(`=MSYNC,EXT` sets both output filters to the Averager). What firmware-sim answers to each command
against what the manual says: docs/conformance/kvh.md (tools/conformance_kvh.py).

The codec is written here from the protocol sheet: messages are packed many at a time into a
numpy structured array (big-endian fields), and their CRC-32/MPEG-2 is computed for all of them
at once with a lookup table (one table step per two byte positions, vectorized over the
messages). One message per sample at the configured rate in device time; the data come from
the world's integrated truth through the sensor error models.

Delivery to a client (what the truth log's time alignment rests on): sample k (k = 1, 2, … since
power-on, sequence number (k − 1) mod 128) is produced whether or not anyone listens, and only a
connected client receives it. When the IMU sees a new client it waits `connect_grace_s` of device
time (the simulator passes 50 ms of wall time: pyserial flushes its input right after opening)
and starts it on a frame boundary (what a client left unread was dropped when it left);
`on_event("imu_connect", t, {"k0": …})`
names the first sample that client gets. A client already there at power-on gets every sample
from k = 1 with no grace. Rate changes and configuration mode, which move the k ↔ device-time
map, are reported as `imu_grid` events (docs/simulator.md).
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from firmware_sim.devices.base import PtyDevice
from firmware_sim.pty import PtyPort

log = logging.getLogger("firmware_sim.kvh")

STANDARD_GRAVITY_M_S2 = 9.80665
"""1 g as a unit for the accel fields (docs/CONVENTIONS.md project notes)."""

HEADER = b"\xfe\x81\xff\x55"
MESSAGE_BYTES = 36
RATES_HZ = (1, 5, 10, 25, 50, 100, 250, 500, 750, 1000)
INVALID_AFTER_RATE_CHANGE = 2

GYRO_VALID = (0x01, 0x02, 0x04)
ACCEL_VALID = (0x10, 0x20, 0x40)

DEFAULT_AXES = "xyz+acc"
GARBAGE_LOG10_RANGE = (2.0, 4.0)
"""A flagged (imu-invalid-rate) message carries |value| log-uniform in 1e2..1e4 in its cleared fields,
with a random sign: what a unit sends during built-in test, finite and far from any real reading."""


def axes_status(axes: str) -> tuple[int, np.ndarray, bool]:
    """`"xy+acc"` → (status valid bits 0x33, gyro axis mask [1, 1, 0], has accelerometer)."""
    from firmware_sim.config import parse_imu_axes

    gyro, has_accel = parse_imu_axes(axes)
    mask = np.array([a in gyro for a in "xyz"], dtype=float)
    bits = sum(b for b, a in zip(GYRO_VALID, "xyz", strict=True) if a in gyro)
    return bits | (sum(ACCEL_VALID) if has_accel else 0), mask, has_accel

MESSAGE_DTYPE = np.dtype([
    ("header", ">u4"),
    ("gyro", ">f4", (3,)),
    ("accel", ">f4", (3,)),
    ("status", "u1"),
    ("sequence", "u1"),
    ("temperature", ">i2"),
    ("crc", ">u4"),
])
assert MESSAGE_DTYPE.itemsize == MESSAGE_BYTES


# ---------------------------------------------------------------------------------------------
# CRC-32/MPEG-2: poly 0x04C11DB7, init 0xFFFFFFFF, no reflection, no final xor
# ---------------------------------------------------------------------------------------------
def _crc_table(bits: int) -> np.ndarray:
    """T[i] = i·x^32 mod P for every `bits`-wide i: one lookup advances the CRC by `bits` bits."""
    crc = np.arange(1 << bits, dtype=np.uint32) << np.uint32(32 - bits)
    for _ in range(bits):
        top = (crc & np.uint32(0x80000000)) != 0
        crc = np.where(top, (crc << np.uint32(1)) ^ np.uint32(0x04C11DB7), crc << np.uint32(1))
    return crc.astype(np.uint32)


CRC_TABLE = _crc_table(8)


def _position_tables(m: int) -> tuple[np.ndarray, int]:
    """For m-byte messages: T[j, b], the CRC (init 0) of b at byte j followed by m − 1 − j zero
    bytes, and the CRC of m zero bytes from init 0xFFFFFFFF. The CRC is affine in the message, so
    crc(row) = that constant ⊕ XOR_j T[j, row[j]]: one gather and one reduction for all rows."""
    tables = np.empty((m, 256), dtype=np.uint32)
    if m:
        tables[m - 1] = CRC_TABLE
    for j in range(m - 2, -1, -1):  # one zero byte more after position j
        nxt = tables[j + 1]
        tables[j] = (nxt << np.uint32(8)) ^ CRC_TABLE[nxt >> np.uint32(24)]
    crc = 0xFFFFFFFF
    for _ in range(m):
        crc = ((crc << 8) & 0xFFFFFFFF) ^ int(CRC_TABLE[crc >> 24])
    return tables, crc


_POSITION_TABLES: dict[int, tuple[np.ndarray, int]] = {}


def crc32_mpeg2_rows(rows: np.ndarray) -> np.ndarray:
    """CRC of each row of a uint8 array [n, m], all rows at once (`_position_tables`)."""
    rows = np.asarray(rows, dtype=np.uint8)
    if rows.ndim != 2:
        raise ValueError("rows must be a 2-D uint8 array [n_messages, n_bytes]")
    m = rows.shape[1]
    if m not in _POSITION_TABLES:
        _POSITION_TABLES[m] = _position_tables(m)
    tables, zeros_crc = _POSITION_TABLES[m]
    terms = tables[np.arange(m), rows]
    return np.bitwise_xor.reduce(terms, axis=1) ^ np.uint32(zeros_crc)


def crc32_mpeg2(data: bytes) -> int:
    """CRC-32/MPEG-2 of one byte string; `crc32_mpeg2(b'123456789') == 0x0376E6E7`."""
    row = np.frombuffer(bytes(data), dtype=np.uint8).reshape(1, -1)
    return int(crc32_mpeg2_rows(row)[0])


# ---------------------------------------------------------------------------------------------
# Message codec
# ---------------------------------------------------------------------------------------------
def pack_messages(gyro: np.ndarray, accel_g: np.ndarray, status: np.ndarray | int,
                  sequence: np.ndarray | int, temperature_c: np.ndarray | int) -> bytes:
    """n format-A messages (gyro [n,3] in the configured format, accel [n,3] in g) → bytes."""
    gyro = np.atleast_2d(np.asarray(gyro, dtype=np.float64))
    n = gyro.shape[0]
    msg = np.zeros(n, dtype=MESSAGE_DTYPE)
    msg["header"] = int.from_bytes(HEADER, "big")
    msg["gyro"] = gyro
    msg["accel"] = np.broadcast_to(np.asarray(accel_g, dtype=np.float64), (n, 3))
    msg["status"] = status
    msg["sequence"] = np.asarray(sequence) & 0x7F
    msg["temperature"] = np.rint(np.asarray(temperature_c, dtype=np.float64)).astype(np.int16)
    raw = msg.view(np.uint8).reshape(n, MESSAGE_BYTES)
    msg["crc"] = crc32_mpeg2_rows(raw[:, :32])
    return msg.tobytes()


def unpack_messages(data: bytes) -> np.ndarray:
    """Whole, aligned messages → structured array (fields as MESSAGE_DTYPE) plus 'crc_ok'."""
    n = len(data) // MESSAGE_BYTES
    msg = np.frombuffer(data[: n * MESSAGE_BYTES], dtype=MESSAGE_DTYPE)
    raw = np.frombuffer(data[: n * MESSAGE_BYTES], dtype=np.uint8).reshape(n, MESSAGE_BYTES)
    ok = crc32_mpeg2_rows(raw[:, :32]) == msg["crc"]
    ok &= msg["header"] == int.from_bytes(HEADER, "big")
    out = np.zeros(n, dtype=MESSAGE_DTYPE.descr + [("crc_ok", "?")])
    for name in MESSAGE_DTYPE.names:
        out[name] = msg[name]
    out["crc_ok"] = ok
    return out


# ---------------------------------------------------------------------------------------------
# BIT messages (manual §3.4 built-in test, §5.3 BIT message; tech. manual "Extended BIT")
# ---------------------------------------------------------------------------------------------
BIT_HEADER = b"\xfe\x81\x00\xaa"
"""Extended BIT message: this header, 6 data bytes, a checksum byte (§5.3)."""
BIT2_HEADER = b"\xfe\x81\x00\xab"
"""Extended BIT, 2 (`?BIT,2`): this header, 8 data bytes, a checksum byte."""
BIT_HEALTHY = 0x7F
"""Every data byte of a healthy unit's BIT message ("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23")."""


def bit_message(extended: bool = False, data: bytes | None = None) -> bytes:
    """A BIT message: header, data bytes (all BIT_HEALTHY unless given), and the checksum, the sum
    of every byte before it modulo 256 — header included: that is what makes the manual's example
    end in 0x23 (0xFE+0x81+0x00+0xAA + 6·0x7F = 0x523)."""
    header = BIT2_HEADER if extended else BIT_HEADER
    body = header + (bytes([BIT_HEALTHY] * (8 if extended else 6)) if data is None else bytes(data))
    return body + bytes([sum(body) & 0xFF])


# ---------------------------------------------------------------------------------------------
# The command table (manual §7 general rules, §8 one entry per command)
# ---------------------------------------------------------------------------------------------
EOL = b"\r\n"
"""Replies end in CR LF (§7: "either one or both of" CR and LF)."""
DR_VALUES_HZ = (1, 5, 10, 25, 50, 100, 250, 500, 750, 1000, 3600, 5000)
"""`=DR` values the unit accepts (§8.8.2); the simulator's configuration starts at one of RATES_HZ."""
BAUD_VALUES = ("9600", "19200", "38400", "57600", "115200", "460800", "576000", "921600", "4147200")
FILTER_TYPES = ("CHEBY", "BUTTER", "AVE")
IDENTITY = np.eye(3)
IDENTITY.flags.writeable = False


class _BadParameter(ValueError):
    """A known keyword with parameters it does not take: answered with its usage prompt (§7)."""


@dataclass(frozen=True)
class Command:
    """One row of the command table: how it is written, what it does, the manual entry."""

    kind: str  # "=" command or "?" query
    key: str
    handler: str
    usage: str
    summary: str
    section: str


def _command_table() -> dict[tuple[str, str], Command]:
    rows = [
        ("=", "AXES", "_cmd_axes", "=AXES,<X0>,<X1>,<X2>,<Y0>,<Y1>,<Y2>,<Z0>,<Z1>,<Z2>",
         "set the alignment matrix applied to gyro and accel data", "8.1"),
        ("?", "AXES", "_cmd_axes", "?AXES", "query the alignment matrix", "8.2"),
        ("=", "BAUD", "_cmd_choice", "=BAUD,<" + "|".join(BAUD_VALUES) + ">", "set the baud rate", "8.3"),
        ("?", "BAUD", "_cmd_choice", "?BAUD", "query the baud rate", "8.4"),
        ("?", "BIT", "_cmd_bit", "?BIT[,2]", "extended built-in test: a BIT message", "8.5"),
        ("=", "CONFIG", "_cmd_config", "=CONFIG,<0|1>", "1 enters Configuration Mode, 0 returns to Normal",
         "3.3, 8"),
        ("?", "CONFIG", "_cmd_config", "?CONFIG", "query the operating mode", "3.3, 8"),
        ("=", "ECHO", "_cmd_echo", "=ECHO[,<value>|,RESET]", "count calls: increment, set or reset", "8.10"),
        ("?", "ECHO", "_cmd_echo", "?ECHO[,<value>|,RESET]", "identical to =ECHO", "8.11"),
        ("=", "DR", "_cmd_dr", "=DR,<" + "|".join(map(str, DR_VALUES_HZ)) + ">", "set the data rate, Hz",
         "8.8"),
        ("?", "DR", "_cmd_dr", "?DR", "query the data rate", "8.9"),
        ("=", "FILTTYPE", "_cmd_filttype", "=FILTTYPE,<A|G>,<CHEBY|BUTTER|AVE>",
         "set the accel (A) or gyro (G) output filter type", "8.16"),
        ("?", "FILTTYPE", "_cmd_filttype", "?FILTTYPE,<A|G>", "query a filter type", "8.17"),
        ("=", "HELP", "_cmd_help", "=HELP[,command]", "list the commands", "8.18"),
        ("?", "HELP", "_cmd_help", "?HELP[,command]", "the same as =HELP", "8.19"),
        ("?", "IS", "_cmd_is", "?IS", "query the unit's serial number", "8.20"),
        ("?", "LOGS", "_cmd_logs", "?LOGS", "the BIT status logs stored in flash", "8.25"),
        ("=", "MSYNC", "_cmd_choice", "=MSYNC,<IMU|EXT>", "output timed by the unit or by MSYNC pulses", "8"),
        ("?", "MSYNC", "_cmd_choice", "?MSYNC", "query the MSYNC mode", "8"),
        ("=", "RESTART", "_cmd_restart", "=RESTART", "restart the unit (power-up BIT message again)", "8"),
        ("=", "ROTFMT", "_cmd_choice", "=ROTFMT,<DELTA|RATE>", "gyro output as delta angle or rate", "8"),
        ("?", "ROTFMT", "_cmd_choice", "?ROTFMT", "query the gyro output format", "8"),
        ("=", "ROTUNITS", "_cmd_choice", "=ROTUNITS,<RAD|DEG>", "gyro output in radians or degrees", "8"),
        ("?", "ROTUNITS", "_cmd_choice", "?ROTUNITS", "query the gyro output units", "8"),
        ("=", "RSTCFG", "_cmd_rstcfg", "=RSTCFG", "restore the factory configuration (baud kept)", "8"),
        ("=", "TEMPUNITS", "_cmd_choice", "=TEMPUNITS,<C|F>", "temperature field in deg C or deg F", "8"),
        ("?", "TEMPUNITS", "_cmd_choice", "?TEMPUNITS", "query the temperature units", "8"),
    ]
    return {(kind, key): Command(kind, key, handler, usage, summary, section)
            for kind, key, handler, usage, summary, section in rows}


COMMANDS = _command_table()
NORMAL_MODE_COMMANDS = {("=", "CONFIG"), ("?", "BIT")}
"""What the unit answers in Normal Mode. The ICD names "the permissible subset of commands … (e.g.,
=config,1 or ?bit)" (§5.1) and lists them in its Table 7-1, which we could not read; §8.5 runs ?BIT
"while it is running in Normal (binary) Mode", and the technical manual (54-0938, "Built-In Test")
names `?bit` and `?bit,2` in Normal mode and `?logs` in Configuration mode. Any other input is
ignored in Normal Mode (§7). So this set is the two the documents name, not Table 7-1's."""
CHOICES = {
    "ROTFMT": ("rot_format", ("DELTA", "RATE")),
    "ROTUNITS": ("rot_units", ("RAD", "DEG")),
    "TEMPUNITS": ("temp_units", ("C", "F")),
    "BAUD": ("baud", BAUD_VALUES),
    "MSYNC": ("msync", ("IMU", "EXT")),
}

DIALOGUE_LINES = (b"CONFIG,1", b"DR,1000", b"ROTFMT,DELTA", b"INVALID,=FOO", b"CONFIG,0")
"""What the imu-dialogue-rate fault puts between messages besides BIT messages: echoes, query
replies and an INVALID line, as a second terminal sharing the line would cause."""


# ---------------------------------------------------------------------------------------------
# The IMU
# ---------------------------------------------------------------------------------------------
class KvhImu(PtyDevice):
    """A format-A IMU on a pty. Samples k = 1, 2, … cover [(k−1)/rate, k/rate] from `epoch`.

    `gyro_model` / `accel_model` are the physics' error models; `make_models(rate_hz)` may be
    given instead to rebuild them after `=DR` (the models are built for one sample rate).
    `axes` ("xyz+acc", "xyz", "y", …): the unit's axes; missing ones send 0.0 with their valid bits
    clear (PROTOCOLS.md §2). `link`: a firmware_sim.link.LinkShaper (latency, hold) or None.
    `invalid_seed`: the stream of the imu-invalid-rate fault (docs/simulator.md).
    """

    name = "imu"

    def __init__(self, world: Any, gyro_model: Any = None, accel_model: Any = None, *,
                 rate_hz: int = 1000, axes: str = DEFAULT_AXES, rot_format: str = "DELTA",
                 rot_units: str = "RAD", lever_arm_b_m: Any = (0.0, 0.0, 0.0), temperature_c: float = 25.0,
                 make_models: Any = None, faults: Any = None, fault_seed: Any = 0,
                 backlog_bytes: int | None = None, connect_grace_s: float = 0.0,
                 on_event: Callable[[str, float, dict[str, Any]], None] | None = None,
                 link: Any = None, invalid_seed: Any = None, serial_number: str = "1775000001",
                 power_up_bit: bool = False) -> None:
        if int(rate_hz) not in RATES_HZ:
            raise ValueError(f"IMU rate {rate_hz} Hz not allowed; use one of {RATES_HZ}")
        self.world = world
        self.valid_bits, self.gyro_mask, self.has_accel = axes_status(axes)
        self.axes = axes
        self.rate_hz = int(rate_hz)
        self.default_rot_format = self.rot_format = rot_format.upper()
        self.default_rot_units = self.rot_units = rot_units.upper()
        self.default_rate_hz = self.rate_hz
        self.serial_number = serial_number
        self._defaults()
        self._bit_due: bytes | None = None
        self.echo_count = 0
        """=ECHO's counter (§8.10): not stored, 0 after a reset."""
        self.bit_log: list[tuple[str, bytes]] = []
        """(source, data bytes) of every BIT message sent, for ?LOGS (§8.25)."""
        self.dialogue_rate = float(getattr(faults, "imu_dialogue_rate", 0.0) or 0.0)
        self.dialogue_rng = np.random.default_rng(fault_seed) if self.dialogue_rate else None
        self.dialogue_sent = 0
        self.power_up_bit = bool(power_up_bit) or self.dialogue_rate > 0
        """Send the power-up BIT message (§3.4) to a client there at power-on. Off unless asked for
        (or imu-dialogue-rate is set), so that a scenario's bytes stay what they were."""
        """Text lines and BIT messages the imu-dialogue-rate fault put between messages."""
        self.lever_arm_b_m = np.asarray(lever_arm_b_m, dtype=float)
        self.temperature_c = float(temperature_c)
        self.make_models = make_models
        if gyro_model is None and make_models is not None:
            gyro_model, accel_model = make_models(self.rate_hz)
        self.gyro_model = gyro_model
        self.accel_model = accel_model
        self.fault_rng = np.random.default_rng(fault_seed)
        self.crc_rate = float(getattr(faults, "imu_crc_rate", 0.0) or 0.0)
        self.drop_rate = float(getattr(faults, "imu_drop_byte_rate", 0.0) or 0.0)
        self.silence = getattr(faults, "imu_silence", None)
        self.invalid_rate = float(getattr(faults, "imu_invalid_rate", 0.0) or 0.0)
        self.invalid_rng = np.random.default_rng(invalid_seed) if self.invalid_rate else None
        self.invalid_count = 0
        """Messages produced with their valid bits cleared (fault or rate change); the truth log
        lists each one's k in `imu_invalid` events."""
        self.link = link
        """A firmware_sim.link.LinkShaper between this IMU and its pty, or None (bytes go straight)."""
        self.disconnect = getattr(faults, "imu_disconnect", None)

        self._backlog_bytes = backlog_bytes
        self.connect_grace_s = float(connect_grace_s)
        self.on_event = on_event
        self.produced = 0
        """Samples produced since power-on (sent, unheard or silenced alike): the next is k = produced + 1."""
        self.k_last_delivered = 0
        self._link: str | None = None  # None until the first advance; then "down", "arming" or "up"
        self._deliver_from_s = -math.inf
        self._t_now = 0.0
        self.port = self._open_port()
        self._link_dir: str | None = None
        self._link_path: str | None = None
        if self.disconnect is not None:  # the endpoint must outlive the pty: a symlink to it
            self._link_dir = tempfile.mkdtemp(prefix="firmware_sim_imu_")
            self._link_path = os.path.join(self._link_dir, "imu")
            os.symlink(self.port.path, self._link_path)
        self._down_until_s: float | None = None

        self.config_mode = False
        self.epoch_s = 0.0  # device time of the current sample grid's origin
        self.emitted = 0  # samples emitted on the current grid
        self.sequence = 0
        self.invalid_left = 0
        self.messages_sent = 0
        self._rx = bytearray()

    def _open_port(self) -> PtyPort:
        if self._backlog_bytes is None:
            return PtyPort("imu")
        return PtyPort("imu", backlog_bytes=self._backlog_bytes)

    def _event(self, name: str, **fields: Any) -> None:
        if self.on_event is not None:
            self.on_event(name, self._t_now, fields)

    def _grid_event(self, reason: str) -> None:
        """The next sample's number and device time (end of its interval): a new anchor of k ↔ t."""
        self._event("imu_grid", reason=reason, k_next=self.produced + 1,
                    t_next_device_s=self.epoch_s + (self.emitted + 1) / self.rate_hz, rate_hz=self.rate_hz)

    # -- Device surface ---------------------------------------------------------------------
    def endpoint(self) -> str:
        return self._link_path or super().endpoint()

    def close(self) -> None:
        super().close()
        if self._link_dir is not None:
            try:
                os.unlink(self._link_path)  # type: ignore[arg-type]
            except OSError:
                pass
            try:
                os.rmdir(self._link_dir)
            except OSError:
                pass
            self._link_dir = None

    def on_input(self, data: bytes, t_device_s: float) -> None:
        self._rx += data
        while (cut := self._rx.find(b"\n")) >= 0:
            line = bytes(self._rx[:cut]).strip(b"\r ").decode("ascii", "replace")
            del self._rx[: cut + 1]
            if line:
                self.advance(t_device_s)  # samples before the command keep the old settings
                self.handle_line(line, t_device_s)
        if len(self._rx) > 4096:
            self._rx.clear()

    def advance(self, t_device_s: float) -> None:
        self._t_now = t_device_s
        if self._link is None:  # power-on: a client already there gets every sample, no grace
            self._link = "arming" if self.port.connected else "down"
            if self.port.connected and self.power_up_bit:  # before the periodic data (§3.4)
                self._write(self._logged_bit("Start up"))
        self._disconnect_events(t_device_s)
        n_due = int(math.floor((t_device_s - self.epoch_s) * self.rate_hz + 1e-9)) - self.emitted
        if n_due > 0:
            if self.config_mode or self.msync == "EXT":  # no data (no MSYNC pulses here); the grid moves on
                self.emitted += n_due
            else:
                self._emit(n_due)
        if self.link is not None:
            self.link.pump(t_device_s, self.port)

    # -- configuration (manual §7 "Commands and Queries", §8 command entries) -------------------
    def handle_line(self, line: str, t: float) -> None:
        """One ASCII line (`=CONFIG,1`, `=DR,100`, `?DR`, …), answered as the manual's §7 says:
        a command is echoed without its `=`, a query answered as `KEY,value`; in Normal Mode only
        NORMAL_MODE_COMMANDS are answered and anything else ignored; in Configuration Mode unknown
        input gets `INVALID,` + the line, bad parameters to a known keyword the usage prompt."""
        for reply in self.answer(line, t):
            self._write(reply)

    def answer(self, line: str, t: float) -> list[bytes]:
        """The unit's reply to one line, as bytes to send (text lines, or a BIT message), applying
        what it commands. Separate from the port so the conformance tool can tabulate it."""
        text = line.strip()
        kind, body = text[:1], text[1:]
        key, _, args = body.partition(",")
        key = key.strip().upper()
        args = args.strip().upper()
        known = COMMANDS.get((kind, key))
        if not self.config_mode and (kind, key) not in NORMAL_MODE_COMMANDS:
            log.info("imu: %r ignored in Normal Mode (manual §7)", text)
            return []
        if known is None:
            return [] if not self.config_mode else [f"INVALID,{text}".upper().encode("ascii") + EOL]
        handler = getattr(self, known.handler)
        try:
            out = handler(kind, key, args, t)
        except _BadParameter:
            return [f"USAGE,{known.usage}".encode("ascii") + EOL]
        return out

    def _echo(self, key: str, args: str) -> list[bytes]:
        return [(f"{key},{args}" if args else key).encode("ascii") + EOL]

    def _cmd_config(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        if kind == "?":
            return self._echo(key, "1" if self.config_mode else "0")
        if args not in ("0", "1"):
            raise _BadParameter
        leaving = self.config_mode and args == "0"
        self.config_mode = args == "1"
        if leaving:  # the grid moved on without samples: a new k ↔ t anchor
            self._grid_event("config_end")
        return self._echo(key, args)

    def _cmd_dr(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        if kind == "?":
            return self._echo(key, str(self.rate_hz))
        if not args.isdigit() or int(args) not in DR_VALUES_HZ:
            raise _BadParameter
        self._set_rate(int(args), t)  # even to the same rate: the sample clock restarts
        return self._echo(key, str(int(args)))

    def _cmd_choice(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        """A setting with a fixed set of values (ROTFMT, ROTUNITS, TEMPUNITS, BAUD, MSYNC)."""
        attr, values = CHOICES[key]
        if kind == "?":
            return self._echo(key, str(getattr(self, attr)))
        if args not in values:
            raise _BadParameter
        setattr(self, attr, args)
        if key == "MSYNC" and args == "EXT":  # Table 8-4: external MSYNC sets both filters to Averager
            self.filter_type = {"A": "AVE", "G": "AVE"}
        return self._echo(key, args)

    def _cmd_filttype(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        which, _, ftype = args.partition(",")
        if which not in ("A", "G"):
            raise _BadParameter
        if kind == "?":
            if ftype:
                raise _BadParameter
            return self._echo(key, f"{which},{self.filter_type[which]}")
        if ftype not in FILTER_TYPES:
            raise _BadParameter
        self.filter_type[which] = ftype
        return self._echo(key, args)

    def _cmd_axes(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        if kind == "=":
            try:
                values = [float(v) for v in args.split(",")]
            except ValueError:
                raise _BadParameter from None
            if len(values) != 9:
                raise _BadParameter
            matrix = np.array(values).reshape(3, 3)
            self.axes_matrix = IDENTITY if np.array_equal(matrix, IDENTITY) else matrix
        return self._echo(key, ",".join(f"{v:+.6E}" for v in self.axes_matrix.ravel()))

    def _cmd_bit(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        if args not in ("", "2"):
            raise _BadParameter
        message = self._logged_bit("?BIT" if args == "" else "?BIT,2", extended=args == "2")
        if self.config_mode:
            return [message]
        self._bit_due = message  # Normal Mode: sent right after the next data message (§8.5)
        return []

    def _cmd_is(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        if args:
            raise _BadParameter
        return self._echo(key, self.serial_number)

    def _cmd_help(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        rows = [c for c in COMMANDS.values() if not args or c.key == args.lstrip("=?")]
        if not rows:
            raise _BadParameter
        return [f"{c.usage} : {c.summary}".encode("ascii") + EOL for c in rows]

    def _cmd_rstcfg(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        if args:
            raise _BadParameter
        baud = self.baud
        self._defaults()
        self.baud = baud  # §8 (=BAUD): the baud rate is not changed by RSTCFG
        if self.rate_hz != self.default_rate_hz:
            self._set_rate(self.default_rate_hz, t)
        return self._echo(key, "")

    def _cmd_restart(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        if args:
            raise _BadParameter
        self.config_mode = False  # the unit comes back in Normal Mode, BIT message first (§3.4)
        self.echo_count = 0
        self._grid_event("restart")
        return self._echo(key, "") + [self._logged_bit("Start up")]

    def _logged_bit(self, source: str, extended: bool = False) -> bytes:
        """A healthy BIT message, recorded for ?LOGS as its source named it."""
        message = bit_message(extended=extended)
        self.bit_log.append((source, message[4:-1]))
        return message

    def _cmd_echo(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        """=ECHO / ?ECHO (§8.10, §8.11): increment the counter; `,<value>` sets it, `,RESET` zeroes it."""
        if args == "":
            self.echo_count += 1
        elif args == "RESET":
            self.echo_count = 0
        elif args.isdigit():
            self.echo_count = int(args)
        else:
            raise _BadParameter
        return self._echo(key, str(self.echo_count))

    def _cmd_logs(self, kind: str, key: str, args: str, t: float) -> list[bytes]:
        """?LOGS (§8.25): the BIT logs in the layout of the manual's example. The example shows 8
        data bytes for a `?BIT` entry; a 6-byte BIT message is logged padded with 0x7F (healthy)."""
        if args:
            raise _BadParameter
        lines = ["Start of log entries!"]
        for n, (source, data) in enumerate(self.bit_log, 1):
            padded = (data + bytes([BIT_HEALTHY] * 8))[:8]
            lines += [f"Log {n}:", f"Source - {source}", "Format - BIT Status",
                      f"Data - 0x{padded.hex().upper()}"]
        lines.append("End of log entries!")
        return [line.encode("ascii") + EOL for line in lines]

    def _defaults(self) -> None:
        """The settings a unit has from the factory (and after =RSTCFG)."""
        self.rot_format = self.default_rot_format
        self.rot_units = self.default_rot_units
        self.temp_units = "C"
        self.baud = "921600"
        self.msync = "IMU"
        self.filter_type = {"A": "CHEBY", "G": "BUTTER"}
        self.axes_matrix = IDENTITY

    def _set_rate(self, rate_hz: int, t: float) -> None:
        """`=DR`: a new sample grid from the last sample's end (no interval skipped or doubled);
        the next 2 messages carry no valid data while the unit's filters settle."""
        self.epoch_s = self.epoch_s + self.emitted / self.rate_hz
        self.emitted = 0
        if rate_hz != self.rate_hz and self.make_models is not None:
            self.gyro_model, self.accel_model = self.make_models(rate_hz)
        self.rate_hz = rate_hz
        self.invalid_left = INVALID_AFTER_RATE_CHANGE
        self._grid_event("rate")

    # -- data ---------------------------------------------------------------------------------
    def _emit(self, n: int) -> None:
        dt = 1.0 / self.rate_hz
        t0 = self.epoch_s + self.emitted * dt
        dtheta, dv = self.world.increments(t0, n, dt, self.lever_arm_b_m)
        if self.gyro_model is not None:  # the true Δv: the specific force its g-sensitivity feels
            dtheta = self.gyro_model.apply(dtheta, dv)
        if self.accel_model is not None:
            dv = self.accel_model.apply(dv)
        self.emitted += n
        gyro = np.asarray(dtheta, dtype=np.float64)
        if self.rot_format == "RATE":
            gyro = gyro / dt
        if self.rot_units == "DEG":
            gyro = np.degrees(gyro)
        status = np.full(n, self.valid_bits, dtype=np.uint8)
        if self.has_accel:
            accel_g = np.asarray(dv, dtype=np.float64) / (dt * STANDARD_GRAVITY_M_S2)
        else:
            accel_g = np.zeros((n, 3))
        if self.axes_matrix is not IDENTITY:  # =AXES (§8.1): data in the user's axes
            gyro = gyro @ self.axes_matrix.T
            accel_g = accel_g @ self.axes_matrix.T
        if not self.gyro_mask.all():  # axes the unit does not have send 0.0
            gyro = gyro * self.gyro_mask
        k_abs = self.produced + 1 + np.arange(n)
        if self.invalid_left:
            k = min(self.invalid_left, n)
            status[:k] = 0
            self.invalid_left -= k
            self._count_invalid(k_abs[:k], "rate_change")
        if self.invalid_rng is not None:
            self._flag_invalid(gyro, accel_g, status, k_abs)
        seq = (self.sequence + np.arange(n)) & 0x7F
        self.sequence = (self.sequence + n) & 0x7F
        self.produced += n
        t_end = t0 + dt * np.arange(1, n + 1)
        keep = np.ones(n, dtype=bool)
        if self.silence is not None:
            start, duration = self.silence
            keep &= ~((t_end >= start - 1e-9) & (t_end < start + duration - 1e-9))
        if self._down_until_s is not None or self.port.closed:
            keep[:] = False
        if not keep.any():
            return
        temperature = self.temperature_c if self.temp_units == "C" else self.temperature_c * 9 / 5 + 32
        data = pack_messages(gyro[keep], accel_g[keep], status[keep], seq[keep], temperature)
        data, sizes = self._corrupt(data)
        self.messages_sent += int(keep.sum())
        self._deliver(data, sizes, k_abs[keep], seq[keep], t_end[keep])
        if self._link == "up":
            self._after_data(int(keep.sum()))

    def _after_data(self, n_messages: int) -> None:
        """What follows data messages on the line: a `?BIT` answer (after the next data message,
        §8.5) and, with the imu-dialogue-rate fault, text lines and BIT messages between them."""
        if self._bit_due is not None:
            self._write(self._bit_due)
            self._bit_due = None
        if self.dialogue_rng is None:
            return
        draws = self.dialogue_rng.random((n_messages, 2))
        picked = draws[draws[:, 0] < self.dialogue_rate, 1]
        if not len(picked):
            return
        options = len(DIALOGUE_LINES) + 1
        out = b"".join(bit_message() if int(u * options) == len(DIALOGUE_LINES)
                       else DIALOGUE_LINES[int(u * options)] + EOL for u in picked)
        self.dialogue_sent += len(picked)
        self._write(out)
        self._event("imu_dialogue", lines=len(picked), bytes=len(out), total=self.dialogue_sent)

    def _count_invalid(self, k: np.ndarray, reason: str) -> None:
        if len(k):
            self.invalid_count += len(k)
            self._event("imu_invalid", reason=reason, k=[int(v) for v in k], count=self.invalid_count)

    def _flag_invalid(self, gyro: np.ndarray, accel_g: np.ndarray, status: np.ndarray,
                      k_abs: np.ndarray) -> None:
        """imu-invalid-rate: flagged messages get their axes' valid bits cleared and garbage in
        those fields (in place). 13 draws per message whatever happens, so the bytes for a seed do
        not depend on how the loop batches the samples."""
        u = self.invalid_rng.random((len(k_abs), 13))  # type: ignore[union-attr]
        flagged = (u[:, 0] < self.invalid_rate) & (status != 0)  # a rate-change message stays as it is
        if not flagged.any():
            return
        lo, hi = GARBAGE_LOG10_RANGE
        garbage = np.where(u[:, 7:] < 0.5, -1.0, 1.0) * 10.0 ** (lo + (hi - lo) * u[:, 1:7])
        fields = np.concatenate([gyro, accel_g], axis=1)
        present = np.concatenate([self.gyro_mask, np.full(3, 1.0 if self.has_accel else 0.0)]) > 0
        rows = np.flatnonzero(flagged)
        fields[np.ix_(rows, np.flatnonzero(present))] = garbage[np.ix_(rows, np.flatnonzero(present))]
        gyro[rows], accel_g[rows] = fields[rows, :3], fields[rows, 3:]
        status[rows] = 0
        self._count_invalid(k_abs[rows], "fault")

    def _deliver(self, data: bytes, sizes: np.ndarray, k_abs: np.ndarray, seq: np.ndarray,
                 t_end: np.ndarray) -> None:
        """Hand the frames to a connected client, starting a new client on a frame boundary."""
        if not self.port.connected:
            if self._link == "up":
                self._event("imu_disconnect", k_last=self.k_last_delivered, port=self.port.path)
            if self._link != "down":
                self.port.discard()
                if self.link is not None:
                    self.link.discard()
            self._link = "down"
            self.port.bytes_unheard += len(data)
            return
        if self._link == "down":  # a new client: let it finish opening (pyserial flushes its input)
            self._link = "arming"
            self._deliver_from_s = self._t_now + self.connect_grace_s
        first = 0  # the first frame this call hands on
        if self._link == "arming":
            late = np.flatnonzero(t_end >= self._deliver_from_s - 1e-9)
            if not len(late):
                self.port.bytes_unheard += len(data)
                return
            i0 = first = int(late[0])
            skip = int(sizes[:i0].sum())
            self.port.bytes_unheard += skip
            data = data[skip:]  # (nothing stale is queued: the last disconnect discarded it)
            self._link = "up"
            if self.dialogue_rate:  # as if powered on with the host listening: BIT message first
                self._write(self._logged_bit("Start up"))
            self._event("imu_connect", k0=int(k_abs[i0]), sequence0=int(seq[i0]),
                        t0_device_s=float(t_end[i0]), rate_hz=self.rate_hz, port=self.port.path)
        self.k_last_delivered = int(k_abs[-1])
        if self.link is not None:
            self.link.send_many(data, sizes[first:], t_end[first:])
        else:
            self.port.write(data)

    def _write(self, data: bytes) -> None:
        """A reply line: through the link when there is one (it keeps the byte order)."""
        if self.link is not None:
            self.link.send(data, self._t_now)
            self.link.pump(self._t_now, self.port)
        else:
            self.port.write(data)

    def _corrupt(self, data: bytes) -> tuple[bytes, np.ndarray]:
        """Apply imu-crc-rate / imu-drop-byte-rate, drawing only from the fault stream; returns the
        bytes and each message's size on the line (36, or 35 with a dropped byte)."""
        n = len(data) // MESSAGE_BYTES
        sizes = np.full(n, MESSAGE_BYTES, dtype=np.int64)
        if not self.crc_rate and not self.drop_rate:
            return data, sizes
        raw = np.frombuffer(data, dtype=np.uint8).reshape(n, MESSAGE_BYTES).copy()
        if self.crc_rate:
            bad = self.fault_rng.random(n) < self.crc_rate
            raw[bad, 35] ^= 0x01
        if not self.drop_rate:
            return raw.tobytes(), sizes
        drop = self.fault_rng.random(n) < self.drop_rate
        which = self.fault_rng.integers(0, MESSAGE_BYTES, n)
        mask = np.ones((n, MESSAGE_BYTES), dtype=bool)
        mask[np.nonzero(drop)[0], which[drop]] = False
        sizes -= drop
        return raw[mask].tobytes(), sizes

    def _disconnect_events(self, t: float) -> None:
        if self.disconnect is None:
            return
        at_s, down_s = self.disconnect
        if self._down_until_s is None and not self.port.closed and at_s <= t < at_s + down_s:
            log.info("imu: port %s disconnected at t=%.3f s for %.3f s", self.port.path, t, down_s)
            if self._link == "up":
                self._event("imu_disconnect", k_last=self.k_last_delivered, port=self.port.path)
            self._link = "down"
            self.port.close()
            # the device node goes with the device, as a USB adapter's does: a link left pointing
            # at the closed pty would, once the client lets go of it, name whatever pty the kernel
            # hands out next under that number — another program's port
            os.unlink(self._link_path)  # type: ignore[arg-type]
            if self.link is not None:
                self.link.discard()
            self._down_until_s = at_s + down_s
        elif self._down_until_s is not None and t >= self._down_until_s:
            self._down_until_s = None
            self.port = self._open_port()
            self._link = "down"
            self._event("imu_port", port=self.port.path, link=self._link_path)
            tmp = self._link_path + ".new"  # type: ignore[operator]
            os.symlink(self.port.path, tmp)
            os.replace(tmp, self._link_path)  # type: ignore[arg-type]
            self._rx.clear()
            self.disconnect = None  # one disconnect per run
            log.info("imu: back at t=%.3f s on %s (link %s)", t, self.port.path, self._link_path)
