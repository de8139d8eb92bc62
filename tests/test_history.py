"""The results history on both back ends (SQLite and a real PostgreSQL server, the same tests):
schema and migrations, rows from run directories keyed by the run's id, filters, CSV, rebuild,
concurrent writers (real processes), the outbox and `history sync` across a real network outage,
the per-user default and the `history` command."""

from __future__ import annotations

import csv
import json
import shutil
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import history_backends
import pytest
from helpers import only_line, run_cli, subprocess_env
from history_backends import TcpRelay, pg_url_or_skip

from northfinder import history
from northfinder.history.store import Database

target = history_backends.target  # the fixtures: each back end / a fresh PostgreSQL schema
pg_schema = history_backends.pg_schema


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


def _columns(db: Database) -> set[str]:
    return {d[0] for d in db.execute("SELECT * FROM runs WHERE 1 = 0").description}


def test_new_database_schema_and_version(target):
    with history.connect(target) as db:
        assert db.schema_version() == history.SCHEMA_VERSION == 3
        assert _columns(db) == set(history.COLUMNS) | {"id"}
        if db.dialect == "sqlite":
            assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
            assert db.execute("PRAGMA busy_timeout").fetchone()[0] == 30000
        else:
            kinds = dict(
                db.execute(
                    "SELECT column_name, data_type FROM information_schema.columns "
                    "WHERE table_name = 'runs' AND table_schema = current_schema()"
                ).fetchall()
            )
            assert kinds["heading_deg"] == "double precision" and kinds["run_id"] == "text"


@pytest.mark.parametrize("old_version", [1, 2])
def test_migrations_keep_the_rows_and_a_recorded_run_replaces_its_legacy_row(target, tmp_path, old_version):
    with history.connect(target, migrate=False) as db:
        db.migrate(target=old_version)
        db.execute(
            "INSERT INTO runs (run_dir, time_utc, kind, unit, heading_deg, sigma_deg) "
            "VALUES (?, '2026-01-01T00:00:00+00:00', 'find', 'SN-7', 12.5, 0.01)",
            (str(tmp_path / "old-run"),),
        )
    with history.connect(target) as db:
        assert db.schema_version() == 3
        (row,) = history.list_runs(db)
        assert (row["run_id"], row["unit"], row["heading_deg"], row["error_deg"], row["simulated"]) == (
            f"legacy:{tmp_path / 'old-run'}",
            "SN-7",
            12.5,
            None,
            0,
        )
    run = make_run(tmp_path, "old-run", "2026-01-01T00:00:00+00:00", "SN-7", heading=12.5)
    assert history.record_run(run, db=target)  # the same directory, now with its run id
    with history.connect(target) as db:
        (row,) = history.list_runs(db)
        assert row["run_id"] == json.loads((run / history.RECORD_JSON).read_text())["run_id"]


def test_a_newer_schema_is_refused_in_one_line(target):
    with history.connect(target) as db:
        with db.transaction():
            db._set_version(99)
    with pytest.raises(history.HistoryError, match="schema version 99 is newer"):
        history.connect(target)


def test_rows_filters_and_csv(target, tmp_path):
    runs = tmp_path / "runs"
    make_run(runs, "a", "2026-03-01T10:00:00+00:00", "SN-1", heading=11.0)
    make_run(runs, "b", "2026-03-02T23:59:00+00:00", "SN-2", heading=12.0)
    make_run(runs, "c", "2026-03-05T08:00:00+00:00", "SN-1", heading=13.0)
    make_run(runs, "d", "2026-03-06T08:00:00+00:00", "SN-1", complete=False)
    recorded = [history.record_run(runs / n, db=target) for n in "abcd"]
    assert [r is not None and not r.pending for r in recorded] == [True, True, True, False]
    assert recorded[0].db == history.label(target)
    kept = json.loads((runs / "a" / history.RECORD_JSON).read_text())  # where the row went
    assert (kept["db"], kept["state"], kept["run_id"]) == (
        history.label(target),
        "recorded",
        recorded[0].run_id,
    )
    with history.connect(target) as db:
        every = history.list_runs(db)
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
        assert [x["heading_deg"] for x in history.list_runs(db, unit="SN-1")] == [11.0, 13.0]
        assert [x["heading_deg"] for x in history.list_runs(db, until="2026-03-02")] == [11.0, 12.0]
        assert [x["heading_deg"] for x in history.list_runs(db, since="2026-03-03")] == [13.0]
        assert history.list_runs(db, kind="campaign") == []
        history.write_csv(every, tmp_path / "h.csv")
        with open(tmp_path / "h.csv", newline="") as fh:
            back = list(csv.DictReader(fh))
        assert [float(x["heading_deg"]) for x in back] == [11.0, 12.0, 13.0]
        assert list(back[0]) == list(history.COLUMNS)
        # recording the same run again updates its row (the run's id is the key)
        assert history.record_run(runs / "a", db=target, unit="SN-9")
        assert history.count(db) == 3 and history.list_runs(db, unit="SN-9")[0]["heading_deg"] == 11.0


