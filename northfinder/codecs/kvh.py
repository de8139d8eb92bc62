"""KVH 1750/1760/1775 "format A" (docs/PROTOCOLS.md §2): bytes ⇄ values, no I/O.

A message is 36 bytes, big-endian: header ``FE 81 FF 55``, gyro x/y/z and accel x/y/z as
float32, status, a 7-bit sequence number, temperature int16 and a CRC-32/MPEG-2 of bytes 0–31.

:class:`KvhDecoder` is the streaming decoder both the live driver and the replay path use, so
the two give bit-identical arrays from the same bytes however those bytes were chunked. Per
chunk it finds every header with numpy, checks every complete candidate's CRC at once
(:func:`crc32_mpeg2_rows`), walks the chain of good frames (a bad CRC or garbage makes it look
for the next header: a resync), decodes all accepted frames with one structured big-endian
dtype, and unwraps the sequence number into a monotonic sample index (gaps = lost samples).
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass, field, replace

import numpy as np

from northfinder.devices.imu import ImuAxes, ImuBlock  # the role's data types, re-exported

__all__ = [
    "FRAME_DTYPE",
    "FRAME_SIZE",
    "HEADER",
    "RATES_HZ",
    "ROT_FORMATS",
    "ROT_UNITS",
    "AXIS_NAMES",
    "DecodedFrames",
    "ImuAxes",
    "ImuStats",
    "KvhDecoder",
    "crc32_mpeg2",
    "crc32_mpeg2_fast",
    "crc32_mpeg2_rows",
    "encode_frame",
    "encode_frames",
    "encode_query",
    "encode_bit_message",
    "find_bit_messages",
    "find_echo",
    "find_refusal",
    "BitMessage",
    "encode_set",
    "find_config_replies",
    "gyro_scale_to_rad_s",
    "parse_config_reply",
    "valid_mask",
]

HEADER = b"\xfe\x81\xff\x55"
FRAME_SIZE = 36
SEQUENCE_MODULO = 128
RATES_HZ = (1, 5, 10, 25, 50, 100, 250, 500, 750, 1000)
ROT_FORMATS = ("DELTA", "RATE")
ROT_UNITS = ("RAD", "DEG")

FRAME_DTYPE = np.dtype(
    [
        ("header", ">u4"),
        ("gyro", ">f4", (3,)),
        ("accel", ">f4", (3,)),
        ("status", "u1"),
        ("sequence", "u1"),
        ("temperature", ">i2"),
        ("crc", ">u4"),
    ]
)
assert FRAME_DTYPE.itemsize == FRAME_SIZE

AXIS_NAMES = ("gx", "gy", "gz", "ax", "ay", "az")
"""The six measured axes in field order; their status bits are 0, 1, 2 (gyro) and 4, 5, 6 (accel)."""
_STATUS_BITS = np.array([0, 1, 2, 4, 5, 6], dtype=np.uint8)
AXES_LEARN_FRAMES = 64
"""Frames whose status bits decide which axes the unit has (PROTOCOLS.md §2): an axis exists when its
bit is set in at least half of them, so a unit that flags a frame now and then keeps its axes."""


def valid_mask(status: np.ndarray) -> np.ndarray:
    """Status bytes [n] → bool [n, 6]: each axis's valid bit (gyro x y z, accel x y z)."""
    st = np.asarray(status, dtype=np.uint8)
    return ((st[:, None] >> _STATUS_BITS[None, :]) & 1).astype(bool)


# --------------------------------------------------------------------------------------------
# CRC-32/MPEG-2: poly 0x04C11DB7, init 0xFFFFFFFF, no reflection, no final xor.


def _make_table() -> np.ndarray:
    table = np.zeros(256, dtype=np.uint32)
    for byte in range(256):
        crc = byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) if crc & 0x80000000 else (crc << 1)
            crc &= 0xFFFFFFFF
        table[byte] = crc
    return table


CRC_TABLE = _make_table()
_CRC_TABLE_LIST = [int(v) for v in CRC_TABLE]


