"""The results history: schema and migrations, rows from run directories, filters, CSV, rebuild,
concurrent writers (two real processes), and the `history` command."""

from __future__ import annotations

import csv
import json
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import only_line, run_cli, subprocess_env

from northfinder import history


def _find_result(heading: float, sigma: float, complete: bool = True) -> dict:
    """A find's result.json with the keys the history reads (docs/result-schema.md)."""
    return {
        "schema": "northfinder.result/1",
        "complete": complete,
        "positions_planned": 8,
        "positions_measured": 8 if complete else 5,
        "method": "exact",
        "heading_deg": heading,
        "heading_std_deg": sigma,
        "methods": {"exact": {"heading_deg": heading}},
        "tilt": {"pitch_deg": 3.0, "roll_deg": 4.0, "tilt_deg": 5.0, "tilt_azimuth_deg": 10.0},
        "latitude_deg": 40.0,
        "duration_device_s": 160.0,
        "faults": {
            "sessions": 1,
            "remeasured": [{"index": 2, "attempt": 1, "reason": "gap"}],
            "stage_errors": [],
            "imu": {"lost_samples": 3, "bad_crc": 0},
            "accel": {"lost_samples": 0, "emcy": 0},
        },
    }


def make_run(root: Path, name: str, utc: str, unit: str | None, heading: float = 10.0, **kw) -> Path:
    """A find run directory: config.json (its command line with --unit), a start event, result.json."""
    d = root / name
    d.mkdir(parents=True)
    argv = ["northfinder", "find", "--simulate"] + (["--unit", unit] if unit else [])
    (d / "config.json").write_text(json.dumps({"bench": {"run": {"dwell_s": 20.0}}, "argv": argv}))
    (d / "events.jsonl").write_text(json.dumps({"event": "start", "utc": utc, "dwell_s": 20.0}) + "\n")
    (d / "result.json").write_text(json.dumps(_find_result(heading, 0.01, **kw)))
    return d


def test_new_database_schema_wal_and_version(tmp_path):
    conn = history.connect(tmp_path / "h.sqlite")
    assert conn.execute("PRAGMA user_version").fetchone()[0] == history.SCHEMA_VERSION == 2
    assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert conn.execute("PRAGMA busy_timeout").fetchone()[0] == 30000
    cols = [r[1] for r in conn.execute("PRAGMA table_info(runs)")]
    assert set(history.COLUMNS) | {"id"} == set(cols)
    conn.close()


def test_migration_from_version_1_keeps_the_rows(tmp_path):
    db = tmp_path / "old.sqlite"
    old = sqlite3.connect(db)
    old.executescript(history.MIGRATIONS[0])
    old.execute("PRAGMA user_version = 1")
    old.execute(
        "INSERT INTO runs (run_dir, time_utc, kind, unit, heading_deg, sigma_deg) "
        "VALUES ('/r/1', '2026-01-01T00:00:00+00:00', 'find', 'SN-7', 12.5, 0.01)"
    )
    old.commit()
    old.close()
    conn = history.connect(db)
    assert conn.execute("PRAGMA user_version").fetchone()[0] == 2
    (row,) = history.list_runs(conn)
    assert (row["unit"], row["heading_deg"], row["error_deg"], row["simulated"]) == ("SN-7", 12.5, None, 0)
    history.upsert(conn, {**row, "error_deg": 0.003, "campaign": "/c"})  # the new columns are writable
    assert history.list_runs(conn)[0]["error_deg"] == 0.003
    conn.close()


def test_a_newer_schema_is_refused_in_one_line(tmp_path):
    db = tmp_path / "new.sqlite"
    c = sqlite3.connect(db)
    c.execute("PRAGMA user_version = 99")
    c.close()
    with pytest.raises(history.HistoryError, match="schema version 99 is newer"):
        history.connect(db)


def test_rows_filters_and_csv(tmp_path):
    runs = tmp_path / "runs"
    make_run(runs, "a", "2026-03-01T10:00:00+00:00", "SN-1", heading=11.0)
    make_run(runs, "b", "2026-03-02T23:59:00+00:00", "SN-2", heading=12.0)
    make_run(runs, "c", "2026-03-05T08:00:00+00:00", "SN-1", heading=13.0)
    make_run(runs, "d", "2026-03-06T08:00:00+00:00", "SN-1", complete=False)
    db = tmp_path / "h.sqlite"
    assert [history.record_run(runs / n, db=db) for n in "abcd"] == [True, True, True, False]
    conn = history.connect(db)
    every = history.list_runs(conn)
    assert [r["heading_deg"] for r in every] == [11.0, 12.0, 13.0]  # the incomplete run is not a result
    r = every[0]
    assert (r["kind"], r["unit"], r["positions"], r["dwell_s"], r["tilt_deg"]) == (
        "find",
        "SN-1",
        8,
        20.0,
        5.0,
    )
    assert json.loads(r["faults"]) == {"remeasured": 1, "imu_lost": 3}
    assert [x["heading_deg"] for x in history.list_runs(conn, unit="SN-1")] == [11.0, 13.0]
    assert [x["heading_deg"] for x in history.list_runs(conn, until="2026-03-02")] == [11.0, 12.0]
    assert [x["heading_deg"] for x in history.list_runs(conn, since="2026-03-03")] == [13.0]
    assert history.list_runs(conn, kind="campaign") == []
    history.write_csv(every, tmp_path / "h.csv")
    with open(tmp_path / "h.csv", newline="") as fh:
        back = list(csv.DictReader(fh))
    assert [float(x["heading_deg"]) for x in back] == [11.0, 12.0, 13.0]
    assert list(back[0]) == list(history.COLUMNS)
    # recording the same run again replaces its row
    assert history.record_run(runs / "a", db=db, unit="SN-9")
    assert (
        len(history.list_runs(conn)) == 3 and history.list_runs(conn, unit="SN-9")[0]["heading_deg"] == 11.0
    )
    conn.close()


