"""Safran Sensonor STIM300/STIM318 normal-mode datagrams and service-mode identity (pure codec).

Reference: STIM300 Datasheet TS1524 rev.31 (February 2024), cited as "TS1524" with its sections
and tables; docs/PROTOCOLS.md "Sensonor STIM" is the project's copy. The STIM318 speaks the same
datagram format (its own datasheet is the reference for its noise figures, not for the bytes).

A normal-mode datagram (TS1524 Table 5-20, 5-21) is: identifier byte; gyro x, y, z (24-bit
two's complement, big-endian) + gyro STATUS; then, as the identifier says, accelerometer x, y, z +
STATUS, inclinometer x, y, z + STATUS, temperatures (16-bit, per axis of each selected cluster +
STATUS), PPS (24-bit + STATUS); then the counter (u8), the latency (u16, µs) and a CRC-32 (u32,
big-endian) over every preceding byte plus the dummy zero bytes of Table 5-22 that make the CRC
input a whole number of 32-bit words (polynomial 0x04C11DB7, seed 0xFFFFFFFF, no reflection, no
final XOR: CRC-32/MPEG-2, TS1524 §5.5.7). Optional <CR><LF> follows.

Units (TS1524 §7.5.2.2): gyro rate 2^14 LSB per °/s, incremental angle 2^21 LSB per °;
accelerometer acceleration 2^20/2^19/2^18/2^16 LSB per g for the 5/10/30/80 g ranges, incremental
velocity 2^23/2^22/2^21/2^19 LSB per m/s; inclinometer 2^22 LSB per g, 2^25 LSB per m/s;
temperature 2^8 LSB per °C.

The decoder never raises on bad bytes: a candidate whose CRC fails costs one skipped byte and a
`crc_errors` count; validity per axis comes from the STATUS bytes (Table 5-23).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from northfinder.codecs.kvh import crc32_mpeg2, crc32_mpeg2_rows

STANDARD_GRAVITY_M_S2 = 9.80665
"""k0 of TS1524 Table 7-2 and g0 of §3.1."""
INTERNAL_RATE_HZ = 2000
"""The counter counts internal samples at this rate (TS1524 §7.5.2.2.18)."""
SAMPLE_RATES_HZ = (125, 250, 500, 1000, 2000)
"""Configurable output rates (TS1524 Table 5-11)."""

# Datagram identifiers (TS1524 Table 5-21): which clusters follow the gyros.
ACC, INCL, TEMP, PPS = 1, 2, 4, 8
DATAGRAM_CONTENT: dict[int, int] = {
    0x90: 0, 0x91: ACC, 0x92: INCL, 0x93: ACC | INCL, 0x94: TEMP, 0xA5: ACC | TEMP, 0xA6: INCL | TEMP,
    0xA7: ACC | INCL | TEMP,
    0xF0: PPS, 0xF1: ACC | PPS, 0xF2: INCL | PPS, 0xF3: ACC | INCL | PPS, 0xF4: TEMP | PPS,
    0xF5: ACC | TEMP | PPS, 0xF6: INCL | TEMP | PPS, 0xF7: ACC | INCL | TEMP | PPS,
}
PART_NUMBER_ID = 0xB1  # Table 5-13 (0xB3 with <CR><LF>)
SERIAL_NUMBER_ID = 0xB5  # Table 5-15 (0xB7 with <CR><LF>)
IDENTITY_DATAGRAM_BYTES = 20

# STATUS byte bits (TS1524 Table 5-23)
STATUS_SYSTEM_INTEGRITY = 0x80
STATUS_START_UP = 0x40
STATUS_OUTSIDE_CONDITIONS = 0x20
STATUS_OVERLOAD = 0x10
STATUS_CHANNEL_ERROR = 0x08
STATUS_Z = 0x04
STATUS_Y = 0x02
STATUS_X = 0x01

GYRO_LSB_PER_DEG_S = 2.0**14
GYRO_LSB_PER_DEG = 2.0**21
ACC_LSB_PER_G = {5: 2.0**20, 10: 2.0**19, 30: 2.0**18, 80: 2.0**16}
ACC_LSB_PER_M_S = {5: 2.0**23, 10: 2.0**22, 30: 2.0**21, 80: 2.0**19}
INCL_LSB_PER_G = 2.0**22
INCL_LSB_PER_M_S = 2.0**25
TEMP_LSB_PER_C = 2.0**8


def layout(datagram_id: int) -> dict[str, int]:
    """Byte offsets of each block in a datagram, its length before the CRC and its CRC dummies."""
    content = DATAGRAM_CONTENT[datagram_id]
    off = {"gyro": 1}
    pos = 11
    for flag, name in ((ACC, "acc"), (INCL, "incl")):
        if content & flag:
            off[name] = pos
            pos += 10
    if content & TEMP:
        off["temp"] = pos
        pos += 7 * (1 + bool(content & ACC) + bool(content & INCL))
    if content & PPS:
        off["pps"] = pos
        pos += 4
    off["counter"] = pos
    off["latency"] = pos + 1
    off["crc"] = pos + 3
    off["length"] = pos + 7
    off["dummies"] = -(pos + 3) % 4
    return off


def datagram_length(datagram_id: int) -> int:
    """Bytes in one datagram without <CR><LF> (TS1524 Table 5-12: 18 for 0x90 … 63 for 0xF7)."""
    return layout(datagram_id)["length"]


def stim_crc(body: bytes) -> int:
    """CRC of the bytes before the checksum, padded with Table 5-22's zero dummies to whole words."""
    return crc32_mpeg2(bytes(body) + bytes(-len(body) % 4))


