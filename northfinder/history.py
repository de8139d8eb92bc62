"""Results history: one SQLite file indexing every completed run (find, align, campaign).

The run directory stays the source of truth: a row is derived from the run's result.json (and
config.json / events.jsonl / campaign.json) by `row_from_run`, so `rebuild` re-indexes any copy of
a runs directory to the same rows. Writers use WAL mode, a busy timeout and one IMMEDIATE
transaction per upsert, so two benches recording into one file at once never corrupt it.
The schema version is SQLite's `PRAGMA user_version`; `MIGRATIONS[k]` takes version k to k + 1.
"""

from __future__ import annotations

import csv
import json
import math
import os
import sqlite3
import sys
import time
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

DB_NAME = "history.sqlite"
ENV_DB = "NORTHFINDER_HISTORY_DB"
"""Environment variable naming the database file (overrides the default next to the runs)."""
ENV_UNIT = "NORTHFINDER_UNIT"
"""Environment variable giving the unit label when a run's command line had no `--unit`."""
DEFAULT_RUNS_DIR = Path("runs")
CAMPAIGN_JSON = "campaign.json"
CAMPAIGN_STATE = "campaign-state.json"
BUSY_TIMEOUT_S = 30.0
KINDS = ("find", "align-swaying", "align-gnss", "campaign")

MIGRATIONS: tuple[str, ...] = (
    # 0 -> 1: the first schema
    """
    CREATE TABLE runs (
        id INTEGER PRIMARY KEY,
        run_dir TEXT NOT NULL UNIQUE,
        time_utc TEXT NOT NULL,
        kind TEXT NOT NULL,
        unit TEXT NOT NULL DEFAULT '',
        latitude_deg REAL,
        positions INTEGER,
        dwell_s REAL,
        method TEXT,
        heading_deg REAL,
        sigma_deg REAL,
        tilt_deg REAL,
        faults TEXT NOT NULL DEFAULT '{}'
    );
    CREATE INDEX runs_time ON runs(time_utc);
    """,
    # 1 -> 2: deviation from the truth/reference, the campaign a find belongs to, simulated flag
    """
    ALTER TABLE runs ADD COLUMN error_deg REAL;
    ALTER TABLE runs ADD COLUMN campaign TEXT;
    ALTER TABLE runs ADD COLUMN simulated INTEGER NOT NULL DEFAULT 0;
    ALTER TABLE runs ADD COLUMN duration_s REAL;
    CREATE INDEX runs_unit ON runs(unit, time_utc);
    """,
)
SCHEMA_VERSION = len(MIGRATIONS)
COLUMNS = (
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


class HistoryError(Exception):
    """The database cannot be opened or a run cannot be indexed (a one-line reason)."""


# ---------------------------------------------------------------------------------------------
# The database
# ---------------------------------------------------------------------------------------------
def default_db(run_dir: str | Path | None = None) -> Path:
    """$NORTHFINDER_HISTORY_DB, else `history.sqlite` in the runs directory holding `run_dir`
    (a campaign's finds count as runs of the campaign's runs directory), else runs/history.sqlite."""
    if os.environ.get(ENV_DB):
        return Path(os.environ[ENV_DB])
    if run_dir is None:
        return DEFAULT_RUNS_DIR / DB_NAME
    runs = Path(run_dir).resolve().parent
    if (runs / CAMPAIGN_JSON).exists() or (runs / CAMPAIGN_STATE).exists():
        runs = runs.parent
    return runs / DB_NAME


def connect(db: str | Path) -> sqlite3.Connection:
    """Open (creating and migrating) the database: WAL, busy timeout, schema SCHEMA_VERSION."""
    path = Path(db)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        conn = sqlite3.connect(path, timeout=BUSY_TIMEOUT_S, isolation_level=None)
        conn.execute(f"PRAGMA busy_timeout = {int(BUSY_TIMEOUT_S * 1000)}")
        _set_wal(conn)
        conn.execute("PRAGMA synchronous = NORMAL")
        migrate(conn)
    except (OSError, sqlite3.Error) as exc:
        raise HistoryError(f"history database {path}: {exc}") from None
    conn.row_factory = sqlite3.Row
    return conn


def _set_wal(conn: sqlite3.Connection) -> None:
    """Switch to WAL. SQLite answers "database is locked" at once, without the busy handler, when
    another process is switching a new database at the same moment (two writers' first rows): retry
    for up to the busy timeout."""
    deadline = time.monotonic() + BUSY_TIMEOUT_S
    while True:
        try:
            conn.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.05)


