#!/usr/bin/env python3
"""Monte Carlo heading accuracy against the white-noise limit, drift, and solver speed.

Usage: python3 tools/accuracy_vs_limit.py OUTDIR [--trials N] [--seed S]

1. White gyro noise over n ∈ {4, 8, 24}, T_total ∈ {120, 600} s, ARW ∈ {0.002, 0.012} °/√h,
   L ∈ {0, 40, 60}°, tilt 0° and 10° (tilt azimuth 90°, the worst k): σ_MC / σ_limit per cell
   (σ_limit from northfinder.estimators.limits, the tilted bound for tilted cells) and the RMS
   reported heading_std_deg / σ_MC.
2. With bias drift (rate random walk): plain least squares vs the drift-aware model (bias linear
   in time), in natural and interleaved position order, per cell.
3. Wall time of 10⁴ trials of a 24-position find (simulate + solve, and solve only).
Writes ratio_vs_limit.png, drift.png and results.md into OUTDIR.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing

import matplotlib  # noqa: E402
import matplotlib.ticker  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from northfinder.estimators import montecarlo as mc  # noqa: E402
from northfinder.estimators.heading import solve_batch  # noqa: E402
from northfinder.estimators.limits import noise_limit_heading_std_deg  # noqa: E402

HEADING_DEG, TILT_AZ_DEG = 30.0, 90.0


def wrap180(x):
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


def white_grid(rng, trials):
    rows = []
    for n, t_total, arw, lat, tilt in itertools.product(
        (4, 8, 24), (120.0, 600.0), (0.002, 0.012), (0.0, 40.0, 60.0), (0.0, 10.0)
    ):
        pitch, roll = mc.pitch_roll_for_tilt(HEADING_DEG, tilt, TILT_AZ_DEG)
        plan = mc.Plan(mc.equally_spaced_deg(n), dwell_s=t_total / n)
        b = mc.simulate(rng, trials, plan, HEADING_DEG, pitch, roll, lat, mc.GyroNoise(arw_deg_rt_h=arw))
        sol = solve_batch(b.table_angle_deg, b.gyro_dph, b.accel_g, lat, gyro_std_dph=b.gyro_std_dph)
        sigma = np.sqrt(np.mean(wrap180(sol.heading_deg - HEADING_DEG) ** 2))
        limit = float(noise_limit_heading_std_deg(arw, t_total, lat, tilt, TILT_AZ_DEG))
        reported = np.sqrt(np.mean(sol.heading_std_deg**2))
        rows.append((n, t_total, arw, lat, tilt, limit, sigma, sigma / limit, reported / sigma))
    return rows


def drift_grid(rng, trials):
    rows = []
    for n, t_total, arw, rrw in itertools.product((8, 24), (120.0, 600.0), (0.002, 0.012), (0.05, 0.5)):
        rms = {}
        for order in ("natural", "interleaved"):
            idx = np.arange(n) if order == "natural" else mc.interleaved_order(n)
            plan = mc.Plan(mc.equally_spaced_deg(n)[idx], dwell_s=t_total / n, gap_s=10.0)
            b = mc.simulate(
                rng,
                trials,
                plan,
                HEADING_DEG,
                1.0,
                2.0,
                40.0,
                mc.GyroNoise(arw_deg_rt_h=arw, rrw_dph_rt_h=rrw),
            )
            for model in ("constant", "linear"):
                sol = solve_batch(
                    b.table_angle_deg,
                    b.gyro_dph,
                    b.accel_g,
                    40.0,
                    bias_model=model,
                    sample_times_s=b.sample_times_s,
                )
                rms[(order, model)] = np.sqrt(np.mean(wrap180(sol.heading_deg - HEADING_DEG) ** 2))
        limit = float(noise_limit_heading_std_deg(arw, t_total, 40.0))
        rows.append((n, t_total, arw, rrw, limit, rms))
    return rows


def timing(rng):
    plan = mc.Plan(mc.equally_spaced_deg(24), dwell_s=25.0)
    gyro, accel = mc.GyroNoise(arw_deg_rt_h=0.01, bias_sigma_dph=0.5), mc.AccelNoise(noise_ug_rt_hz=20.0)
    full, solve = [], []
    for _ in range(5):
        t0 = time.perf_counter()
        b = mc.simulate(rng, 10_000, plan, HEADING_DEG, 2.0, 3.0, 40.0, gyro, accel, three_axis=True)
        t1 = time.perf_counter()
        solve_batch(
            b.table_angle_deg,
            b.gyro_dph,
            b.accel_g,
            40.0,
            gyro_std_dph=b.gyro_std_dph,
            accel_std_g=b.accel_std_g,
        )
        t2 = time.perf_counter()
        full.append(t2 - t0)
        solve.append(t2 - t1)
    return min(full), float(np.median(full)), min(solve)


AGREEMENT_BAND = (0.95, 1.05)
"""The shaded band of ratio_vs_limit.png: within ±5 % of 1 (Monte Carlo agrees with the limit)."""


def _finish(fig, ax, title, path):
    """Title, y grid and the legend outside the axes, saved to `path` at 120 dpi; the figure is returned
    closed (its texts stay readable)."""
    ax.set_title(title)
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return fig


def plot_ratio_vs_limit(white, trials, path):
    """ratio_vs_limit.png: per cell σ_MC/σ_limit (filled) and reported/σ_MC (open), tilt 0° and 10°
    side by side; cells grouped by (n, T_total, ARW), latitude L within each group."""
    groups = sorted({(r[0], r[1], r[2]) for r in white})
    lats = sorted({r[3] for r in white})
    fig, ax = plt.subplots(figsize=(14, 5.2))
    for tilt, marker, dx in ((0.0, "o", -0.15), (10.0, "s", 0.15)):
        rows = [r for r in white if r[4] == tilt]
        slot = [groups.index((r[0], r[1], r[2])) * (len(lats) + 1) + lats.index(r[3]) for r in rows]
        x = np.array(slot) + dx
        ax.plot(x, [r[7] for r in rows], marker, color="C0" if tilt == 0 else "C1",
                label=f"σ_MC / σ_limit, tilt {tilt:g}°")
        ax.plot(x, [r[8] for r in rows], marker, mfc="none", color="C2" if tilt == 0 else "C3",
                label=f"reported σ / σ_MC, tilt {tilt:g}°")
    ax.axhspan(*AGREEMENT_BAND, color="g", alpha=0.1, label="within ±5 % of 1")
    ax.axhline(1.0, color="k", lw=0.8)
    ticks = [g * (len(lats) + 1) + k for g in range(len(groups)) for k in range(len(lats))]
    ax.set_xticks(ticks, [f"{lat:g}" for _ in groups for lat in lats], fontsize=7)
    for g, (n, t_total, arw) in enumerate(groups):
        ax.text(g * (len(lats) + 1) + (len(lats) - 1) / 2, -0.07, f"n {n}\n{t_total:g} s\n{arw:g} °/√h",
                transform=ax.get_xaxis_transform(), ha="center", va="top", fontsize=7)
    ax.set_xlabel("latitude L [°] in each cell group (n positions, T_total, ARW)", labelpad=44)
    ax.set_ylabel("ratio (1 = at the limit / honest σ)")
    title = f"Monte Carlo heading error against the white-noise limit ({trials} trials per cell)"
    return _finish(fig, ax, title, path)


DRIFT_KEYS = (("natural", "constant"), ("natural", "linear"), ("interleaved", "constant"),
              ("interleaved", "linear"))
DRIFT_FIT = {"constant": "plain (constant bias)", "linear": "drift-aware (linear bias)"}


def plot_drift(drift, trials, path):
    """drift.png: RMS heading error per cell (categorical: markers, no lines between cells) for plain
    and drift-aware fits in natural and interleaved order, and each cell's white-noise limit."""
    fig, ax = plt.subplots(figsize=(15, 5.4))
    x = np.arange(len(drift))
    for (k, marker), dx in zip(zip(DRIFT_KEYS, ("o", "s", "^", "v"), strict=True), (-0.24, -0.08, 0.08, 0.24),
                               strict=True):
        ax.semilogy(x + dx, [r[5][k] for r in drift], marker, ls="none",
                    label=f"{DRIFT_FIT[k[1]]}, {k[0]} order")
    ax.semilogy(x, [r[4] for r in drift], "_", color="k", ms=22, mew=1.5, ls="none",
                label="white-noise limit")
    ax.set_xticks(x, [f"n {r[0]}\n{r[1]:g} s\n{r[2]:g} °/√h\n{r[3]:g} °/h/√h" for r in drift], fontsize=7)
    ax.set_xlabel("cell: positions n, T_total, ARW, RRW (bias drift); L = 40°, 10 s move between positions")
    ax.set_ylabel("RMS heading error [°] (log)")
    ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.tick_params(axis="y", which="minor", labelsize=7)
    return _finish(fig, ax, f"Bias drift: plain vs drift-aware fit ({trials} trials per cell)", path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("outdir", type=Path)
    ap.add_argument("--trials", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    out = args.outdir
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)

    white = white_grid(rng, args.trials)
    md = [f"# Heading accuracy vs the noise limit ({args.trials} trials per cell, seed {args.seed})", ""]
    md += ["## White gyro noise", "", "σ_limit: level formula of CONVENTIONS.md × k = √(1 + (tan ε·sin ζ)²) "
           f"(ζ = {TILT_AZ_DEG:g}°, so k = 1/cos ε at 10°).", ""]  # fmt: skip
    md += [
        "| n | T_total [s] | ARW [°/√h] | L [°] | tilt [°] | σ_limit [°] | σ_MC [°] | σ_MC/σ_limit "
        "| reported/σ_MC |"
    ]
    md += ["|---|---|---|---|---|---|---|---|---|"]
    for n, t, arw, lat, tilt, lim, sig, ratio, rep in white:
        md.append(
            f"| {n} | {t:g} | {arw:g} | {lat:g} | {tilt:g} | {lim:.4f} | {sig:.4f} | {ratio:.4f} "
            f"| {rep:.4f} |"
        )
    ratios = np.array([r[7] for r in white])
    reps = np.array([r[8] for r in white])
    line = (f"white noise: σ_MC/σ_limit over {len(white)} cells in [{ratios.min():.4f}, {ratios.max():.4f}], "
            f"reported/σ_MC in [{reps.min():.4f}, {reps.max():.4f}]")  # fmt: skip
    print(line)
    md += ["", line, ""]

    plot_ratio_vs_limit(white, args.trials, out / "ratio_vs_limit.png")

    drift = drift_grid(rng, args.trials)
    md += ["## Bias drift (rate random walk), L = 40°, 10 s move between positions", ""]
    md += ["RMS heading error [°]; *plain* = constant bias (eq 4), *aware* = bias linear in time; "
           "*interleaved* visits opposite positions back to back (0°, 180°, 90°, 270°, …).", ""]  # fmt: skip
    md += [
        "| n | T_total [s] | ARW [°/√h] | RRW [°/h/√h] | σ_limit [°] "
        "| plain natural | aware natural | plain interleaved | aware interleaved | best |"
    ]
    md += ["|---|---|---|---|---|---|---|---|---|---|"]
    for n, t, arw, rrw, lim, rms in drift:
        best = min(rms, key=rms.get)
        vals = " | ".join(
            f"{rms[k]:.4f}"
            for k in (
                ("natural", "constant"),
                ("natural", "linear"),
                ("interleaved", "constant"),
                ("interleaved", "linear"),
            )
        )
        md.append(f"| {n} | {t:g} | {arw:g} | {rrw:g} | {lim:.4f} | {vals} | {best[1]} {best[0]} |")
        print(f"drift n={n} T={t:g} ARW={arw:g} RRW={rrw:g}: limit {lim:.4f}°, {vals}")
    plot_drift(drift, args.trials, out / "drift.png")

    best_full, median_full, best_solve = timing(rng)
    line = (f"10^4 trials of a 24-position find (3-axis, simulate + solve): best {best_full:.3f} s, median "
            f"{median_full:.3f} s; solve only: best {best_solve:.3f} s")  # fmt: skip
    print(line)
    md += ["", "## Speed", "", line]
    (out / "results.md").write_text("\n".join(md) + "\n")
    print(f"wrote {out}/ratio_vs_limit.png drift.png results.md")


if __name__ == "__main__":
    main()