def crc32_mpeg2(data: bytes, crc: int = 0xFFFFFFFF) -> int:
    """CRC-32/MPEG-2 of `data`, table-driven, one byte at a time (the reference version)."""
    table = _CRC_TABLE_LIST
    for byte in data:
        crc = ((crc << 8) & 0xFFFFFFFF) ^ table[(crc >> 24) ^ byte]
    return crc


def crc32_mpeg2_rows(rows: np.ndarray) -> np.ndarray:
    """CRC-32/MPEG-2 of every row of a uint8 [n, L] array at once → uint32 [n].

    The byte loop runs over the L columns; each step is vectorized over the n rows.
    """
    rows = np.asarray(rows, dtype=np.uint8)
    columns = np.ascontiguousarray(rows.T)
    crc = np.full(rows.shape[0], 0xFFFFFFFF, dtype=np.uint32)
    for column in columns:
        crc = (crc << np.uint32(8)) ^ CRC_TABLE[(crc >> np.uint32(24)) ^ column]
    return crc


_BIT_REVERSED = bytes(int(f"{b:08b}"[::-1], 2) for b in range(256))
"""Each byte with its bits in reverse order (a `bytes.translate` table)."""


def crc32_mpeg2_fast(data: bytes) -> int:
    """CRC-32/MPEG-2 of one short byte string through zlib, in C: the same value as
    :func:`crc32_mpeg2`. zlib's CRC-32 is the same polynomial, reflected, with a final xor; fed
    each byte bit-reversed, it runs the MPEG-2 register bit-reversed, so the result is the
    MPEG-2 CRC bit-reversed and inverted."""
    reflected = ~zlib.crc32(data.translate(_BIT_REVERSED)) & 0xFFFFFFFF
    return int.from_bytes(reflected.to_bytes(4, "little").translate(_BIT_REVERSED), "big")


# --------------------------------------------------------------------------------------------
# Encoding (tests, tools, and anyone who needs to emit format A)


def encode_frames(gyro, accel, status, sequence, temperature_c) -> bytes:
    """Many messages at once: gyro/accel [n,3], status/sequence/temperature [n] → n·36 bytes."""
    gyro = np.atleast_2d(np.asarray(gyro, dtype=np.float64))
    n = gyro.shape[0]
    frames = np.zeros(n, dtype=FRAME_DTYPE)
    frames["header"] = int.from_bytes(HEADER, "big")
    frames["gyro"] = gyro
    frames["accel"] = np.atleast_2d(np.asarray(accel, dtype=np.float64))
    frames["status"] = status
    frames["sequence"] = np.asarray(sequence) % SEQUENCE_MODULO
    frames["temperature"] = np.rint(np.asarray(temperature_c, dtype=np.float64)).astype(np.int16)
    raw = frames.view(np.uint8).reshape(n, FRAME_SIZE)
    frames["crc"] = crc32_mpeg2_rows(raw[:, :32])
    return frames.tobytes()


def encode_frame(gyro, accel, status: int, sequence: int, temperature_c: int) -> bytes:
    """One 36-byte message."""
    return encode_frames([gyro], [accel], [status], [sequence], [temperature_c])


def gyro_scale_to_rad_s(rate_hz: float, rot_format: str, rot_units: str) -> float:
    """Factor from the gyro field to rad/s: ×rate for delta angles, ×π/180 for degrees."""
    fmt, units = rot_format.upper(), rot_units.upper()
    if fmt not in ROT_FORMATS or units not in ROT_UNITS:
        raise ValueError(f"rot_format must be one of {ROT_FORMATS}, rot_units one of {ROT_UNITS}")
    factor = float(rate_hz) if fmt == "DELTA" else 1.0
    if units == "DEG":
        factor *= np.pi / 180.0
    return factor


# --------------------------------------------------------------------------------------------
# Configuration lines (ASCII, '\n'-terminated)


def encode_set(key: str, value) -> bytes:
    """``('DR', 1000)`` → ``b'=DR,1000\\n'``; ``('CONFIG', 1)`` → ``b'=CONFIG,1\\n'``."""
    return f"={key.upper()},{value}\n".encode("ascii")


