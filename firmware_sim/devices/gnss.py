"""A GNSS receiver speaking NMEA 0183 (docs/PROTOCOLS.md §5) on its own pty.

Each epoch (1, 5 or 10 Hz of device time; epoch k at t = k / rate, k = 0, 1, …) it sends GGA,
RMC and VTG, talker GN, of the ANTENNA: the IMU reference point's position plus C_b^n·r, and its
velocity plus C_b^n·(ω_nb^b × r), r the lever arm in body axes — with white noise of σ_h on East
and North, σ_v on Up and σ_vel on each velocity axis. NMEA has no vertical velocity, so only the
horizontal velocity reaches the wire (as speed over ground and true course).

Geodetic position from the local ENU truth uses the same curvilinear map as the vehicle's
latitude (firmware_sim.physics.vehicle): L = L0 + N/(R_M+h0), λ = λ0 + E/((R_N+h0)·cos L0),
h = h0 + U, with WGS-84 radii at the site. The GGA altitude is h − geoid_sep_m (geoid
separation 0 by default, so the altitude is the ellipsoidal height).

Formatting and checksum are written here from the protocol sheet (firmware_sim imports
nothing of northfinder's); positions are formatted from integers (1e-7 minute units), so
59.99999999′ never prints as 60′. Noise is drawn per epoch in order, so the bytes do not depend on how
`advance` calls split the time. Faults (own random stream): ``gnss-bad-checksum-rate`` (per
sentence), ``gnss-truncate-rate`` (per sentence: cut at a random byte, then CRLF),
``gnss-nofix=START_S:DURATION_S`` (no-fix sentences in that window).
"""

from __future__ import annotations

import datetime as dt
import logging
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from firmware_sim.devices.base import PtyDevice
from firmware_sim.physics import earth
from firmware_sim.pty import PtyPort

log = logging.getLogger("firmware_sim.gnss")

RATES_HZ = (1, 5, 10)
BAUDRATE = 115200
KNOT_M_S = 1852.0 / 3600.0
DEFAULT_START_UTC = dt.datetime(2026, 11, 22, 12, 0, 0, tzinfo=dt.UTC)
DEFAULT_LONGITUDE_DEG = 116.3
_MINUTE_UNITS = 10_000_000  # 7 decimals of arc minutes
_SENTENCES_PER_EPOCH = 3
_NOFIX_GGA = "0000.0000000,S,00000.0000000,W,0,00,99.9,0.000,M,0.0,M,,"


def nmea_checksum(body: bytes) -> int:
    """XOR of every byte between '$' and '*'."""
    c = 0
    for b in body:
        c ^= b
    return c


def sentence(talker: str, kind: str, fields: str) -> bytes:
    """``$<talker><kind>,<fields>*HH\\r\\n`` with HH upper-case hex."""
    body = f"{talker}{kind},{fields}".encode("ascii")
    return b"$" + body + b"*%02X\r\n" % nmea_checksum(body)


def format_lat(lat_deg: float) -> str:
    """``ddmm.mmmmmmm,N|S`` (7 decimals of minutes, rounded once from an integer count)."""
    units = round(abs(lat_deg) * 60 * _MINUTE_UNITS)
    deg, rest = divmod(units, 60 * _MINUTE_UNITS)
    minutes, frac = divmod(rest, _MINUTE_UNITS)
    return f"{deg:02d}{minutes:02d}.{frac:07d},{'S' if lat_deg < 0 else 'N'}"


def format_lon(lon_deg: float) -> str:
    """``dddmm.mmmmmmm,E|W``."""
    lon = (lon_deg + 180.0) % 360.0 - 180.0
    units = round(abs(lon) * 60 * _MINUTE_UNITS)
    deg, rest = divmod(units, 60 * _MINUTE_UNITS)
    minutes, frac = divmod(rest, _MINUTE_UNITS)
    return f"{deg:03d}{minutes:02d}.{frac:07d},{'W' if lon < 0 else 'E'}"


def format_time(utc: dt.datetime) -> str:
    """``hhmmss.ss`` (centiseconds; the epoch times are whole centiseconds)."""
    cs = round(utc.microsecond / 10_000)
    return f"{utc.hour:02d}{utc.minute:02d}{utc.second:02d}.{cs:02d}"


