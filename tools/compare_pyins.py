#!/usr/bin/env python3
"""GNSS time to < 1° with the prior given: northfinder's sin/cos filter against pyins on the same drives.

    pip install --target /tmp/pyins_pkg python-ins==1.0.1      # NOT a project dependency
    python3 tools/compare_pyins.py OUT_DIR [--pyins-path /tmp/pyins_pkg] [--seed0 1 --seeds 3]
           [--errors 10,45,90,180] [--motion-s 60]

Both filters get the same recorded drive of tools/coverage_align.py's GnssBench (firmware_sim physics,
kvh1760 with drawn turn-on biases, 250 Hz increments, 10 Hz antenna fixes with the same noise), the
same start (the first fix after the 5 s still levelling window), the same heading prior (truth at
the start + the initial error, σ = the initial error) and the same IMU noise figures (the grade's,
GnssAlignConfig.for_imu_grade). Time to < 1° = seconds after motion start from which |error| < 1°
holds at every GNSS update to the end of the record (the record ends `--motion-s` after the motion
starts, the same for both).

What differs, said so in the output: pyins (Position/NedVelocity measurements) cannot estimate a lever
arm, so it is given the TRUE lever arm, where ours starts from 0 ± 1 m and estimates it — an advantage
to pyins (the table's header says so; `--ours-lever-std M` gives ours the true lever arm too, with σ M,
as a user who measured it configures `[gnss] lever_arm_m`/`lever_arm_std_m`). Its roll and pitch start
from the truth with σ 0.5° (ours levels on the still start).
pyins's frames are NED / forward-right-down; ours ENU / right-forward-up: b_pyins = [y, x, −z].

Without pyins importable the tool says so and exits 0 (skips cleanly).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import coverage_align as ca  # noqa: E402

from northfinder.constants import DPH, STANDARD_GRAVITY_M_S2, wrap_deg_180  # noqa: E402

B_TO_FRD = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""Our body (x right, y forward, z up) → pyins's (forward, right, down); a proper rotation."""
LEVEL_S = 5.0


def import_pyins(path: str | None):
    """The pyins modules, or None (not installed: the caller skips)."""
    if path:
        sys.path.append(path)  # appended: the project's own numpy stays first
    try:
        import pandas as pd
        from pyins import filters, inertial_sensor, measurements, strapdown
    except ImportError:
        return None
    return pd, filters, inertial_sensor, measurements, strapdown


class Bench(ca.GnssBench):
    """coverage_align's drive, cut `motion_s` after the motion starts (both filters see the same)."""

    def __init__(self, grade: str, motion_s: float, lever_std_m: float | None = None):
        self.lever_std_m = lever_std_m
        saved = ca.GNSS_TIMES_S
        ca.GNSS_TIMES_S = (motion_s,)
        try:
            super().__init__(grade)
        finally:
            ca.GNSS_TIMES_S = saved

    def config(self, prior_std_deg: float | None):
        """coverage_align's config (lever arm 0 ± 1 m) or, with `lever_std_m`, the true lever arm with that
        σ — what a user who measured it gives `[gnss] lever_arm_m` / `lever_arm_std_m`."""
        cfg = super().config(prior_std_deg)
        if self.lever_std_m is None:
            return cfg
        return replace(cfg, lever_arm_b_m=tuple(ca.LEVER_TRUTH_M), lever_arm_std_m=self.lever_std_m)


def ttc(t_s: np.ndarray, err_deg: np.ndarray) -> float | None:
    """Seconds after motion start from which |error| < 1° to the end (None: never)."""
    bad = np.nonzero(np.abs(err_deg) >= 1.0)[0]
    if len(bad) and bad[-1] == len(err_deg) - 1:
        return None
    return float((t_s[bad[-1] + 1] if len(bad) else t_s[0]) - ca.MOTION_START_S)


def ours(bench: Bench, seed: int, e0_deg: float) -> float | None:
    return ca.time_to_1deg(bench, seed, e0_deg, e0_deg)


