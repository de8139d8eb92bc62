"""`northfinder history`: list, filter and export the results history; --rebuild re-indexes run
directories (the run directory is the source of truth, the database only an index of it)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from northfinder.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "history", help="list the results history (finds, aligns, campaigns)", description=__doc__
    )
    p.add_argument(
        "--db", metavar="PATH", help="database (default $NORTHFINDER_HISTORY_DB or runs/history.sqlite)"
    )
    p.add_argument("--unit", metavar="LABEL", help="only this unit")
    p.add_argument(
        "--kind", choices=("find", "align-swaying", "align-gnss", "campaign"), help="only this kind"
    )
    p.add_argument("--since", metavar="DATE", help="from this UTC date (YYYY-MM-DD) or ISO time on")
    p.add_argument("--until", metavar="DATE", help="up to this UTC date (inclusive) or ISO time")
    p.add_argument("--campaign", metavar="DIR", help="only the finds of this campaign directory")
    p.add_argument("--csv", metavar="PATH", help="write the listed rows as CSV")
    p.add_argument("--rebuild", metavar="RUNS_DIR", help="re-index every run directory under RUNS_DIR first")
    p.set_defaults(func=run)


def _db_path(args: argparse.Namespace) -> Path:
    from northfinder import history

    if args.db:
        return Path(args.db)
    if args.rebuild and not os.environ.get(history.ENV_DB):
        return Path(args.rebuild) / history.DB_NAME
    return history.default_db()


def run(args: argparse.Namespace) -> int:
    from northfinder import history

    db = _db_path(args)
    try:
        if args.rebuild:
            if not Path(args.rebuild).is_dir():
                raise InputError(f"--rebuild {args.rebuild}: no such directory")
            written, skipped = history.rebuild(args.rebuild, db)
            print(
                f"indexed {written} run directories under {args.rebuild} into {db} "
                f"({skipped} without a complete result skipped)"
            )
        elif not db.exists():
            raise InputError(
                f"history database {db} does not exist; give --db PATH or index runs with --rebuild"
            )
        conn = history.connect(db)
        try:
            rows = history.list_runs(
                conn,
                unit=args.unit,
                kind=args.kind,
                since=args.since,
                until=args.until,
                campaign=str(Path(args.campaign).resolve()) if args.campaign else None,
            )
        finally:
            conn.close()
    except history.HistoryError as exc:
        raise InputError(str(exc)) from None
    if args.csv:
        history.write_csv(rows, args.csv)
        print(f"{len(rows)} rows written to {args.csv}")
    _print(rows, db)
    return 0


def _f(v: Any, fmt: str) -> str:
    return "—" if v is None else format(v, fmt)


def _short(path: str) -> str:
    """A run directory relative to the working directory when it lies below it."""
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def _print(rows: list[dict[str, Any]], db: Path) -> None:
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
            escape(_short(r["run_dir"])),
        )
    from northfinder.cli._tables import print_table_fitted  # split by columns at 80: no number cut

    print_table_fitted(console, t)