def format_gga(utc: dt.datetime, lat_deg: float, lon_deg: float, alt_m: float, *, quality: int = 1,
               num_sv: int = 12, hdop: float = 0.8, geoid_sep_m: float = 0.0, talker: str = "GN") -> bytes:
    """GGA: time, position, fix quality, satellites, HDOP, altitude above the geoid, separation."""
    if quality == 0:
        return sentence(talker, "GGA", f"{format_time(utc)},{_NOFIX_GGA}")
    fields = (f"{format_time(utc)},{format_lat(lat_deg)},{format_lon(lon_deg)},{quality:d},{num_sv:02d},"
              f"{hdop:.1f},{alt_m:.3f},M,{geoid_sep_m:.1f},M,,")
    return sentence(talker, "GGA", fields)


def format_rmc(utc: dt.datetime, lat_deg: float, lon_deg: float, speed_knots: float, course_deg: float, *,
               valid: bool = True, talker: str = "GN") -> bytes:
    """RMC: time, status, position, speed over ground [knots], true course, date ddmmyy, mode."""
    date = f"{utc.day:02d}{utc.month:02d}{utc.year % 100:02d}"
    if not valid:
        return sentence(talker, "RMC", f"{format_time(utc)},V,,,,,,,{date},,,N")
    fields = (f"{format_time(utc)},A,{format_lat(lat_deg)},{format_lon(lon_deg)},{speed_knots:.3f},"
              f"{course_deg:.2f},{date},,,A")
    return sentence(talker, "RMC", fields)


def format_vtg(speed_knots: float, course_deg: float, *, valid: bool = True, talker: str = "GN") -> bytes:
    """VTG: true course, (no magnetic), speed in knots and km/h, mode."""
    if not valid:
        return sentence(talker, "VTG", ",T,,M,,N,,K,N")
    kmh = speed_knots * KNOT_M_S * 3.6
    return sentence(talker, "VTG", f"{course_deg:.2f},T,,M,{speed_knots:.3f},N,{kmh:.3f},K,A")


def _fault(faults: Any, name: str) -> Any:
    """A fault by its command-line name from a Faults-like object or a mapping (None if absent)."""
    if faults is None:
        return None
    if isinstance(faults, Mapping):
        return faults.get(name)
    return getattr(faults, name.replace("-", "_"), None)


def _window(value: Any) -> tuple[float, float] | None:
    if value in (None, "", 0, 0.0):
        return None
    if isinstance(value, str):
        parts = value.split(":")
        if len(parts) != 2:
            raise ValueError(f"fault gnss-nofix={value}: expected START_S:DURATION_S, e.g. gnss-nofix=30:5")
        value = parts
    start, dur = (float(v) for v in value)
    if not (math.isfinite(start) and math.isfinite(dur) and start >= 0 and dur > 0):
        raise ValueError(f"fault gnss-nofix={value}: START_S >= 0 and DURATION_S > 0")
    return start, dur


