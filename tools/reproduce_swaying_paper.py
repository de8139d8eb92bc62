#!/usr/bin/env python3
"""Monte Carlo of the swaying-base gyrocompass against the seed paper (0.23°, 1σ).

    python3 tools/reproduce_swaying_paper.py OUT_DIR [--runs 100] [--rate 100] [--grades ...]

Data: firmware_sim's physics — World with a SwayingPlatform (the issue's reference scenario:
roll 10°/8 s, pitch 5°/6 s, yaw 3°/10 s, heave 0.5 m/7 s, lever arm (1, 2, 1.5) m, 40° N) and
the GyroModel/AccelModel presets — with a random heading and random sway phases per run.
Each run records 600 s once; every duration uses the first D seconds of it.
Methods on the same data:
  cone   — northfinder.align.swaying, constrained cone fit (Wahba on the smoothed specific force)
  cone-gls — the same plus one GLS step weighted by the measured noise (the fine alignment a
           Kalman filter on the same windows would give)
  circle — the paper's free space-circle fit on the same smoothed vectors
  coarse — northfinder.align.coarse, the static analytic (TRIAD) alignment
Writes OUT_DIR/table.md, OUT_DIR/results.json, OUT_DIR/heading_error_vs_time.png and prints
the table and the measured wall time of the estimator (300 s at 1000 Hz).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from firmware_sim.physics.sensors import ACCEL_PRESETS, GYRO_PRESETS, AccelModel, GyroModel  # noqa: E402
from firmware_sim.physics.table import TableMotion  # noqa: E402
from firmware_sim.physics.world import Sinusoid, Site, SwayingPlatform, World  # noqa: E402
from northfinder.align.coarse import coarse_align  # noqa: E402
from northfinder.align.grades import IMU_GRADES  # noqa: E402
from northfinder.align.swaying import (  # noqa: E402
    align_swaying,
    attitude_quaternions,
    predicted_heading_std_deg,
)
from northfinder.constants import DEG, OMEGA_EARTH_RAD_S, STANDARD_GRAVITY_M_S2, wrap_deg_180  # noqa: E402
from northfinder.errors import InputError  # noqa: E402
from northfinder.rotations import euler_from_dcm  # noqa: E402

PAPER_SIGMA_DEG = 0.23
LAT_DEG = 40.0
LEVER_ARM_M = (1.0, 2.0, 1.5)
METHODS = ("cone", "cone-gls", "circle", "coarse")


def make_world(heading_deg: float, phases_deg: np.ndarray) -> World:
    """The issue's reference sway with the given heading and phases; the table stays at α = 0."""
    plat = SwayingPlatform(
        heading_deg=heading_deg,
        roll=(Sinusoid(10.0, 8.0, phases_deg[0]),),
        pitch=(Sinusoid(5.0, 6.0, phases_deg[1]),),
        yaw=(Sinusoid(3.0, 10.0, phases_deg[2]),),
        heave=(Sinusoid(0.5, 7.0, phases_deg[3]),),
    )
    return World(Site(LAT_DEG), plat, TableMotion(power_on_deg=0.0))


def record(world: World, grade: str, duration_s: float, rate_hz: float, seed: int):
    """(gyro_rad_s, accel_g) as the IMU driver delivers them, through the grade's error models."""
    n = int(round(duration_s * rate_hz))
    dth, dv = world.increments(0.0, n, 1.0 / rate_hz, LEVER_ARM_M)
    ss = np.random.SeedSequence(seed).spawn(2)
    gyro = GyroModel(GYRO_PRESETS[grade], rate_hz, ss[0]).apply(dth, dv) * rate_hz
    accel = AccelModel(ACCEL_PRESETS[grade], rate_hz, ss[1]).apply(dv) * rate_hz / STANDARD_GRAVITY_M_S2
    return gyro, accel


def truth_heading_deg(world: World, t_s: float) -> float:
    c, _, _ = world.attitude(np.array([t_s]))
    return float(np.degrees(euler_from_dcm(c[0])[0]))


