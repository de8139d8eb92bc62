"""An NMEA 0183 receiver (GGA/RMC/VTG; docs/PROTOCOLS.md §4) as a :class:`GnssReceiver`: the driver
`northfinder.drivers.gnss.Gnss`, the bytes `northfinder.codecs.nmea`."""

from __future__ import annotations

import re
from typing import Any

import numpy as np

from northfinder.codecs.nmea import checksum
from northfinder.devices.gnss import GnssDecoder, GnssReceiver
from northfinder.devices.registry import ModelSpec
from northfinder.drivers.gnss import Gnss, decode_nmea_log
from northfinder.models._section import value

_GGA = re.compile(rb"\$(..GGA,(\d\d)(\d\d)(\d\d(?:\.\d+)?),[^*\r\n$]*)\*([0-9A-Fa-f]{2})")


class NmeaGnss(Gnss, GnssReceiver):
    """An NMEA receiver in the GNSS role."""

    def identity(self) -> dict[str, Any]:
        return {"model": "nmea"}


class NmeaLogDecoder(GnssDecoder):
    def decode_log(self, raw: bytes) -> tuple[list[Any], Any]:
        return decode_nmea_log(raw)

    def epoch_ends(self, raw: bytes, utc_ref_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(byte offset just past each good GGA, its UTC − utc_ref_s): the first sentence of each epoch.

        GGA carries the time of day only: the day comes from `utc_ref_s` (the nearest one), so an
        epoch is placed within ±12 h of the reference. Checksums are verified (a corrupted time
        would fake an early arrival)."""
        ends, times = [], []
        ref_sod = utc_ref_s % 86400.0
        for m in _GGA.finditer(raw):
            if checksum(m.group(1)) != int(m.group(5), 16):
                continue
            sod = int(m.group(2)) * 3600 + int(m.group(3)) * 60 + float(m.group(4))
            ends.append(m.end())
            times.append((sod - ref_sod + 43200.0) % 86400.0 - 43200.0)
        return np.asarray(ends, dtype=np.int64), np.asarray(times, dtype=float)


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> NmeaGnss:
    kwargs = {"transport": options["transport"]} if "transport" in options else {"raw_log": log_path}
    return NmeaGnss(value(section, "port", ""), baudrate=value(section, "baudrate", 115200),
                    timeout_s=options.get("timeout_s", 5.0), **kwargs)


SPEC = ModelSpec("gnss", "nmea", _open, NmeaLogDecoder, "NMEA 0183 receiver (GGA, RMC, VTG)")