def migrate(conn: sqlite3.Connection, target: int = SCHEMA_VERSION) -> int:
    """Bring the schema to `target` in one transaction (another process may be migrating too: the
    version is read again under the write lock). Returns the version found before."""
    conn.execute("BEGIN IMMEDIATE")
    try:
        found = conn.execute("PRAGMA user_version").fetchone()[0]
        if found > SCHEMA_VERSION:
            raise HistoryError(
                f"schema version {found} is newer than this northfinder's {SCHEMA_VERSION}; "
                "upgrade northfinder"
            )
        for version in range(found, target):
            for statement in MIGRATIONS[version].split(";"):
                if statement.strip():
                    conn.execute(statement)
            conn.execute(f"PRAGMA user_version = {version + 1}")
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise
    return found


def upsert(conn: sqlite3.Connection, row: dict[str, Any]) -> None:
    """Insert the row, or replace the one with the same run_dir (one IMMEDIATE transaction)."""
    cols = [c for c in COLUMNS if c in row]
    sets = ", ".join(f"{c} = excluded.{c}" for c in cols if c != "run_dir")
    sql = (
        f"INSERT INTO runs ({', '.join(cols)}) VALUES ({', '.join('?' for _ in cols)}) "
        f"ON CONFLICT(run_dir) DO UPDATE SET {sets}"
    )
    conn.execute("BEGIN IMMEDIATE")
    try:
        conn.execute(sql, [row[c] for c in cols])
        conn.execute("COMMIT")
    except BaseException:
        conn.execute("ROLLBACK")
        raise


