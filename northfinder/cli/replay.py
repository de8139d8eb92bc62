"""`northfinder replay RUN_DIR`: recompute a run's result from its raw logs alone.

A `find` run: decodes imu.raw and can.asc with the drivers' pure decoders, cuts them by the
events log, and runs the same per-position means and estimator as the live run. An `align` run
(its config.json says `"kind": "align-gnss"` or `"align-swaying"`): the mode's own replay
function recomputes it from imu.raw (and gnss.nmea) and the events. Either way the result is
compared with the run's result.json. Exit 0 for a complete run, 1 for an incomplete one, 2 for
a directory that is not a run (or a usage error), 4 for a damaged run (a raw log cut short).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from northfinder import config as bench
from northfinder.cli import _align_summary
from northfinder.cli._summary import print_summary
from northfinder.rundir import RESULT, RunDir, jsonable
from northfinder.runs import kinds

INCOMPLETE_EXIT = 1

# run kind -> its printer in cli/_align_summary.py (a find prints with cli/_summary.py)
ALIGN_SUMMARIES = {"align-gnss": "print_gnss_summary", "align-swaying": "print_swaying_summary"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="recompute a run's result from its raw logs", description=__doc__)
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory written by `northfinder find`")
    p.add_argument("--method", choices=bench.METHODS, help="heading method (default: the run's)")
    p.add_argument("--json", metavar="PATH", help="write the recomputed result JSON here")
    p.add_argument("--report", metavar="PNG", help="draw the report of the recomputed result here")
    p.add_argument("--quiet", action="store_true", help="print only the comparison line")
    p.set_defaults(func=run)


def differences(live: dict[str, Any], again: dict[str, Any], prefix: str = "") -> list[str]:
    """Keys whose values differ (exact comparison; floats bit for bit after the JSON round trip)."""
    out: list[str] = []
    for key in sorted(set(live) | set(again)):
        a, b = live.get(key), again.get(key)
        where = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            out += differences(a, b, where + ".")
        elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            for i, (x, y) in enumerate(zip(a, b, strict=True)):
                if isinstance(x, dict) and isinstance(y, dict):
                    out += differences(x, y, f"{where}[{i}].")
                elif x != y:
                    out.append(f"{where}[{i}]")
        elif a != b:
            out.append(where)
    return out


def _replay_align(args: argparse.Namespace, kind: str) -> int:
    replayed = kinds.KINDS[kind].replay(args.run_dir)
    result, complete = replayed.result, replayed.complete
    rd = RunDir(args.run_dir, create=False)
    again = json.loads(json.dumps(jsonable(result)))
    live_path = rd.file(RESULT)
    if live_path.exists():
        diff = differences(json.loads(live_path.read_text(encoding="utf-8")), again)
        verdict = ("identical to the live result.json" if not diff
                   else f"DIFFERS from the live result.json in {len(diff)} values: {', '.join(diff[:6])}")
    else:
        verdict = "no live result.json to compare with"
    state = "complete" if complete else "incomplete"
    heading = again.get("heading_deg")
    sigma = again.get("heading_std_deg")
    shown = f"{heading:.6f}° ± {sigma:.6f}°" if heading is not None and sigma is not None else "none"
    print(f"{rd.path}: {state} {kind} run; replayed heading {shown}, {verdict}")
    if not args.quiet:
        getattr(_align_summary, ALIGN_SUMMARIES[kind])(again)
    if args.json:
        RunDir(Path(args.json).parent, create=True).write_json(Path(args.json).name, again)
    return 0 if complete else INCOMPLETE_EXIT


def run(args: argparse.Namespace) -> int:
    kind = kinds.kind_of(args.run_dir).kind
    if kind != "find":
        return _replay_align(args, kind)
    outcome = kinds.KINDS["find"].replay(args.run_dir, method=args.method)
    rd = RunDir(args.run_dir, create=False)
    state = "complete" if outcome.complete else "incomplete"
    head = f"{rd.path}: {state} run, {outcome.positions_measured} of {outcome.positions_planned} positions"
    if outcome.result is None:
        print(f"{head}; a heading needs at least 3 positions, nothing to recompute")
        return INCOMPLETE_EXIT
    again = json.loads(json.dumps(jsonable(outcome.result)))
    live_path = rd.file(RESULT)
    if args.method is None and live_path.exists():
        diff = differences(json.loads(live_path.read_text(encoding="utf-8")), again)
        verdict = (
            "identical to the live result.json"
            if not diff
            else (f"DIFFERS from the live result.json in {len(diff)} values: {', '.join(diff[:6])}")
        )
    else:
        verdict = "no live result.json to compare with" if args.method is None else f"method {args.method}"
    print(
        f"{head}; replayed heading {again['heading_deg']:.6f}° ± {again['heading_std_deg']:.6f}°, {verdict}"
    )
    if not args.quiet:
        print_summary(again)
    if args.json:
        RunDir(Path(args.json).parent, create=True).write_json(Path(args.json).name, again)
    if args.report:
        from northfinder.report import write_report

        write_report(again, args.report)
    return 0 if outcome.complete else INCOMPLETE_EXIT
