"""`northfinder replay RUN_DIR`: recompute a run's result from its raw logs alone.

A `find` run: decodes imu.raw and can.asc with the drivers' pure decoders, cuts them by the
events log, and runs the same per-position means and estimator as the live run. An `align` run
(its config.json says `"kind": "align-gnss"` or `"align-swaying"`): the mode's own replay
function recomputes it from imu.raw (and gnss.nmea) and the events. Either way the result is
compared with the run's result.json. A run stopped before 3 positions prints the positions it
has. A campaign directory: every find it lists, and its statistics from the replayed finds. Exit 0
for a complete run, 1 for an incomplete one, 2 for a directory that is not a run (or a usage
error), 4 for a damaged run (a raw log cut short).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from northfinder import config as bench
from northfinder.cli import _align_summary, _common
from northfinder.cli._summary import print_positions, print_summary
from northfinder.errors import InputError
from northfinder.rundir import RESULT, RunDir, jsonable
from northfinder.runs import campaign, kinds

INCOMPLETE_EXIT = 1

# run kind -> its printer in cli/_align_summary.py (a find prints with cli/_summary.py)
ALIGN_SUMMARIES = {"align-gnss": "print_gnss_summary", "align-swaying": "print_swaying_summary"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="recompute a run's result from its raw logs", description=__doc__)
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory (find, align) or a campaign directory")
    p.add_argument("--method", choices=bench.METHODS, help="heading method (default: the run's)")
    p.add_argument("--json", metavar="PATH", help="write the recomputed result JSON here")
    p.add_argument("--report", metavar="PNG", help="draw the report of the recomputed result here")
    p.add_argument("--quiet", action="store_true", help="print only the comparison line")
    _common.add_db_flag(p)  # with --db: also say whether that history holds the run
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
    if args.db:
        print(_common.history_place(args.run_dir))
    if campaign.is_campaign_dir(args.run_dir):
        return _replay_campaign(args)
    kind = kinds.kind_of(args.run_dir).kind
    if kind != "find":
        return _replay_align(args, kind)
    return _replay_find(args, args.run_dir)


def _live_verdict(rd: RunDir, again: dict[str, Any], method: str | None) -> tuple[str, bool]:
    """How the replayed result compares with the live result.json, and whether it is identical."""
    live_path = rd.file(RESULT)
    if method is None and live_path.exists():
        diff = differences(json.loads(live_path.read_text(encoding="utf-8")), again)
        if not diff:
            return "identical to the live result.json", True
        return f"DIFFERS from the live result.json in {len(diff)} values: {', '.join(diff[:6])}", False
    return ("no live result.json to compare with" if method is None else f"method {method}"), True


def _replay_find(args: argparse.Namespace, run_dir: str | Path, quiet: bool | None = None) -> int:
    """Replay one find and print it; the exit code (0 complete, 1 incomplete)."""
    quiet = args.quiet if quiet is None else quiet
    outcome = kinds.KINDS["find"].replay(run_dir, method=args.method)
    rd = RunDir(run_dir, create=False)
    state = "complete" if outcome.complete else "incomplete"
    head = f"{rd.path}: {state} run, {outcome.positions_measured} of {outcome.positions_planned} positions"
    if outcome.result is None:
        resume = "" if outcome.complete else f"; finish it with northfinder find --resume {rd.path}"
        print(f"{head}; a heading needs at least 3 positions, nothing to recompute{resume}")
        if outcome.positions and not quiet:
            print_positions(outcome.positions)
        return INCOMPLETE_EXIT
    again = json.loads(json.dumps(jsonable(outcome.result)))
    verdict, _ = _live_verdict(rd, again, args.method)
    print(
        f"{head}; replayed heading {again['heading_deg']:.6f}° ± {again['heading_std_deg']:.6f}°, {verdict}"
    )
    if not quiet:
        print_summary(again)
    if args.json:
        RunDir(Path(args.json).parent, create=True).write_json(Path(args.json).name, again)
    if args.report:
        from northfinder.report import write_report

        write_report(again, args.report)
    return 0 if outcome.complete else INCOMPLETE_EXIT


def _replay_campaign(args: argparse.Namespace) -> int:
    """A campaign directory: replay every find it lists (one line each), say which were set
    aside, and compare the statistics recomputed from the replayed finds with campaign.json's."""
    cdir = Path(args.run_dir)
    if args.json or args.report:
        flag = "--json" if args.json else "--report"
        example = cdir / campaign.run_name(0, 0)
        raise InputError(f"{flag} with a campaign directory: give one of its finds (e.g. {example})")
    saved, replayed, again = campaign.replay_campaign(cdir, method=args.method)
    if not replayed:
        aside = ", ".join(str(cdir / f["run_dir"]) for f in saved.get("failed", [])) or "none"
        print(f"{cdir}: a campaign with no find done yet; replay one of its finds set aside ({aside}) "
              f"or continue it with northfinder campaign --resume {cdir}")
        return INCOMPLETE_EXIT
    for entry, out in replayed:
        rd = RunDir(cdir / entry["run_dir"], create=False)
        if out.result is None:
            print(f"{rd.path}: {out.positions_measured} of {out.positions_planned} positions, no heading")
            continue
        res = json.loads(json.dumps(jsonable(out.result)))
        verdict, _ = _live_verdict(rd, res, args.method)
        shown = f"{res['heading_deg']:.6f}° ± {res['heading_std_deg']:.6f}°"
        print(f"{rd.path}: replayed heading {shown}, {verdict}")
    for f in saved.get("failed", []):
        print(f"{cdir / f['run_dir']}: set aside (not in the statistics; northfinder replay it on its own)")
    keys = ("statistics", "steps", "mean_tilt_deg")
    diff = differences({k: saved.get(k) for k in keys}, {k: again.get(k) for k in keys})
    stats = ("identical to campaign.json's" if not diff
             else f"DIFFER from campaign.json's in {len(diff)} values: {', '.join(diff[:6])}")
    if args.method is not None:
        stats = f"for method {args.method} (not compared with campaign.json's)"
    n, total = len(replayed), len(campaign.planned(saved["plan"]))
    state = "complete" if saved.get("complete") else "incomplete"
    print(f"{cdir}: {state} campaign, {n} of {total} finds replayed; the statistics from the replayed "
          f"finds are {stats}")
    if not args.quiet and again.get("statistics"):
        from northfinder.cli._campaign_report import print_campaign

        print_campaign(again)
    return 0 if saved.get("complete") else INCOMPLETE_EXIT
