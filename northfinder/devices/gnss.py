"""The GNSS-receiver role: a stream of fixes (time, position, velocity) on the receiver's clock.

:class:`GnssFix` (one epoch: the antenna's position and velocity), :class:`LocalEnu` (the INS's local
map) and :func:`fixes_to_arrays` are the data every GNSS model produces; a model's decoder
(:class:`GnssDecoder`) turns its raw log into fixes for replay.
"""

from __future__ import annotations

import datetime as _dt
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

import numpy as np

from northfinder.constants import radii_of_curvature_m

ROLE = "gnss"


@dataclass(frozen=True)
class LocalEnu:
    """Local East-North-Up metres about a reference (lat0, lon0, h0): the INS's curvilinear map."""

    lat0_deg: float
    lon0_deg: float
    h0_m: float = 0.0

    @property
    def scale_m_per_rad(self) -> tuple[float, float]:
        """(k_E, k_N): metres per radian of longitude and of latitude at the reference."""
        r_m, r_n = radii_of_curvature_m(self.lat0_deg)
        return float((r_n + self.h0_m) * math.cos(math.radians(self.lat0_deg))), float(r_m + self.h0_m)

    def to_enu(self, lat_deg, lon_deg, height_m) -> np.ndarray:
        """Geodetic (degrees, ellipsoidal height) → ENU [m], arrays broadcast; last axis E, N, U."""
        k_e, k_n = self.scale_m_per_rad
        dlon = (np.asarray(lon_deg, dtype=float) - self.lon0_deg + 180.0) % 360.0 - 180.0
        return np.stack(
            [
                np.deg2rad(dlon) * k_e,
                np.deg2rad(np.asarray(lat_deg, dtype=float) - self.lat0_deg) * k_n,
                np.asarray(height_m, dtype=float) - self.h0_m,
            ],
            axis=-1,
        )

    def from_enu(self, enu_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """ENU [m] → (lat_deg, lon_deg, height_m)."""
        k_e, k_n = self.scale_m_per_rad
        enu = np.asarray(enu_m, dtype=float)
        return (self.lat0_deg + np.rad2deg(enu[..., 1] / k_n), self.lon0_deg + np.rad2deg(enu[..., 0] / k_e),
                self.h0_m + enu[..., 2])


@dataclass(frozen=True)
class GnssFix:
    """One epoch of the receiver: the ANTENNA's position and velocity at `time_s`.

    `time_s` is UTC in POSIX seconds (date from RMC); a receiver that never sends a date gives
    seconds of the UTC day instead (`date` None). `alt_m` is the GGA altitude (above the geoid),
    `height_m` = alt_m + geoid_sep_m the ellipsoidal height the ENU map uses. Velocity from
    RMC (else VTG) speed over ground and true course; `vel_enu_m_s` is (E, N, 0.0) — NMEA has no
    vertical speed, so Up is 0 by convention, not measured — and None when neither sentence came.
    """

    time_s: float
    utc_sod_s: float
    date: _dt.date | None
    lat_deg: float
    lon_deg: float
    alt_m: float
    geoid_sep_m: float
    fix_quality: int
    num_sv: int
    hdop: float | None
    speed_m_s: float | None
    course_deg: float | None
    vel_enu_m_s: tuple[float, float, float] | None

    @property
    def height_m(self) -> float:
        """Ellipsoidal height of the antenna [m]."""
        return self.alt_m + self.geoid_sep_m

    def enu_m(self, ref: LocalEnu) -> np.ndarray:
        """The antenna position in local ENU metres about `ref`."""
        return ref.to_enu(self.lat_deg, self.lon_deg, self.height_m)


@dataclass(frozen=True)
class GnssArrays:
    """Fixes as arrays (what a filter takes): time, geodetic, ENU about `ref`, velocity (NaN if unknown)."""

    time_s: np.ndarray  # [n]
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_m: np.ndarray  # ellipsoidal
    pos_enu_m: np.ndarray  # [n, 3] about ref
    vel_enu_m_s: np.ndarray  # [n, 3], Up = 0 (not measured), NaN rows where unknown
    fix_quality: np.ndarray
    num_sv: np.ndarray
    hdop: np.ndarray
    ref: LocalEnu

    def __len__(self) -> int:
        return len(self.time_s)


def fixes_to_arrays(fixes: list[GnssFix], ref: LocalEnu | None = None) -> GnssArrays:
    """Stack fixes into arrays and convert every position to ENU at once (ref: the first fix)."""
    if ref is None:
        if not fixes:
            raise ValueError("no fixes and no reference point: nothing to convert")
        ref = LocalEnu(fixes[0].lat_deg, fixes[0].lon_deg, fixes[0].height_m)
    lat = np.array([f.lat_deg for f in fixes], dtype=float)
    lon = np.array([f.lon_deg for f in fixes], dtype=float)
    h = np.array([f.height_m for f in fixes], dtype=float)
    vel = np.array([f.vel_enu_m_s if f.vel_enu_m_s is not None else (np.nan,) * 3 for f in fixes],
                   dtype=float).reshape(-1, 3)
    return GnssArrays(
        time_s=np.array([f.time_s for f in fixes], dtype=float),
        lat_deg=lat, lon_deg=lon, height_m=h,
        pos_enu_m=ref.to_enu(lat, lon, h).reshape(-1, 3),
        vel_enu_m_s=vel,
        fix_quality=np.array([f.fix_quality for f in fixes], dtype=np.int64),
        num_sv=np.array([f.num_sv for f in fixes], dtype=np.int64),
        hdop=np.array([np.nan if f.hdop is None else f.hdop for f in fixes], dtype=float),
        ref=ref,
    )


class GnssDecoder(ABC):
    """A model's pure decoder of its raw log (replay and the host-time alignment)."""

    @abstractmethod
    def decode_log(self, raw: bytes) -> tuple[list[Any], Any]:
        """The whole log → its fixes (GnssFix) and the decoder's counters."""

    @abstractmethod
    def epoch_ends(self, raw: bytes, utc_ref_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Byte offset just past each epoch's position message, and its time (UTC − utc_ref_s) [s]."""


class GnssReceiver(ABC):
    """A GNSS receiver streaming fixes; a context manager."""

    role = ROLE
    port: str | None = None
    model_name: str = ""
    """The registry name of the model (set by registry.open_device)."""

    @abstractmethod
    def read_fixes(self, n: int, timeout_s: float | None = None) -> list[Any]: ...

    @abstractmethod
    def fixes_until(self, t_s: float, timeout_s: float | None = None) -> list[Any]: ...

    @abstractmethod
    def discard_pending(self) -> int: ...

    @abstractmethod
    def identity(self) -> dict[str, Any]: ...

    @abstractmethod
    def close(self) -> None: ...

    def __enter__(self) -> GnssReceiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
