"""The bench's settings: `SimConfig`, loaded from TOML (same keys) and checked with clear errors.

Degrees, seconds and metres at this edge (suffixes in the names); the simulator converts.
An example with every key: firmware_sim/data/example.toml.

Three scenarios (`scenario`): `bench` (turntable + IMU + CAN accelerometer, the default),
`ship` (the IMU alone on a swaying base, at a lever arm from the centre of rotation) and
`vehicle` (IMU + GNSS receiver on a driving car). A key left as None takes its scenario's
default (`SCENARIO_DEFAULTS`); `check` fills it in, so a checked config has no None there.
"""

from __future__ import annotations

import datetime as dt
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from firmware_sim.faults import FaultError, Faults, parse_faults

IMU_VARIANTS = ("gyro-1axis", "gyro-3axis", "gyro-accel")
IMU_AXES_ALIASES = {"gyro-1axis": "y", "gyro-3axis": "xyz", "gyro-accel": "xyz+acc"}
"""The old `imu_variant` names, still accepted for `imu_axes` (and as the `imu_variant` key)."""
IMU_AXES_HELP = "gyro axis letters then optional +acc, e.g. xyz+acc (default), xyz, y, xy, xy+acc"
IMU_RATES_HZ = (1, 5, 10, 25, 50, 100, 250, 500, 750, 1000)
CAN_INTERFACES = ("slcan", "virtual", "socketcan")
GRADES = ("nav", "kvh1760", "tactical-mems", "consumer", "stim300")
SCENARIOS = ("bench", "ship", "vehicle")
SWAY_AXES = ("roll", "pitch", "yaw", "surge", "sway", "heave")
"""roll, pitch, yaw in degrees; surge (along the mean heading), sway (to its right), heave (up) in m."""
REFERENCE_SWAY: dict[str, list[list[float]]] = {
    "roll": [[10.0, 8.0]], "pitch": [[5.0, 6.0]], "yaw": [[3.0, 10.0]], "heave": [[0.5, 7.0]],
}
"""The swaying-base paper's reference: roll 10°/8 s, pitch 5°/6 s, yaw 3°/10 s, heave 0.5 m/7 s."""
SCENARIO_DEFAULTS: dict[str, dict[str, Any]] = {
    "bench": {"latitude_deg": 45.0, "imu_rate_hz": 1000, "imu_lever_arm_m": (0.0, 0.0, 0.0)},
    "ship": {"latitude_deg": 40.0, "imu_rate_hz": 1000, "imu_lever_arm_m": (1.0, 2.0, 1.5)},
    "vehicle": {"latitude_deg": 40.0, "imu_rate_hz": 250, "imu_lever_arm_m": (0.0, 0.0, 0.0)},
}
STAGE_RIPPLE_PCT = 0.5
"""The bench stage's speed ripple, % of the move speed (our choice; docs/simulator.md)."""
STAGE_RIPPLE_PERIOD_DEG = 4.0
"""Table angle per worm turn (a 90:1 worm): the ripple's period, v/4° Hz (5 Hz at 20 °/s)."""
STAGE_WOBBLE_URAD = (20.0, 5.0)
"""The bench stage's wobble, once and twice per turn, µrad (our choice; docs/simulator.md)."""
GNSS_RATES_HZ = (1, 5, 10)
"""The sensor presets of docs/ARCHITECTURE.md (firmware_sim/physics/sensors.py), named here so that a
wrong name is refused before the physics is imported."""


class ConfigError(ValueError):
    """A setting the user got wrong; the message names the key and says what to write."""


