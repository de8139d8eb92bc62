"""`firmware-sim` / `python -m firmware_sim`: run the bench until SIGINT or SIGTERM.

Prints one JSON line with the endpoints on stdout, then runs. A user mistake (bad flag value,
unknown key or fault, unreadable TOML) is one line on stderr and exit code 2. Imports are kept
lean so the endpoints appear quickly; the physics and devices load in `Simulator.start`.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from typing import Any

from firmware_sim import __version__
from firmware_sim.config import ConfigError, SimConfig, config_from_mapping, load_toml


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="firmware-sim",
        description="The north-finding bench in software: SMC100 turntable and KVH IMU on ptys, "
        "CANopen accelerometer behind an slcan adapter, one physical world.",
    )
    p.add_argument("--heading", type=float, metavar="DEG", help="platform heading ψ, deg")
    p.add_argument("--pitch", type=float, metavar="DEG", help="platform pitch θ, deg")
    p.add_argument("--roll", type=float, metavar="DEG", help="platform roll γ, deg")
    p.add_argument("--latitude", type=float, metavar="DEG", help="site latitude, deg (north positive)")
    p.add_argument("--grade", metavar="NAME", help="sensor preset: nav, kvh1760, tactical-mems, consumer")
    p.add_argument("--seed", type=int, metavar="N", help="random seed (same seed, same bytes)")
    p.add_argument("--time-scale", type=float, metavar="K", help="device time runs K× the wall clock")
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
                      ("time_scale", "time_scale")):
        value = getattr(args, flag)
        if value is not None:
            data[key] = value
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
        while not done.is_set():
            if sim.wait(0.2):
                print(f"firmware-sim: stopped by an internal error: {sim.error!r}", file=sys.stderr)
                return 1
    finally:
        sim.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
