"""`northfinder history`: list, filter and export the results history (the per-user database, or
--db / $NORTHFINDER_HISTORY_DB: a SQLite path or a lab's postgresql:// URL); --rebuild re-indexes
run directories into it (the run directory is the source of truth, the database only an index of
it); `history sync` sends the rows a bench kept while the lab server was unreachable."""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
from pathlib import Path
from typing import Any

from northfinder import runkinds
from northfinder.cli._common import add_db_flag
from northfinder.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "history", help="list the results history (finds, aligns, campaigns)", description=__doc__
    )
    p.add_argument(
        "action", nargs="?", choices=("list", "sync"), default="list",
        help="list (default) or sync: send the rows kept while the lab server was unreachable",
    )
    add_db_flag(p)
    p.add_argument("--unit", metavar="LABEL", help="only this unit")
    p.add_argument(
        "--kind", choices=tuple(runkinds.KINDS), help="only this kind"
    )
    p.add_argument("--since", metavar="DATE", help="from this UTC date (YYYY-MM-DD) or ISO time on")
    p.add_argument("--until", metavar="DATE", help="up to this UTC date (inclusive) or ISO time")
    p.add_argument("--campaign", metavar="DIR", help="only the finds of this campaign directory")
    p.add_argument("--csv", metavar="PATH", help="write the listed rows as CSV")
    p.add_argument("--rebuild", metavar="RUNS_DIR", help="re-index every run directory under RUNS_DIR first")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from northfinder import history

    db = args.db or history.default_db()
    try:
        if args.action == "sync":
            try:
                sent, left = history.sync(db)
            except history.Unreachable as exc:
                raise InputError(f"{exc}; the rows stay in the outbox, sync again when it answers") from None
            print(f"sent {sent} rows to {history.label(db)}; {left} still waiting")
            return 0
        if args.rebuild:
            if not Path(args.rebuild).is_dir():
                raise InputError(f"--rebuild {args.rebuild}: no such directory")
            written, skipped = history.rebuild(args.rebuild, db)
            print(
                f"indexed {written} run directories under {args.rebuild} into {history.label(db)} "
                f"({skipped} without a complete result skipped)"
            )
        elif args.db and not history.is_url(db) and not Path(db).exists():
            raise InputError(f"history database {db} does not exist; check --db or index runs with --rebuild")
        with history.connect(db) as conn:
            total = history.count(conn)
            rows = history.list_runs(
                conn,
                unit=args.unit,
                kind=args.kind,
                since=args.since,
                until=args.until,
                campaign=str(Path(args.campaign).resolve()) if args.campaign else None,
            )
        waiting = history.pending(db)
        hint = history.legacy_hint(db)
    except history.HistoryError as exc:
        raise InputError(str(exc)) from None
    if args.csv:
        history.write_csv(rows, args.csv)
        print(f"{len(rows)} rows written to {args.csv}")
    console = _print(rows, history.label(db))
    say = functools.partial(console.print, markup=False, highlight=False)  # wrapped to the terminal
    say(f"database: {history.label(db)} ({total} rows in all, {len(rows)} listed)")
    if waiting:
        say(f"{waiting} rows wait in {history.outbox_path(db)}: send them with northfinder history sync")
    if hint:
        print(f"note: {hint}", file=sys.stderr)
    return 0


def _f(v: Any, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def _short(path: str) -> str:
    """A run directory relative to the working directory when it lies below it."""
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def _print(rows: list[dict[str, Any]], db: str) -> Any:
    """Print the table; returns the console it used, for the lines after it."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 170))
    t = Table(title=f"results history ({len(rows)} runs, {db})")
    for col in (
        "time (UTC)",
        "kind",
        "unit",
        "lat [°]",
        "plan",
        "method",
        "heading [°]",
        "σ [°]",
        "error [°]",
        "tilt [°]",
        "faults",
        "host",
        "run directory",
    ):
        wide = col in ("run directory", "faults")
        t.add_column(
            escape(col), justify="right" if "[" in col else "left", overflow="fold" if wide else "ellipsis"
        )
    for r in rows:
        plan = (
            f"{r['positions']} × {r['dwell_s']:g} s"
            if r["positions"] and r["dwell_s"]
            else (f"{r['duration_s']:.0f} s" if r["duration_s"] else "—")
        )
        faults = ", ".join(f"{k} {v}" for k, v in json.loads(r["faults"] or "{}").items()) or "—"
        t.add_row(
            r["time_utc"][:19].replace("T", " "),
            r["kind"],
            r["unit"] or "—",
            _f(r["latitude_deg"], ".3f"),
            plan,
            r["method"] or "—",
            _f(r["heading_deg"], ".4f"),
            _f(r["sigma_deg"], ".4f"),
            _f(r["error_deg"], "+.4f"),
            _f(r["tilt_deg"], ".3f"),
            escape(faults),
            escape(r["host"] or "—"),
            escape(_short(r["run_dir"])),
        )
    from northfinder.cli._tables import print_table_fitted  # split by columns at 80: no number cut

    print_table_fitted(console, t)
    return console