@dataclass
class SimConfig:
    """Everything the bench needs; every field is also a TOML key."""

    scenario: str = "bench"
    """bench | ship | vehicle."""
    heading_deg: float = 0.0
    """Platform heading (bench), mean heading (ship), initial heading (vehicle)."""
    pitch_deg: float = 0.0
    roll_deg: float = 0.0
    latitude_deg: float | None = None
    """None: 45 for the bench, 40 for the ship and the vehicle."""
    height_m: float = 0.0
    grade: str = "nav"
    """Gyro + accelerometer preset: nav, kvh1760, tactical-mems, consumer."""
    seed: int = 0
    time_scale: float = 1.0
    # IMU (KVH format A)
    imu_axes: str = "xyz+acc"
    """The KVH unit's axes: gyro letters, then +acc if it has accelerometers (IMU_AXES_HELP)."""
    imu_variant: str | None = None
    """Old name of imu_axes (gyro-1axis | gyro-3axis | gyro-accel); folded into imu_axes by check."""
    imu_rate_hz: int | None = None
    """None: 1000 Hz (bench, ship) or 250 Hz (vehicle)."""
    imu_rot_format: str = "DELTA"
    imu_rot_units: str = "RAD"
    imu_temperature_c: float = 25.0
    imu_lever_arm_m: tuple[float, float, float] | None = None
    """IMU position in b from the centre of rotation; None: (1, 2, 1.5) m for the ship, else 0."""
    # the USB-serial links of the IMU and GNSS ptys (firmware_sim/link.py)
    imu_link_latency_ms: float = 0.0
    """Each IMU message leaves the pty this long (device ms) after it was produced."""
    imu_link_jitter_ms: float = 0.0
    """± uniform jitter on that latency (device ms, <= the latency; order is kept)."""
    gnss_link_latency_ms: float = 0.0
    gnss_link_jitter_ms: float = 0.0
    link_hold_period_s: float | None = None
    """Every this many device seconds the IMU and GNSS links hold their bytes back; None: never."""
    link_hold_ms: float = 0.0
    """How long each hold lasts, in HOST WALL-CLOCK ms; then the held bytes leave in one burst."""
    link_hold_jitter_s: float = 0.0
    """± uniform jitter on each hold period (device s, seeded)."""
    client_stall_wall_s: float = 1.0
    """How long (HOST WALL-CLOCK s) a connected IMU client may stop reading before bytes are dropped:
    it sizes the IMU pty's backlog (a host-side UART overrun loses bytes when its reader stalls)."""
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
    stage_ripple_pct: float | None = None
    """Speed ripple during a move, % of the speed (STAGE_RIPPLE_PCT); 0: off."""
    stage_ripple_period_deg: float | None = None
    """Table angle per worm turn, the ripple's period (STAGE_RIPPLE_PERIOD_DEG)."""
    stage_wobble_urad: Any = None
    """Bearing wobble of the top, µrad: once per turn, or [once, twice, …] per turn (STAGE_WOBBLE_URAD);
    0: off."""
    # gyro terms a moving table shows (None: the grade's preset; 0: off)
    gyro_sf_asymmetry_ppm: Any = None
    """Scale-factor asymmetry (S₊ − S₋)/S, ppm: one number or [x, y, z]."""
    gyro_g_sensitivity_dph_g: Any = None
    """g-sensitivity of the bias, °/h/g: one number or [x, y, z] (diagonal), or 9 (row-major 3×3)."""
    gyro_misalignment_rad: Any = None
    """δ: tilt of the x and y gyros' input axes toward the table axis z, rad: one number or [δx, δy]."""
    # CAN accelerometer
    can_interface: str = "slcan"
    """slcan (adapter on a pty, default) | virtual (in-process; give can_channel) | socketcan."""
    can_channel: str | None = None
    can_bitrate: int = 500000
    can_node_id: int = 0x10
    accel_rate_hz: float = 100.0
    accel_mapping: str = "default"
    """The node's TPDO mapping: default (PROTOCOLS.md §3) or swapped (axes reordered, 0.1 µg)."""
    accel_lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    accel_enabled: bool = True
    # platform motion and faults
    sway: dict[str, Any] | None = None
    """Swaying base: per axis a list of [amplitude, period_s(, phase_deg)]. None: no sway on the
    bench, the reference sway (REFERENCE_SWAY) on the ship; {} a still ship. The ship's terms
    without a phase get one drawn from the seed; the bench's default to 0."""
    # GNSS receiver (vehicle)
    gnss_rate_hz: int = 10
    gnss_lever_arm_m: tuple[float, float, float] = (0.5, 1.5, 1.2)
    """Antenna position in b from the IMU."""
    gnss_start_utc: str = "2026-11-22T12:00:00Z"
    """UTC of device time 0 in the NMEA sentences (ISO 8601, whole centiseconds)."""
    longitude_deg: float = 116.3
    # truth log
    truth_log: str | None = None
    """Path of the JSON-lines truth log (docs/simulator.md); None: none."""
    truth_rate_hz: float = 50.0
    """Truth samples per device second."""
    # the model of each role (issue 24): the same physical world under any combination
    stage_model: str = "smc100"
    """smc100 (Newport, PROTOCOLS.md §1) | apt (Thorlabs KDC101 + PRM1-Z8, §6)."""
    imu_model: str = "kvh"
    """kvh (format A, §2) | stim (Sensonor STIM300/318 normal mode, §7)."""
    tilt_model: str = "nf-accel"
    """nf-accel (our CANopen accelerometer, §3) | cia410 (CiA 410 inclinometer, §8)."""
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
        elif value is None and "None" in t:
            continue
        elif t.startswith("tuple"):
            if not isinstance(value, list | tuple) or len(value) != 3:
                raise ConfigError(f"{f.name} = {value!r}: give three numbers [x, y, z] in metres")
            setattr(cfg, f.name, tuple(float(_number(f.name, v)) for v in value))
        elif t.startswith("float"):
            if value is not None or "None" not in t:
                setattr(cfg, f.name, float(_number(f.name, value)))
        elif t.startswith("int"):
            setattr(cfg, f.name, int(_number(f.name, value, integer=True)))
        elif t == "bool":
            if not isinstance(value, bool):
                raise ConfigError(f"{f.name} = {value!r}: give true or false")
        elif t.startswith("str"):
            if value is not None and not isinstance(value, str):
                raise ConfigError(f"{f.name} = {value!r}: give a string")
    if cfg.scenario not in SCENARIOS:
        raise ConfigError(f"scenario = {cfg.scenario!r}: use one of {', '.join(SCENARIOS)}")
    for key, value in SCENARIO_DEFAULTS[cfg.scenario].items():
        if getattr(cfg, key) is None:
            setattr(cfg, key, value)
    if cfg.scenario == "ship" and cfg.sway is None:
        cfg.sway = {axis: [list(term) for term in terms] for axis, terms in REFERENCE_SWAY.items()}
    if cfg.sway is not None:
        check_sway(cfg.sway)
        if cfg.scenario == "vehicle" and cfg.sway:
            raise ConfigError("sway: the vehicle scenario drives its own trajectory; give sway only "
                              "with scenario = 'bench' or 'ship'")
    if cfg.grade not in GRADES:
        raise ConfigError(f"grade = {cfg.grade!r}: use one of {', '.join(GRADES)}")
    if not -90.0 <= cfg.latitude_deg <= 90.0:
        raise ConfigError(f"latitude_deg = {cfg.latitude_deg}: give a latitude in [-90, 90] degrees")
    if not -90.0 < cfg.pitch_deg < 90.0:
        raise ConfigError(f"pitch_deg = {cfg.pitch_deg}: give a pitch in (-90, 90) degrees")
    if cfg.time_scale <= 0.0:
        raise ConfigError(f"time_scale = {cfg.time_scale}: give a factor > 0 (1 = real time)")
    check_imu_axes(cfg)
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
    if not 1.0 <= cfg.accel_rate_hz <= 1000.0 or cfg.accel_rate_hz != int(cfg.accel_rate_hz):
        raise ConfigError(f"accel_rate_hz = {cfg.accel_rate_hz}: give a whole rate in 1…1000 Hz (0x2100)")
    if cfg.accel_mapping not in ("default", "swapped"):
        raise ConfigError(f"accel_mapping = {cfg.accel_mapping!r}: use default or swapped")
    if cfg.gnss_rate_hz not in GNSS_RATES_HZ:
        raise ConfigError(f"gnss_rate_hz = {cfg.gnss_rate_hz}: use one of {GNSS_RATES_HZ}")
    gnss_start(cfg)
    if not cfg.truth_rate_hz > 0.0:
        raise ConfigError(f"truth_rate_hz = {cfg.truth_rate_hz}: give a rate > 0 samples per device second")
    if cfg.truth_log is not None and not cfg.truth_log.strip():
        raise ConfigError("truth_log = '': give the path of a file to write, or leave it out")
    check_links(cfg)
    check_motion(cfg)
    check_models(cfg)
    for name in ("stage_speed_dps", "stage_accel_dps2", "stage_home_speed_dps", "stage_ringing_hz",
                 "encoder_step_deg"):
        value = getattr(cfg, name)
        if value is not None and value <= 0.0:
            raise ConfigError(f"{name} = {value}: give a value > 0 (or leave it out for the default)")


