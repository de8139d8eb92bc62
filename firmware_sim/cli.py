"""`firmware-sim` / `python -m firmware_sim`: run the bench until SIGINT or SIGTERM.

Prints one JSON line with the endpoints on stdout, then runs. A user mistake (bad flag value,
unknown key or fault, unreadable TOML) is one line on stderr and exit code 2. Imports are kept
lean so the endpoints appear quickly; the physics and devices load in `Simulator.start`.

    firmware-sim                                   # the bench: turntable, IMU, CAN accelerometer
    firmware-sim --scenario ship --sway "roll=10:8,pitch=5:6,yaw=3:10,heave=0.5:7" --lever-arm 1,2,1.5
    firmware-sim --scenario vehicle --lever-arm 0.5,1.5,1.2 --truth-log truth.jsonl
    firmware-sim --can socketcan:vcan0             # the CAN node on a kernel CAN interface
    firmware-sim --imu-axes y --stage-speed 1 --link-latency 20,5 --link-hold 5,200   # real units

`--lever-arm` is the IMU's (from the centre of rotation) for the bench and the ship, the GNSS
antenna's (from the IMU) for the vehicle. Scenarios and the truth log: docs/simulator.md.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
from typing import Any

from firmware_sim import __version__
from firmware_sim.config import (
    CAN_INTERFACES,
    SWAY_AXES,
    ConfigError,
    SimConfig,
    config_from_mapping,
    load_toml,
)

log = logging.getLogger("firmware_sim")

SWAY_EXAMPLE = "roll=10:8,pitch=5:6,yaw=3:10,heave=0.5:7"
SWITCH_INTERVAL_S = 1e-4
"""The interpreter's thread switch interval in the firmware-sim process (Python's default: 5 ms).
The loop holds the GIL most of a tick at high time scales; the arrival thread (firmware_sim.
arrivals) must get it within this to stamp a command when it came — 5 ms of wall is 0.6 device s
at 120×. Contention is rare (once per command), so the shorter interval costs nothing measurable."""


class _Parser(argparse.ArgumentParser):
    """argparse whose mistakes are one line (no usage block), exit code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"firmware-sim: {message} (see firmware-sim --help)\n")


def parse_sway(text: str) -> dict[str, list[list[float]]]:
    """`"roll=10:8,heave=0.5:7:90"` → {"roll": [[10, 8]], "heave": [[0.5, 7, 90]]}; "none" → {} (still).

    AXIS=AMP:PERIOD_S[:PHASE_DEG], comma-separated; an axis given twice gets two terms.
    """
    if text.strip().lower() in ("none", "0", "off"):
        return {}
    out: dict[str, list[list[float]]] = {}
    for item in text.split(","):
        axis, sep, value = item.strip().partition("=")
        axis = axis.strip().lower()
        if not sep or axis not in SWAY_AXES:
            raise ConfigError(f"--sway {item.strip()!r}: write AXIS=AMP:PERIOD_S[:PHASE_DEG] with AXIS "
                              f"one of {', '.join(SWAY_AXES)}, e.g. --sway \"{SWAY_EXAMPLE}\"")
        try:
            numbers = [float(v) for v in value.split(":")]
        except ValueError:
            numbers = []
        if not 2 <= len(numbers) <= 3 or not all(math.isfinite(v) for v in numbers) or numbers[1] <= 0:
            unit = "m" if axis in ("surge", "sway", "heave") else "deg"
            raise ConfigError(f"--sway {item.strip()}: give {axis}=AMP:PERIOD_S[:PHASE_DEG] as numbers "
                              f"(AMP in {unit}, PERIOD_S > 0), e.g. --sway \"{SWAY_EXAMPLE}\"")
        out.setdefault(axis, []).append(numbers)
    return out


