"""NMEA 0183 from a GNSS receiver (docs/PROTOCOLS.md §5): bytes → one :class:`GnssFix` per epoch, no I/O.

Each epoch the receiver sends ``GGA``, ``RMC``, ``VTG`` (talker ``GN``), each
``$<talker><type>,<fields>*HH\\r\\n`` with HH the XOR of the bytes between ``$`` and ``*``.
:class:`NmeaDecoder` is the streaming decoder the live driver and the replay path share, so both
give identical fixes from the same bytes however they were chunked. It frames sentences itself
(so that a wrong checksum, a truncated sentence and garbage are told apart and counted), checks
the checksum, and hands the field parsing of GGA/RMC/VTG to pynmeagps. Bad input is counted and
skipped; nothing raises out of :meth:`NmeaDecoder.feed`. The 8-bit XOR catches every single-byte
error in a sentence, not every pair of them (the protocol's limit, not this decoder's).

pynmeagps notes: it returns ``None`` (no error) for a sentence with a wrong or missing checksum,
hence the framing and XOR here; it converts ``ddmm.mmmmmmm`` to degrees rounded to 1e-10°
(≈ 11 µm on the ground), below the 7-decimal-minute resolution (1.7e-9° ≈ 0.19 mm), so its
latitude/longitude are used as they are.

Epochs: GGA opens an epoch (position, altitude, fix quality, satellites, HDOP); RMC with the same
time adds speed, course and the date; VTG (no time field) adds speed and course — only if nothing
was lost since the epoch's last sentence, else it could be the next epoch's — and closes the
epoch. An epoch is also closed by the next GGA (or an RMC of another time), so a lost VTG costs
no fix. An epoch without a usable GGA gives no fix (``incomplete_epochs``). Velocity is horizontal only: NMEA
carries no vertical speed, so ``vel_enu_m_s`` has Up = 0.0 by convention (see :class:`GnssFix`).

Local ENU: :class:`LocalEnu` is the curvilinear local-level map used by the INS
(northfinder.align.strapdown.LocalLevel): E = Δλ·(R_N+h0)·cos L0, N = ΔL·(R_M+h0), U = h − h0,
with the WGS-84 radii of curvature at the reference latitude. The INS integrates its position in
these metres, so GNSS fixes must be converted with the same map; over a few km it differs from
arc lengths on the ellipsoid by ≲ 0.1 m (at 10 km from the origin by ~1e-3 relative in E).
"""

from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field

import numpy as np
from pynmeagps import VALCKSUM, NMEAReader

from northfinder.constants import radii_of_curvature_m
from northfinder.devices.gnss import GnssArrays, GnssFix, LocalEnu, fixes_to_arrays  # the role's types

__all__ = [
    "KNOT_M_S",
    "MAX_SENTENCE_BYTES",
    "GnssArrays",
    "GnssFix",
    "LocalEnu",
    "NmeaDecoder",
    "NmeaStats",
    "checksum",
    "fixes_to_arrays",
    "radii_of_curvature_m",
]

KNOT_M_S = 1852.0 / 3600.0
"""One knot in m/s."""
MAX_SENTENCE_BYTES = 255
"""Longer than any GGA/RMC/VTG with 7-decimal minutes (~80 bytes): a '$' with no end by then is cut."""
MAX_UNDATED_FIXES = 20
"""Fixes held back waiting for a date (RMC); past this the receiver is taken to send no RMC."""
_MIN_FIELDS = {"GGA": 14, "RMC": 11, "VTG": 8}  # fields after the address, per NMEA 0183 v2.3+
_EPOCH_SECONDS = _dt.date(1970, 1, 1)
_HEX = frozenset(b"0123456789ABCDEFabcdef")


def checksum(body: bytes) -> int:
    """XOR of every byte of `body` (the text between ``$`` and ``*``)."""
    if not body:
        return 0
    return int(np.bitwise_xor.reduce(np.frombuffer(body, dtype=np.uint8)))


