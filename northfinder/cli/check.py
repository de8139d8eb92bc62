"""`northfinder check --config bench.toml`: probe each device and say what answered.

One line per device, the model's own (devices.registry: the stage's version and state, the IMU's
rate and format and that data flows, the accelerometer's heartbeat state and identity) with the
model's name; one clear line for each device that did not answer.
Exit 0 only if every device answered.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from northfinder import config as bench
from northfinder.devices import registry
from northfinder.errors import ConfigError, DeviceError, NorthfinderError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check", help="probe the turntable, the IMU and the accelerometer of a bench", description=__doc__
    )
    p.add_argument("--config", metavar="BENCH_TOML", required=True, help="bench configuration")
    p.set_defaults(func=run)


def probe(role: str) -> Callable[[bench.BenchConfig], str]:
    """The probe of a role: open the section's model (registry), ask its check line, name the model."""

    def fn(cfg: bench.BenchConfig) -> str:
        section = getattr(cfg, role)
        options = {"eds_path": bench.accel_eds_path(cfg)} if role == "accelerometer" else {}
        with registry.open_device(role, section, None, **options) as device:
            return f"{device.check_line()} [model {device.model_name}]"

    return fn


def _probe(
    what: str, port: str, fn: Callable[[bench.BenchConfig], str], cfg: bench.BenchConfig
) -> tuple[bool, str]:
    if not port:
        return False, f"{what}: no port in {cfg.source}; set it and run check again"
    import can

    try:
        return True, fn(cfg)
    except NorthfinderError as exc:
        return False, str(exc)
    except (OSError, can.CanError) as exc:
        return False, f"{what} on {port}: cannot open it ({exc}); check the port in {cfg.source}"


def run(args: argparse.Namespace) -> int:
    cfg = bench.load(args.config)
    ports = [p for p in (cfg.turntable.port, cfg.imu.port) if p]
    if len(set(ports)) < len(ports):
        raise ConfigError(
            f"{cfg.source}: [turntable] port and [imu] port are both {ports[0]!r}; "
            "each device needs its own port"
        )
    results = [
        _probe("turntable", cfg.turntable.port, probe("turntable"), cfg),
        _probe("imu", cfg.imu.port, probe("imu"), cfg),
        _probe("accelerometer", cfg.accelerometer.channel, probe("accelerometer"), cfg),
    ]
    for ok, line in results:
        print(("ok    " if ok else "FAIL  ") + line)
    if math.isnan(cfg.site.latitude_deg):
        print(f"note  [site] latitude_deg is not set in {cfg.source}; `find` needs it")
    failed = sum(not ok for ok, _ in results)
    if failed:
        raise DeviceError(f"{failed} of {len(results)} devices", None, "did not answer (see above)")
    return 0
