"""`northfinder replay RUN_DIR`: recompute a run's result from its raw logs alone.

The run's kind (config.json's `kind`; a campaign directory holds campaign.json) picks its replay
(northfinder.runkinds). A find: imu.raw and can.asc decoded by the recorded models' decoders, cut
by the events log, the same per-position means and estimator as the live run. An align run: the
mode's result function on imu.raw (and gnss.nmea) and the events. A campaign: each listed find
replayed, its statistics recomputed. The result is compared with the run's own result.json (a
campaign's campaign.json). Exit 0 for a complete run, 1 for an incomplete one, 2 for
a directory that is not a run (or a usage error), 4 for a damaged run (a raw log cut short).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from northfinder import config as bench
from northfinder import runkinds
from northfinder.cli import _align_summary, _common
from northfinder.cli._summary import print_positions, print_summary
from northfinder.errors import InputError
from northfinder.rundir import RunDir, jsonable
from northfinder.runs import campaign

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


def _verdict(rd: RunDir, result_file: str, again: dict[str, Any], method: str | None = None) -> str:
    """How the recomputed result compares with the run's own (result.json; a campaign's campaign.json)."""
    if method is not None:
        return f"method {method}"
    live_path = rd.file(result_file)
    if not live_path.exists():
        return f"no live {result_file} to compare with"
    diff = differences(json.loads(live_path.read_text(encoding="utf-8")), again)
    if not diff:
        return f"identical to the live {result_file}"
    return f"DIFFERS from the live {result_file} in {len(diff)} values: {', '.join(diff[:6])}"


def _shown(again: dict[str, Any]) -> str:
    heading, sigma = again.get("heading_deg"), again.get("heading_std_deg")
    return f"{heading:.6f}° ± {sigma:.6f}°" if heading is not None and sigma is not None else "none"


def _print_find(args: argparse.Namespace, rd: RunDir, out: runkinds.Replayed, again: dict[str, Any]) -> None:
    head = f"{rd.path}: {_state(out)} run, {out.positions_measured} of {out.positions_planned} positions"
    verdict = _verdict(rd, runkinds.KINDS["find"].result_file, again, args.method)
    print(f"{head}; replayed heading {_shown(again)}, {verdict}")
    if not args.quiet:
        print_summary(again)


Printer = Callable[[argparse.Namespace, RunDir, runkinds.Replayed, dict[str, Any]], None]
"""A kind's replay view: (the flags, the run directory, the replay's outcome, its result as JSON)."""


def _print_align(kind: str) -> Printer:
    def show(args: argparse.Namespace, rd: RunDir, out: runkinds.Replayed, again: dict[str, Any]) -> None:
        print(f"{rd.path}: {_state(out)} {kind} run; replayed heading {_shown(again)}, "
              f"{_verdict(rd, runkinds.KINDS[kind].result_file, again)}")
        if not args.quiet:
            getattr(_align_summary, ALIGN_SUMMARIES[kind])(again)

    return show


def _state(out: runkinds.Replayed) -> str:
    return "complete" if out.complete else "incomplete"


PRINTERS: dict[str, Printer] = {
    "find": _print_find,
    "align-swaying": _print_align("align-swaying"),
    "align-gnss": _print_align("align-gnss"),
}
"""Each kind's replay line and summary (the views; the kinds themselves are northfinder.runkinds)."""


def run(args: argparse.Namespace) -> int:
    if args.db:
        print(_common.history_place(args.run_dir))
    kind = runkinds.kind_of(args.run_dir)
    if kind.kind == "campaign":
        return _replay_campaign(args)
    out = kind.replay(args.run_dir, method=args.method)
    rd = RunDir(args.run_dir, create=False)
    if out.result is None:
        resume = "" if out.complete else f"; finish it with northfinder find --resume {rd.path}"
        print(f"{rd.path}: {_state(out)} run, {out.positions_measured} of {out.positions_planned} positions; "
              f"a heading needs at least 3 positions, nothing to recompute{resume}")
        if out.positions and not args.quiet:
            print_positions(out.positions)
        return INCOMPLETE_EXIT
    again = json.loads(json.dumps(jsonable(out.result)))
    PRINTERS[kind.kind](args, rd, out, again)
    if args.json:
        RunDir(Path(args.json).parent, create=True).write_json(Path(args.json).name, again)
    if args.report and kind.kind == "find":
        from northfinder.report import write_report

        write_report(again, args.report)
    return 0 if out.complete else INCOMPLETE_EXIT


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
        verdict = _verdict(rd, runkinds.KINDS["find"].result_file, res, args.method)
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