def bias_1sigma_dph(grade: str) -> float:
    """1σ of a horizontal gyro bias for the grade: rms of the x/y turn-on biases ⊕ bias instability."""
    g = GYRO_PRESETS[grade]
    turn_on = np.sqrt(np.mean(np.square(g.bias_dph[:2])))
    return float(np.hypot(turn_on, np.mean(g.bias_instability_dph[:2])))


def bias_floor_deg(grade: str) -> float:
    """εE/(Ωe·cos L) (docs/CONVENTIONS.md) for the grade's 1σ horizontal bias."""
    return float(bias_1sigma_dph(grade) * DEG / 3600.0 / (OMEGA_EARTH_RAD_S * np.cos(LAT_DEG * DEG)) / DEG)


def estimate(method: str, gyro, accel, rate_hz: float, duration_s: float, grade: str):
    """(heading_deg, reported 1σ [deg]) of one method on the first duration_s seconds."""
    n = int(round(duration_s * rate_hz))
    g, a = gyro[:n], accel[:n]
    if method == "coarse":
        s = coarse_align(g, a, rate_hz, LAT_DEG)
        return s.heading_deg, s.heading_std_deg
    # Smoothing rejects periods up to L_w/4; at 60 s it can only be 30 s long (periods ≤ 7.5 s).
    period = min(10.0, duration_s / 8.0)
    accel_bias_ug = float(np.sqrt(np.mean(np.square(ACCEL_PRESETS[grade].bias_ug))))
    s = align_swaying(g, a, rate_hz, LAT_DEG, method=method, max_sway_period_s=period,
                      gyro_bias_dph=bias_1sigma_dph(grade), accel_bias_ug=accel_bias_ug,
                      gyro_sf_asymmetry_ppm=IMU_GRADES[grade].gyro_sf_asymmetry_ppm)
    return s.heading_deg, s.heading_std_deg


