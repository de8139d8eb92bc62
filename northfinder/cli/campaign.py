"""`northfinder campaign`: N finds in a row at one or more base headings, their repeatability
statistics for every method (the paper's table 1) and campaign.png; resumable with --resume.

A real bench (`--config`): before each base heading the operator turns the fixture and presses
Enter; `--reference-deg` gives each step's reference azimuth. `--simulate`: each step is its own
simulated heading (`--headings`), the truth is the reference.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import time
from pathlib import Path

from northfinder import config as bench
from northfinder import runkinds
from northfinder.cli._common import HEADING_RANGE_DEG, add_db_flag
from northfinder.cli._summary import ProgressView, print_summary
from northfinder.errors import InputError
from northfinder.runs import base as run_base
from northfinder.runs import campaign as cp
from northfinder.runs.find import FindRequest
from northfinder.runs.find_pace import time_scale_arg
from northfinder.simulate import SimSettings


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "campaign",
        help="repeat the find N times (at several headings) and report its spread",
        description=__doc__,
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--config", metavar="BENCH_TOML", help="real bench (or an externally started firmware-sim)"
    )
    src.add_argument("--simulate", action="store_true", help="each find on its own firmware-sim subprocess")
    src.add_argument("--resume", metavar="CAMPAIGN_DIR", help="measure the finds a stopped campaign lacks")
    p.add_argument("--repeat", type=int, metavar="N", help="finds per base heading")
    p.add_argument("--reference-deg", metavar="DEG[,DEG…]", help="real bench: reference azimuth of each step")
    p.add_argument(
        "--heading", "--headings", dest="headings", type=str, metavar="DEG[,DEG…]",
        help="--simulate: true heading of each step, from north clockwise (default 37)",
    )
    p.add_argument("--positions", type=int, metavar="N", help="table positions per find")
    p.add_argument("--dwell", type=float, metavar="S", help="dwell per position [device s]")
    p.add_argument("--method", default="exact", choices=bench.METHODS,
                   help="heading method whose σ is checked (the find's --method; default exact)")
    p.add_argument("--unit", default="", metavar="LABEL", help="unit under test (recorded in the history)")
    p.add_argument("--json", metavar="PATH", help="also write the campaign's JSON (campaign.json) here")
    p.add_argument("--out", metavar="CAMPAIGN_DIR",
                   help="campaign directory (default runs/campaign-<UTC time>)")
    add_db_flag(p)  # the results history the campaign and its finds record into
    p.add_argument("--no-report", action="store_true", help="no report.png per find (campaign.png is drawn)")
    sim = p.add_argument_group("simulation (with --simulate)")
    d = SimSettings()
    sim.add_argument("--pitch", type=float, metavar="DEG", help=f"true pitch (default {d.pitch_deg:g})")
    sim.add_argument("--roll", type=float, metavar="DEG", help=f"true roll (default {d.roll_deg:g})")
    sim.add_argument("--latitude", type=float, metavar="DEG",
                     help=f"site latitude, north positive (default {d.latitude_deg:g})")
    sim.add_argument("--grade", default="nav", metavar="NAME",
                     help="sensor grade: nav, kvh1760, tactical-mems, consumer (default nav)")
    sim.add_argument("--seed", type=int, default=1, metavar="N",
                     help="the simulator's random seed; find k of the plan uses seed + k (default 1)")
    sim.add_argument("--time-scale", type=time_scale_arg, default=12.0, metavar="K",
                     help="device time runs K× the wall clock (default 12)")
    sim.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE",
                     help="firmware-sim fault for every find, e.g. imu-silence=10:2 (repeatable)")
    sim.add_argument("--sim-config", metavar="FILE_TOML", help="firmware-sim's own --config file")
    p.set_defaults(func=run)


def _angles(text: str | None, flag: str) -> list[float]:
    try:
        out = [float(v) for v in (text or "").split(",") if v.strip()]
    except ValueError:
        raise InputError(f"{flag} {text}: give degrees separated by commas, e.g. 0,120,240") from None
    if not out or not all(math.isfinite(v) for v in out):
        raise InputError(f"{flag} {text}: give at least one finite angle in degrees")
    lo, hi = HEADING_RANGE_DEG
    for v in out:
        if not lo < v < hi:
            raise InputError(f"{flag} {text}: {v:g} is more than a turn; give headings between {lo:g} "
                             f"and {hi:g}")
    return out


def _new(args: argparse.Namespace) -> tuple[Path, dict]:
    """The campaign directory and its first campaign.json from the flags."""
    if args.repeat is None or args.repeat < 1:
        raise InputError(f"--repeat {args.repeat}: give the number of finds per heading (1 or more)")
    if args.simulate:
        if args.reference_deg:
            raise InputError(
                "--reference-deg: with --simulate the reference is the simulated heading; use --heading"
            )
        refs = _angles(args.headings, "--heading") if args.headings else [37.0]
    else:
        if args.headings:
            raise InputError("--heading: only with --simulate; on a bench give --reference-deg")
        if not args.reference_deg:
            raise InputError("--reference-deg: give the reference azimuth of each fixture position (step)")
        refs = _angles(args.reference_deg, "--reference-deg")
        if not Path(args.config).is_file():
            raise InputError(f"--config {args.config}: no such file")
    plan = {
        "repeat": args.repeat,
        "steps": [{"reference_deg": r} for r in refs],
        "positions": args.positions,
        "dwell_s": args.dwell if args.dwell is not None else (20.0 if args.simulate else None),
        "method": args.method,
        "report": not args.no_report,
        "config": str(Path(args.config).resolve()) if args.config else None,
    }
    if plan["positions"] is None:
        plan["positions"] = 8
    simulate = None
    if args.simulate:
        simulate = {
            "grade": args.grade,
            "seed": args.seed,
            "time_scale": args.time_scale,
            "pitch_deg": args.pitch,
            "roll_deg": args.roll,
            "latitude_deg": args.latitude,
            "sim_config": str(Path(args.sim_config).resolve()) if args.sim_config else None,
            "faults": list(args.fault),
        }
    out = Path(args.out) if args.out else run_base.default_out("campaign")
    if (out / cp.CAMPAIGN_JSON).exists():
        raise InputError(f"--out {out}: a campaign is already there; continue it with --resume {out}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"--out {out}: cannot create the campaign directory ({exc.strerror})") from None
    return out, cp.new_state(plan, args.unit, simulate)


def _prompt(step: int, reference_deg: float) -> None:
    """Real bench: wait for the operator to turn the fixture to this step's reference."""
    try:
        input(
            f"step {step + 1}: turn the fixture to the reference azimuth {reference_deg:g}° and press Enter "
        )
    except EOFError:
        raise InputError(
            "campaign: standard input closed while waiting for Enter at a fixture step; "
            "run it from a terminal"
        ) from None


