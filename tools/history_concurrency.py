"""Concurrent writers into the results history: N processes × M runs each, all starting at the
same instant, every run recorded through `northfinder.history.record_run` (the call a finished
find makes). Prints, per database: rows, distinct run ids, duplicates, the wall time of the whole
and of each writer. Exit 1 if a row is missing or duplicated.

    python3 tools/history_concurrency.py                          # a new SQLite file (+ PostgreSQL
                                                                  #   if NORTHFINDER_TEST_PG_URL is set)
    python3 tools/history_concurrency.py --db postgresql://postgres@/northfinder_test?host=/tmp/x
    python3 tools/history_concurrency.py --writers 4 --runs 200   # the defaults

A PostgreSQL target gets a fresh schema of its own (dropped afterwards), so its count starts at 0.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from urllib.parse import quote

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from northfinder import history  # noqa: E402

WRITER = """
import json, sys, time
from pathlib import Path
from northfinder import history
root, db, n, start = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
while time.time() < start:
    time.sleep(0.001)
t0 = time.monotonic()
for k in range(n):
    assert history.record_run(root / f"run-{k:03d}", db=db)
print(json.dumps({"writer": root.name, "s": time.monotonic() - t0}))
"""


def make_runs(root: Path, writers: int, runs: int) -> list[Path]:
    """`runs` complete find directories per writer (result.json, config.json, a start event)."""
    dirs = []
    for w in range(writers):
        wdir = root / f"bench-{w + 1}"
        for k in range(runs):
            d = wdir / f"run-{k:03d}"
            d.mkdir(parents=True)
            argv = ["northfinder", "find", "--simulate", "--unit", f"NF-CONC-{w + 1}"]
            (d / "config.json").write_text(json.dumps({"argv": argv, "bench": {"run": {"dwell_s": 20.0}}}))
            utc = f"2026-11-25T{w:02d}:{k // 60:02d}:{k % 60:02d}+00:00"
            (d / "events.jsonl").write_text(json.dumps({"event": "start", "utc": utc}) + "\n")
            result = {"complete": True, "method": "exact", "heading_deg": 10.0 + k, "heading_std_deg": 0.01,
                      "positions_measured": 8, "latitude_deg": 45.0}  # fmt: skip
            (d / "result.json").write_text(json.dumps(result))
        dirs.append(wdir)
    return dirs


def fresh_schema(url: str) -> tuple[str, str]:
    import psycopg

    name = f"nf_conc_{uuid.uuid4().hex[:10]}"
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute(f"CREATE SCHEMA {name}")
    sep = "&" if "?" in url else "?"
    return f"{url}{sep}options={quote(f'-csearch_path={name}')}", name


def drop_schema(url: str, name: str) -> None:
    import psycopg

    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute(f"DROP SCHEMA {name} CASCADE")


def run_target(target: str, dirs: list[Path], runs: int) -> bool:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    start = time.time() + 2.0  # every writer imported and waiting
    procs = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(d), target, str(runs), str(start)],
                         env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for d in dirs
    ]  # fmt: skip
    outs = [p.communicate(timeout=900) for p in procs]
    wall = time.time() - start
    ok = all(p.returncode == 0 for p in procs)
    for p, (_out, err) in zip(procs, outs, strict=True):
        if p.returncode:
            print(f"  writer failed (exit {p.returncode}): {err.strip().splitlines()[-1:]}")
    times = [json.loads(o)["s"] for o, _ in outs if o.strip()]
    with history.connect(target) as db:
        total, distinct = db.execute("SELECT COUNT(*), COUNT(DISTINCT run_id) FROM runs").fetchone()
        per_unit = dict(db.execute("SELECT unit, COUNT(*) FROM runs GROUP BY unit ORDER BY unit").fetchall())
        dialect = db.dialect
    expected = len(dirs) * runs
    print(f"{dialect}: {history.label(target)}")
    print(f"  {len(dirs)} writers x {runs} runs: {total} rows, {distinct} distinct run ids, "
          f"{total - distinct} duplicated, {expected - distinct} missing; per unit {per_unit}")  # fmt: skip
    print(f"  wall {wall:.2f} s for {expected} rows ({expected / wall:.0f} rows/s); "
          f"per writer {', '.join(f'{t:.2f}' for t in times)} s")  # fmt: skip
    return ok and total == distinct == expected


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--db", action="append", help="a SQLite path or postgresql:// URL (repeatable)")
    ap.add_argument("--writers", type=int, default=4)
    ap.add_argument("--runs", type=int, default=200, help="runs per writer")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="nf-hist-conc-") as tmp:
        root = Path(tmp)
        targets = args.db or [str(root / "history.sqlite")] + (
            [os.environ["NORTHFINDER_TEST_PG_URL"]] if os.environ.get("NORTHFINDER_TEST_PG_URL") else []
        )
        ok = True
        for n, target in enumerate(targets):
            dirs = make_runs(root / f"target-{n}", args.writers, args.runs)
            schema = None
            if history.is_url(target):
                target, schema = fresh_schema(target)
            try:
                ok &= run_target(target, dirs, args.runs)
            finally:
                if schema:
                    drop_schema(target.split("options=")[0].rstrip("?&"), schema)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