@dataclass
class NmeaStats:
    """Counters of an NMEA stream. Every sentence-like run of bytes lands in exactly one of
    sentences / bad_checksum / truncated / malformed / unknown; `no_fix` counts the parsed GGA/RMC/VTG
    that say "no fix" (and are not used)."""

    bytes: int = 0
    sentences: int = 0  # GGA/RMC/VTG with a good checksum and parsable fields (no-fix ones included)
    bad_checksum: int = 0  # `$…*HH` whose XOR is not HH
    truncated: int = 0  # no `*HH` trailer before the line ended / the next `$`, or too few fields
    malformed: int = 0  # good checksum, but pynmeagps could not parse the fields (or a fix without position)
    unknown: int = 0  # good checksum, a sentence type other than GGA/RMC/VTG
    no_fix: int = 0  # GGA quality 0, RMC status V, VTG mode N
    garbage_bytes: int = 0  # bytes outside any sentence (line ends excepted)
    fixes: int = 0  # epochs decoded into a GnssFix
    incomplete_epochs: int = 0  # epochs with no usable GGA (RMC/VTG only): no fix
    no_velocity: int = 0  # fixes whose RMC and VTG were both lost
    missed_epochs: int = 0  # gaps between consecutive fixes, in epochs (interval = smallest seen)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass
class _Epoch:
    sod_s: float
    gga: dict | None = None
    date: _dt.date | None = None
    rmc_vel: tuple[float, float | None] | None = None  # (speed m/s, course deg)
    vtg_vel: tuple[float, float | None] | None = None
    damage_mark: int = 0  # the decoder's damage count when this epoch last took a sentence


def _sod(t) -> float | None:
    """datetime.time → seconds of the day."""
    if not isinstance(t, _dt.time):
        return None
    return (t.hour * 3600 + t.minute * 60 + t.second) + t.microsecond / 1e6


def _num(value) -> float | None:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def _enu_velocity(speed_m_s: float, course_deg: float | None) -> tuple[float, float, float] | None:
    if course_deg is None:
        return (0.0, 0.0, 0.0) if speed_m_s == 0.0 else None
    c = math.radians(course_deg)
    return (speed_m_s * math.sin(c), speed_m_s * math.cos(c), 0.0)