def encode_query(key: str) -> bytes:
    """``'DR'`` → ``b'?DR\\n'``."""
    return f"?{key.upper()}\n".encode("ascii")


_REPLY_RE = re.compile(rb"([A-Z]{2,8}),([0-9A-Za-z.+-]+)\r?\n")


def parse_config_reply(line: bytes) -> tuple[str, str]:
    """``b'DR,1000\\n'`` → ('DR', '1000'); ValueError if the line is not a KEY,VALUE reply."""
    m = _REPLY_RE.fullmatch(line)
    if m is None:
        raise ValueError(f"not a KVH configuration reply: {line!r}")
    return m.group(1).decode(), m.group(2).decode()


def find_config_reply(data: bytes, key: str) -> tuple[str, int] | None:
    """The first ``KEY,VALUE\\n`` reply to the query `key` in a byte buffer → (value, end offset).

    Matches the asked key exactly: a reply that follows binary data directly may be preceded by
    bytes that look like upper-case letters, which a generic key pattern would swallow.
    """
    m = re.search(re.escape(key.encode("ascii")) + rb",([0-9A-Za-z.+-]+)\r?\n", data)
    return None if m is None else (m.group(1).decode(), m.end())


def find_config_replies(data: bytes) -> list[tuple[str, str, int]]:
    """Every ``KEY,VALUE\\n`` reply in a byte buffer → (key, value, end offset)."""
    return [(m.group(1).decode(), m.group(2).decode(), m.end()) for m in _REPLY_RE.finditer(data)]


def find_echo(data: bytes, key: str, value: object) -> int | None:
    """End offset of the unit's echo of ``=KEY,VALUE`` (manual §7: the command without its '=',
    in upper case: ``KEY,VALUE``) in a byte buffer, or None. The echo may follow binary data
    directly (Normal Mode), so the line is matched by its exact text, not by a key pattern."""
    line = f"{key},{value}".upper().encode("ascii")
    m = re.search(re.escape(line) + rb"\r?\n", data)
    return None if m is None else m.end()


_REFUSAL_RE = re.compile(rb"((?:INVALID|USAGE),[ -~]*)\r?\n")


def find_refusal(data: bytes, key: str | None = None) -> tuple[str, int] | None:
    """The first refusal in a byte buffer (of the command ``=KEY`` when `key` is given) → (its
    text, end offset), or None. Manual §7, in Configuration Mode: unknown or unaccepted input is
    answered ``INVALID,`` + the line received; bad parameters to a known keyword the usage prompt
    (``USAGE,`` + how to write it). Both name the command, so another command's refusal (an earlier
    line's, or a second terminal's) is not taken for this one's."""
    for m in _REFUSAL_RE.finditer(data):
        text = m.group(1).decode("ascii")
        if key is None or re.search(rf"[=?]{re.escape(key.upper())}(,|$)", text.upper()):
            return text, m.end()
    return None


BIT_HEADER = b"\xfe\x81\x00\xaa"
"""Extended BIT message (manual §3.4, §5.3): this header, 6 data bytes, a checksum."""
BIT2_HEADER = b"\xfe\x81\x00\xab"
"""Extended BIT, 2 (``?BIT,2``): this header, 8 data bytes, a checksum."""
BIT_HEALTHY = 0x7F
"""A healthy unit's BIT data byte ("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23" is normal status)."""


@dataclass(frozen=True)
class BitMessage:
    """One BIT message from the stream: its data bytes and whether its checksum (the sum of every
    byte before it, header included, modulo 256) holds."""

    data: bytes
    checksum_ok: bool
    extended2: bool = False

    @property
    def healthy(self) -> bool:
        """Checksum good and every data byte 0x7F (all tests passed)."""
        return self.checksum_ok and all(b == BIT_HEALTHY for b in self.data)

    def describe(self) -> str:
        """``BIT 7F 7F 7F 7F 7F 7F: all passed`` or what failed."""
        text = " ".join(f"{b:02X}" for b in self.data)
        if not self.checksum_ok:
            return f"BIT {text}: checksum wrong (garbled on the line?)"
        if self.healthy:
            return f"BIT {text}: all passed"
        failed = [f"byte {i} bits {BIT_HEALTHY & ~b:#04x}"
                  for i, b in enumerate(self.data) if b != BIT_HEALTHY]
        return f"BIT {text}: not passed ({', '.join(failed)}) — see the manual's BIT tables"