def run_pyins(py, bench: Bench, seed: int, e0_deg: float) -> float | None:
    """pyins's feedback filter on the same seed's data, prior heading truth + e0 (σ = e0)."""
    pd, filters, inertial_sensor, measurements, strapdown = py
    imu, gnss = bench.data(seed)
    dth, dv = imu.increments()
    rate = bench.rate_hz
    n = len(dth)
    t_imu = np.round(np.arange(n + 1) / rate, 6)  # the fixes fall exactly on sample ends (no extra rows)
    gyro = np.vstack([np.zeros(3), dth @ B_TO_FRD.T])
    accel = np.vstack([np.zeros(3), dv @ B_TO_FRD.T])
    frame = pd.DataFrame(np.hstack([gyro, accel]), index=t_imu,
                         columns=["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"])
    increments = strapdown.compute_increments_from_imu(frame, "increment")
    ll = gnss.local_level()
    lat, lon, alt = ll.from_enu(gnss.pos_enu_m)
    fixes = pd.DataFrame({"lat": np.rad2deg(lat), "lon": np.rad2deg(lon), "alt": alt,
                          "VN": gnss.vel_enu_m_s[:, 1], "VE": gnss.vel_enu_m_s[:, 0],
                          "VD": -gnss.vel_enu_m_s[:, 2]}, index=np.round(gnss.t_s, 6))
    lever_frd = B_TO_FRD @ np.asarray(ca.LEVER_TRUTH_M)
    pos = measurements.Position(fixes, ca.GNSS_POS_STD_M[0], lever_frd)
    pos.R = np.diag(np.square(ca.GNSS_POS_STD_M))
    vel = measurements.NedVelocity(fixes, ca.GNSS_VEL_STD_M_S, lever_frd)
    j0 = int(np.searchsorted(gnss.t_s, LEVEL_S - 1e-9))
    t0 = float(fixes.index[j0])
    psi, pitch, roll = (np.rad2deg(np.asarray(a, float)) for a in bench.traj.euler_rad(t0)[0])
    c_bn = bench.traj.c_bn(np.array([t0]))[0]
    imu_enu = gnss.pos_enu_m[j0] - c_bn @ np.asarray(ca.LEVER_TRUTH_M)
    lat0, lon0, alt0 = ll.from_enu(imu_enu)
    pva = pd.Series({"lat": math.degrees(lat0), "lon": math.degrees(lon0), "alt": float(alt0),
                     "VN": fixes.VN.iloc[j0], "VE": fixes.VE.iloc[j0], "VD": fixes.VD.iloc[j0],
                     "roll": float(roll), "pitch": float(pitch), "heading": (float(psi) + e0_deg) % 360.0},
                    name=t0)
    cfg = bench.config(e0_deg)
    g0 = 1e-6 * STANDARD_GRAVITY_M_S2
    gyro_model = inertial_sensor.EstimationModel(
        bias_sd=cfg.gyro_bias_std_dph * DPH, noise=math.radians(cfg.gyro_arw_deg_sqrt_h) / 60.0,
        bias_walk=cfg.gyro_bias_rw_dph_sqrt_s * DPH)
    accel_model = inertial_sensor.EstimationModel(
        bias_sd=cfg.accel_bias_std_ug * g0, noise=cfg.accel_vrw_ug_sqrt_hz * g0,
        bias_walk=cfg.accel_bias_rw_ug_sqrt_s * g0)
    # pyins 1.0.1's σ output fails on a trajectory index with repeated times (a fix on a sample end);
    # only the trajectory is used here, so its σ computation is skipped.
    filters._compute_sd = lambda *a, **k: (None, None, None)
    out = filters.run_feedback_filter(pva, 1.0, cfg.vel_std_m_s, cfg.tilt_std_deg, e0_deg, increments,
                                      gyro_model, accel_model, measurements=[pos, vel], time_step=0.1)
    traj = out.trajectory
    at = traj.loc[traj.index.isin(fixes.index[j0 + 1:])]
    t = np.asarray(at.index, float)
    err = np.asarray(wrap_deg_180(at.heading.values - bench.heading_deg(t)), float)
    return ttc(t, err)


def fmt(v: float | None) -> str:
    return "never" if v is None else f"{v:.1f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--pyins-path", default=None, help="where pyins was installed with pip --target")
    ap.add_argument("--seed0", type=int, default=1)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--errors", default="10,45,90,180")
    ap.add_argument("--motion-s", type=float, default=60.0)
    ap.add_argument("--grade", default="kvh1760")
    ap.add_argument("--ours-lever-std", type=float, default=None, metavar="M",
                    help="give ours the true lever arm with this 1σ (as pyins gets it) instead of 0 ± 1 m")
    args = ap.parse_args(argv)
    py = import_pyins(args.pyins_path)
    if py is None:
        print("pyins is not importable: skipped (pip install --target DIR python-ins==1.0.1, then "
              "--pyins-path DIR)")
        return 0
    bench = Bench(args.grade, args.motion_s, args.ours_lever_std)
    seeds = range(args.seed0, args.seed0 + args.seeds)
    rows, t_wall = [], time.perf_counter()
    ours_la = ("lever arm 0 ± 1 m" if args.ours_lever_std is None
               else f"true lever arm ± {args.ours_lever_std:g} m")
    lines = [f"| initial error | ours, {ours_la} (seeds; median) | pyins, TRUE lever arm (seeds; median) |",
             "|---:|---|---|"]
    print(lines[0], flush=True)
    for e0 in (float(x) for x in args.errors.split(",")):
        a = [ours(bench, s, e0) for s in seeds]
        b = [run_pyins(py, bench, s, e0) for s in seeds]
        med = [float(np.median([np.inf if v is None else v for v in x])) for x in (a, b)]
        rows.append({"initial_error_deg": e0, "ours_s": a, "pyins_s": b})
        lines.append(f"| {e0:g}° | {'/'.join(fmt(v) for v in a)} ({med[0]:.1f}) | "
                     f"{'/'.join(fmt(v) for v in b)} ({med[1]:.1f}) |")
        print(lines[-1], flush=True)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / "compare_pyins.json").write_text(json.dumps({"args": vars(args) | {"out_dir": str(
        args.out_dir)}, "rows": rows}, indent=1))
    (args.out_dir / "compare_pyins.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out_dir}/compare_pyins.md ({time.perf_counter() - t_wall:.0f} s wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