_MOTION_SIZES = {"stage_wobble_urad": (1, 2, 3, 4), "gyro_sf_asymmetry_ppm": (1, 3),
                 "gyro_g_sensitivity_dph_g": (1, 3, 9), "gyro_misalignment_rad": (1, 2)}


def check_motion(cfg: SimConfig) -> None:
    """The motion-error keys: lists of finite numbers of an allowed length, folded to tuples."""
    for name, sizes in _MOTION_SIZES.items():
        value = getattr(cfg, name)
        if value is None:
            continue
        items = list(value) if isinstance(value, list | tuple) else [value]
        if len(items) not in sizes:
            raise ConfigError(f"{name} = {value!r}: give {' or '.join(map(str, sizes))} numbers")
        setattr(cfg, name, tuple(float(_number(name, v)) for v in items))
    for name in ("stage_ripple_pct", "stage_ripple_period_deg"):
        value = getattr(cfg, name)
        if value is not None and (value < 0.0 or (name.endswith("deg") and value == 0.0)):
            raise ConfigError(f"{name} = {value}: give a value {'> 0' if name.endswith('deg') else '>= 0'} "
                              "(or leave it out for the default)")
    if cfg.stage_ripple_pct is not None and cfg.stage_ripple_pct >= 50.0:
        raise ConfigError(f"stage_ripple_pct = {cfg.stage_ripple_pct}: a ripple is a few % of the speed; "
                          "give less than 50")


