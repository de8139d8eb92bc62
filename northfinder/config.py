"""Bench configuration (`bench.toml`): parsing and validation.

One dataclass per table of the file. Every malformed or out-of-range value raises
:class:`northfinder.errors.ConfigError` with one line naming the key, the value and what is
allowed, so the CLI can print it without a traceback. See docs/bench.example.toml.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from northfinder.align.grades import IMU_GRADES
from northfinder.align.limits import latitude_problem
from northfinder.align.swaying import METHODS as SWAYING_METHODS
from northfinder.devices import registry
from northfinder.errors import ConfigError
from northfinder.estimators.heading import MAX_ABS_LATITUDE_DEG
from northfinder.estimators.plan import KINDS as PLAN_KINDS

METHODS = ("exact", "vector", "coordinate_transform", "uncompensated", "eq11")
ORDERS = ("sequential", "alternating")
RUN_PLANS = PLAN_KINDS
"""Kinds of turntable run `find` carries out, the ones northfinder.estimators.plan models: the
dwells only, every sample of the same stop-and-go schedule, or a sweep (rests at distinct angles
reached the long way round, whole turns in alternating directions; plan.sweep_targets_deg)."""
IMU_RATES_HZ = (1, 5, 10, 25, 50, 100, 250, 500, 750, 1000)
ROT_FORMATS = ("DELTA", "RATE")
ROT_UNITS = ("RAD", "DEG")
ALIGN_MODES = ("swaying", "gnss")
GNSS_ALIGN_MIN_DURATION_S = 10.0
"""The GNSS alignment's shortest window [device s]: 5 s of levelling standing still, then the drive."""
MAX_SWAY_PERIOD_S = 120.0
CAN_BITRATES = (10_000, 20_000, 50_000, 100_000, 125_000, 250_000, 500_000, 800_000, 1_000_000)


@dataclass
class TurntableConfig:
    """`[turntable]`: the SMC100 rotation stage."""

    model: str = "smc100"
    """The rotation stage's model (northfinder.devices.registry; a package may add its own)."""
    port: str = ""
    address: int = 1
    baudrate: int = 57600
    allow_home: bool = True
    """Home (`OR`) when the stage is NOT REFERENCED; if false such a stage is an error."""
    speed_deg_s: float = 0.0
    """The stage's slew speed [deg/s] (the SMC100 subset cannot ask it; `VA` is not in it). 0:
    unknown, then moves are bounded as if the stage turned at 1 deg/s (the slowest supported)."""
    settle_s: float = 5.0
    """Without a gyro z, the table counts as at rest this long after READY [device s]. Default:
    16 decay times of the 0.3 s ringing the bench shows (envelope below 1e-7 of its start)."""


@dataclass
class ImuConfig:
    """`[imu]`: the KVH format-A gyro/IMU."""

    model: str = "kvh"
    """The IMU's model (northfinder.devices.registry; a package may add its own)."""
    port: str = ""
    rate_hz: int = 1000
    baudrate: int = 921600
    rot_format: str = "DELTA"
    """Gyro field as the IMU is configured to send it (`?ROTFMT`): DELTA angle or RATE."""
    rot_units: str = "RAD"
    """Gyro units (`?ROTUNITS`): RAD or DEG."""
    grade: str = ""
    """align --mode gnss: the IMU class (nav, kvh1760, tactical-mems, consumer) whose data-sheet noise the
    filter then uses (align.grades.IMU_GRADES); empty: not known, conservative default noise."""


