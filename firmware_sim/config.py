"""The bench's settings: `SimConfig`, loaded from TOML (same keys) and checked with clear errors.

Degrees, seconds and metres at this edge (suffixes in the names); the simulator converts.
An example with every key: firmware_sim/data/example.toml.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from firmware_sim.faults import FaultError, Faults, parse_faults

IMU_VARIANTS = ("gyro-1axis", "gyro-3axis", "gyro-accel")
IMU_RATES_HZ = (1, 5, 10, 25, 50, 100, 250, 500, 750, 1000)
CAN_INTERFACES = ("slcan", "virtual", "socketcan")
GRADES = ("nav", "kvh1760", "tactical-mems", "consumer")
"""The sensor presets of docs/ARCHITECTURE.md (firmware_sim/physics/sensors.py), named here so that a
wrong name is refused before the physics (and scipy) is imported."""


class ConfigError(ValueError):
    """A setting the user got wrong; the message names the key and says what to write."""


@dataclass
class SimConfig:
    """Everything the bench needs; every field is also a TOML key."""

    heading_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    latitude_deg: float = 45.0
    height_m: float = 0.0
    grade: str = "nav"
    """Gyro + accelerometer preset: nav, kvh1760, tactical-mems, consumer."""
    seed: int = 0
    time_scale: float = 1.0
    # IMU (KVH format A)
    imu_variant: str = "gyro-accel"
    imu_rate_hz: int = 1000
    imu_rot_format: str = "DELTA"
    imu_rot_units: str = "RAD"
    imu_temperature_c: float = 25.0
    imu_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # turntable (SMC100)
    stage_address: int = 1
    stage_power_on_deg: float | None = None
    """Table angle at power-on, before homing (unknown to the host)."""
    stage_speed_dps: float | None = None
    stage_accel_dps2: float | None = None
    stage_home_speed_dps: float | None = None
    stage_ringing_deg: float | None = None
    """Ringing amplitude after a stop from full deceleration."""
    stage_ringing_hz: float | None = None
    stage_ringing_decay_s: float | None = None
    encoder_step_deg: float | None = None
    """None: the physics' default for each stage setting."""
    # CAN accelerometer
    can_interface: str = "slcan"
    """slcan (adapter on a pty, default) | virtual (in-process; give can_channel) | socketcan."""
    can_channel: str | None = None
    can_bitrate: int = 500000
    can_node_id: int = 0x10
    accel_rate_hz: float = 100.0
    accel_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    accel_enabled: bool = True
    # platform motion and faults
    sway: dict[str, Any] | None = None
    """Swaying base, passed to the physics' World (e.g. amplitudes and periods per axis)."""
    faults: Faults = field(default_factory=Faults)

    def __post_init__(self) -> None:
        check(self)


def _number(key: str, value: Any, *, integer: bool = False) -> float | int:
    if isinstance(value, bool) or not isinstance(value, int | float | str):
        raise ConfigError(f"{key} = {value!r}: give a number")
    try:
        out = int(value) if integer else float(value)
    except ValueError:
        raise ConfigError(f"{key} = {value!r}: give a{'n integer' if integer else ' number'}") from None
    if integer and float(value) != out:
        raise ConfigError(f"{key} = {value!r}: give an integer")
    if not math.isfinite(out):
        raise ConfigError(f"{key} = {value!r}: give a finite number")
    return out