def parse_imu_axes(spec: str) -> tuple[str, bool]:
    """`"xy+acc"` → ("xy", True); an old variant name maps through IMU_AXES_ALIASES.

    Gyro letters are any of x, y, z, each at most once (returned in x, y, z order)."""
    text = IMU_AXES_ALIASES.get(str(spec).strip().lower(), str(spec).strip().lower())
    gyro, sep, acc = text.partition("+")
    letters = "".join(a for a in "xyz" if a in gyro)
    if (not gyro or len(letters) != len(gyro) or (sep and acc != "acc")):
        raise ConfigError(f"imu_axes = {spec!r}: give {IMU_AXES_HELP}")
    return letters, bool(sep)


def check_imu_axes(cfg: SimConfig) -> None:
    """Normalize imu_axes; fold the old imu_variant key into it (a clash is an error)."""
    if not isinstance(cfg.imu_axes, str):
        raise ConfigError(f"imu_axes = {cfg.imu_axes!r}: give {IMU_AXES_HELP}")
    gyro, acc = parse_imu_axes(cfg.imu_axes)
    axes = gyro + ("+acc" if acc else "")
    if cfg.imu_variant is not None:
        if cfg.imu_variant not in IMU_VARIANTS:
            raise ConfigError(f"imu_variant = {cfg.imu_variant!r}: use one of {', '.join(IMU_VARIANTS)} "
                              f"(or imu_axes: {IMU_AXES_HELP})")
        old = IMU_AXES_ALIASES[cfg.imu_variant]
        if axes not in ("xyz+acc", old):
            raise ConfigError(f"imu_variant = {cfg.imu_variant!r} and imu_axes = {cfg.imu_axes!r} disagree; "
                              "give only imu_axes")
        axes, cfg.imu_variant = old, None
    cfg.imu_axes = axes


def check_links(cfg: SimConfig) -> None:
    """Latency and jitter >= 0 with jitter <= latency; a hold needs a period > 0 and a length > 0;
    a client stall > 0 s."""
    if not cfg.client_stall_wall_s > 0.0:
        raise ConfigError(f"client_stall_wall_s = {cfg.client_stall_wall_s}: give a stall > 0 wall s")
    for dev in ("imu", "gnss"):
        lat, jit = getattr(cfg, f"{dev}_link_latency_ms"), getattr(cfg, f"{dev}_link_jitter_ms")
        if lat < 0.0 or jit < 0.0 or jit > lat:
            raise ConfigError(f"{dev}_link_latency_ms = {lat}, {dev}_link_jitter_ms = {jit}: give a latency "
                              ">= 0 and a jitter between 0 and the latency (device ms)")
    if cfg.link_hold_period_s is None:
        if cfg.link_hold_ms:
            raise ConfigError(f"link_hold_ms = {cfg.link_hold_ms} needs link_hold_period_s (device s)")
        return
    if not cfg.link_hold_period_s > 0.0 or not cfg.link_hold_ms > 0.0:
        raise ConfigError(f"link_hold_period_s = {cfg.link_hold_period_s}, link_hold_ms = "
                          f"{cfg.link_hold_ms}: give a period > 0 device s and a hold > 0 wall ms")
    if not 0.0 <= cfg.link_hold_jitter_s < cfg.link_hold_period_s:
        raise ConfigError(f"link_hold_jitter_s = {cfg.link_hold_jitter_s}: give 0 <= jitter < "
                          f"link_hold_period_s ({cfg.link_hold_period_s})")