@dataclass
class AccelerometerConfig:
    """`[accelerometer]`: the CANopen accelerometer node (python-can interface/channel)."""

    model: str = "nf-accel"
    """The accelerometer (tilt sensor)'s model (northfinder.devices.registry; a package may add its own)."""
    interface: str = "slcan"
    channel: str = ""
    bitrate: int = 500_000
    node_id: int = 0x10
    rate_hz: float = 0.0
    """The sample rate written to the node over SDO at the start of a run; 0 (default) leaves the
    node's own rate, read back over SDO. The dwell is collected as dwell_s·rate samples."""
    eds: str = ""
    """The node's EDS file (default: northfinder's reference node, data/accelerometer.eds)."""
    rate_object: str = "2100:0"
    """The object that holds the rate: a manufacturer's rate in Hz (index:sub, hex), or a TPDO event
    timer such as 1800:5 (ms)."""
    heartbeat_ms: int = 1000
    """Producer heartbeat time written to 0x1017 at the start of a run (0: off — not advised)."""
    bus_options: dict[str, Any] = field(default_factory=dict)
    """Extra python-can bus arguments, e.g. `{sleep_after_open = 0.1}` for an slcan adapter that
    does not reset when its port opens (python-can waits 2 s by default)."""


@dataclass
class GnssConfig:
    """`[gnss]`: the NMEA receiver of `align --mode gnss` and what the filter assumes about it."""

    model: str = "nmea"
    """The GNSS receiver's model (northfinder.devices.registry; a package may add its own)."""
    port: str = ""
    baudrate: int = 115200
    lever_arm_m: tuple[float, float, float] | None = None
    """Antenna position in IMU body axes (x right, y forward, z up) [m], tape-measured."""
    lever_arm_std_m: float = 0.3
    """1σ of the tape-measured lever arm; without `lever_arm_m` the prior is 0 ± 1 m."""
    pos_std_m: tuple[float, float, float] = (0.5, 0.5, 1.0)
    vel_std_m_s: float = 0.05
    latency_s: float = 0.0
    """Receiver output latency (epoch → first byte) subtracted in the host time alignment."""


@dataclass
class SwayingConfig:
    """`[swaying]`: `align --mode swaying` (its flags --duration, --method, --sway-period override)."""

    duration_s: float = 300.0
    """The alignment window [device s]: 300 s gives ~0.05° with a navigation-grade IMU."""
    method: str = "cone"
    """cone (constrained fit), cone-gls (plus a noise-weighted step) or circle (docs/swaying.md §4)."""
    sway_period_s: float = 10.0
    """The longest sway period [s]: the smoothing window is 4 of them, the window must hold 8."""


@dataclass
class GnssAlignmentConfig:
    """`[gnss_alignment]`: `align --mode gnss` (--duration overrides)."""

    duration_s: float = 300.0
    """The alignment window [device s]: 5 s standing still for levelling, then the drive."""


@dataclass
class SiteConfig:
    """`[site]`: where the bench stands."""

    latitude_deg: float = float("nan")
    height_m: float = 0.0


@dataclass
class RunConfig:
    """`[run]`: the position plan, dwell and settle rule (device time throughout)."""

    positions: int = 8
    dwell_s: float = 30.0
    order: str = "sequential"
    plan: str = "positions+motion"
    """"positions": the dwell means only; "positions+motion": every gyro sample from the first dwell
    to the rest after the return (or the last dwell), each at its own table angle (needs a z gyro;
    otherwise the dwells, and the result says why) — docs/estimators.md §10."""
    start_deg: float = 0.0
    settle_window_s: float = 0.2
    """Length of one settle window of gyro-z samples [device s]."""
    settle_min_s: float = 0.4
    """Never start the dwell earlier than this after READY [device s]."""
    settle_max_s: float = 10.0
    """Start the dwell anyway (and say so in the events log) after this long [device s]."""
    settle_ratio: float = 0.8
    """Settled once a window's gyro-z spread is no longer below this fraction of the previous one."""
    settle_rest_dph: float = 360.0
    """…and its gyro-z mean is below this [deg/h] (the table is not turning; a slew is ~10⁵ deg/h)."""
    return_to_start: bool = True


@dataclass
class EstimatorConfig:
    """`[estimator]`: which heading method gives the reported heading."""

    method: str = "exact"