def test_rebuild_is_idempotent_and_a_copy_keeps_the_run_ids(target, tmp_path):
    runs = tmp_path / "runs"
    for k in range(5):
        make_run(runs, f"find-{k}", f"2026-04-0{k + 1}T12:00:00+00:00", "SN-3", heading=float(k))
    assert history.rebuild(runs, target) == (5, 0)
    with history.connect(target) as db:
        first = history.list_runs(db)
        assert history.rebuild(runs, target) == (5, 0)
        assert history.list_runs(db) == first
    for k in range(5):
        history.record_run(runs / f"find-{k}", db=target)  # writes each run's history.json
    with history.connect(target) as db:
        assert history.list_runs(db) == first  # same ids: the run's id was the UUID5 rebuild used
    copy = tmp_path / "copy"
    shutil.copytree(runs, copy)
    other = tmp_path / "other.sqlite"
    history.rebuild(copy, other)
    with history.connect(other) as db:
        second = history.list_runs(db)

    def strip(rows: list[dict], root: Path) -> list[dict]:
        return [{**r, "run_dir": str(Path(r["run_dir"]).relative_to(root.resolve()))} for r in rows]

    assert strip(second, copy) == strip(first, runs)  # run_id and host travel with the directory


WRITER = """
import sys, time
from pathlib import Path
from northfinder import history
root, db, n = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
while time.time() < float(sys.argv[4]):  # every writer starts at the same instant
    time.sleep(0.001)
for k in range(n):
    assert history.record_run(root / f"run-{k:03d}", db=db)
"""


def test_two_processes_writing_200_rows_each_leave_400_none_duplicated(target, tmp_path):
    n = 200
    for w in ("A", "B"):
        for k in range(n):
            make_run(
                tmp_path / w, f"run-{k:03d}", f"2026-05-01T00:{k // 60:02d}:{k % 60:02d}+00:00", f"bench-{w}"
            )
    start = time.time() + 1.5
    t0 = time.monotonic()
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", WRITER, str(tmp_path / w), str(target), str(n), str(start)],
            env=subprocess_env(),
            stderr=subprocess.PIPE,
            text=True,
        )
        for w in ("A", "B")
    ]
    errs = [p.communicate(timeout=300)[1] for p in procs]
    assert [p.returncode for p in procs] == [0, 0], errs
    with history.connect(target) as db:
        rows = tuple(db.execute("SELECT COUNT(*), COUNT(DISTINCT run_id) FROM runs").fetchone())
        per_unit = dict(db.execute("SELECT unit, COUNT(*) FROM runs GROUP BY unit").fetchall())
        dialect = db.dialect
    print(
        f"\n{dialect}: two writers x {n}: rows {rows}, per unit {per_unit}, "
        f"{time.monotonic() - t0 - 1.5:.1f} s"
    )
    assert rows == (2 * n, 2 * n)
    assert per_unit == {"bench-A": n, "bench-B": n}
    if dialect == "sqlite":
        conn = sqlite3.connect(target)
        assert conn.execute("PRAGMA integrity_check").fetchall() == [("ok",)]
        conn.close()


def test_a_bench_offline_keeps_its_rows_and_sync_delivers_them_once(pg_schema, tmp_path, capsys):
    relay = TcpRelay(pg_schema.base_url)
    url = relay.url(pg_schema.name)
    runs = [
        make_run(tmp_path, f"r{k}", f"2026-07-01T00:0{k}:00+00:00", "SN-OFF", heading=float(k))
        for k in range(3)
    ]
    relay.start()
    try:
        assert not history.record_run(runs[0], db=url).pending  # online
        relay.stop()  # the network goes down
        for run in runs[1:]:
            done = history.record_run(run, db=url)
            assert done.pending and done.outbox == history.outbox_path(url)
        assert json.loads((runs[1] / history.RECORD_JSON).read_text())["state"] == "pending"
        assert history.pending(url) == 2
        with pytest.raises(history.Unreachable):
            history.sync(url)  # still down: nothing lost, nothing sent
        assert history.pending(url) == 2
        relay.start()  # back
        assert history.sync(url) == (2, 0)
        assert history.sync(url) == (0, 0)  # delivered once
        with history.connect(url) as db:
            rows = history.list_runs(db)
        assert [r["heading_deg"] for r in rows] == [0.0, 1.0, 2.0]
        assert json.loads((runs[2] / history.RECORD_JSON).read_text())["state"] == "recorded"
    finally:
        relay.stop()


