#!/usr/bin/env python3
"""Reproduce the GNSS/INS large-misalignment alignment paper's figures on the simulator.

    python3 tools/reproduce_gnss_paper.py OUT_DIR [--seed 1] [--grade kvh1760]

One simulated 300 s drive (firmware_sim World + VehicleTrajectory + the grade's GyroModel /
AccelModel, GNSS antenna fixes at 10 Hz with σ 0.5 m / 1 m / 0.05 m/s, lever arm (0.5, 1.5, 1.2) m),
then on the SAME data, from initial heading errors 10°, 45°, 90°, 135°, 180°:

  sincos            the paper's δsin/δcos filter, lever arm from a tape measure (0.2–0.25 m off, σ 0.3 m)
  sincos-unknown-la the same with no lever-arm knowledge (prior 0, σ 1 m)
  sincos-no-la      the lever arm ignored (fixed at 0, not estimated) — the paper's fig 8 case
  small-30          the small-angle filter, heading prior 30°, same lever-arm prior as sincos
  small-5           the small-angle filter, heading prior 5° (a conventional fine-alignment setup)
  small-1           the small-angle filter, heading prior 1° (a good coarse alignment's claim)
                    — these three feed φ̂ back after every 0.1 s update, like the paper's eq 23
  small-5-10s       heading prior 5°, attitude fed back only every 10 s (periodic reset)
  small-5-30s       heading prior 5°, attitude fed back only every 30 s
  small-5-open      heading prior 5°, open loop on attitude: φ̂ applied only at the end (the
                    conventional small-misalignment configuration; position, velocity, biases and
                    lever arm stay closed loop)

A variant "fails" from an initial error when it is not under 1° by the end, or when its final
error exceeds 3× its claimed 1σ; the tool prints, per variant, the initial errors it fails from.

Writes heading_error.png, position_error.png, lever_arm.png, biases.png, table.md, table.json
into OUT_DIR and prints the table. Times are seconds after the vehicle starts moving (t = 10 s);
"t<1°" is the first time after which |heading error| stays below 1° until the end.
Also prints the wall time of one strapdown pass (75 000 IMU samples).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from firmware_sim.physics.vehicle import simulate_drive  # noqa: E402
from northfinder.align.gnss_ins import GnssAlignConfig, GnssSeries, ImuSeries, align_gnss  # noqa: E402
from northfinder.align.small_angle import align_gnss_small_angle  # noqa: E402
from northfinder.align.strapdown import NavState, Strapdown  # noqa: E402

ERRORS_DEG = (10.0, 45.0, 90.0, 135.0, 180.0)
MOTION_START_S = 10.0
LEVER_TRUTH = (0.5, 1.5, 1.2)
LEVER_MEASURED = (0.7, 1.3, 1.45)


def configs() -> dict[str, tuple]:
    base = GnssAlignConfig(lever_arm_b_m=LEVER_MEASURED, lever_arm_std_m=0.3)
    prior5 = replace(base, heading_std_deg=5.0)
    return {
        "sincos": (align_gnss, base),
        "sincos-unknown-la": (align_gnss, replace(base, lever_arm_b_m=(0.0, 0.0, 0.0), lever_arm_std_m=1.0)),
        "sincos-no-la": (align_gnss, replace(base, lever_arm_b_m=(0.0, 0.0, 0.0), lever_arm_std_m=0.0)),
        "small-30": (align_gnss_small_angle, replace(base, heading_std_deg=30.0)),
        "small-5": (align_gnss_small_angle, prior5),
        "small-1": (align_gnss_small_angle, replace(base, heading_std_deg=1.0)),
        "small-5-10s": (partial(align_gnss_small_angle, attitude_feedback=10.0), prior5),
        "small-5-30s": (partial(align_gnss_small_angle, attitude_feedback=30.0), prior5),
        "small-5-open": (partial(align_gnss_small_angle, attitude_feedback="end"), prior5),
    }


SMALL_ANGLE_VARIANTS = ("small-30", "small-5", "small-1", "small-5-10s", "small-5-30s", "small-5-open")
TITLES = {
    "sincos": "paper: δsin/δcos filter (feedback every update)",
    "small-30": "small-angle, prior 30°, feedback every update",
    "small-5": "small-angle, prior 5°, feedback every update",
    "small-1": "small-angle, prior 1°, feedback every update",
    "small-5-10s": "small-angle, prior 5°, attitude reset every 10 s",
    "small-5-30s": "small-angle, prior 5°, attitude reset every 30 s",
    "small-5-open": "small-angle, prior 5°, open loop (applied at the end)",
}


def fails(row: dict) -> bool:
    """Not under 1° by the end, or a final error beyond 3× the claimed 1σ."""
    return row["t_below_1deg_s"] is None or abs(row["final_error_deg"]) > 3.0 * row["final_std_deg"]


def time_below(t_s: np.ndarray, err_deg: np.ndarray, thr_deg: float) -> float | None:
    """First time after which |err| stays < thr until the end (None: never)."""
    bad = np.nonzero(np.abs(err_deg) >= thr_deg)[0]
    if len(bad) and bad[-1] == len(err_deg) - 1:
        return None
    return float(t_s[bad[-1] + 1] if len(bad) else t_s[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--grade", default="kvh1760")
    args = ap.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    drive = simulate_drive(seed=args.seed, grade=args.grade, lever_arm_b_m=LEVER_TRUTH)
    print(f"simulated 300 s drive ({len(drive.dtheta_rad)} IMU samples, {len(drive.gnss_t_s)} fixes) "
          f"in {time.perf_counter() - t0:.2f} s wall")
    imu = ImuSeries.from_increments(drive.dtheta_rad, drive.dv_m_s, drive.rate_hz)
    n = len(drive.gnss_t_s)
    site = drive.site
    gnss = GnssSeries(drive.gnss_t_s, drive.gnss_pos_enu_m, drive.gnss_vel_enu_m_s,
                      np.tile(drive.gnss_pos_std_m, (n, 1)), np.tile(drive.gnss_vel_std_m_s, (n, 1)),
                      (site.latitude_deg, 0.0, site.height_m))
    traj = drive.trajectory

    # strapdown speed: one free-running pass over all samples
    c0 = traj.c_bn(np.array([0.0]))[0]
    ins = Strapdown(NavState(np.zeros(3), np.zeros(3), c0), drive.rate_hz, gnss.local_level())
    t0 = time.perf_counter()
    for k in range(0, len(drive.dtheta_rad), 25):
        ins.propagate(drive.dtheta_rad[k:k + 25], drive.dv_m_s[k:k + 25])
    print(f"strapdown: {len(drive.dtheta_rad)} samples in {time.perf_counter() - t0:.2f} s wall")

    rows, curves = [], {}
    for name, (fn, cfg) in configs().items():
        for e0 in ERRORS_DEG:
            psi_true0 = float(np.rad2deg(traj.heading_rad(np.array([0.0]))[0][0]))
            t_run = time.perf_counter()
            res = fn(imu, gnss, psi_true0 + e0, cfg)
            wall = time.perf_counter() - t_run
            h = res.history
            err = (h.heading_deg - np.rad2deg(traj.heading_rad(h.t_s)[0]) + 180.0) % 360.0 - 180.0
            pos_err = np.linalg.norm((h.pos_enu_m - traj.position_enu_m(h.t_s))[:, :2], axis=1)
            t1, t05 = time_below(h.t_s, err, 1.0), time_below(h.t_s, err, 0.5)
            after = h.t_s >= (t1 if t1 is not None else np.inf)
            rows.append({
                "filter": name,
                "initial_error_deg": e0,
                "t_below_1deg_s": None if t1 is None else round(t1 - MOTION_START_S, 1),
                "t_below_0p5deg_s": None if t05 is None else round(t05 - MOTION_START_S, 1),
                "error_at_60s_deg": round(float(err[np.searchsorted(h.t_s, MOTION_START_S + 60)]), 3),
                "error_at_100s_deg": round(float(err[np.searchsorted(h.t_s, MOTION_START_S + 100)]), 3),
                "final_error_deg": round(float(err[-1]), 3),
                "final_std_deg": round(res.heading_std_deg, 3),
                "max_pos_err_after_1deg_m": round(float(pos_err[after].max()), 2) if after.any() else None,
                "lever_arm_err_m": round(float(np.linalg.norm(res.lever_arm_m - np.asarray(LEVER_TRUTH))), 3),
                "wall_s": round(wall, 2),
            })
            rows[-1]["error_over_std"] = round(abs(float(err[-1])) / res.heading_std_deg, 1)
            rows[-1]["fails"] = fails(rows[-1])
            curves[(name, e0)] = (h, err, pos_err)
            r = rows[-1]
            print(f"{name:18s} {e0:5.0f}°  t<1°={r['t_below_1deg_s']}  t<0.5°={r['t_below_0p5deg_s']}  "
                  f"err60={r['error_at_60s_deg']}  err100={r['error_at_100s_deg']}  "
                  f"end={r['final_error_deg']}±{r['final_std_deg']}  pos={r['max_pos_err_after_1deg_m']}  "
                  f"la_err={r['lever_arm_err_m']}  fails={r['fails']}"
                  f"  ({wall:.1f} s wall)", flush=True)

    print("fails (not under 1° at the end, or final |error| > 3σ) from initial errors:")
    for name in configs():
        bad = [f"{r['initial_error_deg']:.0f}°" for r in rows if r["filter"] == name and r["fails"]]
        print(f"  {name:18s} {', '.join(bad) if bad else 'none'}")
    (args.out_dir / "table.json").write_text(json.dumps(rows, indent=1))
    keys = list(rows[0])
    md = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    md += ["| " + " | ".join(str(r[k]) for k in keys) + " |" for r in rows]
    (args.out_dir / "table.md").write_text("\n".join(md) + "\n")
    plot(args.out_dir, curves, rows)
    print(f"wrote {args.out_dir}/: heading_error, position_error, lever_arm, biases .png; table.md/json")
    return 0


def plot(out: Path, curves: dict, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = dict(zip(ERRORS_DEG, ["C0", "C1", "C2", "C3", "C4"], strict=True))
    panels = ("sincos", *SMALL_ANGLE_VARIANTS)
    fig, grid = plt.subplots(2, 4, figsize=(22, 9.5))
    axes = grid.ravel()
    for ax, name in zip(axes, panels, strict=False):
        for e0 in ERRORS_DEG:
            h, err, _ = curves[(name, e0)]
            ax.semilogy(h.t_s - MOTION_START_S, np.maximum(np.abs(err), 1e-4), color=colors[e0],
                        label=f"{e0:.0f}°")
            ax.semilogy(h.t_s - MOTION_START_S, h.heading_std_deg, color=colors[e0], ls=":", lw=0.8)
        ax.axhline(1.0, color="k", lw=0.6)
        ax.axhline(0.5, color="k", lw=0.6, ls="--")
        ax.axvline(100.0, color="grey", lw=0.6)
        ax.set_title(TITLES[name], fontsize=10)
        ax.set_xlabel("time since motion start [s]")
        ax.set_ylim(1e-3, 200)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_ylabel("|heading error| [deg] (dotted: filter 1σ)")
    axes[0].legend(title="initial error")
    # last panel: final |error| against the initial error, every variant; open marker = fails
    ax = axes[len(panels)]
    for i, name in enumerate(panels):
        rs = [r for r in rows if r["filter"] == name]
        e0 = np.array([r["initial_error_deg"] for r in rs])
        fe = np.maximum(np.abs([r["final_error_deg"] for r in rs]), 1e-3)
        bad = np.array([r["fails"] for r in rs])
        ax.semilogy(e0, fe, color=f"C{i}", lw=0.8, label=name)
        ax.semilogy(e0[~bad], fe[~bad], "o", color=f"C{i}")
        ax.semilogy(e0[bad], fe[bad], "o", mfc="none", color=f"C{i}")
    ax.axhline(1.0, color="k", lw=0.6)
    ax.set_xticks(ERRORS_DEG)
    ax.set_xlabel("initial heading error [deg]")
    ax.set_ylabel("|final heading error| [deg] (open marker: fails)")
    ax.set_title("final error after 300 s, every variant", fontsize=10)
    ax.set_ylim(1e-3, 200)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "heading_error.png", dpi=100)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4.5))
    for name, ls in (("sincos", "-"), ("sincos-no-la", "--")):
        for e0 in (10.0, 180.0):
            h, _, pe = curves[(name, e0)]
            ax.plot(h.t_s - MOTION_START_S, pe, ls=ls, color=colors[e0], label=f"{name} {e0:.0f}°")
    ax.axhline(2.0, color="k", lw=0.6)
    ax.set_xlabel("time since motion start [s]")
    ax.set_ylabel("horizontal IMU position error [m]")
    ax.set_ylim(0, 5)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "position_error.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5), sharey=True)
    for ax, name in zip(axes, ("sincos", "sincos-unknown-la"), strict=True):
        for e0 in ERRORS_DEG:
            h, _, _ = curves[(name, e0)]
            for i, ls in enumerate(("-", "--", ":")):
                ax.plot(h.t_s - MOTION_START_S, h.lever_arm_m[:, i], ls=ls, color=colors[e0], lw=0.9)
        for v in LEVER_TRUTH:
            ax.axhline(v, color="k", lw=0.6)
        ax.set_title(f"{name}: lever arm x (—), y (--), z (··); truth in black")
        ax.set_xlabel("time since motion start [s]")
        ax.set_ylim(-1.0, 2.5)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("lever arm estimate [m]")
    fig.tight_layout()
    fig.savefig(out / "lever_arm.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.5))
    for e0 in ERRORS_DEG:
        h, _, _ = curves[("sincos", e0)]
        for i, ls in enumerate(("-", "--", ":")):
            axes[0].plot(h.t_s - MOTION_START_S, h.gyro_bias_dph[:, i], ls=ls, color=colors[e0], lw=0.9)
            axes[1].plot(h.t_s - MOTION_START_S, h.accel_bias_ug[:, i], ls=ls, color=colors[e0], lw=0.9)
    axes[0].set_ylabel("gyro bias estimate [°/h] (x —, y --, z ··)")
    axes[1].set_ylabel("accelerometer bias estimate [µg]")
    axes[0].set_ylim(-3, 3)
    axes[1].set_ylim(-2000, 2000)
    for ax in axes:
        ax.set_xlabel("time since motion start [s]")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "biases.png", dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