def encode_bit_message(data: bytes = bytes([BIT_HEALTHY] * 6), extended2: bool = False) -> bytes:
    """A BIT message as the unit sends it (tests)."""
    body = (BIT2_HEADER if extended2 else BIT_HEADER) + bytes(data)
    return body + bytes([sum(body) & 0xFF])


def find_bit_messages(data: bytes) -> list[tuple[BitMessage, int]]:
    """Every complete BIT message in a byte buffer → (message, start offset)."""
    out = []
    for header, size, ext in ((BIT_HEADER, 6, False), (BIT2_HEADER, 8, True)):
        p = data.find(header)
        while p >= 0 and p + 4 + size + 1 <= len(data):
            body = data[p:p + 4 + size]
            out.append((BitMessage(body[4:], (sum(body) & 0xFF) == data[p + 4 + size], ext), p))
            p = data.find(header, p + 1)
    return sorted(out, key=lambda item: item[1])


# --------------------------------------------------------------------------------------------
# Streaming decoder


@dataclass
class ImuStats:
    """Counters of a KVH stream: good frames, bad CRCs, resyncs, sequence gaps and lost samples."""

    frames: int = 0
    bad_crc: int = 0
    resyncs: int = 0
    sequence_gaps: int = 0
    lost_samples: int = 0
    bytes: int = 0
    skipped_bytes: int = 0
    discarded_frames: int = 0
    unknown_gaps: int = 0
    """Sequence gaps whose bytes never arrived: 128·k more samples may be missing than counted."""
    invalid_gx: int = 0
    invalid_gy: int = 0
    invalid_gz: int = 0
    invalid_ax: int = 0
    invalid_ay: int = 0
    invalid_az: int = 0
    """Frames whose valid bit is cleared, per axis the unit has (counted once its axes are known)."""

    def invalid_samples(self, axes: ImuAxes | None) -> dict[str, int]:
        """{axis: frames flagged not valid} for the axes the unit has."""
        if axes is None:
            return {}
        names = [a for a, p in zip(AXIS_NAMES, axes.present, strict=True) if p]
        return {a: int(getattr(self, f"invalid_{a}")) for a in names}

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class DecodedFrames:
    """Accepted frames of one chunk: device sample index and the raw field values."""

    sample_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    frames: np.ndarray = field(default_factory=lambda: np.zeros(0, FRAME_DTYPE))
    lost_samples: int = 0  # gaps inside this chunk (and before its first frame)

    def __len__(self) -> int:
        return len(self.sample_index)


_CHAIN_MAX_BYTES = 128 * FRAME_SIZE
"""Up to this many bytes a chunk of whole good frames is decoded in plain Python (KvhDecoder._feed_chain);
above it the vectorized path is the faster one."""
_HEADER_VALUES = np.frombuffer(HEADER, dtype=np.uint8)
_OFFSETS = np.arange(FRAME_SIZE)


def _header_positions(buf: np.ndarray) -> np.ndarray:
    n = len(buf) - 3
    if n <= 0:
        return np.zeros(0, dtype=np.intp)
    hit = buf[:n] == _HEADER_VALUES[0]
    for k in range(1, 4):
        hit &= buf[k : n + k] == _HEADER_VALUES[k]
    return np.flatnonzero(hit)