def run(args: argparse.Namespace) -> int:
    from northfinder.cli._campaign_report import print_campaign, write_figure

    if args.resume:
        cdir = Path(args.resume)
        state = cp.read_state(cdir)
        if state["complete"]:
            raise InputError(f"--resume {cdir}: the campaign is already complete")
        state["sessions"] = int(state.get("sessions", 1)) + 1
    else:
        cdir, state = _new(args)
    cp.write_state(cdir, state)
    prompt = None if state["simulate"] else _prompt
    state = cp.run_campaign(cdir, state, runner=_run_find, prompt=prompt,
                            echo=lambda s: print(s, file=sys.stderr))
    write_figure(state, cdir / "campaign.png")
    print_campaign(state)
    if args.json:
        Path(args.json).write_text(json.dumps(state, indent=2) + "\n", encoding="utf-8")
    print(f"campaign directory: {cdir} (campaign.json, campaign.png)")
    return 0


def _run_find(req: FindRequest, summary_path: Path) -> None:
    """One find of the campaign with the live progress view; its summary goes to `summary_path`."""
    t_wall = time.monotonic()
    summary_path.parent.mkdir(parents=True, exist_ok=True)
    with open(summary_path, "w", encoding="utf-8") as fh, contextlib.redirect_stdout(fh):
        result, rundir, label = runkinds.KINDS["find"].measure(req, progress=ProgressView)
        print_summary(result, run_dir=rundir.path)
    print(f"wall time {time.monotonic() - t_wall:.1f} s ({label})", file=sys.stderr)
