"""KVH 1750/1760/1775 format A (docs/PROTOCOLS.md §2) as an :class:`InertialStream`: the driver
`northfinder.drivers.imu.Imu`, the bytes `northfinder.codecs.kvh`."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from northfinder.codecs.kvh import KvhDecoder, decode_imu_stream
from northfinder.devices.imu import ImuBlock, ImuDecoder, InertialStream
from northfinder.devices.registry import ModelSpec
from northfinder.drivers.imu import Imu
from northfinder.errors import DeviceError, InputError
from northfinder.models._section import value


class KvhImu(Imu, InertialStream):
    """The KVH in the inertial-stream role."""

    gyro_range_dps = 490.0  # ±490 °/s, the 1750/1760/1775 data sheets (align.swaying.KVH_GYRO_RANGE_DPS)

    def identity(self) -> dict[str, Any]:
        return {"model": "kvh", "axes": self.axes.describe(), "rate_hz": self.rate_hz}

    def recorded_settings(self) -> dict[str, Any]:
        return {"rate_hz": self.rate_hz, "rot_format": self.rot_format, "rot_units": self.rot_units}

    def configure_for_run(self, rate_hz: float | None) -> None:
        """Read the rate and gyro format back (the decoder must know them); set the rate if asked."""
        self.configure()
        if rate_hz is not None and float(rate_hz) != self.rate_hz:
            self.configure(rate_hz=rate_hz)

    def check_line(self) -> str:
        """Rate and format read back, a tenth of a second of data, the axes from the status bits."""
        rate, fmt, units = self.query("DR"), self.query("ROTFMT"), self.query("ROTUNITS")
        block = self.read(max(2, int(self.rate_hz // 10)), timeout_s=3.0)
        axes, stats = self.axes, self.stats
        if "y" not in axes.gyro:
            raise DeviceError("imu", self.port, f"{axes.describe()} (status bits): north finding needs a "
                              "gyro y, or x and y — is it the right unit, mounted y along the table plane?")
        settle = "settles by gyro z" if "z" in axes.gyro else "no gyro z: READY + [turntable] settle_s"
        bit, bit_source = self.built_in_test()  # the power-up BIT message, else ?BIT (manual §7)
        return (
            f"imu on {self.port}: {rate} Hz, format A, {fmt} {units}; {axes.describe()} ({settle}); "
            f"{len(block.sample_index)} samples read, {stats.bad_crc} bad CRC, {stats.lost_samples} lost; "
            f"{bit_source} {bit.describe()}"
        )

    def reopen(self, timeout_s: float) -> int:
        return self.reconnect(timeout_s=timeout_s)


class KvhLogDecoder(ImuDecoder):
    """imu.raw of a KVH run → samples (the live driver's decoder and conversion: bit-identical)."""

    counter_period = 128
    counter_name = "7-bit sequence"

    def decode_log(self, raw: bytes, settings: dict[str, Any]) -> tuple[ImuBlock, Any]:
        return decode_imu_stream(raw, settings["rate_hz"], settings.get("rot_format", "DELTA"),
                                 settings.get("rot_units", "RAD"))

    def index_chunks(self, chunks: Sequence[bytes]) -> list[np.ndarray]:
        dec = KvhDecoder()
        return [dec.feed(chunk).sample_index for chunk in chunks]

    def first_counter(self, raw: bytes) -> int:
        out = KvhDecoder().feed(raw[: 1 << 16])
        if not len(out):
            raise InputError("imu.raw holds no format-A frame")
        return int(out.frames["sequence"][0])


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> KvhImu:
    kwargs = {k: options[k] for k in ("rate_hz", "rot_format", "rot_units", "transport") if k in options}
    if "transport" not in kwargs:
        kwargs["raw_log"] = log_path
    return KvhImu(value(section, "port", ""), baudrate=value(section, "baudrate", 921600),
                  timeout_s=options.get("timeout_s", 10.0), **kwargs)  # ≥ 10 s host time: a loaded host


SPEC = ModelSpec("imu", "kvh", _open, KvhLogDecoder, "KVH 1750/1760/1775, format A")
