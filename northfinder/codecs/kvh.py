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
    "crc32_mpeg2_rows",
    "encode_frame",
    "encode_frames",
    "encode_query",
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