def check_sway(spec: Mapping[str, Any]) -> None:
    """Axis names, and terms [amplitude, period_s(, phase_deg)] of finite numbers with period_s > 0."""
    for axis, terms in spec.items():
        if axis not in SWAY_AXES:
            raise ConfigError(f"sway.{axis}: unknown axis; use {', '.join(SWAY_AXES)}")
        if not isinstance(terms, list | tuple):
            raise ConfigError(f"sway.{axis}: give a list of [amplitude, period_s(, phase_deg)]")
        for term in terms:
            try:
                if isinstance(term, Mapping):
                    values = [term["amplitude"], term["period_s"], term.get("phase_deg", 0.0)]
                else:
                    values = list(term)
                if not 2 <= len(values) <= 3 or any(isinstance(v, bool) for v in values):
                    raise ValueError
                numbers = [float(v) for v in values]
            except (KeyError, TypeError, ValueError):
                raise ConfigError(
                    f"sway.{axis}: term {term!r} is not [amplitude, period_s(, phase_deg)]") from None
            if not all(math.isfinite(v) for v in numbers):
                raise ConfigError(f"sway.{axis}: term {term!r} must hold finite numbers")
            if not numbers[1] > 0.0:
                raise ConfigError(f"sway.{axis}: period_s must be > 0 in {term!r}")


def gnss_start(cfg: SimConfig) -> dt.datetime:
    """`gnss_start_utc` as an aware datetime; ConfigError if it is not ISO 8601 in whole centiseconds."""
    text = cfg.gnss_start_utc
    try:
        start = dt.datetime.fromisoformat(str(text).strip())
    except ValueError:
        raise ConfigError(f"gnss_start_utc = {text!r}: give an ISO 8601 UTC time, "
                          "e.g. \"2026-11-22T12:00:00Z\"") from None
    if start.tzinfo is None:
        start = start.replace(tzinfo=dt.UTC)
    if start.microsecond % 10_000:
        raise ConfigError(f"gnss_start_utc = {text!r}: give whole centiseconds (NMEA time resolution)")
    return start.astimezone(dt.UTC)


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


STAGE_MODELS = ("smc100", "apt")
IMU_MODELS = ("kvh", "stim")
TILT_MODELS = ("nf-accel", "cia410")
STIM_RATES_HZ = (125, 250, 500, 1000, 2000)


def check_models(cfg: SimConfig) -> None:
    """The model names of the three roles, and what each model allows (docs/PROTOCOLS.md §6–8)."""
    roles = (("stage_model", STAGE_MODELS), ("imu_model", IMU_MODELS), ("tilt_model", TILT_MODELS))
    for key, allowed in roles:
        if getattr(cfg, key) not in allowed:
            raise ConfigError(f"{key} = {getattr(cfg, key)!r}: use one of {', '.join(allowed)}")
    if cfg.imu_model == "stim" and cfg.imu_rate_hz is not None and cfg.imu_rate_hz not in STIM_RATES_HZ:
        raise ConfigError(f"imu_rate_hz = {cfg.imu_rate_hz}: a STIM samples at one of {STIM_RATES_HZ}")
    if cfg.tilt_model == "cia410" and 1000.0 / cfg.accel_rate_hz != int(1000.0 / cfg.accel_rate_hz):
        raise ConfigError(f"accel_rate_hz = {cfg.accel_rate_hz}: a CiA 410 node's event timer is whole ms; "
                          "give 1000 / N Hz")
