"""Results history: one database indexing every completed run (find, align, campaign).

Where: `--db` / `$NORTHFINDER_HISTORY_DB`, else one file per user in the platform's data directory
(`platformdirs.user_data_path("northfinder")/history.sqlite`), whatever `--out` and the working
directory are. A target is a SQLite path or a lab's `postgresql://` URL (store.py: one SQL text,
two back ends). The run directory stays the source of truth: a row is derived from its files
(rows.py), keyed by the run's id, so re-indexing and re-sending are idempotent. A bench that cannot
reach the lab server keeps the row in a local outbox (a SQLite history per target) until
`northfinder history sync` sends it.
"""

from __future__ import annotations

import csv
import hashlib
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from northfinder.history.rows import (
    CAMPAIGN_JSON,
    CAMPAIGN_STATE,
    ENV_UNIT,
    RECORD_JSON,
    row_from_run,
    run_id,
    unit_from_argv,
    write_record,
)
from northfinder.history.store import (
    BUSY_TIMEOUT_S,
    MIGRATIONS,
    SCHEMA_VERSION,
    Database,
    HistoryError,
    Unreachable,
    connect,
    is_url,
    label,
    migration_sql,
)

__all__ = [
    "BUSY_TIMEOUT_S",
    "CAMPAIGN_JSON",
    "CAMPAIGN_STATE",
    "COLUMNS",
    "DB_NAME",
    "ENV_DB",
    "ENV_UNIT",
    "MIGRATIONS",
    "RECORD_JSON",
    "SCHEMA_VERSION",
    "Database",
    "HistoryError",
    "Recorded",
    "Unreachable",
    "connect",
    "count",
    "default_db",
    "is_url",
    "label",
    "legacy_hint",
    "list_runs",
    "migration_sql",
    "outbox_path",
    "pending",
    "rebuild",
    "record_or_warn",
    "record_run",
    "row_from_run",
    "run_dirs",
    "run_id",
    "sync",
    "unit_from_argv",
    "upsert",
    "write_csv",
]

APP_NAME = "northfinder"
DB_NAME = "history.sqlite"
ENV_DB = "NORTHFINDER_HISTORY_DB"
"""Environment variable naming the history (a SQLite path or a postgresql:// URL)."""
LEGACY_PLACES = (Path("runs") / DB_NAME, Path(DB_NAME))
"""Where histories made before the per-user default lie (next to the runs), relative to the cwd."""
COLUMNS = (
    "run_id",
    "host",
    "run_dir",
    "time_utc",
    "kind",
    "unit",
    "latitude_deg",
    "positions",
    "dwell_s",
    "duration_s",
    "method",
    "heading_deg",
    "sigma_deg",
    "error_deg",
    "tilt_deg",
    "faults",
    "campaign",
    "simulated",
)
"""The row's columns (besides `id`), in the order `list_runs` and the CSV export give them."""


def data_dir() -> Path:
    """The user's data directory by the platform's convention (XDG_DATA_HOME on Linux)."""
    from platformdirs import user_data_path

    return Path(user_data_path(APP_NAME, appauthor=False))


def default_db() -> str | Path:
    """$NORTHFINDER_HISTORY_DB, else the per-user history.sqlite in the user's data directory."""
    return os.environ.get(ENV_DB) or data_dir() / DB_NAME


def outbox_path(target: str | Path) -> Path:
    """The local SQLite history that keeps a lab server's rows while it cannot be reached."""
    digest = hashlib.sha1(label(target).encode()).hexdigest()[:12]
    return data_dir() / "outbox" / f"{digest}.sqlite"


# ---------------------------------------------------------------------------------------------
# Rows
# ---------------------------------------------------------------------------------------------
def upsert(db: Database, row: dict[str, Any]) -> None:
    """Insert the row, or update the one with the same run_id, in one write transaction."""
    with db.transaction():
        _write_row(db, row)