class KvhDecoder:
    """Stateful format-A decoder: ``feed(bytes) -> DecodedFrames``; counts in ``stats``.

    Its output does not depend on how the stream is cut into chunks. Definitions: a *bad CRC*
    is a complete 36-byte candidate that starts with the header and fails the CRC; a *resync*
    is a good frame that follows skipped bytes (garbage, a broken frame, or the middle of a
    frame when the stream was joined late); a *sequence gap* is a jump of the 7-bit sequence
    by more than 1, and its missing numbers are *lost samples*.
    """

    def __init__(self) -> None:
        self.stats = ImuStats()
        self._tail = b""
        self._skipped_pending = False
        self._last_sequence: int | None = None
        self._last_index = -1
        self._last_end_byte = 0
        self.unknown_gap_indices: list[int] = []
        """Sample index of the first frame after each gap of unknown length (see `_index`)."""
        self._learn_status: list[np.ndarray] = []
        self.axes: ImuAxes | None = None
        """The unit's axes, from the status bits of the first AXES_LEARN_FRAMES frames (None before)."""
        self._axis_bits: list[tuple[str, int]] | None = None  # (name, status bit) of each axis the unit has
        self._axis_want = 0  # those bits together

    @property
    def pending_bytes(self) -> int:
        """Bytes held for the next chunk (a frame begun, or the last 3 bytes that may start a
        header); always < 36. ``stats.bytes == 36·stats.frames + stats.skipped_bytes +
        pending_bytes``: every byte is a frame, skipped, or pending."""
        return len(self._tail)

    def feed(self, data: bytes) -> DecodedFrames:
        """Decode every complete frame in the buffered bytes plus `data`."""
        self.stats.bytes += len(data)
        raw = self._tail + bytes(data)
        if len(raw) <= _CHAIN_MAX_BYTES:
            chained = self._feed_chain(raw)
            if chained is not None:
                return chained
        buf = np.frombuffer(raw, dtype=np.uint8)
        n = len(buf)
        cand = _header_positions(buf)
        complete = cand[cand + FRAME_SIZE <= n]
        incomplete = cand[cand + FRAME_SIZE > n]
        if len(complete):
            rows = buf[complete[:, None] + _OFFSETS]
            stored = np.ascontiguousarray(rows[:, 32:36]).view(">u4").ravel()
            valid = crc32_mpeg2_rows(rows[:, :32]) == stored
        else:
            rows = np.zeros((0, FRAME_SIZE), np.uint8)
            valid = np.zeros(0, bool)

        good = complete[valid]
        if len(good) < 2 or np.all(np.diff(good) >= FRAME_SIZE):
            take = np.ones(len(good), bool)
        else:  # overlapping good candidates (a header+CRC inside a frame): the greedy chain
            take = np.zeros(len(good), bool)
            p = 0
            for k, pos in enumerate(good.tolist()):
                if pos >= p:
                    take[k] = True
                    p = pos + FRAME_SIZE
        accepted = good[take]
        accepted_rows = rows[valid][take]

        # bad CRCs: failing candidates not inside an accepted frame
        bad = complete[~valid]
        if len(bad) and len(accepted):
            j = np.searchsorted(accepted, bad, side="right") - 1
            inside = (j >= 0) & (bad < accepted[np.maximum(j, 0)] + FRAME_SIZE)
            bad = bad[~inside]
        self.stats.bad_crc += len(bad)

        # skipped bytes before each accepted frame → resyncs
        p_end = int(accepted[-1]) + FRAME_SIZE if len(accepted) else 0
        if len(accepted):
            prev_end = np.concatenate(([0], accepted[:-1] + FRAME_SIZE))
            gaps = accepted - prev_end
            skipped = gaps > 0
            skipped[0] |= self._skipped_pending
            self.stats.resyncs += int(np.count_nonzero(skipped))
            self.stats.skipped_bytes += int(gaps.sum())
            self._skipped_pending = False
        later = incomplete[incomplete >= p_end]
        keep_from = int(later[0]) if len(later) else max(p_end, n - 3)
        if keep_from > p_end:
            self.stats.skipped_bytes += keep_from - p_end
            self._skipped_pending = True
        self._tail = raw[keep_from:]

        frames = np.ascontiguousarray(accepted_rows).view(FRAME_DTYPE).ravel()
        return self._index(frames, self.stats.bytes - n + accepted)

    def _feed_chain(self, raw: bytes) -> DecodedFrames | None:
        """The common small chunk, decoded without numpy's per-call cost: whole frames back to back
        from the first byte, each with a good CRC, and what follows them the start of the next one
        (or under 4 bytes). Gives exactly what the general path gives for such a chunk (the greedy
        chain takes these frames; a header inside one of them is ignored there too); None for any
        other chunk, which the general path then decodes. This is what makes a real-time chunk
        (~216 B, 6 frames) cheap: issue 27 measured ~190 µs per call on the general path."""
        m, rest = divmod(len(raw), FRAME_SIZE)
        if m == 0 or (rest >= 4 and raw[m * FRAME_SIZE:m * FRAME_SIZE + 4] != HEADER):
            return None
        mirrored = raw.translate(_BIT_REVERSED)  # see crc32_mpeg2_fast: CRCs through zlib
        crc32 = zlib.crc32
        for p in range(0, m * FRAME_SIZE, FRAME_SIZE):
            if raw[p:p + 4] != HEADER or crc32(mirrored[p:p + 32]) ^ 0xFFFFFFFF != int.from_bytes(
                    mirrored[p + 32:p + 36], "little"):
                return None
        if self._skipped_pending:  # bytes were skipped before this chunk: its first frame resyncs
            self.stats.resyncs += 1
            self._skipped_pending = False
        self._tail = raw[m * FRAME_SIZE:]
        frames = np.frombuffer(raw, dtype=FRAME_DTYPE, count=m).copy()
        first_byte = self.stats.bytes - len(raw)
        sequences = raw[FRAME_SIZE - 7::FRAME_SIZE][:m]  # byte 29 of each frame
        statuses = raw[FRAME_SIZE - 8::FRAME_SIZE][:m]  # byte 28
        return self._index_chain(frames, sequences, statuses, first_byte)

    def _index_chain(self, frames: np.ndarray, sequences: bytes, statuses: bytes,
                     first_byte: int) -> DecodedFrames:
        """`_index` for frames back to back from stream offset `first_byte`, in plain Python (a
        handful of frames: cheaper than numpy's per-call cost); the same numbers as `_index`."""
        index: list[int] = []
        k = self._last_index
        prev = sequences[0] - 1 if self._last_sequence is None else self._last_sequence
        lost = gaps = 0
        for i, seq in enumerate(sequences):
            step = (seq - prev) % SEQUENCE_MODULO or SEQUENCE_MODULO
            k += step
            index.append(k)
            prev = seq
            if step > 1:
                gaps += 1
                lost += step - 1
                arrived = first_byte - self._last_end_byte if i == 0 else 0
                if FRAME_SIZE * (step - 1) - arrived >= FRAME_SIZE and not (
                        i == 0 and self._last_sequence is None):
                    self.unknown_gap_indices.append(k)
                    self.stats.unknown_gaps += 1
        m = len(sequences)
        self.stats.frames += m
        self.stats.sequence_gaps += gaps
        self.stats.lost_samples += lost
        self._last_sequence = sequences[-1]
        self._last_index = k
        self._last_end_byte = first_byte + m * FRAME_SIZE
        if self.axes is None:
            self._count_invalid(np.frombuffer(statuses, dtype=np.uint8))
        else:
            self._count_invalid_chain(statuses)
        return DecodedFrames(np.array(index, dtype=np.int64), frames, lost)

    def _count_invalid_chain(self, statuses: bytes) -> None:
        """`_count_invalid` once the axes are known, in plain Python: most frames have every bit
        of the unit's axes set and cost one comparison."""
        assert self.axes is not None
        if self._axis_bits is None:
            self._axis_bits = [(a, int(b)) for a, b, p in zip(AXIS_NAMES, _STATUS_BITS, self.axes.present,
                                                              strict=True) if p]
            self._axis_want = sum(1 << b for _, b in self._axis_bits)
        want = self._axis_want
        for st in statuses:
            if st & want != want:
                for name, b in self._axis_bits:
                    if not st >> b & 1:
                        setattr(self.stats, f"invalid_{name}", getattr(self.stats, f"invalid_{name}") + 1)

    def _index(self, frames: np.ndarray, start_byte: np.ndarray) -> DecodedFrames:
        """Unwrap the 7-bit sequence into a monotonic index; count gaps and lost samples; mark the
        gaps whose length the sequence cannot tell (`unknown_gap_indices`).

        `start_byte`: each frame's offset in the whole stream. A gap is counted as the smallest jump
        of the 7-bit number, which is exact only if no more than 127 samples went missing. Where the
        missing samples' bytes arrived (a CRC error, a byte dropped inside a frame) it is exact; where
        at least a frame's worth of bytes never arrived (a line overrun, a device silence), 128·k
        more samples may have gone and the gap's length is unknown."""
        if len(frames) == 0:
            return DecodedFrames()
        seq = frames["sequence"].astype(np.int64)
        prev = seq[0] - 1 if self._last_sequence is None else self._last_sequence
        step = np.diff(seq, prepend=prev) % SEQUENCE_MODULO
        step[step == 0] = SEQUENCE_MODULO  # same number again: a whole wrap went missing
        index = self._last_index + np.cumsum(step)
        lost = int((step - 1).sum())
        prev_end = np.concatenate(([self._last_end_byte], start_byte[:-1] + FRAME_SIZE))
        bytes_missing = FRAME_SIZE * (step - 1) - (start_byte - prev_end)
        unknown = (step > 1) & (bytes_missing >= FRAME_SIZE)
        if self._last_sequence is None:
            unknown[0] = False
        self.unknown_gap_indices.extend(int(k) for k in index[unknown])
        self.stats.unknown_gaps += int(np.count_nonzero(unknown))
        self.stats.frames += len(frames)
        self.stats.sequence_gaps += int(np.count_nonzero(step > 1))
        self.stats.lost_samples += lost
        self._last_sequence = int(seq[-1])
        self._last_index = int(index[-1])
        self._last_end_byte = int(start_byte[-1]) + FRAME_SIZE
        self._count_invalid(frames["status"])
        return DecodedFrames(index, frames, lost)

    def _count_invalid(self, status: np.ndarray) -> None:
        """Learn the axes from the first frames' status bits, then count cleared bits per axis."""
        if self.axes is None:
            self._learn_status.append(np.array(status, dtype=np.uint8))
            seen = np.concatenate(self._learn_status)
            if len(seen) < AXES_LEARN_FRAMES:
                return
            self.axes = ImuAxes.from_valid(valid_mask(seen[:AXES_LEARN_FRAMES]))
            self._learn_status = []
            status = seen
        cleared = (~valid_mask(status)).sum(axis=0)
        for name, present, n in zip(AXIS_NAMES, self.axes.present, cleared.tolist(), strict=True):
            if present:
                setattr(self.stats, f"invalid_{name}", getattr(self.stats, f"invalid_{name}") + n)