def wall_time_1000hz() -> dict:
    """Measured wall time of the attitude chain and of a full estimate: 300 s at 1000 Hz."""
    w = make_world(33.0, np.array([10.0, 20.0, 30.0, 40.0]))
    gyro, accel = record(w, "nav", 300.0, 1000.0, 99)
    t0 = time.perf_counter()
    attitude_quaternions(gyro / 1000.0)
    t1 = time.perf_counter()
    s = align_swaying(gyro, accel, 1000.0, LAT_DEG, gyro_bias_dph=bias_1sigma_dph("nav"))
    t2 = time.perf_counter()
    err = float(wrap_deg_180(s.heading_deg - truth_heading_deg(w, 300.0)))
    return {"attitude_300s_1000hz_s": t1 - t0, "estimate_300s_1000hz_s": t2 - t1,
            "error_deg": err, "std_deg": s.heading_std_deg}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir")
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--rate", type=float, default=100.0, help="IMU rate of the Monte Carlo [Hz]")
    ap.add_argument("--grades", default="nav,kvh1760,tactical-mems,consumer")
    ap.add_argument("--durations", default="60,120,300,600")
    ap.add_argument("--curve-runs", type=int, default=20, help="runs drawn in the error-vs-time plot")
    ap.add_argument("--seed", type=int, default=20240)
    args = ap.parse_args(argv)
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    grades = [g for g in args.grades.split(",") if g]
    durations = [float(d) for d in args.durations.split(",") if d]
    t_rec = max(durations)
    t_start = time.perf_counter()

    timing = wall_time_1000hz()
    print(f"wall time, 300 s at 1000 Hz (300 000 samples): attitude chain "
          f"{timing['attitude_300s_1000hz_s']:.3f} s, full estimate {timing['estimate_300s_1000hz_s']:.3f} s "
          f"(error {timing['error_deg']:+.4f}°, "
          f"1σ {timing['std_deg']:.4f}°)")

    fine = fine_alignment_bound(durations)
    print(fine)

    rows = []
    curve = None
    for grade in grades:
        err = {(m, d): [] for m in METHODS for d in durations}
        std = {(m, d): [] for m in METHODS for d in durations}
        failed = {(m, d): 0 for m in METHODS for d in durations}
        curve_t = np.arange(80.0, t_rec + 1e-9, 20.0)
        curve_err, curve_std = [], []
        for run in range(args.runs):
            seed = args.seed + 1000 * grades.index(grade) + run
            rng = np.random.default_rng(seed)
            world = make_world(float(rng.uniform(0.0, 360.0)), rng.uniform(0.0, 360.0, 4))
            gyro, accel = record(world, grade, t_rec, args.rate, seed)
            for d in durations:
                truth = truth_heading_deg(world, d)
                for m in METHODS:
                    try:
                        h, s = estimate(m, gyro, accel, args.rate, d, grade)
                    except (InputError, np.linalg.LinAlgError, FloatingPointError):
                        failed[(m, d)] += 1
                        continue
                    err[(m, d)].append(float(wrap_deg_180(h - truth)))
                    std[(m, d)].append(s)
            if grade == "nav" and run < args.curve_runs:
                e_run, s_run = [], []
                for t in curve_t:
                    h, s = estimate("cone", gyro, accel, args.rate, t, grade)
                    e_run.append(float(wrap_deg_180(h - truth_heading_deg(world, t))))
                    s_run.append(s)
                curve_err.append(e_run)
                curve_std.append(s_run)
        if curve_err:
            curve = (curve_t, np.array(curve_err), np.array(curve_std))
        for m in METHODS:
            for d in durations:
                e = np.array(err[(m, d)])
                rows.append({
                    "method": m, "grade": grade, "duration_s": d, "runs": int(e.size),
                    "failed": failed[(m, d)],
                    "sigma_deg": float(e.std(ddof=1)) if e.size > 1 else float("nan"),
                    "mean_deg": float(e.mean()) if e.size else float("nan"),
                    "rms_deg": float(np.sqrt(np.mean(e**2))) if e.size else float("nan"),
                    "reported_1sigma_deg": (float(np.sqrt(np.mean(np.square(std[(m, d)]))))
                                            if e.size else float("nan")),
                    "paper_sigma_deg": PAPER_SIGMA_DEG,
                    "bias_floor_deg": bias_floor_deg(grade),
                })
        print(f"  {grade}: done ({time.perf_counter() - t_start:.0f} s)", flush=True)

    table = format_table(rows, args)
    print(table)
    (out / "table.md").write_text(table + "\n\n" + fine + "\n")
    (out / "results.json").write_text(
        json.dumps({"rows": rows, "timing": timing, "args": vars(args)}, indent=1))
    plot(out / "heading_error_vs_time.png", rows, curve, grades, durations)
    print(f"wrote {out / 'table.md'}, {out / 'results.json'}, {out / 'heading_error_vs_time.png'} "
          f"({time.perf_counter() - t_start:.0f} s)")
    return 0


def fine_alignment_bound(durations) -> str:
    """What a Kalman fine alignment on the same windows can gain: GLS vs the unweighted fit (nav)."""
    g, a = GYRO_PRESETS["nav"], ACCEL_PRESETS["nav"]
    arw, acc = float(np.mean(g.arw_deg_rt_h)), float(np.mean(a.noise_ug_rt_hz))
    n = arw * DEG / 60.0
    lines = [f"Fine alignment bound, white noise only (nav: {arw:g} °/√h, {acc:g} µg/√Hz, {LAT_DEG:g}° N, "
             "L_w = 40 s):", "",
             "| T [s] | cone fit σψ [°] | GLS ≡ KF on the windows σψ [°] | gain | limit N/(Ωe·cosL·√T) [°] |",
             "|---:|---:|---:|---:|---:|"]
    for d in durations:
        if d < 80.0:
            continue
        ols = predicted_heading_std_deg(d, LAT_DEG, arw, acc)
        gls = predicted_heading_std_deg(d, LAT_DEG, arw, acc, weighting="gls")
        lim = n / (OMEGA_EARTH_RAD_S * np.cos(LAT_DEG * DEG) * np.sqrt(d)) / DEG
        lines.append(f"| {d:.0f} | {ols:.4f} | {gls:.4f} | {100 * (1 - gls / ols):.1f} % | {lim:.4f} |")
    return "\n".join(lines)