def _write_row(db: Database, row: dict[str, Any]) -> None:
    """The upsert inside a transaction (a row indexed before run ids existed, `legacy:` + the same
    path, is replaced by this one)."""
    cols = [c for c in COLUMNS if c in row]
    sets = ", ".join(f"{c} = excluded.{c}" for c in cols if c != "run_id")
    db.execute("DELETE FROM runs WHERE run_id = ?", ("legacy:" + row["run_dir"],))
    db.execute(
        f"INSERT INTO runs ({', '.join(cols)}) VALUES ({', '.join('?' for _ in cols)}) "
        f"ON CONFLICT (run_id) DO UPDATE SET {sets}",
        [row[c] for c in cols],
    )


def count(db: Database) -> int:
    return int(db.execute("SELECT COUNT(*) FROM runs").fetchone()[0])


def list_runs(
    db: Database,
    *,
    unit: str | None = None,
    kind: str | None = None,
    since: str | None = None,
    until: str | None = None,
    campaign: str | None = None,
) -> list[dict[str, Any]]:
    """Rows, oldest first, filtered by unit, kind, campaign and UTC date (`since` ≤ time < `until`
    + 1 day for a bare date YYYY-MM-DD, or an ISO time)."""
    where, params = [], []
    for col, value in (("unit", unit), ("kind", kind), ("campaign", campaign)):
        if value is not None:
            where.append(f"{col} = ?")
            params.append(value)
    if since:
        where.append("time_utc >= ?")
        params.append(_iso_bound(since, end=False))
    if until:
        where.append("time_utc < ?")
        params.append(_iso_bound(until, end=True))
    sql = f"SELECT {', '.join(COLUMNS)} FROM runs"
    if where:
        sql += " WHERE " + " AND ".join(where)
    sql += " ORDER BY time_utc, run_dir, run_id"
    return db.rows(sql, params)


def _iso_bound(text: str, end: bool) -> str:
    """A date or ISO time as the UTC string the rows are compared with; a bare date's `until`
    includes that whole day."""
    try:
        if len(text) == 10:
            d = datetime.fromisoformat(text).replace(tzinfo=UTC)
            if end:
                d = datetime.fromordinal(d.toordinal() + 1).replace(tzinfo=UTC)
        else:
            d = datetime.fromisoformat(text)
            d = d.replace(tzinfo=UTC) if d.tzinfo is None else d.astimezone(UTC)
    except ValueError:
        raise HistoryError(f"{text!r}: use a date YYYY-MM-DD or an ISO time") from None
    return d.isoformat()


def write_csv(rows: Sequence[dict[str, Any]], path: str | Path) -> None:
    """The rows as CSV with a header of COLUMNS."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(COLUMNS))
        w.writeheader()
        for r in rows:
            w.writerow({c: r.get(c) for c in COLUMNS})


# ---------------------------------------------------------------------------------------------
# Recording a run, the outbox, rebuilding
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Recorded:
    """Where a run's row went: `db` (as printed), `pending` when it waits in `outbox`."""

    run_id: str
    db: str
    pending: bool = False
    outbox: Path | None = None

    def line(self) -> str:
        if self.pending:
            return (
                f"results history: {self.db} not reachable; row kept in {self.outbox}, "
                "send it with: northfinder history sync"
            )
        return f"results history: row recorded in {self.db}"


def record_run(
    run_dir: str | Path, *, db: str | Path | None = None, unit: str | None = None
) -> Recorded | None:
    """Index one run directory (upsert by the run's id) and write where its row went into the
    run's history.json. A lab server that cannot be reached gets the row later through the
    outbox. None if the directory has no complete result."""
    d = Path(run_dir).resolve()
    row = row_from_run(d, unit)
    if row is None:
        return None
    target = db or default_db()
    try:
        with connect(target) as conn:
            upsert(conn, row)
        done = Recorded(row["run_id"], label(target))
    except Unreachable:
        box = outbox_path(target)
        with connect(box) as conn:
            upsert(conn, row)
        done = Recorded(row["run_id"], label(target), pending=True, outbox=box)
    where: dict[str, Any] = {"db": done.db, "state": "pending" if done.pending else "recorded"}
    if done.outbox:
        where["outbox"] = str(done.outbox)
    try:
        write_record(d, row, where)
    except OSError:
        pass  # a read-only copy: the row is in the database, the id is the UUID5 of its path
    return done


