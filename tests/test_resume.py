"""Interrupted finds stay useful (issue 25 item 6), end to end on firmware-sim:

Ctrl-C a simulated find after 2 of 8 positions → `replay` prints the 2 positions and says a heading
needs 3 → `find --resume` → the heading uses the motion samples of both sessions (a gyro bias per
session: their counters do not join) → `replay` of the resumed run equals the live result bit for
bit → its σ against an uninterrupted run of the same plan and seed, both against the σ model: the
white-noise σ of the samples each fit used, σ² (AᵀA)⁻¹ with the grade's ARW (CONVENTIONS.md's noise
limit, per sample at the IMU's rate). A campaign directory given to `replay` replays its finds."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from helpers import northfinder_line, read_events, run_cli, sigint_when, start_cli

from northfinder.estimators import plan as P
from northfinder.estimators.motion_fit import RUN_TERMS
from northfinder.estimators.motion_sessions import session_design
from northfinder.report import draw_report
from northfinder.rundir import RunDir
from northfinder.runs.find_motion import report_samples
from northfinder.runs.find_sessions import session_motion_samples

pytestmark = pytest.mark.slow

PLAN = ("--simulate", "--positions", "8", "--dwell", "5", "--seed", "3", "--no-report")
GRADE = "nav"  # SimSettings' default grade
LATITUDE_DEG = 40.0  # SimSettings' default latitude
SIGMA_REL_TOL = 0.01
"""Reported σ against the model σ: the reported one scales the model's by the residual RMS over
the grade's per-sample σ, whose relative standard error is 1/√(2·n) ≈ 0.002 for the n ≳ 1e5
residuals of a 8 × 5 s run at 1 kHz; the tilt's share of the heading σ (accelerometer noise
10 µg/√Hz) is below 1e-4 of it. 1 % is five standard errors."""


def _model_sigma_deg(run_dir: Path) -> float:
    """σψ of the samples the run's per-sample fit used, white gyro noise only: σ_v from
    σ² (AᵀA)⁻¹ of the session design, σψ = σ_v / (Ωe cos L) (the exact method at small tilt)."""
    rd = RunDir(run_dir, create=False)
    events = rd.events()
    parts, why = session_motion_samples(rd, events)
    assert parts, why
    alpha, omega = (np.concatenate([p[k] for p in parts]) for k in range(2))
    session = np.concatenate([np.full(p[0].size, p[3]["session"]) for p in parts])
    a_mat, names = session_design(alpha, omega, session, ("x", "y"), RUN_TERMS)
    rate_hz = float(next(e for e in events if e["event"] == "start")["imu"]["rate_hz"])
    sample_sigma_dph = P.GRADES[GRADE].arw_deg_rt_h * 60.0 * math.sqrt(rate_hz)
    cov = sample_sigma_dph**2 * np.linalg.inv(a_mat.T @ a_mat)
    sigma_v_dph = math.sqrt(0.5 * (cov[0, 0] + cov[1, 1]))
    return math.degrees(sigma_v_dph / (P.EARTH_RATE_DPH * math.cos(math.radians(LATITUDE_DEG))))


def _positions(run_dir: Path) -> int:
    return sum(e["event"] == "position" for e in read_events(run_dir))


def test_ctrl_c_replay_resume_replay_and_sigma_against_an_uninterrupted_run(tmp_path):
    part = tmp_path / "part"
    proc = start_cli("find", *PLAN, "--out", str(part), cwd=tmp_path)
    _, err = sigint_when(proc, [(lambda: _positions(part) >= 2, "two positions")], timeout_s=120)
    assert proc.returncode == 130 and "after 2 of 8 positions" in northfinder_line(err)

    partial = run_cli("replay", str(part), cwd=tmp_path)
    assert partial.returncode == 1, partial.stderr
    first = partial.stdout.splitlines()[0]
    assert "incomplete run, 2 of 8 positions" in first and "needs at least 3" in first
    assert f"find --resume {part}" in first
    rows = [ln for ln in partial.stdout.splitlines() if ln.startswith("│")]
    assert [r.split("│")[2].strip() for r in rows] == ["0.000", "45.000"]  # α of the two positions

    resumed = run_cli("find", "--resume", str(part), "--no-report", cwd=tmp_path, timeout_s=300)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    res = json.loads((part / "result.json").read_text())
    motion = res["motion_fit"]
    assert res["complete"] and res["faults"]["sessions"] == 2 and motion["available"], motion
    assert [s["session"] for s in motion["sessions"]] == [1, 2] and motion["join"].startswith("none")
    assert all(s["motion"] > 0 for s in motion["sessions"])  # both sessions' moves are in the fit
    assert "in 2 sessions" in resumed.stdout

    fig = draw_report(res, samples=report_samples(RunDir(part, create=False)))
    texts = [t.get_text() for ax in fig.axes for t in ax.texts]
    assert any(t.startswith(" session 2 (resumed") for t in texts), texts  # where session 2 begins
    import matplotlib.pyplot as plt  # after draw_report chose the Agg backend

    plt.close(fig)

    again = run_cli("replay", str(part), "--quiet", cwd=tmp_path)
    assert again.returncode == 0 and "identical to the live result.json" in again.stdout, again.stdout

    full = tmp_path / "full"
    whole = run_cli("find", *PLAN, "--out", str(full), cwd=tmp_path, timeout_s=300)
    assert whole.returncode == 0, whole.stderr[-3000:]
    ref = json.loads((full / "result.json").read_text())
    assert ref["motion_fit"]["available"] and "sessions" not in ref["motion_fit"]

    model_resumed, model_full = _model_sigma_deg(part), _model_sigma_deg(full)
    for result, model in ((res, model_resumed), (ref, model_full)):
        assert result["motion_fit"]["samples"]["stretches_disturbed"] == 0
        assert result["heading_std_deg"] == pytest.approx(model, rel=SIGMA_REL_TOL)
        assert abs(result["error_deg"]) < 4.0 * model
    # the resumed run: worse than the uninterrupted one by what the model says (a second bias, the
    # lost move between the sessions), better than its own dwells alone
    ratio = res["heading_std_deg"] / ref["heading_std_deg"]
    assert ratio == pytest.approx(model_resumed / model_full, rel=2 * SIGMA_REL_TOL)
    assert res["heading_std_deg"] < res["dwell_fit"]["heading_std_deg"]
    print(f"σ resumed {res['heading_std_deg']:.5f}° (model {model_resumed:.5f}°), uninterrupted "
          f"{ref['heading_std_deg']:.5f}° (model {model_full:.5f}°), dwells only after resume "
          f"{res['dwell_fit']['heading_std_deg']:.5f}°")


SIM_TOML = ("stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n"
            "accel_rate_hz = 50.0\n")  # a fast stage, as in test_campaign


def test_replay_of_a_campaign_directory_replays_its_finds(tmp_path):
    (tmp_path / "sim.toml").write_text(SIM_TOML)
    out = tmp_path / "camp"
    camp = run_cli("campaign", "--simulate", "--repeat", "2", "--heading", "10", "--positions", "4",
                   "--dwell", "2", "--time-scale", "20", "--sim-config", str(tmp_path / "sim.toml"),
                   "--no-report", "--out", str(out), cwd=tmp_path, timeout_s=300)  # fmt: skip
    assert camp.returncode == 0, camp.stderr[-3000:]
    proc = run_cli("replay", str(out), "--quiet", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    for name in ("step1-run01", "step1-run02"):
        same = [ln for ln in lines if ln.startswith(f"{out / name}: replayed heading")]
        assert len(same) == 1 and same[0].endswith("identical to the live result.json"), proc.stdout
    assert lines[-1] == (f"{out}: complete campaign, 2 of 2 finds replayed; the statistics from the "
                         "replayed finds are identical to campaign.json's")
    json_flag = run_cli("replay", str(out), "--json", str(tmp_path / "r.json"), cwd=tmp_path)
    assert json_flag.returncode == 2 and "give one of its finds" in northfinder_line(json_flag.stderr)
    # a find changed behind the campaign's back: the statistics no longer match
    state = json.loads((out / "campaign.json").read_text())
    state["runs"][0]["heading_deg"] += 0.5
    state["statistics"]["exact"]["mean_deg"] += 0.25
    (out / "campaign.json").write_text(json.dumps(state))
    changed = run_cli("replay", str(out), "--quiet", cwd=tmp_path)
    assert "DIFFER from campaign.json's" in changed.stdout.splitlines()[-1], changed.stdout


def test_replay_of_a_campaign_with_no_find_done_names_the_finds_set_aside(tmp_path):
    """A campaign stopped in its first find lists none: replay says which find to give instead."""
    out = tmp_path / "camp"
    out.mkdir()
    state = {"schema": "northfinder.campaign/1", "complete": False, "method": "exact",
             "plan": {"repeat": 2, "steps": [{"reference_deg": 10.0}], "method": "exact"},
             "runs": [], "failed": [{"index": 0, "run_dir": "step1-run01.failed-1", "reason": "SIGINT"}]}
    (out / "campaign.json").write_text(json.dumps(state))
    proc = run_cli("replay", str(out), cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr
    assert proc.stdout.strip() == (
        f"{out}: a campaign with no find done yet; replay one of its finds set aside "
        f"({out / 'step1-run01.failed-1'}) or continue it with northfinder campaign --resume {out}")
