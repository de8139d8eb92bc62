"""`northfinder align --mode swaying|gnss`: strapdown alignment without a turntable.

The flags common to both modes live here; each mode module (`align_swaying`, `align_gnss`)
exposes `add_arguments(parser)` for its own flags and `run(args) -> int`.
"""

from __future__ import annotations

import argparse
import importlib

from northfinder.cli._common import add_db_flag
from northfinder.errors import InputError

DESCRIPTION = """\
Find true north with a strapdown IMU and no turntable, in one of two modes:

  --mode swaying  the IMU alone on a swaying base (a ship at anchor): gyrocompassing on the
                  inertial-frame cone of gravity (docs/swaying.md); needs the site latitude.
  --mode gnss     the IMU and an NMEA GNSS receiver on a vehicle that starts standing still and
                  then drives: a GNSS/INS filter with a sin/cos heading state (docs/gnss-alignment.md).

Real hardware: --config BENCH_TOML ([imu], [site] or [gnss]; docs/bench.example.toml).
Simulated: --simulate starts firmware-sim (flags --grade, --seed, --time-scale, --fault).
Every run writes a run directory (--out) that `northfinder replay RUN_DIR` recomputes bit for bit.
"""

MODES = {"swaying": "northfinder.cli.align_swaying", "gnss": "northfinder.cli.align_gnss"}


def _mode_module(mode: str):
    try:
        return importlib.import_module(MODES[mode])
    except ModuleNotFoundError as exc:
        if exc.name == MODES[mode]:
            return None
        raise


def register(sub: argparse._SubParsersAction) -> None:
    from northfinder.runs.gnss_live import SIM_DEFAULT_TIME_SCALE as gnss_k
    from northfinder.runs.swaying import SIM_DEFAULT_TIME_SCALE as sway_k

    p = sub.add_parser(
        "align",
        help="align a strapdown IMU: on a swaying base or GNSS-aided on the move",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--mode", choices=sorted(MODES), required=True,
                   help="swaying: gyrocompass on a swaying base (IMU alone); gnss: GNSS-aided, on the move")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="alignment window [device s]")
    p.add_argument("--json", metavar="PATH", help="write the result JSON here")
    p.add_argument("--out", metavar="RUN_DIR", help="run directory for raw logs and the report")
    p.add_argument("--config", metavar="BENCH_TOML", help="bench configuration for real hardware")
    p.add_argument("--unit", metavar="LABEL", help="unit under test, recorded in the results history")
    add_db_flag(p)  # the results history it records into
    p.add_argument("--simulate", action="store_true", help="start firmware-sim and align on it")
    p.add_argument("--grade", default=None, metavar="NAME",
                   help="simulated sensor grade: nav, kvh1760, tactical-mems, consumer (default: kvh1760 "
                   "gnss, the ship's IMU swaying)")
    p.add_argument("--seed", type=int, default=None, metavar="N",
                   help="the simulator's random seed: the same seed draws the same sensor noise (default 1)")
    p.add_argument("--time-scale", type=float, default=None, metavar="K",
                   help=f"simulated device time runs K× the wall clock (default: {sway_k:g} swaying, "
                   f"{gnss_k:g} gnss)")
    p.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE",
                   help="firmware-sim fault, e.g. imu-silence=10:2 (repeatable)")
    for mode in MODES:
        module = _mode_module(mode)
        if module is not None:
            module.add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    module = _mode_module(args.mode)
    if module is None:
        raise InputError(f"align mode '{args.mode}' is not available in this build")
    return module.run(args)
