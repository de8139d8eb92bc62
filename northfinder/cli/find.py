"""`northfinder find`: measure at n table positions and report true north with its uncertainty.

`--config bench.toml` drives real hardware (or an externally started firmware-sim);
`--simulate` starts firmware-sim as a subprocess, passes the truth and the knobs on, and
reports the error against the truth. Every run leaves a run directory (northfinder.rundir).

Exit codes: 0 done; 2 a usage or input error (bad flag, bad config, bad latitude); 3 a device
error or a fault the run could not get past (what was measured is saved; finish it with
--resume); 4 a damaged run directory (--resume of a cut-short raw log); 130/143 stopped by
SIGINT/SIGTERM (saved).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import textwrap
import time

from northfinder import config as bench
from northfinder.cli._common import add_db_flag, heading_deg, preload_matplotlib
from northfinder.cli._summary import ProgressView, print_summary
from northfinder.runs import find as find_run
from northfinder.runs.find_pace import pace_line, time_scale_arg
from northfinder.simulate import SimSettings

SIM_STAGES, SIM_IMUS, SIM_TILTS = ("smc100", "apt"), ("kvh", "stim"), ("nf-accel", "cia410")
"""The models firmware-sim emulates per role (firmware-sim --stage/--imu/--tilt)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "find", help="find true north on a turntable (real bench or --simulate)", description=__doc__
    )
    sim_dwell_s = find_run.SIM_DEFAULT_DWELL_S
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--config", metavar="BENCH_TOML", help="bench configuration (real hardware or firmware-sim)"
    )
    src.add_argument(
        "--simulate", action="store_true", help="start firmware-sim as a subprocess and run on it"
    )
    src.add_argument(
        "--resume",
        metavar="RUN_DIR",
        help="finish an interrupted run: re-open its devices from its saved config (a simulated run "
        "starts firmware-sim again), measure the missing positions, write the complete result",
    )
    run_d, est_d = bench.BenchConfig().run, bench.BenchConfig().estimator
    p.add_argument("--positions", type=int, metavar="N",
                   help=f"number of table positions, ≥ 3 (default [run] positions; {run_d.positions} "
                   "if --simulate)")
    p.add_argument(
        "--dwell",
        type=float,
        metavar="S",
        help=f"dwell per position [device s] (default [run] dwell_s, {sim_dwell_s:g} if --simulate)",
    )
    p.add_argument("--order", choices=bench.ORDERS,
                   help=f"position order (default [run] order, {run_d.order})")
    p.add_argument("--method", choices=bench.METHODS,
                   help=f"heading method reported as the result (default [estimator] method, {est_d.method})")
    p.add_argument(
        "--plan",
        choices=bench.RUN_PLANS,
        help="positions: the dwell means only; positions+motion (default [run] plan): every gyro sample, "
        "also those taken while the table turns and settles (needs a z gyro); sweep: rests at --positions "
        "angles reached the long way round, whole turns in both directions, every sample (needs a z gyro "
        "and soft limits -360…360)",
    )
    goal = p.add_mutually_exclusive_group()
    goal.add_argument("--target-std", type=float, metavar="DEG",
                      help="choose the plan (n, dwell, kind) that reaches this heading 1σ soonest "
                      "(northfinder plan's model; needs --grade)")  # fmt: skip
    goal.add_argument("--time-budget", type=float, metavar="S",
                      help="choose the plan with the smallest σ in this much device time (needs --grade)")
    p.add_argument("--json", metavar="PATH", help="also write the result JSON here")
    p.add_argument("--out", metavar="RUN_DIR", help="run directory (default: runs/find-<UTC time>)")
    p.add_argument("--no-report", action="store_true", help="skip report.png")
    p.add_argument("--unit", metavar="LABEL", help="unit under test, recorded in the results history")
    add_db_flag(p)  # the results history it records into
    sim = p.add_argument_group("simulation (with --simulate; passed on to firmware-sim)")
    d = SimSettings()
    sim.add_argument("--heading", type=heading_deg, default=d.heading_deg, metavar="DEG",
                     help=f"true heading, from north clockwise (default {d.heading_deg:g})")
    sim.add_argument("--pitch", type=float, default=d.pitch_deg, metavar="DEG",
                     help=f"true pitch (default {d.pitch_deg:g})")
    sim.add_argument("--roll", type=float, default=d.roll_deg, metavar="DEG",
                     help=f"true roll (default {d.roll_deg:g})")
    sim.add_argument(
        "--latitude",
        type=float,
        default=None,
        metavar="DEG",
        help=f"site latitude, north positive (default {d.latitude_deg:g} simulated; overrides [site] "
        "with --config)",
    )
    sim.add_argument("--grade", default=None, metavar="NAME",
                     help=f"sensor grade: nav, kvh1760, tactical-mems, consumer, stim300 (simulated: "
                     f"default {d.grade}, stim300 with --imu stim; with --config: the grade "
                     "--target-std/--time-budget plan for)")
    sim.add_argument(
        "--seed",
        type=int,
        default=d.seed,
        metavar="N",
        help=f"the simulator's random seed: the same seed draws the same sensor noise (default {d.seed})",
    )
    sim.add_argument(
        "--time-scale",
        type=time_scale_arg,
        default=find_run.DEFAULT_TIME_SCALE,
        metavar="K",
        help=f"device time runs K× the wall clock (default {find_run.DEFAULT_TIME_SCALE:g}); auto: the "
        "highest this host keeps up with, paced after each position (the run's time_scale events)",
    )
    for flag, models, default in (("--stage", SIM_STAGES, "smc100"), ("--imu", SIM_IMUS, "kvh"),
                                  ("--tilt", SIM_TILTS, "nf-accel")):
        sim.add_argument(flag, choices=models, default=None, metavar="MODEL",
                         help=f"the simulated {flag[2:]}'s model: {', '.join(models)} (default {default}; "
                         "bench.toml's `model =`)")
    sim.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE",
                     help="firmware-sim fault, e.g. imu-silence=10:2 (repeatable)")
    sim.add_argument("--sim-config", metavar="FILE_TOML", help="firmware-sim's own --config file")
    sim.add_argument("--can", metavar="INTERFACE[:CHANNEL]",
                     help="firmware-sim's CAN node on this bus, e.g. socketcan:vcan0 (default: its slcan "
                     "adapter on a pty)")
    p.set_defaults(func=run)


def request(args: argparse.Namespace) -> find_run.FindRequest:
    """The parsed flags as the run's request."""
    names = find_run.FindRequest.__dataclass_fields__
    return find_run.FindRequest(**{k: v for k, v in vars(args).items() if k in names})


def run(args: argparse.Namespace) -> int:
    """`northfinder find`: run the find with the live progress view, print the summary."""
    t_wall = time.monotonic()
    if not args.no_report:
        # matplotlib takes a second or two to import: do it while the devices are opened and homed.
        preload_matplotlib()
    result, rundir, label = find_run.run_find(request(args), progress=ProgressView)
    print_summary(result, run_dir=rundir.path)
    events = rundir.events()
    paced = pace_line(events)
    if paced:
        print(paced, file=sys.stderr)
    note = find_run.pace_note(events)
    if note:  # wrapped to a terminal's width (at 80 columns too); one line into a pipe or file
        width = shutil.get_terminal_size().columns if sys.stderr.isatty() else 0
        print(textwrap.fill(f"note: {note}", width, subsequent_indent="  ") if width else f"note: {note}",
              file=sys.stderr)
    print(f"wall time {time.monotonic() - t_wall:.1f} s ({label})", file=sys.stderr)
    return 0