def list_runs(
    conn: sqlite3.Connection,
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
    sql += " ORDER BY time_utc, run_dir"
    return [dict(r) for r in conn.execute(sql, params)]


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
# A run directory as a row
# ---------------------------------------------------------------------------------------------
def _read(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _start_event(run_dir: Path) -> dict[str, Any]:
    try:
        with open(run_dir / "events.jsonl", encoding="utf-8") as fh:
            for line in fh:
                try:
                    e = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if e.get("event") == "start":
                    return e
    except FileNotFoundError:
        pass
    return {}


def unit_from_argv(argv: Iterable[str] | None) -> str | None:
    """The value of `--unit X` / `--unit=X` in a saved command line."""
    args = list(argv or [])
    for k, a in enumerate(args):
        if a == "--unit" and k + 1 < len(args):
            return args[k + 1]
        if a.startswith("--unit="):
            return a.split("=", 1)[1]
    return None


def _faults(result: dict[str, Any]) -> dict[str, int]:
    """The non-zero fault counters of a find (re-measured positions, stage errors, lost samples,
    EMCY, resumed sessions) or an align (lost IMU samples)."""
    f = result.get("faults") or {}
    out: dict[str, int] = {}
    if f:
        imu, acc = f.get("imu", {}), f.get("accel", {})
        out = {
            "remeasured": len(f.get("remeasured", [])),
            "stage_errors": len(f.get("stage_errors", [])),
            "imu_lost": int(imu.get("lost_samples", 0)),
            "imu_bad_crc": int(imu.get("bad_crc", 0)),
            "accel_lost": int(acc.get("lost_samples", 0)),
            "emcy": int(acc.get("emcy", 0)),
            "sessions_resumed": int(f.get("sessions", 1)) - 1,
        }
    elif isinstance(result.get("imu"), dict):
        out = {"imu_lost": int(result["imu"].get("lost_samples", 0))}
    return {k: v for k, v in out.items() if v}


def _tilt_deg(result: dict[str, Any]) -> float | None:
    t = result.get("tilt")
    if isinstance(t, dict) and t.get("tilt_deg") is not None:
        return float(t["tilt_deg"])
    p, r = result.get("pitch_deg"), result.get("roll_deg")
    if p is None or r is None:
        return None
    c = max(-1.0, min(1.0, math.cos(math.radians(p)) * math.cos(math.radians(r))))
    return math.degrees(math.acos(c))


def _utc(start: dict[str, Any], fallback: Path) -> str:
    """The run's start time (UTC ISO) from its start event, else the file's modification time."""
    if start.get("utc"):
        d = datetime.fromisoformat(str(start["utc"]))
        return (d.replace(tzinfo=UTC) if d.tzinfo is None else d.astimezone(UTC)).isoformat()
    return datetime.fromtimestamp(fallback.stat().st_mtime, UTC).isoformat()


def row_from_run(run_dir: str | Path, unit: str | None = None) -> dict[str, Any] | None:
    """The history row of a completed run directory; None if it holds no complete result."""
    d = Path(run_dir).resolve()
    if (d / CAMPAIGN_JSON).exists():
        return _campaign_row(d, unit)
    result = _read(d / "result.json")
    if not result or not result.get("complete", False):
        return None
    config = _read(d / "config.json") or {}
    start = _start_event(d)
    kind = str(result.get("kind") or config.get("kind") or "find")
    parent = d.parent
    in_campaign = (parent / CAMPAIGN_JSON).exists() or (parent / CAMPAIGN_STATE).exists()
    run_cfg = (config.get("bench") or {}).get("run", {}) if kind == "find" else {}
    return {
        "run_dir": str(d),
        "time_utc": _utc(start, d / "result.json"),
        "kind": kind,
        "unit": unit
        or unit_from_argv(config.get("argv"))
        or _campaign_unit(parent)
        or os.environ.get(ENV_UNIT, ""),
        "latitude_deg": result.get("latitude_deg"),
        "positions": result.get("positions_measured") if kind == "find" else None,
        "dwell_s": run_cfg.get("dwell_s", start.get("dwell_s")) if kind == "find" else None,
        "duration_s": result.get("duration_device_s"),
        "method": result.get("method"),
        "heading_deg": result.get("heading_deg"),
        "sigma_deg": result.get("heading_std_deg"),
        "error_deg": result.get("error_deg"),
        "tilt_deg": _tilt_deg(result),
        "faults": json.dumps(_faults(result), sort_keys=True),
        "campaign": str(parent) if in_campaign else None,
        "simulated": int(bool(config.get("simulate") or result.get("truth"))),
    }


def _campaign_unit(parent: Path) -> str | None:
    """The unit of the campaign a find belongs to (a resumed campaign's command line has none)."""
    c = _read(parent / CAMPAIGN_JSON)
    return (c or {}).get("unit") or None


def _campaign_row(d: Path, unit: str | None) -> dict[str, Any] | None:
    """A finished campaign: the main method's mean deviation, observed σ and mean tilt."""
    c = _read(d / CAMPAIGN_JSON)
    if not c or not c.get("complete"):
        return None
    stats = c.get("statistics", {}).get(c.get("method", "exact"), {})
    plan = c.get("plan", {})
    return {
        "run_dir": str(d),
        "time_utc": str(c.get("started_utc")),
        "kind": "campaign",
        "unit": unit or c.get("unit") or os.environ.get(ENV_UNIT, ""),
        "latitude_deg": c.get("latitude_deg"),
        "positions": plan.get("positions"),
        "dwell_s": plan.get("dwell_s"),
        "duration_s": None,
        "method": c.get("method"),
        "heading_deg": None,
        "sigma_deg": stats.get("std_deg"),
        "error_deg": stats.get("mean_deg"),
        "tilt_deg": c.get("mean_tilt_deg"),
        "faults": json.dumps({"failed_finds": len(c["failed"])} if c.get("failed") else {}),
        "campaign": None,
        "simulated": int(bool(c.get("simulate"))),
    }


def record_run(run_dir: str | Path, *, db: str | Path | None = None, unit: str | None = None) -> bool:
    """Index one run directory (upsert by its path). False if it has no complete result."""
    row = row_from_run(run_dir, unit)
    if row is None:
        return False
    conn = connect(db or default_db(run_dir))
    try:
        upsert(conn, row)
    finally:
        conn.close()
    return True


def record_or_warn(run_dir: str | Path, *, unit: str | None = None) -> None:
    """record_run for a run that just finished: a failure to record never fails the run, it is
    one warning line on stderr."""
    try:
        record_run(run_dir, unit=unit)
    except Exception as exc:  # noqa: BLE001 — the run is saved; the index can be rebuilt
        print(
            f"northfinder: warning: {run_dir} not recorded in the history ({exc}); "
            "index it later with northfinder history --rebuild",
            file=sys.stderr,
        )


def run_dirs(root: str | Path) -> list[Path]:
    """Every run directory under `root` (one with result.json or campaign.json), sorted."""
    root = Path(root)
    found = {p.parent for p in root.rglob("result.json")} | {p.parent for p in root.rglob(CAMPAIGN_JSON)}
    return sorted(found)


def rebuild(root: str | Path, db: str | Path) -> tuple[int, int]:
    """Re-index every run directory under `root` (idempotent: rows are upserted by path).
    Returns (rows written, directories skipped as incomplete)."""
    conn = connect(db)
    written = skipped = 0
    try:
        for d in run_dirs(root):
            row = row_from_run(d)
            if row is None:
                skipped += 1
                continue
            upsert(conn, row)
            written += 1
    finally:
        conn.close()
    return written, skipped