def parse_lever_arm(text: str) -> tuple[float, float, float]:
    """`"1,2,1.5"` → (1.0, 2.0, 1.5) metres in b (x right, y forward, z up)."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"--lever-arm {text}: give three numbers X,Y,Z in metres (b axes: x right, "
                          "y forward, z up), e.g. --lever-arm 1,2,1.5")
    return values  # type: ignore[return-value]


def _numbers(text: str, sep: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(sep)]
    except ValueError:
        return []
    return values if all(math.isfinite(v) for v in values) else []


def parse_link_hold(text: str) -> dict[str, float]:
    """`"5,200"` → hold the IMU and GNSS links every 5 device s for 200 wall ms; `"5,200,1"` adds
    ±1 s of seeded jitter on the period."""
    values = _numbers(text, ",")
    if len(values) not in (2, 3) or values[0] <= 0 or values[1] <= 0 or (len(values) == 3 and not
                                                                        0 <= values[2] < values[0]):
        raise ConfigError(f"--link-hold {text}: give PERIOD_S,HOLD_MS[,JITTER_S] (device s, wall ms, "
                          "0 <= JITTER_S < PERIOD_S), e.g. --link-hold 5,200")
    out = {"link_hold_period_s": values[0], "link_hold_ms": values[1]}
    if len(values) == 3:
        out["link_hold_jitter_s"] = values[2]
    return out


def parse_link_latency(text: str) -> dict[str, float]:
    """`"20,5"` → 20 ± 5 device ms on the IMU and GNSS links; `"imu=20:5,gnss=100:10"` per device."""
    example = "e.g. --link-latency 20,5 or --link-latency imu=20:5,gnss=100:10"
    items = [(d.strip().lower(), v) for d, _, v in (p.partition("=") for p in text.split(","))] \
        if "=" in text else [("imu", text.replace(",", ":")), ("gnss", text.replace(",", ":"))]
    out: dict[str, float] = {}
    for device, value in items:
        values = _numbers(value, ":")
        if device not in ("imu", "gnss") or len(values) not in (1, 2):
            raise ConfigError(f"--link-latency {text}: give MS,JITTER_MS or imu=MS:JITTER_MS,"
                              f"gnss=MS:JITTER_MS (device ms), {example}")
        latency, jitter = values[0], (values[1] if len(values) == 2 else 0.0)
        if latency < 0 or not 0 <= jitter <= latency:
            raise ConfigError(f"--link-latency {text}: the latency must be >= 0 and the jitter between 0 "
                              f"and the latency (device ms), {example}")
        out[f"{device}_link_latency_ms"], out[f"{device}_link_jitter_ms"] = latency, jitter
    return out


def parse_can(text: str) -> dict[str, str]:
    """`"socketcan:vcan0"` → can_interface socketcan, can_channel vcan0; `"slcan"` → the emulated adapter."""
    interface, _, channel = (part.strip() for part in text.strip().partition(":"))
    interface = interface.lower()
    if interface not in CAN_INTERFACES or (interface != "slcan" and not channel):
        raise ConfigError(f"--can {text}: give INTERFACE[:CHANNEL] with INTERFACE one of "
                          f"{', '.join(CAN_INTERFACES)} (a channel for virtual and socketcan), "
                          "e.g. --can socketcan:vcan0")
    return {"can_interface": interface, **({"can_channel": channel} if channel else {})}


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="firmware-sim",
        description="The north-finding bench in software: SMC100 turntable and KVH IMU on ptys, "
        "CANopen accelerometer behind an slcan adapter, one physical world.",
    )
    p.add_argument("--heading", type=float, metavar="DEG", help="platform heading ψ, deg")
    p.add_argument("--pitch", type=float, metavar="DEG", help="platform pitch θ, deg")
    p.add_argument("--roll", type=float, metavar="DEG", help="platform roll γ, deg")
    p.add_argument("--latitude", type=float, metavar="DEG", help="site latitude, deg (north positive)")
    p.add_argument("--grade", metavar="NAME", help="sensor preset: nav, kvh1760, tactical-mems, consumer")
    p.add_argument("--seed", type=int, metavar="N",
                   help="random seed: every device's noise is drawn by its own sample index, so the same "
                   "seed gives the same bytes when the host's commands land at the same device times "
                   "(always, for a bench the host does not move); docs/simulator.md")
    p.add_argument("--time-scale", type=float, metavar="K", help="device time runs K× the wall clock")
    p.add_argument("--control-stdin", action="store_true",
                   help="read commands from standard input, one a line: `time-scale K` (device time "
                   "runs K× the wall clock from then on, continuous); for a client that paces the "
                   "simulation to its host (northfinder find --time-scale auto)")
    p.add_argument("--scenario", metavar="NAME",
                   help="bench (turntable + IMU + CAN accelerometer, default) | ship (IMU on a swaying "
                   "base) | vehicle (IMU + GNSS on a driving car; its device time starts when a client "
                   "opens the imu or gnss port, so the client sees the 10 s still start)")
    p.add_argument("--sway", metavar="SPEC",
                   help=f"sway per axis, AXIS=AMP:PERIOD_S[:PHASE_DEG] (deg; m for surge/sway/heave), "
                   f"'none' for still; the ship's default is {SWAY_EXAMPLE!r} with phases from the seed")
    p.add_argument("--lever-arm", metavar="X,Y,Z",
                   help="metres in b: the IMU's from the centre of rotation (bench, ship; ship default "
                   "1,2,1.5), the GNSS antenna's from the IMU (vehicle; default 0.5,1.5,1.2)")
    p.add_argument("--imu-rate", type=int, metavar="HZ", help="IMU data rate (default 1000; vehicle 250)")
    p.add_argument("--accel-rate", type=float, metavar="HZ", help="CAN accelerometer rate, 1…1000 (100)")
    p.add_argument("--can", metavar="INTERFACE[:CHANNEL]",
                   help="where the CAN node sits: slcan (behind the emulated USB-CAN adapter on a pty, "
                   "default), socketcan:vcan0 (a kernel CAN interface), virtual:bench "
                   "(python-can, in-process)")
    p.add_argument("--accel-mapping", choices=("default", "swapped"),
                   help="CAN accelerometer TPDO mapping (swapped: axes reordered, 0.1 µg scale)")
    p.add_argument("--imu-axes", metavar="SPEC",
                   help="the KVH unit's axes: gyro letters then optional +acc: xyz+acc (default), xyz "
                   "(gyro-only FOG), y (single-axis FOG), xy, xy+acc")
    p.add_argument("--link-hold", metavar="PERIOD_S,HOLD_MS",
                   help="every PERIOD_S device s the IMU/GNSS links hold their bytes for HOLD_MS wall ms, "
                   "then release them in one burst (optional ,JITTER_S on the period)")
    p.add_argument("--link-latency", metavar="MS,JITTER_MS",
                   help="IMU/GNSS messages leave their pty MS ± JITTER_MS device ms after they were made "
                   "(order kept); per device: imu=MS:J,gnss=MS:J")
    p.add_argument("--stage-speed", type=float, metavar="DEG_S", help="SMC100 move (and homing) speed, deg/s")
    p.add_argument("--stage-accel", type=float, metavar="DEG_S2", help="SMC100 acceleration, deg/s²")
    p.add_argument("--stage", choices=("smc100", "apt"), help="rotation stage model (default smc100)")
    p.add_argument("--imu", choices=("kvh", "stim"), help="IMU model (default kvh)")
    p.add_argument("--tilt", choices=("nf-accel", "cia410"), help="tilt sensor on CAN (nf-accel)")
    p.add_argument("--truth-log", metavar="PATH", help="write the truth as JSON lines (docs/simulator.md)")
    p.add_argument("--truth-rate", type=float, metavar="HZ", help="truth samples per device second (50)")
    p.add_argument("--config", metavar="FILE.toml", help="the other settings (keys as SimConfig)")
    p.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE",
                   help="inject a fault (repeatable), e.g. imu-silence=10:2")
    p.add_argument("-v", "--verbose", action="count", default=0, help="log to stderr (-vv: raw traffic)")
    p.add_argument("--version", action="version", version=f"firmware-sim {__version__}")
    return p


def config_from_args(args: argparse.Namespace) -> SimConfig:
    """TOML first, then the flags on top; faults from both."""
    data: dict[str, Any] = {}
    source = "command line"
    if args.config:
        data = load_toml(args.config)
        source = f"config file {args.config}"
    faults = data.pop("faults", None)
    fault_specs: list[str] = []
    if isinstance(faults, dict):
        fault_specs = [f"{k}={v}" for k, v in faults.items()]
    elif isinstance(faults, list):
        fault_specs = [str(f) for f in faults]
    elif faults is not None:
        raise ConfigError(f"{source}: faults must be a table or a list of \"NAME=VALUE\" strings")
    for flag, key in (("heading", "heading_deg"), ("pitch", "pitch_deg"), ("roll", "roll_deg"),
                      ("latitude", "latitude_deg"), ("grade", "grade"), ("seed", "seed"),
                      ("time_scale", "time_scale"), ("scenario", "scenario"), ("imu_rate", "imu_rate_hz"),
                      ("truth_log", "truth_log"), ("truth_rate", "truth_rate_hz"), ("imu_axes", "imu_axes"),
                      ("stage_speed", "stage_speed_dps"), ("stage_accel", "stage_accel_dps2"),
                      ("accel_rate", "accel_rate_hz"), ("accel_mapping", "accel_mapping"),
                      ("stage", "stage_model"), ("imu", "imu_model"), ("tilt", "tilt_model")):
        value = getattr(args, flag)
        if value is not None:
            data[key] = value
    if args.can is not None:
        data.update(parse_can(args.can))
    if args.sway is not None:
        data["sway"] = parse_sway(args.sway)
    if args.link_hold is not None:
        data.update(parse_link_hold(args.link_hold))
    if args.link_latency is not None:
        data.update(parse_link_latency(args.link_latency))
    if args.lever_arm is not None:
        key = "gnss_lever_arm_m" if data.get("scenario", "bench") == "vehicle" else "imu_lever_arm_m"
        data[key] = parse_lever_arm(args.lever_arm)
    data["faults"] = fault_specs + list(args.fault)
    return config_from_mapping(data, source=source)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.verbose:
        logging.basicConfig(level=logging.DEBUG if args.verbose > 1 else logging.INFO,
                            format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
    try:
        config = config_from_args(args)
    except ConfigError as exc:
        print(f"firmware-sim: {exc}", file=sys.stderr)
        return 2

    from firmware_sim.simulator import Simulator

    sys.setswitchinterval(SWITCH_INTERVAL_S)
    done = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        done.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    sim = Simulator(config)
    try:
        try:
            endpoints = sim.start()
        except ConfigError as exc:
            print(f"firmware-sim: {exc}", file=sys.stderr)
            return 2
        except OSError as exc:
            print(f"firmware-sim: cannot open the bench's ports ({exc})", file=sys.stderr)
            return 1
        print(json.dumps(endpoints), flush=True)
        if args.control_stdin:
            threading.Thread(target=_control_loop, args=(sim, done), name="firmware_sim-control",
                             daemon=True).start()
        while not done.is_set():
            if sim.wait(0.2):
                print(f"firmware-sim: stopped by an internal error: {sim.error!r}", file=sys.stderr)
                return 1
    finally:
        sim.stop()
    return 0


def _control_loop(sim: Any, done: threading.Event) -> None:
    """--control-stdin: apply each command line; a bad line is reported on stderr and skipped. End of
    input ends the simulator (its client has gone)."""
    for line in sys.stdin:
        words = line.split()
        if len(words) == 2 and words[0] == "time-scale":
            try:
                sim.clock.set_scale(float(words[1]))
                log.info("time scale %s", words[1])
                continue
            except ValueError:
                pass
        if words:
            print(f"firmware-sim: unknown control line {line.strip()!r} (use: time-scale K, K > 0)",
                  file=sys.stderr)
    done.set()


if __name__ == "__main__":
    sys.exit(main())