def test_rebuild_is_idempotent_and_a_copy_gives_the_same_rows(tmp_path):
    runs = tmp_path / "runs"
    for k in range(5):
        make_run(runs, f"find-{k}", f"2026-04-0{k + 1}T12:00:00+00:00", "SN-3", heading=float(k))
    db = tmp_path / "h.sqlite"
    assert history.rebuild(runs, db) == (5, 0)
    conn = history.connect(db)
    first = history.list_runs(conn)
    assert history.rebuild(runs, db) == (5, 0)
    assert history.list_runs(conn) == first
    conn.close()
    copy = tmp_path / "copy"
    shutil.copytree(runs, copy)
    db2 = tmp_path / "h2.sqlite"
    history.rebuild(copy, db2)
    conn2 = history.connect(db2)
    second = history.list_runs(conn2)
    conn2.close()

    def strip(rows: list[dict], root: Path) -> list[dict]:
        return [{**r, "run_dir": str(Path(r["run_dir"]).relative_to(root.resolve()))} for r in rows]

    assert strip(second, copy) == strip(first, runs)


WRITER = """
import sys, time
from pathlib import Path
from northfinder import history
root, db, n = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
while time.time() < float(sys.argv[4]):  # both writers start at the same instant
    time.sleep(0.001)
for k in range(n):
    assert history.record_run(root / f"run-{k:03d}", db=db)
"""


def test_two_processes_writing_200_rows_each_leave_400_and_an_intact_database(tmp_path):
    n = 200
    db = tmp_path / "shared.sqlite"
    for w in ("A", "B"):
        for k in range(n):
            make_run(
                tmp_path / w, f"run-{k:03d}", f"2026-05-01T00:{k // 60:02d}:{k % 60:02d}+00:00", f"bench-{w}"
            )
    start = time.time() + 1.5
    t0 = time.monotonic()
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", WRITER, str(tmp_path / w), str(db), str(n), str(start)],
            env=subprocess_env(),
            stderr=subprocess.PIPE,
            text=True,
        )
        for w in ("A", "B")
    ]
    errs = [p.communicate(timeout=120)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    conn = sqlite3.connect(db)
    rows = conn.execute("SELECT COUNT(*), COUNT(DISTINCT run_dir) FROM runs").fetchone()
    per_unit = dict(conn.execute("SELECT unit, COUNT(*) FROM runs GROUP BY unit").fetchall())
    check = conn.execute("PRAGMA integrity_check").fetchall()
    conn.close()
    print(
        f"\ntwo writers x {n}: rows {rows}, per unit {per_unit}, integrity_check {check}, "
        f"{time.monotonic() - t0 - 1.5:.1f} s"
    )
    assert rows == (2 * n, 2 * n)
    assert per_unit == {"bench-A": n, "bench-B": n}
    assert check == [("ok",)]


def test_a_recording_failure_is_one_warning_line_and_no_exception(tmp_path, monkeypatch, capsys):
    run = make_run(tmp_path / "runs", "r", "2026-01-01T00:00:00+00:00", None)
    (tmp_path / "blocker").write_text("a file where the database's directory should be")
    monkeypatch.setenv(history.ENV_DB, str(tmp_path / "blocker" / "h.sqlite"))
    history.record_or_warn(run)
    line = only_line(capsys.readouterr().err)
    assert line.startswith("northfinder: warning:") and "--rebuild" in line


def test_the_default_database_is_next_to_the_runs(tmp_path, monkeypatch):
    monkeypatch.delenv(history.ENV_DB, raising=False)
    run = make_run(tmp_path / "runs", "r", "2026-01-01T00:00:00+00:00", None)
    assert history.default_db(run) == (tmp_path / "runs" / history.DB_NAME).resolve()
    camp = tmp_path / "runs" / "campaign-1"
    camp.mkdir()
    (camp / "campaign.json").write_text("{}")
    assert history.default_db(camp / "step1-run01") == (tmp_path / "runs" / history.DB_NAME).resolve()


def test_history_command_lists_filters_exports_and_rebuilds(tmp_path):
    runs = tmp_path / "runs"
    make_run(runs, "a", "2026-06-01T10:00:00+00:00", "SN-1", heading=21.0)
    make_run(runs, "b", "2026-06-02T10:00:00+00:00", "SN-2", heading=22.0)
    out = run_cli("history", "--rebuild", str(runs), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "indexed 2 run directories" in out.stdout
    out = run_cli("history", "--unit", "SN-2", "--csv", "x.csv", cwd=tmp_path)  # default runs/history.sqlite
    assert out.returncode == 0, out.stderr
    assert "22.0000" in out.stdout and "21.0000" not in out.stdout and "(1 runs" in out.stdout
    assert len((tmp_path / "x.csv").read_text().splitlines()) == 2
    bad = run_cli("history", "--db", str(tmp_path / "none.sqlite"), cwd=tmp_path)
    assert bad.returncode == 2 and "does not exist" in only_line(bad.stderr)
    bad = run_cli("history", "--since", "March", cwd=tmp_path)
    assert bad.returncode == 2 and "YYYY-MM-DD" in only_line(bad.stderr)
