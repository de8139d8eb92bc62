"""Fault hooks: parse and check `NAME=VALUE` specs (times in device seconds) into one `Faults`.

Faults exist so that the drivers' handling of a misbehaving bench can be tested. An absent fault
changes nothing: each device draws its fault decisions from its own random stream, never from
the sensor models' streams, so the same seed gives the same bytes with and without `Faults()`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields


class FaultError(ValueError):
    """A fault spec the user got wrong; the message names the fault and says what to write."""


@dataclass(frozen=True)
class Faults:
    """Every fault the bench knows; None (or 0.0 for rates) means absent."""

    imu_crc_rate: float = 0.0
    """Probability per KVH message that its CRC is corrupted."""
    imu_drop_byte_rate: float = 0.0
    """Probability per KVH message that one of its bytes is lost on the line."""
    imu_invalid_rate: float = 0.0
    """Probability per KVH message that it is flagged invalid (built-in test): the valid bits of the
    unit's axes cleared, garbage in those fields, CRC and sequence intact."""
    imu_dialogue_rate: float = 0.0
    """Probability per KVH message that the unit's text output follows it on the line (echoes,
    query replies, INVALID lines, BIT messages), as a second terminal would cause; a new client
    also gets the power-up BIT message before its first frame."""
    imu_silence: tuple[float, float] | None = None
    """(start_s, duration_s): the IMU sends nothing in that window (its counter runs on)."""
    imu_disconnect: tuple[float, float] | None = None
    """(at_s, down_s): the IMU port vanishes at at_s and comes back down_s later on a new pty."""
    stage_stall: int | None = None
    """The N-th move (PA/PR, counted from 1 since start) stalls: following error, DISABLE."""
    accel_loss_rate: float = 0.0
    """Probability per CAN TPDO frame that it is lost."""
    accel_emcy: tuple[float, int] | None = None
    """(at_s, code): the CAN accelerometer sends an emergency (code 0x5000 unless given)."""
    accel_heartbeat_loss: float | None = None
    """Device time from which the CAN accelerometer sends no heartbeat."""
    accel_sdo_silent: float | None = None
    """Device time from which the CAN accelerometer answers no SDO request."""
    accel_start_lag: float | None = None
    """Device seconds from each NMT start to the CAN accelerometer's first sample (a sensor whose
    filter settles first, or a link that lags: its dwell then ends that much after the IMU's)."""
    disturbance: tuple[float, float, float] | None = None
    """(start_s, duration_s, amplitude_deg): a knock on the platform."""
    gnss_bad_checksum_rate: float = 0.0
    """Probability per NMEA sentence that its checksum is wrong (vehicle scenario)."""
    gnss_truncate_rate: float = 0.0
    """Probability per NMEA sentence that it is cut short before its checksum."""
    gnss_nofix: tuple[float, float] | None = None
    """(start_s, duration_s): the GNSS receiver reports no fix in that window."""

    @property
    def active(self) -> list[str]:
        """Names of the faults that are set, as on the command line."""
        out = []
        for f in fields(self):
            value = getattr(self, f.name)
            if value not in (None, 0.0):
                out.append(f.name.replace("_", "-"))
        return out

    def for_accel(self) -> dict[str, object]:
        """The accel-* faults as the CAN node's `faults` mapping (names as on the command line)."""
        out: dict[str, object] = {}
        if self.accel_loss_rate:
            out["accel-loss-rate"] = self.accel_loss_rate
        if self.accel_emcy is not None:
            out["accel-emcy"] = f"{self.accel_emcy[0]!r}:{self.accel_emcy[1]:#06x}"
        if self.accel_heartbeat_loss is not None:
            out["accel-heartbeat-loss"] = self.accel_heartbeat_loss
        if self.accel_sdo_silent is not None:
            out["accel-sdo-silent"] = self.accel_sdo_silent
        if self.accel_start_lag is not None:
            out["accel-start-lag"] = self.accel_start_lag
        return out


_DOC = {
    "imu-crc-rate": "a probability 0..1, e.g. imu-crc-rate=0.01",
    "imu-drop-byte-rate": "a probability 0..1, e.g. imu-drop-byte-rate=0.001",
    "imu-invalid-rate": "a probability 0..1 per KVH message, e.g. imu-invalid-rate=0.01",
    "imu-dialogue-rate": "a probability 0..1 per KVH message, e.g. imu-dialogue-rate=0.002",
    "imu-silence": "START_S:DURATION_S in device seconds, e.g. imu-silence=10:2",
    "imu-disconnect": "AT_S or AT_S:DOWN_S in device seconds, e.g. imu-disconnect=5:1",
    "stage-stall": "a move number counted from 1, e.g. stage-stall=2",
    "accel-loss-rate": "a probability 0..1, e.g. accel-loss-rate=0.01",
    "accel-emcy": "AT_S or AT_S:CODE (device seconds, CANopen code), e.g. accel-emcy=3:0x5000",
    "accel-heartbeat-loss": "AT_S in device seconds, e.g. accel-heartbeat-loss=4",
    "accel-sdo-silent": "AT_S in device seconds, e.g. accel-sdo-silent=0",
    "accel-start-lag": "LAG_S in device seconds after each NMT start, e.g. accel-start-lag=2",
    "disturbance": "START_S:DURATION_S:AMPLITUDE_DEG, e.g. disturbance=20:0.5:0.1",
    "gnss-bad-checksum-rate": "a probability 0..1 per NMEA sentence, e.g. gnss-bad-checksum-rate=0.01",
    "gnss-truncate-rate": "a probability 0..1 per NMEA sentence, e.g. gnss-truncate-rate=0.01",
    "gnss-nofix": "START_S:DURATION_S in device seconds, e.g. gnss-nofix=30:5",
}

