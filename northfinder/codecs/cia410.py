"""CiA 410 inclinometer objects and their default TPDO, and slopes → specific force (pure codec).

References: CiA DS 410 "CANopen device profile for inclinometer" version 1.2 (2 August 2006) for
the objects; the operating-parameter bits and the scaling equation as the profile states them
are also printed in vendors' manuals (SIKO IK360-CAN 23.01.2017 §8.25–8.28, Baumer GCA3 Rev10
§10.3). docs/PROTOCOLS.md "CiA 410 inclinometer" is the project's copy; CiA 301 (SDO, NMT,
heartbeat, PDO) is the same as for our accelerometer node (PROTOCOLS.md §3).

    0x6000      resolution, UNSIGNED16, rw: LSB of the 16-bit slopes in 0.001° (1, 10, 100, 1000)
    0x6010      slope long16, INTEGER16, ro, mappable: longitudinal (x) axis against the horizontal
    0x6011      slope long16 operating parameter, UNSIGNED8: bit 0 inversion, bit 1 scaling
    0x6012      slope long16 preset value, INTEGER16
    0x6013      slope long16 offset, INTEGER16
    0x6014      differential slope long16 offset, INTEGER16
    0x6020–24   the same for the lateral (y) axis
    TPDO1       default mapping 0x6010 then 0x6020: 4 data bytes, little-endian

With scaling on, slope = physical + differential offset + offset; with inversion, −physical
(as 0x10000 − X in 16 bits). Each slope is the angle between that axis and the horizontal plane,
measured for each axis independently, so the gravity components are exactly g·sin(slope): see
`specific_force_from_slopes` and docs/estimators.md "Inclinometer slopes as specific force".
"""

from __future__ import annotations

import math
import struct

import numpy as np

RESOLUTION = 0x6000
SLOPE_LONG16 = 0x6010
SLOPE_LONG16_OPERATING = 0x6011
SLOPE_LONG16_PRESET = 0x6012
SLOPE_LONG16_OFFSET = 0x6013
SLOPE_LONG16_DIFF_OFFSET = 0x6014
SLOPE_LATERAL16 = 0x6020
SLOPE_LATERAL16_OPERATING = 0x6021
SLOPE_LATERAL16_PRESET = 0x6022
SLOPE_LATERAL16_OFFSET = 0x6023
SLOPE_LATERAL16_DIFF_OFFSET = 0x6024

OPERATING_INVERT = 0x01
OPERATING_SCALING = 0x02

RESOLUTIONS_MDEG = (1, 10, 100, 1000)
"""Allowed 0x6000 values: the slope LSB in millidegrees."""
DEVICE_PROFILE = 410
"""Low word of 0x1000 device type for a CiA 410 device (CiA 301 §7.5.2.1: profile number)."""

TPDO1_BASE = 0x180
DEFAULT_TPDO1_MAPPING = ((SLOPE_LONG16 << 16) | 0x10, (SLOPE_LATERAL16 << 16) | 0x10)
"""0x1A00 sub 1, 2: 0x60100010, 0x60200010 (index, sub 0, 16 bits)."""


def encode_slopes(long_counts: int, lateral_counts: int) -> bytes:
    """TPDO1 payload of the default mapping: two INTEGER16 little-endian."""
    return struct.pack("<hh", long_counts, lateral_counts)


def decode_slopes(payload: bytes) -> tuple[int, int]:
    """TPDO1 payload → (slope long16, slope lateral16) counts; ValueError unless 4 bytes."""
    if len(payload) != 4:
        raise ValueError(f"the default TPDO1 carries 4 bytes, not {len(payload)}")
    long_counts, lateral_counts = struct.unpack("<hh", payload)
    return long_counts, lateral_counts


def decode_slope_frames(payloads: list[bytes]) -> tuple[np.ndarray, int]:
    """Many TPDO1 payloads → ((n, 2) int counts of the good ones, number of bad payloads)."""
    good = [p for p in payloads if len(p) == 4]
    if not good:
        return np.zeros((0, 2), dtype=np.int64), len(payloads)
    arr = np.frombuffer(b"".join(good), dtype="<i2").reshape(-1, 2).astype(np.int64)
    return arr, len(payloads) - len(good)


def deg_from_counts(counts: np.ndarray | int, resolution_mdeg: int) -> np.ndarray:
    """Slope counts → degrees with the 0x6000 resolution."""
    if resolution_mdeg not in RESOLUTIONS_MDEG:
        raise ValueError(f"resolution {resolution_mdeg} not one of {RESOLUTIONS_MDEG} (0.001° units)")
    return np.asarray(counts, dtype=float) * (resolution_mdeg * 1e-3)


def counts_from_deg(slope_deg: np.ndarray | float, resolution_mdeg: int) -> np.ndarray:
    """Degrees → INTEGER16 counts, rounded and saturated to ±32767 (what a device sends at its limit)."""
    counts = np.rint(np.asarray(slope_deg, dtype=float) / (resolution_mdeg * 1e-3))
    return np.clip(counts, -32768, 32767).astype(np.int64)


def apply_operating_parameter(physical: int, operating: int, offset: int = 0, diff_offset: int = 0) -> int:
    """What 0x6010 shows for a physical slope under its operating parameter (the profile's table:
    X, −X, X + offset + differential offset, −X + offset + differential offset), wrapped to 16 bits."""
    value = -physical if operating & OPERATING_INVERT else physical
    if operating & OPERATING_SCALING:
        value += offset + diff_offset
    return (value + 0x8000) % 0x10000 - 0x8000


def preset_offset(preset: int, physical: int, diff_offset: int = 0) -> int:
    """0x6013 after a write of `preset` to 0x6012: offset = preset − physical − differential offset."""
    return preset - physical - diff_offset


def specific_force_from_slopes(long_deg: np.ndarray, lateral_deg: np.ndarray,
                               g_m_s2: float) -> np.ndarray:
    """Slopes (each axis against the horizontal) → specific force [m/s²] in the sensor's (x, y, z).

    The x axis raised by β_x sees f_x = g·sin β_x (and likewise y), and the unit vector of f has
    f_z = √(1 − sin²β_x − sin²β_y) (z up, the sensor right way up). Exact for any tilt with
    sin²β_x + sin²β_y ≤ 1; docs/estimators.md gives the derivation and the errors of the
    small-angle form and of reading Euler angles as slopes."""
    sx = np.sin(np.radians(np.asarray(long_deg, dtype=float)))
    sy = np.sin(np.radians(np.asarray(lateral_deg, dtype=float)))
    sz = np.sqrt(np.clip(1.0 - sx * sx - sy * sy, 0.0, None))
    return g_m_s2 * np.stack([sx, sy, sz], axis=-1)


def slopes_from_specific_force(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse, for the simulator and tests: (x, y, z) specific force → slopes in degrees."""
    f = np.atleast_2d(np.asarray(f, dtype=float))
    norm = np.linalg.norm(f, axis=-1)
    return (np.degrees(np.arcsin(np.clip(f[:, 0] / norm, -1, 1))),
            np.degrees(np.arcsin(np.clip(f[:, 1] / norm, -1, 1))))


def quantization_ug(resolution_mdeg: int) -> float:
    """One slope LSB as specific force at level [µg]: sin(LSB)·1e6 (17.45 µg at 0.001°)."""
    return math.sin(math.radians(resolution_mdeg * 1e-3)) * 1e6
