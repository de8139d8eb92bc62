"""`northfinder check --config bench.toml` (or `--simulate`): probe each device and say what answered.

One line per device: the stage's version and state, the IMU's rate and format (and that data
flows), the accelerometer's heartbeat state; one clear line for each device that did not answer.
Exit 0 only if every device answered.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from northfinder import config as bench
from northfinder.errors import ConfigError, DeviceError, NorthfinderError

HEARTBEAT_STATES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check", help="probe the turntable, the IMU and the accelerometer of a bench", description=__doc__
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--config", metavar="BENCH_TOML", help="bench configuration")
    src.add_argument("--simulate", action="store_true",
                     help="start firmware-sim, probe its emulated devices, stop it (check without hardware)")
    p.set_defaults(func=run)


def probe_turntable(cfg: bench.BenchConfig) -> str:
    from northfinder.drivers.turntable import Turntable

    t = cfg.turntable
    with Turntable(t.port, address=t.address, baudrate=t.baudrate, timeout_s=5.0) as tt:
        version = tt.version()
        st = tt.status()
        errors = ", ".join(st.error_names) if st.errors else "no errors"
        return f"turntable on {t.port}: {version}; state {st.state_name} (0x{st.state:02X}), {errors}"


def probe_imu(cfg: bench.BenchConfig) -> str:
    from northfinder.drivers.imu import Imu

    i = cfg.imu
    with Imu(i.port, baudrate=i.baudrate) as imu:
        rate = imu.query("DR")
        fmt = imu.query("ROTFMT")
        units = imu.query("ROTUNITS")
        block = imu.read(max(2, int(imu.rate_hz // 10)), timeout_s=3.0)
        axes = imu.axes
        bit, bit_source = imu.built_in_test()
        stats = imu.stats
        if "y" not in axes.gyro:
            raise DeviceError("imu", i.port, f"{axes.describe()} (status bits): north finding needs a "
                              "gyro y, or x and y — is it the right unit, mounted y along the table plane?")
        settle = "settles by gyro z" if "z" in axes.gyro else "no gyro z: READY + [turntable] settle_s"
        return (
            f"imu on {i.port}: {rate} Hz, format A, {fmt} {units}; {axes.describe()} ({settle}); "
            f"{len(block.sample_index)} samples read, {stats.bad_crc} bad CRC, {stats.lost_samples} lost; "
            f"{bit_source} {bit.describe()}"
        )


def probe_accelerometer(cfg: bench.BenchConfig) -> str:
    from northfinder.drivers.accelerometer import Accelerometer

    a = cfg.accelerometer
    with Accelerometer(
        a.interface, a.channel, bitrate=a.bitrate, node_id=a.node_id, bus_options=a.bus_options or None,
        eds_path=bench.accel_eds_path(cfg),
    ) as acc:
        state = acc.wait_heartbeat(timeout_s=3.0)
        if state == 0x04:  # stopped: CiA 301 has no SDO there; pre-operational changes nothing else
            acc.enter_pre_operational()
        ident = acc.identity()  # SDO, read only: check writes nothing to the node
        layout = acc.read_mapping()
        rate_hz = acc.read_rate(a.rate_object)
    name = HEARTBEAT_STATES.get(state, f"unknown 0x{state:02X}")
    return (
        f"accelerometer node 0x{a.node_id:02X} on {a.interface} {a.channel}: heartbeat {name} "
        f"(0x{state:02X}); "
        f"{ident['device_name']!r}, vendor ID 0x{ident['vendor_id']:08X}, product code "
        f"0x{ident['product_code']:08X}, revision 0x{ident['revision']:08X}, serial number "
        f"0x{ident['serial_number']:08X}; rate {rate_hz:g} Hz ({a.rate_object}); mapping {layout.describe()}"
    )


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
    ports = [p for p in (cfg.turntable.port, cfg.imu.port) if p]
    if len(set(ports)) < len(ports):
        raise ConfigError(
            f"{cfg.source}: [turntable] port and [imu] port are both {ports[0]!r}; "
            "each device needs its own port"
        )
    results = [
        _probe("turntable", cfg.turntable.port, probe_turntable, cfg),
        _probe("imu", cfg.imu.port, probe_imu, cfg),
        _probe("accelerometer", cfg.accelerometer.channel, probe_accelerometer, cfg),
    ]
    for ok, line in results:
        print(("ok    " if ok else "FAIL  ") + line)
    if math.isnan(cfg.site.latitude_deg):
        print(f"note  [site] latitude_deg is not set in {cfg.source}; `find` needs it")
    failed = sum(not ok for ok, _ in results)
    if failed:
        raise DeviceError(f"{failed} of {len(results)} devices", None, "did not answer (see above)")
    return 0