DEFAULT_DISCONNECT_DOWN_S = 1.0


def _floats(name: str, text: str, n_min: int, n_max: int) -> list[float]:
    parts = str(text).split(":")
    if not n_min <= len(parts) <= n_max:
        raise FaultError(f"fault {name}={text}: expected {_DOC[name]}")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise FaultError(f"fault {name}={text}: expected {_DOC[name]}") from None
    if not all(math.isfinite(v) and v >= 0.0 for v in values):
        raise FaultError(f"fault {name}={text}: values must be finite and >= 0; expected {_DOC[name]}")
    return values


def _rate(name: str, text: object) -> float:
    (p,) = _floats(name, str(text), 1, 1)
    if p > 1.0:
        raise FaultError(f"fault {name}={text}: expected {_DOC[name]}")
    return p


def parse_fault(name: str, value: object) -> tuple[str, object]:
    """One fault: (field name in `Faults`, checked value). Raises FaultError naming it."""
    key = str(name).strip().lower().replace("_", "-")
    if key not in _DOC:
        known = ", ".join(sorted(_DOC))
        raise FaultError(f"unknown fault {name!r}; known faults: {known}")
    text = str(value).strip()
    if key in ("imu-crc-rate", "imu-drop-byte-rate", "imu-invalid-rate", "imu-dialogue-rate",
               "accel-loss-rate", "gnss-bad-checksum-rate", "gnss-truncate-rate"):
        parsed: object = _rate(key, text)
    elif key in ("imu-silence", "gnss-nofix"):
        start, dur = _floats(key, text, 2, 2)
        if key == "gnss-nofix" and dur <= 0.0:
            raise FaultError(f"fault {key}={text}: DURATION_S must be > 0; expected {_DOC[key]}")
        parsed = (start, dur)
    elif key == "imu-disconnect":
        vals = _floats(key, text, 1, 2)
        down = vals[1] if len(vals) > 1 else DEFAULT_DISCONNECT_DOWN_S
        if down <= 0.0:
            raise FaultError(f"fault {key}={text}: DOWN_S must be > 0; expected {_DOC[key]}")
        parsed = (vals[0], down)
    elif key == "stage-stall":
        try:
            index = int(text)
        except ValueError:
            raise FaultError(f"fault {key}={text}: expected {_DOC[key]}") from None
        if index < 1:
            raise FaultError(f"fault {key}={text}: expected {_DOC[key]}")
        parsed = index
    elif key == "accel-emcy":
        at_text, _, code_text = text.partition(":")
        (at_s,) = _floats(key, at_text, 1, 1)
        try:
            code = int(code_text, 0) if code_text else 0x5000
        except ValueError:
            raise FaultError(f"fault {key}={text}: expected {_DOC[key]}") from None
        if not 0 <= code <= 0xFFFF:
            raise FaultError(f"fault {key}={text}: CODE must fit 16 bits; expected {_DOC[key]}")
        parsed = (at_s, code)
    elif key in ("accel-heartbeat-loss", "accel-sdo-silent", "accel-start-lag"):
        (parsed,) = _floats(key, text, 1, 1)
    else:  # disturbance
        start, dur, amp = _floats(key, text, 3, 3)
        parsed = (start, dur, amp)
    return key.replace("-", "_"), parsed


def parse_faults(specs: Iterable[str] | Mapping[str, object] | Faults | None) -> Faults:
    """`["imu-silence=10:2", ...]` (the CLI) or `{"imu-silence": "10:2"}` (TOML) → Faults."""
    if specs is None:
        return Faults()
    if isinstance(specs, Faults):
        return specs
    items: list[tuple[str, object]] = []
    if isinstance(specs, Mapping):
        items = list(specs.items())
    else:
        for spec in specs:
            name, sep, value = str(spec).partition("=")
            if not sep or not value.strip():
                raise FaultError(f"fault {spec!r}: write NAME=VALUE, e.g. imu-silence=10:2")
            items.append((name, value))
    values = dict(parse_fault(name, value) for name, value in items)
    return Faults(**values)