def check(cfg: SimConfig) -> None:
    """Coerce and check every field in place; ConfigError names the first bad key."""
    for f in fields(cfg):
        value = getattr(cfg, f.name)
        t = str(f.type)
        if f.name == "faults":
            try:
                cfg.faults = parse_faults(value)
            except FaultError as exc:
                raise ConfigError(str(exc)) from None
        elif f.name == "sway":
            if value is not None and not isinstance(value, Mapping):
                raise ConfigError(f"sway = {value!r}: give a table, e.g. [sway] with amplitudes and periods")
        elif t.startswith("tuple"):
            if not isinstance(value, list | tuple) or len(value) != 3:
                raise ConfigError(f"{f.name} = {value!r}: give three numbers [x, y, z] in metres")
            setattr(cfg, f.name, tuple(float(_number(f.name, v)) for v in value))
        elif t.startswith("float"):
            if value is not None or "None" not in t:
                setattr(cfg, f.name, float(_number(f.name, value)))
        elif t == "int":
            setattr(cfg, f.name, int(_number(f.name, value, integer=True)))
        elif t == "bool":
            if not isinstance(value, bool):
                raise ConfigError(f"{f.name} = {value!r}: give true or false")
        elif t.startswith("str"):
            if value is not None and not isinstance(value, str):
                raise ConfigError(f"{f.name} = {value!r}: give a string")
    if cfg.grade not in GRADES:
        raise ConfigError(f"grade = {cfg.grade!r}: use one of {', '.join(GRADES)}")
    if not -90.0 <= cfg.latitude_deg <= 90.0:
        raise ConfigError(f"latitude_deg = {cfg.latitude_deg}: give a latitude in [-90, 90] degrees")
    if not -90.0 < cfg.pitch_deg < 90.0:
        raise ConfigError(f"pitch_deg = {cfg.pitch_deg}: give a pitch in (-90, 90) degrees")
    if cfg.time_scale <= 0.0:
        raise ConfigError(f"time_scale = {cfg.time_scale}: give a factor > 0 (1 = real time)")
    if cfg.imu_variant not in IMU_VARIANTS:
        raise ConfigError(f"imu_variant = {cfg.imu_variant!r}: use one of {', '.join(IMU_VARIANTS)}")
    if cfg.imu_rate_hz not in IMU_RATES_HZ:
        raise ConfigError(f"imu_rate_hz = {cfg.imu_rate_hz}: use one of {IMU_RATES_HZ}")
    cfg.imu_rot_format = cfg.imu_rot_format.upper()
    cfg.imu_rot_units = cfg.imu_rot_units.upper()
    if cfg.imu_rot_format not in ("DELTA", "RATE"):
        raise ConfigError(f"imu_rot_format = {cfg.imu_rot_format!r}: use DELTA or RATE")
    if cfg.imu_rot_units not in ("RAD", "DEG"):
        raise ConfigError(f"imu_rot_units = {cfg.imu_rot_units!r}: use RAD or DEG")
    if not 1 <= cfg.stage_address <= 31:
        raise ConfigError(f"stage_address = {cfg.stage_address}: give an SMC100 address 1..31")
    if cfg.can_interface not in CAN_INTERFACES:
        raise ConfigError(f"can_interface = {cfg.can_interface!r}: use one of {', '.join(CAN_INTERFACES)}")
    if cfg.can_interface in ("virtual", "socketcan") and not cfg.can_channel:
        example = "vcan0" if cfg.can_interface == "socketcan" else "bench"
        raise ConfigError(f"can_channel is required with can_interface = {cfg.can_interface!r}, "
                          f"e.g. can_channel = {example!r}")
    if not 1 <= cfg.can_node_id <= 127:
        raise ConfigError(f"can_node_id = {cfg.can_node_id}: give a CANopen node id 1..127")
    if cfg.accel_rate_hz <= 0.0:
        raise ConfigError(f"accel_rate_hz = {cfg.accel_rate_hz}: give a rate > 0")
    for name in ("stage_speed_dps", "stage_accel_dps2", "stage_home_speed_dps", "stage_ringing_hz",
                 "encoder_step_deg"):
        value = getattr(cfg, name)
        if value is not None and value <= 0.0:
            raise ConfigError(f"{name} = {value}: give a value > 0 (or leave it out for the default)")


KEYS = tuple(f.name for f in fields(SimConfig))


def config_from_mapping(data: Mapping[str, Any], *, source: str = "config",
                        base: SimConfig | None = None) -> SimConfig:
    """Keys as SimConfig's; `faults` a list of NAME=VALUE or a table. Unknown keys are an error."""
    unknown = [k for k in data if k not in KEYS]
    if unknown:
        raise ConfigError(f"{source}: unknown key {unknown[0]!r}; known keys: {', '.join(KEYS)}")
    values = dict(data)
    if base is not None:
        return replace(base, **values)
    return SimConfig(**values)


def load_toml(path: str | Path) -> dict[str, Any]:
    """Read a TOML file; ConfigError names the file and what is wrong."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"config file {p} does not exist; give the path of a .toml file") from None
    except OSError as exc:
        raise ConfigError(f"config file {p}: cannot read it ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {p}: not valid TOML ({exc})") from None