@dataclass
class BenchConfig:
    """The whole bench.toml."""

    turntable: TurntableConfig = field(default_factory=TurntableConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    accelerometer: AccelerometerConfig = field(default_factory=AccelerometerConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    swaying: SwayingConfig = field(default_factory=SwayingConfig)
    gnss_alignment: GnssAlignmentConfig = field(default_factory=GnssAlignmentConfig)
    site: SiteConfig = field(default_factory=SiteConfig)
    run: RunConfig = field(default_factory=RunConfig)
    estimator: EstimatorConfig = field(default_factory=EstimatorConfig)
    source: str = "<defaults>"

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of every table (what goes into the run directory's config.json)."""
        out = dataclasses.asdict(self)
        out.pop("source")
        return out

    def validate(self) -> BenchConfig:
        """Check every range; raise ConfigError naming the first bad key."""
        _validate(self)
        return self


_SECTIONS = {
    "turntable": TurntableConfig,
    "imu": ImuConfig,
    "accelerometer": AccelerometerConfig,
    "gnss": GnssConfig,
    "swaying": SwayingConfig,
    "gnss_alignment": GnssAlignmentConfig,
    "site": SiteConfig,
    "run": RunConfig,
    "estimator": EstimatorConfig,
}


def _bad(key: str, value: Any, allowed: str, source: str) -> ConfigError:
    return ConfigError(f"{source}: {key} = {value!r} is not allowed; {allowed}")


_TRIPLES = {("gnss", "lever_arm_m"), ("gnss", "pos_std_m")}
"""Keys that hold three numbers [x, y, z] (a TOML array)."""


def _triple(key: str, value: Any, source: str) -> tuple[float, float, float]:
    if not (
        isinstance(value, list | tuple)
        and len(value) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value)
    ):
        raise _bad(key, value, "use three numbers [x, y, z] in metres", source)
    return (float(value[0]), float(value[1]), float(value[2]))


def _coerce(section: str, name: str, value: Any, default: Any, source: str) -> Any:
    key = f"[{section}] {name}"
    if (section, name) in _TRIPLES:
        return _triple(key, value, source)
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise _bad(key, value, "use true or false", source)
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise _bad(key, value, "use a whole number", source)
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise _bad(key, value, "use a number", source)
        return float(value)
    if isinstance(default, dict):
        if not isinstance(value, dict):
            raise _bad(key, value, "use an inline table, e.g. {sleep_after_open = 0.1}", source)
        return dict(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise _bad(key, value, "use a quoted string", source)
        return value
    return value  # pragma: no cover - every field has a typed default


RETIRED_KEYS = {"imu": ("link_timeout_s",)}
"""Keys older bench files and run directories (config.json) hold that no longer mean anything,
read and ignored: `[imu] link_timeout_s` made host silence a pause of the IMU stream; a pause is now
decided from the bytes alone (a gap whose bytes never came)."""


def from_dict(data: dict[str, Any], source: str = "<dict>") -> BenchConfig:
    """Build and validate a BenchConfig from parsed TOML; unknown tables or keys are errors."""
    cfg = BenchConfig(source=source)
    for section, body in data.items():
        if section not in _SECTIONS:
            raise ConfigError(f"{source}: unknown table [{section}]; allowed: {', '.join(_SECTIONS)}")
        if not isinstance(body, dict):
            raise ConfigError(f"{source}: {section} must be a table [{section}]")
        target = getattr(cfg, section)
        names = {f.name for f in dataclasses.fields(target)}
        for name, value in body.items():
            if name in RETIRED_KEYS.get(section, ()):
                continue
            if name not in names:
                raise ConfigError(
                    f"{source}: unknown key [{section}] {name}; allowed: {', '.join(sorted(names))}"
                )
            if value is None and getattr(target, name) is None:
                continue  # an optional key left out (to_dict writes it as null into config.json)
            setattr(target, name, _coerce(section, name, value, getattr(target, name), source))
    return cfg.validate()


def load(path: str | Path) -> BenchConfig:
    """Read and validate a bench.toml; a missing file or a TOML syntax error names file and line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such configuration file; see docs/bench.example.toml") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the configuration file ({exc.strerror})") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: TOML syntax error: {exc}") from None
    return from_dict(data, source=str(p))


def _validate(cfg: BenchConfig) -> None:
    s = cfg.source

    def need(ok: bool, key: str, value: Any, allowed: str) -> None:
        if not ok:
            raise _bad(key, value, allowed, s)

    _validate_devices(cfg, need)
    _validate_site_run(cfg, need)
    _validate_align(cfg, need)


def _validate_devices(cfg: BenchConfig, need: Callable[[bool, str, Any, str], None]) -> None:
    """The ranges of [turntable], [imu] and [accelerometer]."""
    t, i, a = cfg.turntable, cfg.imu, cfg.accelerometer
    for role in registry.ROLES:
        name = getattr(cfg, role).model
        if not registry.is_builtin(role, name):  # the installed packages are read only for another
            models = registry.available(role)
            need(name in models, f"[{role}] model", name,
                 f"use one of {', '.join(models)} (or install its package)")
    need(1 <= t.address <= 31, "[turntable] address", t.address, "use 1…31")
    need(t.baudrate > 0, "[turntable] baudrate", t.baudrate, "use a positive baud rate")
    need(math.isfinite(t.speed_deg_s) and t.speed_deg_s >= 0, "[turntable] speed_deg_s", t.speed_deg_s,
         "use the stage's speed in deg/s, or 0 when unknown")
    need(math.isfinite(t.settle_s) and t.settle_s >= 0, "[turntable] settle_s", t.settle_s, "use 0 s or more")
    need(
        i.rate_hz in IMU_RATES_HZ,
        "[imu] rate_hz",
        i.rate_hz,
        f"use one of {', '.join(map(str, IMU_RATES_HZ))}",
    )
    need(i.baudrate > 0, "[imu] baudrate", i.baudrate, "use a positive baud rate")
    need(
        bool(a.interface),
        "[accelerometer] interface",
        a.interface,
        "name a python-can interface (slcan, socketcan, virtual, …)",
    )
    need(
        a.bitrate in CAN_BITRATES,
        "[accelerometer] bitrate",
        a.bitrate,
        f"use one of {', '.join(map(str, CAN_BITRATES))}",
    )
    need(1 <= a.node_id <= 127, "[accelerometer] node_id", a.node_id, "use 1…127")
    need(
        math.isfinite(a.rate_hz) and 0 <= a.rate_hz <= 1000,
        "[accelerometer] rate_hz",
        a.rate_hz,
        "use a rate in Hz up to 1000, or 0 to keep the node's own",
    )
    need(_is_object(a.rate_object), "[accelerometer] rate_object", a.rate_object,
         "name an object as INDEX:SUB in hex, e.g. 2100:0 or 1800:5")
    need(0 <= a.heartbeat_ms <= 0xFFFF, "[accelerometer] heartbeat_ms", a.heartbeat_ms, "use 0…65535")


def _validate_site_run(cfg: BenchConfig, need: Callable[[bool, str, Any, str], None]) -> None:
    """The ranges of [site] (the turntable find's latitude limit), [run] and [estimator]."""
    site, r, e = cfg.site, cfg.run, cfg.estimator
    lim = MAX_ABS_LATITUDE_DEG
    if not math.isnan(site.latitude_deg):
        need(
            -lim <= site.latitude_deg <= lim,
            "[site] latitude_deg",
            site.latitude_deg,
            f"use −{lim:g}…{lim:g} (north positive; within {90 - lim:g}° of a pole the heading is undefined)",
        )
    need(
        math.isfinite(site.height_m) and -500.0 <= site.height_m <= 10_000.0,
        "[site] height_m",
        site.height_m,
        "use −500…10000 m",
    )
    need(r.positions >= 3, "[run] positions", r.positions, "use at least 3 positions")
    need(r.positions <= 360, "[run] positions", r.positions, "use at most 360 positions")
    need(
        math.isfinite(r.dwell_s) and r.dwell_s > 0, "[run] dwell_s", r.dwell_s, "use a dwell greater than 0 s"
    )
    need(r.order in ORDERS, "[run] order", r.order, f"use one of {', '.join(ORDERS)}")
    need(r.plan in RUN_PLANS, "[run] plan", r.plan, f"use one of {', '.join(RUN_PLANS)}")
    need(
        math.isfinite(r.start_deg) and -360.0 <= r.start_deg <= 360.0,
        "[run] start_deg",
        r.start_deg,
        "use −360…360",
    )
    need(r.settle_window_s > 0, "[run] settle_window_s", r.settle_window_s, "use a window greater than 0 s")
    need(r.settle_min_s >= 0, "[run] settle_min_s", r.settle_min_s, "use 0 s or more")
    need(
        r.settle_max_s >= r.settle_min_s,
        "[run] settle_max_s",
        r.settle_max_s,
        f"use at least settle_min_s = {r.settle_min_s}",
    )
    need(0.0 < r.settle_ratio < 1.0, "[run] settle_ratio", r.settle_ratio, "use a fraction between 0 and 1")
    need(
        math.isfinite(r.settle_rest_dph) and r.settle_rest_dph > 0,
        "[run] settle_rest_dph",
        r.settle_rest_dph,
        "use a rate greater than 0 deg/h",
    )
    need(e.method in METHODS, "[estimator] method", e.method, f"use one of {', '.join(METHODS)}")


def _validate_align(cfg: BenchConfig, need: Callable[[bool, str, Any, str], None]) -> None:
    """The ranges of what only `align` reads: the IMU's gyro format and the `[gnss]` table."""
    i, g = cfg.imu, cfg.gnss
    formats, units = ", ".join(ROT_FORMATS), ", ".join(ROT_UNITS)
    need(i.rot_format in ROT_FORMATS, "[imu] rot_format", i.rot_format, f"use one of {formats}")
    need(i.rot_units in ROT_UNITS, "[imu] rot_units", i.rot_units, f"use one of {units}")
    need(not i.grade or i.grade in IMU_GRADES, "[imu] grade", i.grade,
         f"use one of {', '.join(IMU_GRADES)}, or leave it out (conservative default noise)")
    need(g.baudrate > 0, "[gnss] baudrate", g.baudrate, "use a positive baud rate")
    for key, v in (("[gnss] lever_arm_std_m", g.lever_arm_std_m), ("[gnss] vel_std_m_s", g.vel_std_m_s)):
        need(math.isfinite(v) and v > 0, key, v, "use a number greater than 0")
    need(all(v > 0 for v in g.pos_std_m), "[gnss] pos_std_m", list(g.pos_std_m), "use three σ greater than 0")
    need(math.isfinite(g.latency_s) and 0 <= g.latency_s < 1, "[gnss] latency_s", g.latency_s, "use 0 … 1 s")
    sw, ga = cfg.swaying, cfg.gnss_alignment
    methods, p_max, d_min = ", ".join(SWAYING_METHODS), MAX_SWAY_PERIOD_S, GNSS_ALIGN_MIN_DURATION_S
    need(sw.method in SWAYING_METHODS, "[swaying] method", sw.method, f"use one of {methods}")
    need(math.isfinite(sw.sway_period_s) and 0 < sw.sway_period_s <= p_max, "[swaying] sway_period_s",
         sw.sway_period_s, f"give the longest sway period in seconds (0 … {p_max:g})")
    need(math.isfinite(sw.duration_s) and sw.duration_s > 0, "[swaying] duration_s", sw.duration_s,
         "use a window greater than 0 s (at least 8 sway periods)")
    need(math.isfinite(ga.duration_s) and ga.duration_s >= d_min, "[gnss_alignment] duration_s",
         ga.duration_s, f"use at least {d_min:g} device seconds")


def accel_eds_path(cfg: BenchConfig) -> Path | None:
    """`[accelerometer] eds`, relative to the bench file's folder; None: the reference node's EDS."""
    eds = cfg.accelerometer.eds
    if not eds:
        return None
    path = Path(eds).expanduser()
    source = Path(cfg.source)
    if not path.is_absolute() and source.is_file():
        path = source.parent / path
    return path


def _is_object(text: str) -> bool:
    index, sep, sub = text.partition(":")
    try:
        return bool(sep) and 0 < int(index, 16) <= 0xFFFF and 0 <= int(sub, 16) <= 0xFF
    except ValueError:
        return False


def require_ports(cfg: BenchConfig) -> None:
    """For a real-hardware run: every device must have a port, and no two the same one."""
    if not cfg.turntable.port:
        raise ConfigError(f"{cfg.source}: [turntable] port is missing; give the stage's serial port")
    if not cfg.imu.port:
        raise ConfigError(f"{cfg.source}: [imu] port is missing; give the IMU's serial port")
    if not cfg.accelerometer.channel:
        raise ConfigError(f"{cfg.source}: [accelerometer] channel is missing; give the CAN channel")
    if math.isnan(cfg.site.latitude_deg):
        raise ConfigError(f"{cfg.source}: [site] latitude_deg is missing; give the bench's latitude")
    ports = {"[turntable] port": cfg.turntable.port, "[imu] port": cfg.imu.port}
    if cfg.accelerometer.interface == "slcan":
        ports["[accelerometer] channel"] = cfg.accelerometer.channel
    seen: dict[str, str] = {}
    for key, port in ports.items():
        if port in seen:
            raise ConfigError(
                f"{cfg.source}: {key} = {port!r} is also {seen[port]}; each device needs its own port"
            )
        seen[port] = key


def require_align(cfg: BenchConfig, mode: str, latitude_deg: float | None = None) -> float:
    """For a real-hardware `align --mode MODE` run: the ports it reads (the IMU; the GNSS receiver
    for gnss, on its own port) and, for swaying, the site latitude inside the align estimators'
    range (`latitude_deg`, from --latitude, overrides [site]). Returns the latitude (NaN for gnss,
    which takes its position from the receiver)."""
    s = cfg.source
    if not cfg.imu.port:
        raise ConfigError(f"{s}: [imu] port is missing; give the IMU's serial port")
    if mode == "gnss":
        if not cfg.gnss.port:
            raise ConfigError(f"{s}: [gnss] port is missing; give the GNSS receiver's serial port")
        if cfg.gnss.port == cfg.imu.port:
            raise ConfigError(
                f"{s}: [imu] port and [gnss] port are both {cfg.imu.port}; give each its own port"
            )
        return float("nan")
    if latitude_deg is not None:
        return float(latitude_deg)  # the CLI checked --latitude with the same words
    lat = cfg.site.latitude_deg
    if math.isnan(lat):
        raise ConfigError(
            f"{s}: [site] latitude_deg is missing; give the site's latitude (or --latitude DEG)"
        )
    problem = latitude_problem(lat)
    if problem:
        raise _bad("[site] latitude_deg", lat, problem, s)
    return lat


def position_plan_deg(n: int, start_deg: float = 0.0, order: str = "sequential") -> list[float]:
    """Table angles α_i = α_0 + (i−1)·360°/n in the visiting order.

    `sequential` visits them in increasing angle; `alternating` visits 0, 180°, 90°, 270°-style
    opposite pairs so that a linear bias drift does not alias into the cos/sin harmonic.
    Angles stay inside the stage's default soft limits (−360°, +360°).
    """
    base = [start_deg + k * 360.0 / n for k in range(n)]
    if order == "sequential":
        return base
    if n % 2 == 0:  # opposite pairs k, k + n/2 interleaved
        half = n // 2
        return [base[k + j * half] for k in range(half) for j in (0, 1)]
    return base[0::2] + base[1::2]