def record_or_warn(run_dir: str | Path, *, unit: str | None = None) -> Recorded | None:
    """record_run for a run that just finished: where the row went, one line on stderr; a failure
    to record never fails the run, it is one warning line."""
    try:
        done = record_run(run_dir, unit=unit)
    except Exception as exc:  # noqa: BLE001 — the run is saved; the index can be rebuilt
        print(
            f"northfinder: warning: {run_dir} not recorded in the history ({exc}); "
            "index it later with northfinder history --rebuild",
            file=sys.stderr,
        )
        return None
    if done is not None:
        print(done.line(), file=sys.stderr)
    return done


def pending(target: str | Path) -> int:
    """Rows waiting in the outbox of this lab server (0 for a SQLite target)."""
    box = outbox_path(target)
    if not is_url(target) or not box.exists():
        return 0
    with connect(box) as conn:
        return count(conn)


def sync(target: str | Path) -> tuple[int, int]:
    """Send the rows waiting in the outbox to the lab server, then drop them from the outbox (a
    row sent twice after a crash in between is upserted by its id: never duplicated). Returns
    (rows sent, rows still waiting)."""
    if not is_url(target):
        raise HistoryError(f"history sync: {label(target)} is not a postgresql:// server; nothing to send")
    box = outbox_path(target)
    if not box.exists():
        return 0, 0
    with connect(box) as local:
        rows = local.rows(f"SELECT {', '.join(COLUMNS)} FROM runs ORDER BY time_utc, run_id")
        if not rows:
            return 0, 0
        with connect(target) as server:
            with server.transaction():
                for row in rows:
                    _write_row(server, row)
        with local.transaction():
            for row in rows:
                local.execute("DELETE FROM runs WHERE run_id = ?", (row["run_id"],))
        _mark_sent(rows, label(target))
        return len(rows), count(local)


def _mark_sent(rows: list[dict[str, Any]], db: str) -> None:
    """history.json of each sent run (where it still exists): recorded in the server now."""
    for row in rows:
        d = Path(row["run_dir"])
        if (d / RECORD_JSON).exists():
            try:
                write_record(d, row, {"db": db, "state": "recorded"})
            except OSError:
                pass


def run_dirs(root: str | Path) -> list[Path]:
    """Every run directory under `root` (one with result.json or campaign.json), sorted."""
    root = Path(root)
    found = {p.parent for p in root.rglob("result.json")} | {p.parent for p in root.rglob(CAMPAIGN_JSON)}
    return sorted(found)


def rebuild(root: str | Path, db: str | Path | None = None) -> tuple[int, int]:
    """Re-index every run directory under `root` into `db` (default: the per-user history);
    idempotent, rows are upserted by the run's id. Returns (rows written, directories skipped as
    incomplete)."""
    written = skipped = 0
    with connect(db or default_db()) as conn:
        for d in run_dirs(root):
            row = row_from_run(d.resolve())
            if row is None:
                skipped += 1
                continue
            upsert(conn, row)
            written += 1
    return written, skipped


def legacy_hint(db: str | Path) -> str | None:
    """One line when a history made before the per-user default (runs/history.sqlite or
    history.sqlite in the working directory) holds runs `db` does not: how to bring them in."""
    for old in LEGACY_PLACES:
        if not old.exists() or (not is_url(db) and old.resolve() == Path(db).resolve()):
            continue
        try:
            with connect(old, migrate=False) as conn:
                dirs = {r["run_dir"] for r in conn.rows("SELECT run_dir FROM runs")}
            with connect(db) as conn:
                known = {r["run_dir"] for r in conn.rows("SELECT run_dir FROM runs")}
        except Exception:  # noqa: BLE001 — a hint only
            continue
        missing = dirs - known
        if missing:
            where = os.path.commonpath([str(Path(p).parent) for p in missing])
            return (
                f"{old} (an older history next to the runs) holds {len(missing)} runs not in {label(db)}; "
                f"bring them in with: northfinder history --rebuild {where}"
            )
    return None