@dataclass
class NmeaDecoder:
    """Streaming NMEA decoder: `feed(bytes)` → the fixes completed by those bytes; counts the rest."""

    stats: NmeaStats = field(default_factory=NmeaStats)

    def __post_init__(self) -> None:
        self._buf = bytearray()
        self._epoch: _Epoch | None = None
        self._date: tuple[_dt.date, float] | None = None  # last (date, sod) from an RMC
        self._undated: list[GnssFix] = []
        self._dateless = False
        self._last_time_s: float | None = None
        self._min_dt_s: float | None = None

    @property
    def pending_bytes(self) -> int:
        """Bytes of a sentence begun but not ended yet (waiting for the next chunk)."""
        return len(self._buf)

    # -- framing ---------------------------------------------------------------------------
    def feed(self, data: bytes) -> list[GnssFix]:
        """Decode what `data` completes; partial sentences wait for the next call."""
        self.stats.bytes += len(data)
        self._buf += data
        out: list[GnssFix] = []
        buf = self._buf
        while buf:
            start = buf.find(b"$")
            if start < 0:
                self._garbage(buf)
                buf.clear()
                break
            if start:
                self._garbage(buf[:start])
                del buf[:start]
            end = buf.find(b"\n")
            nxt = buf.find(b"$", 1)
            stop = min((i for i in (end, nxt) if i >= 0), default=-1)
            if stop < 0 and len(buf) <= MAX_SENTENCE_BYTES:
                break  # wait for the rest of the sentence
            if stop < 0 or stop > MAX_SENTENCE_BYTES:  # chunk-independent: same cut live and in replay
                self.stats.truncated += 1
                del buf[:MAX_SENTENCE_BYTES]
                continue
            line = bytes(buf[:stop])
            del buf[: stop + 1 if stop == end else stop]
            self._line(line.rstrip(b"\r"), out)
        return out

    def _damage(self) -> int:
        """Sentences (or bytes) lost so far: any of them may have been another epoch's GGA."""
        s = self.stats
        return s.bad_checksum + s.truncated + s.malformed + s.garbage_bytes

    def _garbage(self, chunk: bytes | bytearray) -> None:
        self.stats.garbage_bytes += len(chunk) - chunk.count(b"\r") - chunk.count(b"\n")

    def _line(self, line: bytes, out: list[GnssFix]) -> None:
        """One candidate sentence starting with '$' (line end stripped)."""
        star = line.rfind(b"*")
        if star < 0 or len(line) - star != 3 or not all(c in _HEX for c in line[star + 1:]):
            self.stats.truncated += 1
            return
        body = line[1:star]
        if checksum(body) != int(line[star + 1:], 16):
            self.stats.bad_checksum += 1
            return
        kind = body[2:5].decode("ascii", errors="replace") if body[:1] != b"P" else ""
        if kind not in _MIN_FIELDS or body[5:6] != b",":
            self.stats.unknown += 1
            return
        if body.count(b",") < _MIN_FIELDS[kind]:
            self.stats.truncated += 1
            return
        try:  # third-party parser on untrusted bytes: any failure is a malformed sentence
            msg = NMEAReader.parse(line + b"\r\n", validate=VALCKSUM)
        except Exception:  # noqa: BLE001
            msg = None
        if msg is None:
            self.stats.malformed += 1
            return
        getattr(self, f"_on_{kind.lower()}")(msg, out)

    # -- sentences -------------------------------------------------------------------------
    def _on_gga(self, msg, out: list[GnssFix]) -> None:
        sod = _sod(getattr(msg, "time", None))
        quality = getattr(msg, "quality", "")
        lat, lon, alt = (_num(getattr(msg, k, None)) for k in ("lat", "lon", "alt"))
        if isinstance(quality, int) and quality == 0:
            self.stats.sentences += 1
            self.stats.no_fix += 1
            self._close(out)
            return
        if sod is None or not isinstance(quality, int) or None in (lat, lon, alt):
            self.stats.malformed += 1
            return
        self.stats.sentences += 1
        self._close(out)
        sep = _num(getattr(msg, "sep", None)) or 0.0
        hdop = _num(getattr(msg, "HDOP", None))
        num_sv = getattr(msg, "numSV", "")
        self._epoch = _Epoch(sod, damage_mark=self._damage(), gga={
            "lat": lat, "lon": lon, "alt": alt, "sep": sep, "quality": quality,
            "num_sv": num_sv if isinstance(num_sv, int) else 0, "hdop": hdop,
        })

    def _on_rmc(self, msg, out: list[GnssFix]) -> None:
        sod = _sod(getattr(msg, "time", None))
        if sod is None:
            self.stats.malformed += 1
            return
        self.stats.sentences += 1
        date = getattr(msg, "date", None)
        if isinstance(date, _dt.date):
            self._learn_date(date, sod, out)
        if getattr(msg, "status", "") != "A":
            self.stats.no_fix += 1
            return
        if self._epoch is None or self._epoch.sod_s != sod:
            self._close(out)
            self._epoch = _Epoch(sod)
        if isinstance(date, _dt.date):
            self._epoch.date = date
        self._epoch.damage_mark = self._damage()
        speed = _num(getattr(msg, "spd", None))
        if speed is not None:
            self._epoch.rmc_vel = (speed * KNOT_M_S, _num(getattr(msg, "cog", None)))

    def _on_vtg(self, msg, out: list[GnssFix]) -> None:
        self.stats.sentences += 1
        if getattr(msg, "posMode", "") == "N":
            self.stats.no_fix += 1
            return
        if self._epoch is None:
            self.stats.incomplete_epochs += 1  # an orphan VTG: its GGA and RMC were lost
            return
        if self._epoch.damage_mark != self._damage():  # VTG has no time: with a sentence lost since the
            self._close(out)  # epoch's last one, it may be the next epoch's (whose GGA was lost)
            return
        knots = _num(getattr(msg, "sogn", None))
        kmh = _num(getattr(msg, "sogk", None))
        speed = knots * KNOT_M_S if knots is not None else (kmh / 3.6 if kmh is not None else None)
        if speed is not None:
            self._epoch.vtg_vel = (speed, _num(getattr(msg, "cogt", None)))
        self._close(out)

    # -- epochs ----------------------------------------------------------------------------
    def _close(self, out: list[GnssFix]) -> None:
        ep, self._epoch = self._epoch, None
        if ep is None:
            return
        if ep.gga is None:
            self.stats.incomplete_epochs += 1
            return
        vel = None
        speed = course = None
        for source in (ep.rmc_vel, ep.vtg_vel):
            if source is not None and (v := _enu_velocity(*source)) is not None:
                vel, (speed, course) = v, source
                break
        if vel is None:
            self.stats.no_velocity += 1
        g = ep.gga
        date = ep.date or self._date_for(ep.sod_s)
        fix = GnssFix(
            time_s=math.nan, utc_sod_s=ep.sod_s, date=date, lat_deg=g["lat"], lon_deg=g["lon"],
            alt_m=g["alt"], geoid_sep_m=g["sep"], fix_quality=g["quality"], num_sv=g["num_sv"],
            hdop=g["hdop"], speed_m_s=speed, course_deg=course, vel_enu_m_s=vel,
        )
        if date is None and not self._dateless:
            self._undated.append(fix)
            if len(self._undated) > MAX_UNDATED_FIXES:  # this receiver sends no date: seconds of day
                self._dateless = True
                held, self._undated = self._undated, []
                for f in held:
                    self._emit(f, out)
            return
        self._emit(fix, out)

    def _date_for(self, sod_s: float) -> _dt.date | None:
        """Date of an epoch from the last RMC date (a jump back of > 12 h is midnight)."""
        if self._date is None:
            return None
        date, ref_sod = self._date
        if sod_s < ref_sod - 43200.0:
            return date + _dt.timedelta(days=1)
        if sod_s > ref_sod + 43200.0:
            return date - _dt.timedelta(days=1)
        return date

    def _learn_date(self, date: _dt.date, sod_s: float, out: list[GnssFix]) -> None:
        self._date = (date, sod_s)
        if self._undated:
            held, self._undated = self._undated, []
            for f in held:
                self._emit(_replace_date(f, self._date_for(f.utc_sod_s)), out)

    def _emit(self, fix: GnssFix, out: list[GnssFix]) -> None:
        if fix.date is not None:
            days = (fix.date - _EPOCH_SECONDS).days
            t = days * 86400.0 + fix.utc_sod_s
        else:
            t = fix.utc_sod_s
        fix = _replace_time(fix, t)
        if self._last_time_s is not None:
            dt = t - self._last_time_s
            if dt > 0:
                self._min_dt_s = dt if self._min_dt_s is None else min(self._min_dt_s, dt)
                step = round(dt / self._min_dt_s)
                if step > 1:
                    self.stats.missed_epochs += step - 1
        self._last_time_s = t
        self.stats.fixes += 1
        out.append(fix)


def _replace_date(fix: GnssFix, date: _dt.date | None) -> GnssFix:
    return GnssFix(**{**fix.__dict__, "date": date})


def _replace_time(fix: GnssFix, time_s: float) -> GnssFix:
    return GnssFix(**{**fix.__dict__, "time_s": time_s})