def test_a_lost_outbox_delete_resends_without_duplicating(pg_schema, tmp_path):
    """sync crashed after the server's commit and before the outbox was emptied: the next sync
    sends the same rows again, upserted by their ids."""
    run = make_run(tmp_path, "r", "2026-07-02T00:00:00+00:00", "SN-X")
    row = history.row_from_run(run.resolve())
    with history.connect(pg_schema.url) as db:
        history.upsert(db, row)
    with history.connect(history.outbox_path(pg_schema.url)) as box:
        history.upsert(box, row)
    assert history.sync(pg_schema.url) == (1, 0)
    with history.connect(pg_schema.url) as db:
        assert history.count(db) == 1


def test_a_recording_failure_is_one_warning_line_and_no_exception(tmp_path, monkeypatch, capsys):
    run = make_run(tmp_path / "runs", "r", "2026-01-01T00:00:00+00:00", None)
    (tmp_path / "blocker").write_text("a file where the database's directory should be")
    monkeypatch.setenv(history.ENV_DB, str(tmp_path / "blocker" / "h.sqlite"))
    history.record_or_warn(run)
    line = only_line(capsys.readouterr().err)
    assert line.startswith("northfinder: warning:") and "--rebuild" in line


def test_the_default_database_is_per_user_whatever_the_run_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "data"))
    assert history.default_db() == tmp_path / "data" / "northfinder" / history.DB_NAME
    elsewhere = make_run(tmp_path / "somewhere" / "else", "r", "2026-01-01T00:00:00+00:00", "SN-D")
    history.record_or_warn(elsewhere)
    assert only_line(capsys.readouterr().err) == f"results history: row recorded in {history.default_db()}"
    with history.connect(history.default_db()) as db:
        assert [r["unit"] for r in history.list_runs(db)] == ["SN-D"]
    monkeypatch.setenv(history.ENV_DB, "postgresql://lab@db.example/northfinder")
    assert history.default_db() == "postgresql://lab@db.example/northfinder"
    assert history.label("postgresql://lab:secret@db/x") == "postgresql://lab:***@db/x"


def test_history_command_lists_filters_exports_and_rebuilds_into_the_default(tmp_path):
    runs = tmp_path / "elsewhere"
    make_run(runs, "a", "2026-06-01T10:00:00+00:00", "SN-1", heading=21.0)
    make_run(runs, "b", "2026-06-02T10:00:00+00:00", "SN-2", heading=22.0)
    out = run_cli("history", "--rebuild", str(runs), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert f"indexed 2 run directories under {runs} into {history.default_db()}" in out.stdout
    out = run_cli("history", "--unit", "SN-2", "--csv", "x.csv", cwd=tmp_path / "elsewhere")  # any cwd
    assert out.returncode == 0, out.stderr
    assert "22.0000" in out.stdout and "21.0000" not in out.stdout and "(1 runs" in out.stdout
    assert f"database: {history.default_db()} (2 rows in all, 1 listed)" in out.stdout
    assert len((runs / "x.csv").read_text().splitlines()) == 2
    bad = run_cli("history", "--db", str(tmp_path / "none.sqlite"), cwd=tmp_path)
    assert bad.returncode == 2 and "does not exist" in only_line(bad.stderr)
    bad = run_cli("history", "--since", "March", cwd=tmp_path)
    assert bad.returncode == 2 and "YYYY-MM-DD" in only_line(bad.stderr)
    bad = run_cli("history", "sync", cwd=tmp_path)
    assert bad.returncode == 2 and "not a postgresql:// server" in only_line(bad.stderr)


def test_an_older_history_next_to_the_runs_gets_a_one_line_hint(tmp_path):
    old_runs = tmp_path / "runs"
    make_run(old_runs, "find-1", "2026-02-01T10:00:00+00:00", "SN-OLD")
    with history.connect(old_runs / history.DB_NAME, migrate=False) as old:
        old.migrate(target=2)
        old.execute(
            "INSERT INTO runs (run_dir, time_utc, kind) VALUES (?, '2026-02-01T10:00:00+00:00', 'find')",
            (str((old_runs / "find-1").resolve()),),
        )
    out = run_cli("history", cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert "(0 rows in all" in out.stdout
    hint = only_line(out.stderr)
    assert "runs/history.sqlite" in hint and f"northfinder history --rebuild {old_runs.resolve()}" in hint
    assert run_cli("history", "--rebuild", str(old_runs), cwd=tmp_path).returncode == 0
    out = run_cli("history", cwd=tmp_path)
    assert "SN-OLD" in out.stdout and out.stderr.strip() == ""  # brought in: no hint any more


def test_every_command_takes_db_and_the_postgresql_url(tmp_path):
    url = pg_url_or_skip()
    from northfinder.cli import build_parser

    (sub,) = [a for a in build_parser()._actions if a.dest == "command"]
    for cmd in ("find", "align", "campaign", "history", "replay"):
        assert "--db" in sub.choices[cmd]._option_string_actions, cmd
    out = run_cli("history", "--db", url, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert f"database: {history.label(url)} (" in out.stdout