# -- decoded samples in edge units (the live driver and replay share these) --------------------
def frames_to_block(sample_index: np.ndarray, frames: np.ndarray, rate_hz: float, rot_format: str,
                    rot_units: str) -> ImuBlock:
    """Decoded format-A frames → an ImuBlock in rad/s and g (live and replay use this one)."""
    scale = gyro_scale_to_rad_s(rate_hz, rot_format, rot_units)
    index = np.asarray(sample_index, dtype=np.int64)
    lost = int(index[-1] - index[0] + 1 - len(index)) if len(index) else 0
    valid = valid_mask(frames["status"])
    return ImuBlock(
        sample_index=index,
        gyro_rad_s=np.where(valid[:, :3], frames["gyro"].astype(np.float64) * scale, np.nan),
        accel_g=np.where(valid[:, 3:], frames["accel"].astype(np.float64), np.nan),
        status=frames["status"].astype(np.uint8),
        temperature_c=frames["temperature"].astype(np.float64),
        lost_samples=lost,
        rate_hz=float(rate_hz),
    )


def decode_imu_stream(raw: bytes, rate_hz: float = 1000.0, rot_format: str = "DELTA",
                      rot_units: str = "RAD") -> tuple[ImuBlock, ImuStats]:
    """Decode a whole raw IMU log (replay): every good frame (fields flagged not valid are NaN,
    as live), and the stream's counters."""
    decoder = KvhDecoder()
    out = decoder.feed(raw)
    block = frames_to_block(out.sample_index, out.frames, rate_hz, rot_format, rot_units)
    return replace(block, unknown_gaps=tuple(decoder.unknown_gap_indices)), decoder.stats