def format_table(rows, args) -> str:
    lines = [
        f"Reference sway, {LAT_DEG:g}° N, {args.runs} runs per cell at {args.rate:g} Hz (firmware_sim "
        "physics), random heading and sway phases. σψ = sample std of the heading error at the end of "
        "the window.",
        "",
        "| method | grade | T [s] | σψ [°] | mean [°] | rms [°] | reported 1σ [°] | paper [°] "
        "| bias floor εE/(Ωe·cosL) [°] | failed |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['method']} | {r['grade']} | {r['duration_s']:.0f} | {r['sigma_deg']:.4f} | "
            f"{r['mean_deg']:+.4f} | {r['rms_deg']:.4f} | {r['reported_1sigma_deg']:.4f} | "
            f"{r['paper_sigma_deg']:.2f} | "
            f"{_floor(r['bias_floor_deg'])} | {r['failed']} |")
    return "\n".join(lines)


def _floor(x: float) -> str:
    """The small-angle bias floor is meaningless beyond ~1 rad: say so instead of printing 880°."""
    return f"{x:.4f}" if x < 57.3 else "> 1 rad (no north)"


def plot(path: Path, rows, curve, grades, durations) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 6.0))
    if curve is not None:
        t, e, s = curve
        for k in range(e.shape[0]):
            ax1.plot(t, e[k], color="tab:blue", lw=0.8, alpha=0.5)
        sig = np.sqrt(np.mean(s**2, axis=0))
        ax1.plot(t, sig, "k--", lw=1.5, label="reported ±1σ (rms over runs)")
        ax1.plot(t, -sig, "k--", lw=1.5)
        ax1.plot(t, e.std(axis=0, ddof=1), color="tab:red", lw=1.5, label="Monte Carlo σψ")
        ax1.axhline(PAPER_SIGMA_DEG, color="tab:green", lw=1, ls=":", label="paper 0.23° (1σ)")
        ax1.axhline(-PAPER_SIGMA_DEG, color="tab:green", lw=1, ls=":")
        ax1.set_ylim(-0.4, 0.4)
        ax1.set_title(f"cone fit, nav grade: heading error vs alignment time ({e.shape[0]} runs)")
        ax1.set_xlabel("alignment window [s device time]")
        ax1.set_ylabel("heading error [°]")
        ax1.grid(alpha=0.3)
        ax1.legend(loc="upper right", fontsize=8)
    styles = {"cone": "-o", "cone-gls": "-x", "circle": "--s", "coarse": ":^"}
    colors = dict(zip(grades, ["tab:blue", "tab:orange", "tab:purple", "tab:gray"], strict=False))
    for r_grade in grades:
        for m in METHODS:
            sel = [r for r in rows if r["grade"] == r_grade and r["method"] == m]
            ax2.semilogy([r["duration_s"] for r in sel], [r["sigma_deg"] for r in sel], styles[m],
                         color=colors.get(r_grade), label=f"{m}, {r_grade}", ms=4)
        if bias_floor_deg(r_grade) < 57.3:  # beyond 1 rad the small-angle floor means "no north"
            ax2.axhline(bias_floor_deg(r_grade), color=colors.get(r_grade), lw=0.8, ls="-.", alpha=0.6)
    ax2.axhline(PAPER_SIGMA_DEG, color="tab:green", lw=1.5, ls=":", label="paper 0.23°")
    ax2.set_xlabel("alignment window [s]")
    ax2.set_ylabel("σψ [°] (dash-dot: bias floor per grade)")
    ax2.set_title("σψ by method, grade and duration")
    ax2.grid(alpha=0.3, which="both")
    ax2.set_ylim(0.01, 300.0)
    ax2.legend(fontsize=6, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.12))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    raise SystemExit(main())
