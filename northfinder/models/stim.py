"""Safran Sensonor STIM300/STIM318 in Normal Mode (docs/PROTOCOLS.md §7, STIM300 datasheet TS1524
rev.31) as an :class:`InertialStream`; the bytes are `northfinder.codecs.stim`, the start-up and the
role mapping docs/second-models.md "Sensonor STIM IMU".

Start-up: `SERVICEMODE` → the listing (TS1524 §8.7, Figure 8-1): product, serial and part number,
sample rate, output units and accelerometer range, datagram; `x N` back to Normal Mode (§9.14).
Everything the port delivers goes to the raw log; what follows the listing goes through one
:class:`StimStream` (live and in replay alike, from the recorded `stream_from_byte`), which turns
the datagrams' counter into a device sample index: the counter counts the unit's 2000 Hz internal
samples (§7.5.2.2.18), so a datagram steps it by 2000/rate and a gap
is exact while it is shorter than the counter's period; a gap whose datagrams' bytes never came
(a silence, the service-mode pause) may hide whole periods and is *unknown*. A datagram whose CRC
fails is skipped (counted) and is an exact gap of one. Per-axis validity is the STATUS bytes'
(Table 5-23): a flagged field is NaN.
"""

from __future__ import annotations

import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from northfinder.codecs import stim
from northfinder.devices.imu import ImuAxes, ImuBlock, ImuDecoder, InertialStream
from northfinder.devices.registry import ModelSpec
from northfinder.drivers._stream import SampleQueue, StreamReader, read_bounds
from northfinder.errors import DeviceError, InputError
from northfinder.models._section import value
from northfinder.transport import SerialTransport

DEVICE = "imu"
LISTING_KEYS = ("PRODUCT", "SERIAL NUMBER", "PART NUMBER", "GYRO OUTPUT UNIT", "ACCELEROMETER OUTPUT UNIT",
                "SAMPLE RATE [SAMPLES/S]")
LISTING_QUIET_S = 0.2
"""Host seconds without a byte that end the service-mode listing once its keys are there (the
unit sends no datagram in Service Mode, TS1524 §8)."""
_RANGE = re.compile(r"±\s*(\d+)\s*g", re.IGNORECASE)
_LISTING_KEYS_KNOWN = ("SERIAL NUMBER", "PRODUCT", "PART NUMBER", "FW CONFIG", "GYRO OUTPUT UNIT",
                       "ACCELEROMETER OUTPUT UNIT", "INCLINOMETER OUTPUT UNIT", "SAMPLE RATE", "DATAGRAM",
                       "ACCELEROMETER RANGE")


def listing_text(raw: bytes) -> str:
    """The listing out of what arrived after SERVICEMODE: datagrams still in flight (or left in the
    port's buffer by an earlier session) run into its first line, so a line that holds a key of
    TS1524 Figure 8-1 starts at that key."""
    lines = raw.decode("utf-8", "replace").replace("\r", "\n").split("\n")
    out = []
    for line in lines:
        found = [k for k in (line.find(key) for key in _LISTING_KEYS_KNOWN) if k >= 0]
        out.append(line[min(found):] if found else line)
    return "\n".join(out)