class GnssReceiver(PtyDevice):
    """NMEA receiver of the antenna on a vehicle (or on the bench's platform) on its own pty.

    `world_or_trajectory`: a World (its platform's position if it has one — a VehicleTrajectory
    — else a fixed position; attitude and rates from ``world.attitude``, disturbances included;
    site from ``world.site``), or a trajectory with ``antenna_enu(t, r)`` (then `site` gives the
    reference latitude/height; default 40° N, 0 m). The antenna is fixed to the platform: the
    table's angle is not applied (a vehicle has none). `rng`: the noise stream (a Generator or a
    seed); `fault_seed`: the fault decisions' own stream.
    """

    name = "gnss"

    def __init__(self, world_or_trajectory: Any, *, rate_hz: int = 10,
                 lever_arm_b_m: Any = (0.5, 1.5, 1.2), sigma_h_m: float = 0.5, sigma_v_m: float = 1.0,
                 sigma_vel_m_s: float = 0.05, rng: Any = None, start_utc: dt.datetime = DEFAULT_START_UTC,
                 faults: Any = None, fault_seed: Any = 0, site: Any = None,
                 longitude_deg: float = DEFAULT_LONGITUDE_DEG, num_sv: int = 12, hdop: float = 0.8,
                 geoid_sep_m: float = 0.0, talker: str = "GN", port: PtyPort | None = None,
                 link: Any = None) -> None:
        if int(rate_hz) != rate_hz or int(rate_hz) not in RATES_HZ:
            raise ValueError(f"GNSS rate {rate_hz} Hz not allowed; use one of {RATES_HZ}")
        sigmas = (("sigma_h_m", sigma_h_m), ("sigma_v_m", sigma_v_m), ("sigma_vel_m_s", sigma_vel_m_s))
        for label, value in sigmas:
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"GNSS {label} = {value}: give a standard deviation >= 0")
        src = world_or_trajectory
        self.world = src if hasattr(src, "platform") and hasattr(src, "attitude") else None
        self.trajectory = src if self.world is None else None
        if self.world is None and not hasattr(src, "antenna_enu"):
            raise TypeError("GnssReceiver needs a World or a trajectory with antenna_enu(t_s, lever_arm_b_m)")
        site = self.world.site if self.world is not None else site
        self.lat0_deg = float(getattr(site, "latitude_deg", 40.0))
        self.h0_m = float(getattr(site, "height_m", 0.0))
        self.lon0_deg = float(getattr(site, "longitude_deg", longitude_deg))
        r_m, r_n = earth.radii_m(math.radians(self.lat0_deg))
        self._k_n = float(r_m) + self.h0_m  # metres per radian of latitude
        self._k_e = (float(r_n) + self.h0_m) * math.cos(math.radians(self.lat0_deg))

        self.rate_hz = int(rate_hz)
        self.lever_arm_b_m = np.asarray(lever_arm_b_m, dtype=float).reshape(3)
        self.sigma_pos_m = np.array([sigma_h_m, sigma_h_m, sigma_v_m], dtype=float)
        self.sigma_vel_m_s = float(sigma_vel_m_s)
        self.rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        self.fault_rng = np.random.default_rng(fault_seed)
        if start_utc.tzinfo is None:
            start_utc = start_utc.replace(tzinfo=dt.UTC)
        self.start_utc = start_utc
        self.num_sv, self.hdop, self.talker = int(num_sv), float(hdop), talker
        self.geoid_sep_m = float(geoid_sep_m)
        self.bad_checksum_rate = float(_fault(faults, "gnss-bad-checksum-rate") or 0.0)
        self.truncate_rate = float(_fault(faults, "gnss-truncate-rate") or 0.0)
        for label, p in (("gnss-bad-checksum-rate", self.bad_checksum_rate),
                         ("gnss-truncate-rate", self.truncate_rate)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"fault {label}={p}: expected a probability 0..1")
        self.nofix = _window(_fault(faults, "gnss-nofix"))

        self.port = port if port is not None else PtyPort("gnss")
        self.link = link
        """A firmware_sim.link.LinkShaper between the receiver and its pty, or None."""
        self.next_epoch = 0
        self.epochs_sent = 0
        self.sentences_corrupted = 0
        self.sentences_truncated = 0

    # -- Device surface ---------------------------------------------------------------------
    def input_port(self) -> PtyPort | None:
        return None  # the receiver takes no commands

    def advance(self, t_device_s: float) -> None:
        """Send every epoch k with k / rate ≤ t (never beyond it)."""
        last = math.floor(t_device_s * self.rate_hz + 1e-9)
        if last >= self.next_epoch:
            k = np.arange(self.next_epoch, last + 1)
            self.next_epoch = last + 1
            self.epochs_sent += len(k)
            if self.link is None:
                self.port.write(self.epoch_bytes(k))
            else:  # epoch by epoch, each with its time (the same bytes: noise is drawn per epoch)
                for ki in k.tolist():
                    self.link.send(self.epoch_bytes([ki]), float(self.epoch_time_s(ki)))
        if self.link is not None:
            if not self.port.connected:
                self.link.discard()
            self.link.pump(t_device_s, self.port)

    # -- truth and sentences ------------------------------------------------------------------
    def epoch_time_s(self, k) -> np.ndarray:
        """Device time of epochs k."""
        return np.asarray(k, dtype=float) / self.rate_hz

    def antenna_truth(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """The antenna's true ENU position [N,3] (about the site) and velocity [N,3] at device times."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        r = self.lever_arm_b_m
        if self.world is None:
            pos, vel = self.trajectory.antenna_enu(t, r)
            return np.asarray(pos, float).reshape(-1, 3), np.asarray(vel, float).reshape(-1, 3)
        platform = self.world.platform
        c, w, _ = self.world.attitude(t)
        kin = platform.kinematics(t, self.world.site)
        base = platform.position_enu_m(t) if hasattr(platform, "position_enu_m") else np.zeros((len(t), 3))
        pos = np.asarray(base, float).reshape(-1, 3) + np.einsum("nij,j->ni", c, r)
        vel = np.asarray(kin.vel_enu_m_s, float).reshape(-1, 3) + np.einsum("nij,nj->ni", c, np.cross(w, r))
        return pos, vel

    def enu_to_geodetic(self, enu_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local ENU [m] about the site → (lat_deg, lon_deg, ellipsoidal height_m)."""
        enu = np.asarray(enu_m, dtype=float)
        return (self.lat0_deg + np.degrees(enu[..., 1] / self._k_n),
                self.lon0_deg + np.degrees(enu[..., 0] / self._k_e), self.h0_m + enu[..., 2])

    def utc(self, k: int) -> dt.datetime:
        """UTC of epoch k: start + k / rate, exact in microseconds (rates 1, 5, 10 Hz)."""
        return self.start_utc + dt.timedelta(microseconds=int(k) * (1_000_000 // self.rate_hz))

    def epoch_bytes(self, k) -> bytes:
        """GGA, RMC, VTG for each epoch in k (consecutive, in order), noise and faults applied."""
        k = np.atleast_1d(np.asarray(k, dtype=np.int64))
        t = self.epoch_time_s(k)
        pos, vel = self.antenna_truth(t)
        noise = self.rng.standard_normal((len(k), 6))  # one draw per epoch whatever its content
        pos = pos + noise[:, :3] * self.sigma_pos_m
        vel = vel + noise[:, 3:] * self.sigma_vel_m_s
        lat, lon, h = self.enu_to_geodetic(pos)
        speed_kn = np.hypot(vel[:, 0], vel[:, 1]) / KNOT_M_S
        course = np.degrees(np.arctan2(vel[:, 0], vel[:, 1])) % 360.0
        course = np.where(np.round(course, 2) >= 360.0, 0.0, course)
        u = self.fault_rng.random((len(k), 3 * _SENTENCES_PER_EPOCH))  # fixed count per epoch
        out = bytearray()
        for i, ki in enumerate(k.tolist()):
            utc = self.utc(ki)
            fix = self.nofix is None or not (self.nofix[0] <= t[i] < self.nofix[0] + self.nofix[1])
            parts = (
                format_gga(utc, lat[i], lon[i], h[i] - self.geoid_sep_m, quality=1 if fix else 0,
                           num_sv=self.num_sv if fix else 0, hdop=self.hdop, geoid_sep_m=self.geoid_sep_m,
                           talker=self.talker),
                format_rmc(utc, lat[i], lon[i], speed_kn[i], course[i], valid=fix, talker=self.talker),
                format_vtg(speed_kn[i], course[i], valid=fix, talker=self.talker),
            )
            for j, s in enumerate(parts):
                out += self._apply_faults(s, u[i, 3 * j: 3 * j + 3])
        return bytes(out)

    def _apply_faults(self, s: bytes, u: np.ndarray) -> bytes:
        """u: 3 uniforms of this sentence (corrupt?, truncate?, where). A truncation cuts off any
        checksum, so each faulty sentence is counted once, as what a decoder will see."""
        if u[1] < self.truncate_rate:  # lose the tail: cut inside the sentence, the line still ends
            cut = 1 + int(u[2] * (len(s) - 4))  # at most up to the '*': the checksum is gone
            self.sentences_truncated += 1
            return s[:cut] + b"\r\n"
        if u[0] < self.bad_checksum_rate:  # flip the checksum to another valid-looking value
            wrong = int(s[-4:-2], 16) ^ (1 + int(u[2] * 255))
            self.sentences_corrupted += 1
            return s[:-4] + b"%02X\r\n" % wrong
        return s
