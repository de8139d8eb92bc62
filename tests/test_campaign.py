"""`northfinder campaign` end to end on firmware-sim: a short simulated campaign (2 finds at each
of 2 base headings), Ctrl-C in the middle of a find then --resume (no find repeated or lost), a
real-bench campaign against an externally started simulator (the operator's Enter on stdin), and
the one-line mistakes. Short dwells and a fast stage as in test_e2e_find."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import (
    northfinder_line,
    only_line,
    read_events,
    run_cli,
    sigint_when,
    start_cli,
    start_sim,
    subprocess_env,
)

from northfinder import history
from northfinder.estimators.campaign_stats import deviation_deg

pytestmark = pytest.mark.slow

DWELL_S = 2.0
POSITIONS = 4  # short finds: the campaign, not the find, is under test (test_e2e_find runs 8)
TIME_SCALE = 20.0
SIM_TOML = (
    "stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\naccel_rate_hz = 50.0\n"
)
HEADINGS = (10.0, 200.0)
REPEAT = 2


def _campaign_argv(tmp_path: Path, out: Path) -> list[str]:
    (tmp_path / "sim.toml").write_text(SIM_TOML)
    return [
        "campaign", "--simulate", "--repeat", str(REPEAT), "--headings", ",".join(map(str, HEADINGS)),
        "--positions", str(POSITIONS), "--dwell", str(DWELL_S), "--time-scale", str(TIME_SCALE),
        "--sim-config", str(tmp_path / "sim.toml"), "--unit", "SN-T1", "--out", str(out), "--no-report",
    ]  # fmt: skip


def _check_complete(out: Path) -> dict:
    """campaign.json lists every planned find once, each a complete run directory whose
    result.json gives exactly the listed numbers, and the statistics recomputed from them."""
    c = json.loads((out / "campaign.json").read_text())
    assert c["complete"] is True
    assert [r["index"] for r in c["runs"]] == list(range(REPEAT * len(HEADINGS)))
    names = [r["run_dir"] for r in c["runs"]]
    assert names == [f"step{s + 1}-run{k + 1:02d}" for s in range(len(HEADINGS)) for k in range(REPEAT)]
    errors = []
    for r in c["runs"]:
        res = json.loads((out / r["run_dir"] / "result.json").read_text())
        assert res["complete"] and res["positions_measured"] == POSITIONS
        ref = HEADINGS[r["step"]]
        assert r["reference_deg"] == ref == res["truth"]["heading_deg"]  # simulated: truth = reference
        assert r["heading_deg"] == res["heading_deg"] and r["heading_std_deg"] == res["heading_std_deg"]
        assert r["error_deg"] == pytest.approx(res["error_deg"], abs=1e-12)
        assert abs(r["error_deg"]) < 4.0 * r["heading_std_deg"]  # each find honest to its own σ
        errors.append(r["error_deg"])
    s = c["statistics"]["exact"]
    assert s["n"] == len(errors)
    assert s["mean_deg"] == pytest.approx(float(np.mean(errors)))
    assert s["std_deg"] == pytest.approx(float(np.std(errors, ddof=1)))
    assert s["std_arcmin"] == pytest.approx(60.0 * s["std_deg"])
    for m in ("coordinate_transform", "vector", "eq11", "uncompensated"):
        dev = [deviation_deg(json.loads((out / r["run_dir"] / "result.json").read_text())["methods"][m]
                             ["heading_deg"], r["reference_deg"]) for r in c["runs"]]  # fmt: skip
        assert c["statistics"][m]["rms_deg"] == pytest.approx(math.sqrt(float(np.mean(np.square(dev)))))
    assert (out / "campaign.png").stat().st_size > 20_000
    return c


def _history_rows(db: Path) -> list[dict]:
    conn = history.connect(db)
    try:
        return history.list_runs(conn)
    finally:
        conn.close()


def test_simulated_campaign_two_headings_table_figure_and_history(tmp_path):
    out = tmp_path / "runs" / "camp"
    proc = run_cli(*_campaign_argv(tmp_path, out), cwd=tmp_path, timeout_s=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    c = _check_complete(out)
    assert "layout of the paper's table 1" in proc.stdout
    for label in ("mean (deviation from reference)", "standard deviation", "RMS", "mean reported σ"):
        assert label in proc.stdout
    assert f"{c['statistics']['exact']['std_arcmin']:.3f}′" in proc.stdout
    rows = _history_rows(history.default_db())  # the per-user history (this test's own)
    assert sorted(r["kind"] for r in rows) == ["campaign"] + ["find"] * 4
    assert {r["unit"] for r in rows} == {"SN-T1"}
    finds = [r for r in rows if r["kind"] == "find"]
    assert {r["campaign"] for r in finds} == {str(out.resolve())}
    assert sorted(r["heading_deg"] for r in finds) == sorted(r["heading_deg"] for r in c["runs"])
    again = run_cli(*_campaign_argv(tmp_path, out), cwd=tmp_path)
    assert again.returncode == 2 and "--resume" in only_line(again.stderr)
    # the campaign is a kind of run (northfinder.runkinds): replay replays each find and recomputes
    # campaign.json's records and statistics, identical to the live ones …
    replayed = run_cli("replay", str(out), "--quiet", cwd=tmp_path, timeout_s=300)
    assert replayed.returncode == 0, replayed.stderr[-3000:]
    n = REPEAT * len(HEADINGS)
    assert f"complete campaign, {n} of {n} finds replayed" in replayed.stdout
    assert "statistics from the replayed finds are identical to campaign.json's" in replayed.stdout, \
        replayed.stdout
    # … and says where a campaign.json no longer matches its finds
    c["statistics"]["exact"]["mean_deg"] += 1e-9
    (out / "campaign.json").write_text(json.dumps(c, indent=2))
    tampered = run_cli("replay", str(out), "--quiet", cwd=tmp_path, timeout_s=300)
    assert "DIFFER from campaign.json's in 1 values: statistics.exact.mean_deg" in tampered.stdout, \
        tampered.stdout


def test_ctrl_c_mid_find_then_resume_repeats_and_loses_nothing(tmp_path):
    out = tmp_path / "runs" / "camp"
    proc = start_cli(*_campaign_argv(tmp_path, out), cwd=tmp_path)

    def listed() -> int:
        try:
            return len(json.loads((out / "campaign.json").read_text())["runs"])
        except (FileNotFoundError, json.JSONDecodeError):
            return 0

    _, err = sigint_when(
        proc,
        [
            (lambda: listed() == 1, "the first find listed"),
            (
                lambda: sum(e["event"] == "position" for e in read_events(out / "step1-run02")) >= 2,
                "the second find at its third position",
            ),
        ],  # fmt: skip
        timeout_s=300.0,
    )
    assert proc.returncode == 130, err[-3000:]
    line = northfinder_line(err)
    assert "1 of 4 finds done" in line and f"--resume {out}" in line
    assert "stopped by SIGINT" in line and f"saved in {out / 'step1-run02.failed-1'} " in line  # its new name
    stopped = json.loads((out / "campaign.json").read_text())
    assert [r["index"] for r in stopped["runs"]] == [0] and not stopped["complete"]
    assert [f["index"] for f in stopped["failed"]] == [1]
    assert (out / "step1-run02.failed-1" / "events.jsonl").exists()  # the stopped find kept for replay
    first = (out / "step1-run01" / "result.json").read_bytes()
    # as if killed between the find's result.json and campaign.json: the complete find is not listed
    stopped["runs"] = []
    (out / "campaign.json").write_text(json.dumps(stopped))

    resumed = run_cli("campaign", "--resume", str(out), cwd=tmp_path, timeout_s=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    c = _check_complete(out)
    assert c["sessions"] == 2
    assert (out / "step1-run01" / "result.json").read_bytes() == first  # adopted, not measured again
    assert "find 1/4 (step1-run01" in resumed.stderr
    for r in c["runs"]:
        starts = [e for e in read_events(out / r["run_dir"]) if e["event"] == "start"]
        assert len(starts) == 1  # every listed find measured in exactly one session
    live = _history_rows(history.default_db())
    finds = [r for r in live if r["kind"] == "find"]
    assert sorted(Path(r["run_dir"]).name for r in finds) == sorted(r["run_dir"] for r in c["runs"])
    assert {r["unit"] for r in live} == {"SN-T1"}  # the resumed session's command line has no --unit
    shutil.copytree(tmp_path / "runs", tmp_path / "copy")
    history.rebuild(tmp_path / "copy", tmp_path / "rebuilt.sqlite")
    rebuilt = _history_rows(tmp_path / "rebuilt.sqlite")
    assert _relative(rebuilt, tmp_path / "copy") == _relative(live, tmp_path / "runs")


def _relative(rows: list[dict], root: Path) -> list[dict]:
    """Rows with their paths relative to the runs directory (a copy has other absolute paths)."""
    rel = lambda p: p and str(Path(p).relative_to(root.resolve()))  # noqa: E731
    return [{**r, "run_dir": rel(r["run_dir"]), "campaign": rel(r["campaign"])} for r in rows]


def test_real_bench_campaign_prompts_and_records_the_reference(tmp_path):
    (tmp_path / "sim.toml").write_text(SIM_TOML)
    sim = start_sim(
        "--heading", "37.0", "--time-scale", str(TIME_SCALE), "--config", str(tmp_path / "sim.toml")
    )
    try:
        ep = json.loads(sim.stdout.readline())
        bench = tmp_path / "bench.toml"
        bench.write_text(
            f"[turntable]\nport = '{ep['turntable']}'\n[imu]\nport = '{ep['imu']}'\n"
            f"[accelerometer]\ninterface = 'slcan'\nchannel = '{ep['can']['channel']}'\nrate_hz = 50.0\n"
            "bus_options = {sleep_after_open = 0.05}\n[site]\nlatitude_deg = 40.0\n"
        )
        out = tmp_path / "camp"
        argv = ["campaign", "--config", str(bench), "--reference-deg", "37", "--repeat", "2", "--positions",
                str(POSITIONS), "--dwell", str(DWELL_S), "--out", str(out), "--no-report"]  # fmt: skip
        proc = _run_with_stdin(argv, tmp_path, "\n")
    finally:
        sim.terminate()
        sim.wait(timeout=10)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.count("turn the fixture to the reference azimuth 37°") == 1  # once per step
    c = json.loads((out / "campaign.json").read_text())
    assert c["simulate"] is None and [r["reference_deg"] for r in c["runs"]] == [37.0, 37.0]
    for r in c["runs"]:
        assert abs(r["error_deg"]) < 4.0 * r["heading_std_deg"]


def _run_with_stdin(argv: list[str], cwd: Path, stdin: str) -> subprocess.CompletedProcess[str]:
    """The CLI with `stdin` as its standard input (the operator's Enter)."""
    return subprocess.run(
        [sys.executable, "-m", "northfinder", *argv],
        input=stdin,
        capture_output=True,
        text=True,
        cwd=cwd,
        env=subprocess_env(),
        timeout=300,
    )


@pytest.mark.parametrize(
    ("argv", "words"),
    [
        (["--simulate"], "--repeat"),
        (["--simulate", "--repeat", "2", "--reference-deg", "5"], "use --heading"),
        (["--simulate", "--repeat", "2", "--headings", "north"], "--heading north"),
        (["--config", "nosuch.toml", "--repeat", "2", "--reference-deg", "5"], "nosuch.toml"),
        (["--config", "nosuch.toml", "--repeat", "2"], "--reference-deg"),
        (["--resume", "nosuch"], "not a campaign directory"),
    ],
)
def test_mistakes_are_one_line(tmp_path, argv, words):
    proc = run_cli("campaign", *argv, cwd=tmp_path)
    assert proc.returncode == 2
    assert words in only_line(proc.stderr)