@dataclass(frozen=True)
class StimConfig:
    """What the decoder must know, from the listing: datagram id, output units, rate."""

    datagram_id: int
    gyro: str
    accel: str
    accel_range_g: int
    rate_hz: int

    @property
    def units(self) -> stim.StimUnits:
        return stim.StimUnits(gyro=self.gyro, accel=self.accel, accel_range_g=self.accel_range_g)

    def as_dict(self) -> dict[str, Any]:
        return {"datagram_id": self.datagram_id, "gyro_unit": self.gyro, "accel_unit": self.accel,
                "accel_range_g": self.accel_range_g, "rate_hz": float(self.rate_hz)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StimConfig:
        return cls(int(d["datagram_id"]), str(d["gyro_unit"]), str(d["accel_unit"]), int(d["accel_range_g"]),
                   int(round(float(d["rate_hz"]))))


def config_from_listing(text: str) -> tuple[stim.StimIdentity, StimConfig]:
    """The listing → identity and decoder configuration; ValueError naming what cannot be decoded."""
    ident = stim.identity_from_listing(text)
    kv = ident.extra
    gyro_text = kv.get("GYRO OUTPUT UNIT", "").upper()
    acc_text = kv.get("ACCELEROMETER OUTPUT UNIT", "").upper()
    if "INCREMENTAL ANGLE" in gyro_text:
        gyro = "increment"
    elif "ANGULAR RATE" in gyro_text and "AVERAGE" not in gyro_text:
        gyro = "rate"
    else:
        raise ValueError(f"gyro output unit {gyro_text!r}: set INCREMENTAL ANGLE or ANGULAR RATE")
    if "INCREMENTAL VELOCITY" in acc_text:
        accel = "increment"
    elif "ACCELERATION" in acc_text and "AVERAGE" not in acc_text:
        accel = "acceleration"
    else:
        raise ValueError(f"accelerometer output unit {acc_text!r}: set INCREMENTAL VELOCITY or ACCELERATION")
    ranges = {int(m) for m in _RANGE.findall(text)}
    if len(ranges) != 1 or next(iter(ranges)) not in stim.ACC_LSB_PER_G:
        raise ValueError(f"accelerometer range {sorted(ranges) or 'not listed'}: one of "
                         f"{sorted(stim.ACC_LSB_PER_G)} g on every axis")
    rate = ident.sample_rate_hz
    if rate not in stim.SAMPLE_RATES_HZ:
        raise ValueError(f"sample rate {rate}: one of {stim.SAMPLE_RATES_HZ} (TS1524 Table 5-11)")
    dg = kv.get("DATAGRAM", "0x93")
    try:
        datagram_id = int(dg, 16)
    except ValueError:
        raise ValueError(f"datagram {dg!r}: give it as its identifier (0x90…0xF7)") from None
    if datagram_id not in stim.DATAGRAM_CONTENT:
        raise ValueError(f"datagram 0x{datagram_id:02X}: not a normal-mode datagram (TS1524 Table 5-21)")
    return ident, StimConfig(datagram_id, gyro, accel, next(iter(ranges)), int(rate))


class StimStream:
    """Bytes → (device sample index, samples), chunk by chunk, the same live and in replay."""

    def __init__(self, cfg: StimConfig) -> None:
        self.cfg = cfg
        self.decoder = stim.StimDecoder(cfg.datagram_id, cfg.units, cfg.rate_hz)
        self.step = stim.INTERNAL_RATE_HZ // cfg.rate_hz
        self.period = 256 // self.step
        """Datagrams after which the counter wraps."""
        self.size = self.decoder.size
        self._last: tuple[int, int, int] | None = None  # (index, counter, byte offset)
        self.lost_samples = 0
        self.gaps = 0
        self.unknown_gaps: list[int] = []
        self.invalid = np.zeros(6, dtype=np.int64)
        """Samples flagged not valid per axis (gyro x y z, accelerometer x y z: STATUS, Table 5-23)."""

    def feed(self, data: bytes) -> tuple[np.ndarray, stim.StimSamples]:
        s = self.decoder.feed(data)
        n = len(s)
        if n == 0:
            return np.empty(0, dtype=np.int64), s
        counter, offset = s.counter.astype(np.int64), s.byte_offset.astype(np.int64)
        if self._last is None:
            i0, c0, o0 = counter[0] // self.step - 1, counter[0] - self.step, offset[0] - self.size
        else:
            i0, c0, o0 = self._last
        prev_c = np.concatenate(([c0], counter[:-1]))
        prev_o = np.concatenate(([o0], offset[:-1]))
        steps = ((counter - prev_c) % 256) // self.step
        steps[steps == 0] = self.period
        index = i0 + np.cumsum(steps)
        missing_bytes = offset - prev_o - self.size
        unknown = missing_bytes < (steps - 1) * self.size  # bytes of lost datagrams never came
        self.unknown_gaps.extend(int(k) for k in index[unknown])
        self.lost_samples += int(np.sum(steps - 1))
        self.gaps += int(np.count_nonzero(steps > 1))
        self._last = (int(index[-1]), int(counter[-1]), int(offset[-1]))
        self.invalid += np.count_nonzero(~np.hstack([s.valid(0), s.valid(1)]), axis=0)
        return index, s

    def stats(self) -> dict[str, int]:
        """The decoder's counters, and the stream counters under the names the run's faults use
        (frames, bad_crc, resyncs, sequence_gaps, lost_samples, skipped_bytes, invalid_<axis>)."""
        d = self.decoder.stats
        axes = ("gx", "gy", "gz", "ax", "ay", "az")
        return {**d.as_dict(), "frames": d.datagrams, "bad_crc": d.crc_errors, "resyncs": d.crc_errors,
                "sequence_gaps": self.gaps, "lost_samples": self.lost_samples,
                "unknown_gaps": len(self.unknown_gaps),
                **{f"invalid_{a}": int(v) for a, v in zip(axes, self.invalid, strict=True)}}


def samples_to_block(index: np.ndarray, s: stim.StimSamples, cfg: StimConfig,
                     unknown_gaps: Sequence[int] = ()) -> ImuBlock:
    """Decoded datagrams → ImuBlock: gyro [rad/s], accelerometer [g], NaN where STATUS flags it."""
    dt = 1.0 / cfg.rate_hz
    gyro = np.radians(s.gyro) / (dt if cfg.gyro == "increment" else 1.0)
    accel = s.accel / (dt * stim.STANDARD_GRAVITY_M_S2) if cfg.accel == "increment" else s.accel.copy()
    gyro[~s.valid(0)] = np.nan
    accel[~s.valid(1)] = np.nan
    lost = int(np.sum(np.diff(index) - 1)) if len(index) > 1 else 0
    return ImuBlock(sample_index=np.asarray(index, dtype=np.int64), gyro_rad_s=gyro, accel_g=accel,
                    status=(s.status[:, 0] | s.status[:, 1]).astype(np.uint8),
                    temperature_c=np.full(len(index), np.nan), lost_samples=lost, rate_hz=float(cfg.rate_hz),
                    unknown_gaps=tuple(int(k) for k in unknown_gaps))


class StimImu(SampleQueue, StreamReader, InertialStream):
    """A STIM in Normal Mode on a pyserial URL; a context manager with a background reader."""

    device = DEVICE

    def __init__(self, port: str, *, baudrate: int = 921600, raw_log: str | Path | None = None,
                 timeout_s: float = 5.0) -> None:
        super().__init__(port, timeout_s)
        self._text = bytearray()
        self._stream: StimStream | None = None
        self._pending: list[tuple[np.ndarray, stim.StimSamples]] = []
        self._pending_n = 0
        self._stalls: list[int] = []
        self._unknown_seen = 0
        self._t = SerialTransport(port, device=DEVICE, baudrate=baudrate, timeout_s=0.05, raw_log=raw_log)
        self._start_reader()
        try:
            self.ident, self.cfg = self._service_listing()
            self.rate_hz = float(self.cfg.rate_hz)
            with self._cond:  # the stream starts after the listing (replay: `stream_from_byte`)
                self._stream = StimStream(self.cfg)
                self.stream_from_byte = len(self._text)
            self._t.write(stim.EXIT_TO_NORMAL_COMMAND)
            self._wait_first()
        except BaseException:
            self.close()
            raise

    # -- start-up ----------------------------------------------------------------------------
    def _service_listing(self) -> tuple[stim.StimIdentity, StimConfig]:
        self._t.write(stim.SERVICE_MODE_COMMAND)
        deadline = time.monotonic() + self.timeout_s
        with self._cond:
            while True:
                text = listing_text(bytes(self._text))
                kv = stim.parse_service_listing(text)
                if all(k in kv for k in LISTING_KEYS) and time.monotonic() - self._last_rx >= LISTING_QUIET_S:
                    break
                if time.monotonic() > deadline:
                    raise DeviceError(DEVICE, self.port, "no STIM service-mode listing within "
                                      f"{self.timeout_s:g} s after SERVICEMODE — is it a Sensonor STIM on "
                                      "this port, at its bit rate?")
                self._cond.wait(0.05)
        try:
            return config_from_listing(text)
        except ValueError as exc:
            raise DeviceError(DEVICE, self.port, f"the STIM's configuration cannot be decoded: {exc} "
                              "(service mode; TS1524 §9)") from None

    def _wait_first(self) -> None:
        with self._cond:
            self._wait_locked(lambda: self._pending_n > 0, self.timeout_s,
                              lambda: f"no STIM datagram with a good CRC on {self.port} within "
                              f"{self.timeout_s:g} s after `x N` — is the unit in Normal Mode?")

    # -- reader ------------------------------------------------------------------------------
    _last_rx = 0.0

    def _on_bytes(self, data: bytes) -> None:
        self._last_rx = time.monotonic()
        if self._stream is None:  # the listing (and any datagram before it): not data
            self._text += data
            return
        self._feed(data)

    def _feed(self, data: bytes) -> None:
        assert self._stream is not None
        index, s = self._stream.feed(data)
        unknown = self._stream.unknown_gaps
        if len(unknown) > self._unknown_seen:
            self._stalls.extend(unknown[self._unknown_seen:])
            self._unknown_seen = len(unknown)
        if not len(index):
            return
        self._pending.append((index, s))
        self._pending_n += len(index)
        self._newest_index = int(index[-1])

    # -- the role ----------------------------------------------------------------------------
    def read(self, n_samples: int, timeout_s: float | None = None) -> ImuBlock:
        n, wait_s = read_bounds(n_samples, self.rate_hz, self.timeout_s, timeout_s)
        with self._cond:
            self._wait_locked(lambda: self._pending_n >= n, wait_s,
                              lambda: f"only {self._pending_n} of {n} samples arrived within {wait_s:g} s on "
                              f"{self.port} — is the STIM still streaming (cable, left in Service Mode)?")
            taken = self._take_pending(n, _take)
            index = np.concatenate([c[0] for c in taken])
            gaps = [k for k in self._stream.unknown_gaps if index[0] <= k <= index[-1]]  # type: ignore[union-attr]
        return samples_to_block(index, _concat([c[1] for c in taken]), self.cfg, gaps)

    @property
    def failed(self) -> BaseException | None:
        with self._cond:
            return self._error

    @property
    def stall_indices(self) -> list[int]:
        with self._cond:
            return list(self._stalls)

    @property
    def axes(self) -> ImuAxes:
        acc = bool(stim.DATAGRAM_CONTENT[self.cfg.datagram_id] & stim.ACC)
        return ImuAxes((True, True, True, acc, acc, acc))

    @property
    def stats(self) -> Any:
        with self._cond:
            return _Stats(self._stream.stats() if self._stream else {})

    def identity(self) -> dict[str, Any]:
        return {"model": "stim", "unit": self.ident.describe(), "rate_hz": self.rate_hz}

    def recorded_settings(self) -> dict[str, Any]:
        return {**self.cfg.as_dict(), "stream_from_byte": self.stream_from_byte}

    def configure_for_run(self, rate_hz: float | None) -> None:
        """The rate is the unit's (its listing); another asked for is a one-line error."""
        if rate_hz is not None and float(rate_hz) != self.rate_hz:
            raise DeviceError(DEVICE, self.port, f"the STIM sends {self.rate_hz:g} samples/s (its "
                              f"service-mode listing), [imu] rate_hz asks {float(rate_hz):g}: set rate_hz = "
                              f"{self.rate_hz:g} (the rate is the unit's configuration, TS1524 §9)")

    def check_line(self) -> str:
        block = self.read(max(2, int(self.rate_hz // 10)), timeout_s=3.0)
        st = self._stream.stats() if self._stream else {}
        c = self.cfg
        return (f"imu on {self.port}: {self.ident.describe()}; {c.rate_hz} samples/s, datagram "
                f"0x{c.datagram_id:02X}, gyro {c.gyro}, accelerometer {c.accel} ±{c.accel_range_g} g; "
                f"{self.axes.describe()}; {len(block)} samples read, {st.get('crc_errors', 0)} bad CRC, "
                f"{st.get('lost_samples', 0)} lost")

    def close(self) -> None:
        self._stop_reader()
        self._t.close()


@dataclass
class _Stats:
    counters: dict[str, int]

    def as_dict(self) -> dict[str, int]:
        return dict(self.counters)


def _take(s: stim.StimSamples, a: int, b: int) -> stim.StimSamples:
    return stim.StimSamples(s.gyro[a:b], s.accel[a:b], s.incl[a:b], s.status[a:b], s.counter[a:b],
                            s.latency_us[a:b], s.byte_offset[a:b])


def _concat(parts: list[stim.StimSamples]) -> stim.StimSamples:
    if len(parts) == 1:
        return parts[0]
    return stim.StimSamples(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                              ("gyro", "accel", "incl", "status", "counter", "latency_us", "byte_offset")))


class StimLogDecoder(ImuDecoder):
    """imu.raw of a STIM run → samples (the live driver's StimStream and conversion: bit-identical)."""

    counter_period = 0
    """0: the STIM's counter period depends on the recorded rate (256·rate/2000 datagrams), which this
    class attribute cannot say; the align runs' clock placement (index_chunks, first_counter with
    counter_period) does not take a STIM yet — only the turntable find does."""

    def decode_log(self, raw: bytes, settings: dict[str, Any]) -> tuple[ImuBlock, Any]:
        cfg = StimConfig.from_dict(settings)
        stream = StimStream(cfg)
        index, s = stream.feed(raw[int(settings.get("stream_from_byte", 0)):])
        return samples_to_block(index, s, cfg, stream.unknown_gaps), _Stats(stream.stats())

    def index_chunks(self, chunks: Sequence[bytes]) -> list[np.ndarray]:
        raise InputError("align runs do not take a STIM IMU yet (its raw log is decoded with the run's "
                         "recorded settings); use it with northfinder find")

    def first_counter(self, raw: bytes) -> int:
        for dg_id in stim.DATAGRAM_CONTENT:
            s = stim.StimDecoder(dg_id).feed(raw[: 1 << 16])
            if len(s):
                return int(s.counter[0])
        raise InputError("imu.raw holds no STIM datagram")


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> StimImu:
    return StimImu(value(section, "port", ""), baudrate=value(section, "baudrate", 921600), raw_log=log_path,
                   timeout_s=options.get("timeout_s", 5.0))


SPEC = ModelSpec("imu", "stim", _open, StimLogDecoder, "Sensonor STIM300/STIM318, normal-mode datagrams")