def _int24(b: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 big-endian two's complement → int64."""
    v = (b[:, 0].astype(np.int64) << 16) | (b[:, 1].astype(np.int64) << 8) | b[:, 2].astype(np.int64)
    return v - ((v & 0x800000) << 1)


def _pack24(values: np.ndarray) -> np.ndarray:
    """int array (n, k) → (n, 3k) big-endian 24-bit bytes, saturated to the 24-bit range."""
    v = np.clip(np.rint(values), -(2**23), 2**23 - 1).astype(np.int64) & 0xFFFFFF
    out = np.stack([(v >> 16) & 0xFF, (v >> 8) & 0xFF, v & 0xFF], axis=-1).astype(np.uint8)
    return out.reshape(v.shape[0], -1)


@dataclass(frozen=True)
class StimUnits:
    """The unit's configured output (service mode `i`, or the order code): what an LSB means."""

    gyro: str = "rate"  # rate | increment (°/s or ° per sample; average rate decodes as rate)
    accel: str = "acceleration"  # acceleration | increment (g or m/s per sample)
    incl: str = "acceleration"
    accel_range_g: int = 10

    def gyro_lsb(self) -> float:
        return GYRO_LSB_PER_DEG if self.gyro == "increment" else GYRO_LSB_PER_DEG_S

    def accel_lsb(self) -> float:
        return (ACC_LSB_PER_M_S if self.accel == "increment" else ACC_LSB_PER_G)[self.accel_range_g]

    def incl_lsb(self) -> float:
        return INCL_LSB_PER_M_S if self.incl == "increment" else INCL_LSB_PER_G


def encode_datagrams(datagram_id: int, gyro: np.ndarray, status_gyro: np.ndarray | int, counter: np.ndarray,
                     latency_us: np.ndarray | int, units: StimUnits = StimUnits(),
                     accel: np.ndarray | None = None,
                     status_accel: np.ndarray | int = 0, incl: np.ndarray | None = None,
                     status_incl: np.ndarray | int = 0, crlf: bool = False) -> bytes:
    """n datagrams from values in the configured units (°/s or °, g or m/s); temperatures read 25 °C
    and PPS 0 when the identifier carries them."""
    gyro = np.atleast_2d(np.asarray(gyro, dtype=float))
    n = gyro.shape[0]
    lay = layout(datagram_id)
    content = DATAGRAM_CONTENT[datagram_id]
    body = np.zeros((n, lay["crc"]), dtype=np.uint8)
    body[:, 0] = datagram_id
    body[:, 1:10] = _pack24(gyro * units.gyro_lsb())
    body[:, 10] = np.broadcast_to(np.asarray(status_gyro, dtype=np.uint8), (n,))
    for name, values, status, lsb in (("acc", accel, status_accel, units.accel_lsb()),
                                      ("incl", incl, status_incl, units.incl_lsb())):
        if name in lay:
            v = np.zeros((n, 3)) if values is None else np.atleast_2d(np.asarray(values, dtype=float))
            body[:, lay[name] : lay[name] + 9] = _pack24(v * lsb)
            body[:, lay[name] + 9] = np.broadcast_to(np.asarray(status, dtype=np.uint8), (n,))
    if content & TEMP:
        t = int(25 * TEMP_LSB_PER_C).to_bytes(2, "big", signed=True) * 3 + b"\0"
        clusters = 1 + bool(content & ACC) + bool(content & INCL)
        body[:, lay["temp"] : lay["temp"] + 7 * clusters] = np.frombuffer(t * clusters, dtype=np.uint8)
    body[:, lay["counter"]] = np.broadcast_to(np.asarray(counter, dtype=np.int64) & 0xFF, (n,))
    lat = np.broadcast_to(np.asarray(latency_us, dtype=np.int64), (n,))
    body[:, lay["latency"]] = (lat >> 8) & 0xFF
    body[:, lay["latency"] + 1] = lat & 0xFF
    out = bytearray()
    for row in body:
        chunk = row.tobytes()
        out += chunk + stim_crc(chunk).to_bytes(4, "big") + (b"\r\n" if crlf else b"")
    return bytes(out)


@dataclass
class StimStats:
    """What the decoder saw. Every byte fed ends up in a datagram, skipped, or pending."""

    datagrams: int = 0
    crc_errors: int = 0
    """Damaged stretches: a candidate whose CRC fails, up to the next good datagram (so two
    damaged datagrams in a row count once; the counter gap says how many samples were lost)."""
    skipped_bytes: int = 0
    identity_datagrams: int = 0
    invalid_samples: int = 0
    """Datagrams with any STATUS byte not zero."""
    counter_gaps: int = 0
    """Internal samples missing between consecutive datagrams (counter steps beyond the expected one)."""

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class StimSamples:
    """Decoded datagrams (n rows). Values in the configured units; validity per axis from STATUS."""

    gyro: np.ndarray
    accel: np.ndarray
    incl: np.ndarray
    status: np.ndarray
    """(n, 3) uint8: gyro, accelerometer, inclinometer STATUS (0 where the datagram lacks the cluster)."""
    counter: np.ndarray
    latency_us: np.ndarray
    byte_offset: np.ndarray

    def __len__(self) -> int:
        return len(self.counter)

    def valid(self, cluster: int = 0) -> np.ndarray:
        """(n, 3) bool per axis of `cluster` (0 gyro, 1 accelerometer, 2 inclinometer): invalid when
        the STATUS flags the unit (bits 7–5) or flags that axis's channel (bit 4 or 3 with its bit)."""
        return status_valid(self.status[:, cluster])


def status_valid(status: np.ndarray) -> np.ndarray:
    """STATUS bytes (n,) → (n, 3) per-axis validity (TS1524 Table 5-23)."""
    s = np.asarray(status, dtype=np.uint8)
    unit_bad = (s & (STATUS_SYSTEM_INTEGRITY | STATUS_START_UP | STATUS_OUTSIDE_CONDITIONS)) != 0
    channel = (s & (STATUS_OVERLOAD | STATUS_CHANNEL_ERROR)) != 0
    axes = np.stack([(s & bit) != 0 for bit in (STATUS_X, STATUS_Y, STATUS_Z)], axis=-1)
    return ~(unit_bad[:, None] | (channel[:, None] & axes))


def _empty(n: int = 0) -> StimSamples:
    z3 = np.zeros((n, 3))
    return StimSamples(z3, z3.copy(), z3.copy(), np.zeros((n, 3), np.uint8), np.zeros(n, np.int64),
                       np.zeros(n, np.int64), np.zeros(n, np.int64))


class StimDecoder:
    """Incremental decoder for one configured datagram id. `feed(bytes)` → StimSamples.

    Identity datagrams (part number 0xB1, serial number 0xB5) met in the stream are kept in
    `identity` as raw bytes; anything else that does not check out is skipped byte by byte.
    `rate_hz` sets the expected counter step (2000 / rate internal samples per datagram).
    """

    def __init__(self, datagram_id: int = 0x93, units: StimUnits = StimUnits(), rate_hz: int = 500,
                 crlf: bool = False) -> None:
        if datagram_id not in DATAGRAM_CONTENT:
            raise ValueError(f"0x{datagram_id:02X}: not a normal-mode datagram id (TS1524 Table 5-21)")
        self.datagram_id = datagram_id
        self.units = units
        self.layout = layout(datagram_id)
        self.size = self.layout["length"] + (2 if crlf else 0)
        self.counter_step = INTERNAL_RATE_HZ // rate_hz if rate_hz in SAMPLE_RATES_HZ else 1
        self.stats = StimStats()
        self.identity: list[bytes] = []
        self._buf = bytearray()
        self._offset = 0
        self._last_counter: int | None = None
        self._resyncing = False

    @property
    def pending_bytes(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes) -> StimSamples:
        self._buf += data
        buf = self._buf
        rows: list[int] = []
        body_len = self.layout["crc"]
        i = 0
        while len(buf) - i >= 1:
            b0 = buf[i]
            if b0 == self.datagram_id:
                if len(buf) - i < self.size:
                    break
                run = self._good_run(buf, i)
                if run:  # consecutive good datagrams, checked at once (the common case)
                    rows.extend(range(i, i + run * self.size, self.size))
                    i += run * self.size
                    self._resyncing = False
                    continue
                crc = int.from_bytes(buf[i + body_len : i + body_len + 4], "big")
                if stim_crc(bytes(buf[i : i + body_len])) == crc:
                    rows.append(i)
                    i += self.size
                    self._resyncing = False
                    continue
                if not self._resyncing:  # one count per damaged stretch, not per false start in it
                    self.stats.crc_errors += 1
                    self._resyncing = True
            elif b0 in (PART_NUMBER_ID, SERIAL_NUMBER_ID):
                if len(buf) - i < IDENTITY_DATAGRAM_BYTES:
                    break
                chunk = bytes(buf[i : i + IDENTITY_DATAGRAM_BYTES])
                if stim_crc(chunk[:16]) == int.from_bytes(chunk[16:], "big"):
                    self.identity.append(chunk)
                    self.stats.identity_datagrams += 1
                    i += IDENTITY_DATAGRAM_BYTES
                    continue
            i += 1
            self.stats.skipped_bytes += 1
        out = self._decode_rows(bytes(buf[: i]), rows)
        del buf[:i]
        self._offset += i
        return out

    def _good_run(self, buf: bytearray, i: int) -> int:
        """How many datagrams starting at buf[i], back to back, have their identifier and a good
        CRC (vectorized: the same test as the byte-wise path, many datagrams at a time)."""
        m = (len(buf) - i) // self.size
        if m < 2:
            return 0
        block = np.frombuffer(bytes(buf[i : i + m * self.size]), dtype=np.uint8).reshape(m, self.size)
        starts = block[:, 0] == self.datagram_id
        m = int(np.argmin(starts)) if not starts.all() else m
        if m == 0:
            return 0
        body_len = self.layout["crc"]
        body = block[:m, :body_len]
        pad = -body_len % 4
        if pad:
            body = np.hstack([body, np.zeros((m, pad), dtype=np.uint8)])
        crc = block[:m, body_len : body_len + 4].astype(np.uint32)
        sent = (crc[:, 0] << 24) | (crc[:, 1] << 16) | (crc[:, 2] << 8) | crc[:, 3]
        good = crc32_mpeg2_rows(body) == sent
        return m if good.all() else int(np.argmin(good))

    def _decode_rows(self, chunk: bytes, rows: list[int]) -> StimSamples:
        n = len(rows)
        if n == 0:
            return _empty()
        raw = np.frombuffer(chunk, dtype=np.uint8)
        idx = np.asarray(rows, dtype=np.int64)
        dg = raw[idx[:, None] + np.arange(self.layout["crc"])]
        lay = self.layout
        out = _empty(n)
        out.gyro = _int24(dg[:, 1:10].reshape(-1, 3)).reshape(n, 3) / self.units.gyro_lsb()
        out.status[:, 0] = dg[:, 10]
        clusters = (("acc", self.units.accel_lsb()), ("incl", self.units.incl_lsb()))
        for k, (name, lsb) in enumerate(clusters, 1):
            if name in lay:
                block = dg[:, lay[name] : lay[name] + 9].reshape(-1, 3)
                setattr(out, "accel" if name == "acc" else "incl", _int24(block).reshape(n, 3) / lsb)
                out.status[:, k] = dg[:, lay[name] + 9]
        out.counter = dg[:, lay["counter"]].astype(np.int64)
        out.latency_us = (dg[:, lay["latency"]].astype(np.int64) << 8) | dg[:, lay["latency"] + 1]
        out.byte_offset = self._offset + idx
        self._count(out)
        return out

    def _count(self, s: StimSamples) -> None:
        self.stats.datagrams += len(s)
        self.stats.invalid_samples += int(np.count_nonzero(s.status.any(axis=1)))
        counters = s.counter
        if self._last_counter is not None:
            counters = np.concatenate(([self._last_counter], s.counter))
        steps = np.diff(counters) % 256
        self.stats.counter_gaps += int(np.sum(np.maximum(steps - self.counter_step, 0)))
        self._last_counter = int(s.counter[-1])


# ---------------------------------------------------------------------------------------------
# Identity: the serial-number datagram and the service-mode listing
# ---------------------------------------------------------------------------------------------
def parse_serial_datagram(chunk: bytes) -> str:
    """Serial Number datagram (Table 5-15) → 'N' + 14 BCD digits, e.g. 'N25582405002002'."""
    if len(chunk) < 9 or chunk[0] not in (SERIAL_NUMBER_ID, SERIAL_NUMBER_ID + 2):
        raise ValueError("not a serial-number datagram")
    digits = "".join(f"{b >> 4}{b & 0xF}" for b in chunk[2:9])
    return chr(chunk[1]) + digits


def encode_serial_datagram(serial: str) -> bytes:
    """'N' + 14 digits → the 20-byte datagram 0xB5 with its CRC (no dummies: 16 bytes, Table 5-22)."""
    if len(serial) != 15 or not serial[1:].isdigit():
        raise ValueError("a STIM serial number is a letter and 14 digits")
    body = bytes([SERIAL_NUMBER_ID, ord(serial[0])])
    body += bytes(int(serial[k]) << 4 | int(serial[k + 1]) for k in range(1, 15, 2)) + bytes(7)
    return body + stim_crc(body).to_bytes(4, "big")


SERVICE_MODE_COMMAND = b"SERVICEMODE\r"
"""Normal-mode command (TS1524 §8.7): the unit answers with its identity and configuration."""
EXIT_TO_NORMAL_COMMAND = b"x N\r"
"""Service-mode `x N` (TS1524 §9.14, Table 9-54): back to Normal Mode at once, no hold time."""


def parse_service_listing(text: str) -> dict[str, str]:
    """`KEY = value` lines of the service-mode listing (TS1524 Figure 8-1) → {KEY: value}."""
    out: dict[str, str] = {}
    for line in text.replace("\r", "\n").split("\n"):
        key, sep, value = line.partition("=")
        if sep and key.strip():
            out[key.strip().upper()] = value.strip()
    return out


@dataclass(frozen=True)
class StimIdentity:
    product: str
    serial_number: str
    part_number: str
    sample_rate_hz: int | None = None
    extra: dict[str, str] = field(default_factory=dict)

    def describe(self) -> str:
        return f"Sensonor {self.product} s/n {self.serial_number} p/n {self.part_number}"


def identity_from_listing(text: str) -> StimIdentity:
    """The service-mode listing → identity; ValueError naming what is missing."""
    kv = parse_service_listing(text)
    missing = [k for k in ("PRODUCT", "SERIAL NUMBER", "PART NUMBER") if k not in kv]
    if missing:
        raise ValueError(f"service-mode listing lacks {', '.join(missing)}")
    rate = kv.get("SAMPLE RATE [SAMPLES/S]")
    return StimIdentity(kv["PRODUCT"], kv["SERIAL NUMBER"], kv["PART NUMBER"],
                        int(rate) if rate and rate.isdigit() else None, kv)
