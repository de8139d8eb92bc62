"""`northfinder check --config bench.toml` (or `--simulate`): probe each device and say what answered.

One line per device, the model's own (devices.registry: the stage's version and state, the IMU's
rate and format and that data flows, the accelerometer's heartbeat state and identity, the GNSS
receiver's next fix when bench.toml has a [gnss] port) with the model's name; one clear line for
each device that did not answer.
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
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", metavar="BENCH_TOML", help="bench configuration")
    src.add_argument("--simulate", action="store_true",
                     help="start firmware-sim, probe its emulated devices, stop it (check without hardware)")
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
    if getattr(args, "simulate", False):
        return run_simulated()
    return check_bench(bench.load(args.config))


def run_simulated() -> int:
    """`check --simulate`: firmware-sim's bench (default truth and grade) probed like real hardware."""
    from northfinder.simulate import SimSettings, SimulatorProcess, bench_config

    settings = SimSettings()
    sim = SimulatorProcess(settings)
    endpoints = sim.start()
    try:
        pid = sim.proc.pid if sim.proc else "?"
        print(f"note  firmware-sim started (pid {pid}, grade {settings.grade}); probing its devices",
              flush=True)  # before the wait for its IMU, which takes a few seconds
        _wait_for_simulated_imu(str(endpoints["imu"]))
        return check_bench(bench_config(endpoints, settings.latitude_deg))
    finally:
        print(f"note  firmware-sim stopped (exit code {sim.stop()})")


SIM_IMU_START_S = 20.0
"""firmware-sim prints its endpoints a few seconds (3–5 s measured on a quiet host) before its IMU
streams to the first client; check waits this long for that first frame, so that the probe's own
2 s timeout tests the link and not the simulator's start-up."""


def _wait_for_simulated_imu(port: str) -> None:
    from northfinder.drivers.imu import Imu

    try:
        with Imu(port, timeout_s=SIM_IMU_START_S):
            pass
    except NorthfinderError:
        pass  # the probe below says what is wrong, in its own words


def check_bench(cfg: bench.BenchConfig) -> int:
    """Probe each device of `cfg`; one line per device; exit 0 only if each answered."""
    ports = [(role, p) for role, p in (("turntable", cfg.turntable.port), ("imu", cfg.imu.port),
                                        ("gnss", cfg.gnss.port)) if p]
    for k, (role, port) in enumerate(ports):
        other = next((r for r, p in ports[k + 1:] if p == port), None)
        if other is not None:
            raise ConfigError(
                f"{cfg.source}: [{role}] port and [{other}] port are both {port!r}; "
                "each device needs its own port"
            )
    results = [
        _probe("turntable", cfg.turntable.port, probe("turntable"), cfg),
        _probe("imu", cfg.imu.port, probe("imu"), cfg),
        _probe("accelerometer", cfg.accelerometer.channel, probe("accelerometer"), cfg),
    ]
    if cfg.gnss.port:  # a [gnss] section (align --mode gnss): probed too; a turntable bench has none
        results.append(_probe("gnss", cfg.gnss.port, probe("gnss"), cfg))
    for ok, line in results:
        print(("ok    " if ok else "FAIL  ") + line)
    if math.isnan(cfg.site.latitude_deg):
        print(f"note  [site] latitude_deg is not set in {cfg.source}; `find` needs it")
    failed = sum(not ok for ok, _ in results)
    if failed:
        raise DeviceError(f"{failed} of {len(results)} devices", None, "did not answer (see above)")
    return 0
