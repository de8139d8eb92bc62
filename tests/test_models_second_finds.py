"""Finds on firmware-sim with the second models (issue 24): each model with the others at their
defaults, with the faults that apply to it (APT stall, STIM corrupt and flagged datagrams), and the
mixed bench (APT + STIM + CiA 410) in one find.

Short in device time (8 × 2 s: with 4 positions the motion fit's extra terms put σ up to 30 %
over the white-noise limit) at time scale 10 on the stiffer simulated stage; the tolerances come
from the noise limit of docs/CONVENTIONS.md for the grade's ARW in northfinder's own grade table
(estimators.plan.GRADES), never from a printed run; replay must give the live result bit for bit.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli
from scipy import stats

from northfinder.estimators.limits import noise_limit_heading_std_deg
from northfinder.estimators.plan import GRADES
from northfinder.rotations import tilt_and_azimuth
from northfinder.rundir import RESULT, jsonable
from northfinder.runs.find import replay

pytestmark = pytest.mark.slow

POSITIONS, DWELL_S, TIME_SCALE = 8, 2.0, 10.0
FAST_STAGE_TOML = "stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n"
SIGMA_TOLERANCE = 0.20
SIGMA_TOLERANCE_SHORT_STIM = 0.35
T10_AT_NORMAL_3_SIGMA = float(stats.t.ppf(stats.norm.cdf(3.0), 10))
"""Student-t quantile, 10 dof, with the false-alarm rate of a normal 3σ (two-sided 0.27 %): 3.96."""
"""A STIM300 over 8 × 2 s: σ/limit measured 0.80–1.26 (and 0.85–1.14 over 8 × 5 s, seeds 1–3): its
bias instability (0.3 °/h, 100 s) is not small against the ~1 °/h a 5° σ means, and the motion
fit's σ over a span mostly in motion scatters. The 20 % claim for the STIM is shown at 8 × 20 s by
tools/second_models_table.py (σ/limit 0.98–1.03)."""


def _limit_deg(result: dict, grade: str) -> float:
    t = result["truth"]
    tilt, tilt_az = tilt_and_azimuth(*np.deg2rad([t["heading_deg"], t["pitch_deg"], t["roll_deg"]]))
    motion = result["motion_fit"]
    used_s = motion["samples"]["used_device_s"] if motion["available"] else result["duration_device_s"]
    return float(
        noise_limit_heading_std_deg(
            GRADES[grade].arw_deg_rt_h,
            used_s,
            result["latitude_deg"],
            np.rad2deg(tilt),
            np.rad2deg(tilt_az),
            gyro_axes=2,
        )
    )


def _find(tmp_path: Path, models: dict[str, str], grade: str, *faults: str) -> tuple[dict, Path]:
    sim_toml = tmp_path / "fast.toml"
    sim_toml.write_text(FAST_STAGE_TOML)
    run_dir = tmp_path / "run"
    argv = [
        "find",
        "--simulate",
        "--positions",
        str(POSITIONS),
        "--dwell",
        str(DWELL_S),
        "--time-scale",
        str(TIME_SCALE),
        "--grade",
        grade,
        "--sim-config",
        str(sim_toml),
        "--no-report",
        "--out",
        str(run_dir),
    ]
    for role, name in models.items():
        argv += [f"--{role}", name]
    for fault in faults:
        argv += ["--fault", fault]
    out = run_cli(*argv, cwd=tmp_path, timeout_s=240)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads((run_dir / RESULT).read_text()), run_dir


def _check(result: dict, run_dir: Path, grade: str, models: dict[str, str],
           sigma_tolerance: float | None = SIGMA_TOLERANCE, k_sigma: float = 3.0) -> None:
    assert result["complete"] and result["positions_measured"] == POSITIONS
    roles = {"stage": "turntable", "imu": "imu", "tilt": "accelerometer"}
    assert {roles[r]: m for r, m in models.items()}.items() <= {
        r: d["model"] for r, d in result["devices"].items()
    }.items()
    err = (result["heading_deg"] - result["truth"]["heading_deg"] + 180.0) % 360.0 - 180.0
    sigma, limit = result["heading_std_deg"], _limit_deg(result, grade)
    assert abs(err) < k_sigma * sigma, (err, sigma)
    if sigma_tolerance is not None:
        assert abs(sigma / limit - 1.0) < sigma_tolerance, (sigma, limit)
    again = replay(run_dir)
    assert json.loads(json.dumps(jsonable(again.result))) == json.loads((run_dir / RESULT).read_text())


@pytest.mark.slow
def test_apt_stage_finds_north_and_a_stall_is_retried_after_re_enabling(tmp_path):
    models = {"stage": "apt"}
    result, run_dir = _find(tmp_path, models, "nav", "stage-stall=2")
    _check(result, run_dir, "nav", models)
    assert result["devices"]["turntable"]["identity"]["controller"].startswith("Thorlabs KDC101")
    errors = result["faults"]["stage_errors"]
    assert len(errors) == 1 and "position error, error" in errors[0]["error"], errors


@pytest.mark.slow
def test_stim_finds_north_with_corrupt_and_flagged_datagrams_counted(tmp_path):
    models = {"imu": "stim"}
    result, run_dir = _find(tmp_path, models, "stim300", "imu-crc-rate=0.002", "imu-invalid-rate=0.002")
    # σ is not held to the limit here: the motion fit leaves out every stretch between dwells that
    # holds a lost sample (faults.md), which at this rate is most or all of them, and the dwells'
    # own σ (8 means, 10 degrees of freedom) scatters by ~22 % around the limit. The error over
    # that estimated σ is then Student-t with 10 dof: 3σ would fail 1.3 % of honest runs (once in
    # CI, 3.27σ, when the host's load moved the dwells onto other noise); the bound with the normal
    # 3σ's false-alarm rate (0.27 %) is t₁₀ = 3.96.
    _check(result, run_dir, "stim300", models, sigma_tolerance=None, k_sigma=T10_AT_NORMAL_3_SIGMA)
    motion = result["motion_fit"]
    assert not motion["available"] or motion["samples"]["stretches_dropped"] > 0, motion
    imu = result["faults"]["imu"]
    assert imu["bad_crc"] > 0 and imu["lost_samples"] >= imu["bad_crc"], imu
    assert sum(imu["invalid_samples"].values()) > 0 and sum(imu["invalid_in_dwells"].values()) > 0, imu
    assert result["devices"]["imu"]["identity"]["unit"].startswith("Sensonor STIM300")


@pytest.mark.slow
def test_cia410_inclinometer_gives_the_tilt(tmp_path):
    models = {"tilt": "cia410"}
    result, run_dir = _find(tmp_path, models, "nav")
    _check(result, run_dir, "nav", models)
    assert result["tilt"]["pitch_deg"] == pytest.approx(result["truth"]["pitch_deg"], abs=0.01)
    assert result["tilt"]["roll_deg"] == pytest.approx(result["truth"]["roll_deg"], abs=0.01)


@pytest.mark.slow
def test_mixed_bench_apt_stim_cia410_in_one_find(tmp_path):
    models = {"stage": "apt", "imu": "stim", "tilt": "cia410"}
    result, run_dir = _find(tmp_path, models, "stim300")
    _check(result, run_dir, "stim300", models, SIGMA_TOLERANCE_SHORT_STIM)
    assert json.loads((run_dir / "config.json").read_text())["simulate"]["models"] == {
        "stage": "apt",
        "imu": "stim",
        "tilt": "cia410",
    }
