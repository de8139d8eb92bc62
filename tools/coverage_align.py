#!/usr/bin/env python3
"""Coverage of the align modes' reported 1σ: the fraction of runs with |error| ≤ kσ, k = 1, 2, 3.

    python3 tools/coverage_align.py OUT_DIR [--mode gnss|swaying|both|gnss-ttc] [--seeds 100]
           [--gnss-prior unknown|DEG] [--grade kvh1760] [--swaying-grade nav]

An honest σ puts 68.3 / 95.4 / 99.7 % of the errors inside 1σ / 2σ / 3σ. This tool measures it
at the estimator level on firmware_sim physics (the pattern of tools/reproduce_gnss_paper.py and
tools/reproduce_swaying_paper.py): one run per seed, every seed with its own sensor noise, its own
turn-on biases (drawn per axis as N(0, b²) with b the grade's preset value — the presets are one
fixed draw, and a Monte Carlo over one fixed bias would test nothing), its own GNSS noise and, for
swaying, its own heading and sway phases. The gyros' g-sensitivity is driven by the true specific
force, as the simulated device does.

  gnss     the 310 s default drive (motion from 10 s, still again from 298 s), kvh1760, 250 Hz,
           GNSS 10 Hz; the filter set up as `northfinder align --mode gnss --simulate` sets it up
           (lever arm 0 ± 1 m). Initial heading: `--gnss-prior unknown` draws the initial error
           uniformly in [−180°, 180°) and tells the filter "unknown"; `--gnss-prior 10` draws it
           from N(0, 10°) and gives the filter that prior (the simulated prior = truth + error).
           Times: 10, 30, 60, 120, 300 s after the vehicle starts moving.
  swaying  the issue-5 reference sway at 40° N, 100 Hz; the estimate on the first T seconds for
           T = 60, 120, 300 s (a window shorter than 8 × the longest sway period is refused by the
           estimator, so 10 and 30 s do not exist; 60 s uses periods ≤ 7.5 s like the reproduce
           tool). σ as `northfinder align --mode swaying --simulate` reports it for the grade.

`--mode gnss-ttc` prints instead the time to < 1° (after motion, to the end) from 10/45/90/180° with
the prior given (σ = the initial error) and unknown, per seed and the median.

Prints, per time, the fraction within 1σ/2σ/3σ against 68.3/95.4/99.7 % and the difference in
absolute percentage points; "ok" = within ±10 points at all three k. Writes OUT_DIR/coverage.json
and OUT_DIR/coverage.md.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from firmware_sim.physics.sensors import (  # noqa: E402
    ACCEL_PRESETS,
    GYRO_PRESETS,
    AccelModel,
    GyroModel,
    accel_errors,
    gyro_errors,
)
from firmware_sim.physics.table import TableMotion  # noqa: E402
from firmware_sim.physics.vehicle import VehicleTrajectory  # noqa: E402
from firmware_sim.physics.world import Sinusoid, Site, SwayingPlatform, World  # noqa: E402
from northfinder.align.gnss_ins import GnssAlignConfig, GnssSeries, ImuSeries, align_gnss  # noqa: E402
from northfinder.align.swaying import align_swaying, grade_bias_prior  # noqa: E402
from northfinder.constants import STANDARD_GRAVITY_M_S2, wrap_deg_180  # noqa: E402
from northfinder.rotations import euler_from_dcm  # noqa: E402

EXPECTED = (0.6827, 0.9545, 0.9973)
TOLERANCE_PP = 10.0
GNSS_TIMES_S = (10.0, 30.0, 60.0, 120.0, 300.0)
SWAYING_TIMES_S = (60.0, 120.0, 300.0)
MOTION_START_S = 10.0
GNSS_POS_STD_M = (0.5, 0.5, 1.0)
GNSS_VEL_STD_M_S = 0.05
LEVER_TRUTH_M = (0.5, 1.5, 1.2)
LAT_DEG = 40.0
SWAY_LEVER_M = (1.0, 2.0, 1.5)


def drawn_biases(grade: str, rng: np.random.Generator) -> tuple[dict, dict]:
    """Per-seed turn-on biases: N(0, b²) per axis with b the preset's value (the presets are one draw)."""
    g, a = GYRO_PRESETS[grade], ACCEL_PRESETS[grade]
    return (
        {"bias_dph": tuple(rng.standard_normal(3) * np.abs(g.bias_dph))},
        {"bias_ug": tuple(rng.standard_normal(3) * np.abs(a.bias_ug))},
    )


def coverage(err: np.ndarray, std: np.ndarray) -> list[float]:
    """Fractions of |err| ≤ kσ for k = 1, 2, 3 (NaN rows, runs without an estimate, count as outside)."""
    z = np.abs(err) / std
    return [float(np.mean(np.nan_to_num(z, nan=np.inf) <= k)) for k in (1, 2, 3)]


# ---------------------------------------------------------------------------------------------
# GNSS
# ---------------------------------------------------------------------------------------------
class GnssBench:
    """The drive's truth once (increments and antenna track); per seed only the errors change."""

    def __init__(self, grade: str, rate_hz: float = 250.0, gnss_rate_hz: float = 10.0, noise: str = "grade"):
        self.grade, self.rate_hz, self.noise = grade, rate_hz, noise
        self.traj = VehicleTrajectory(duration_s=MOTION_START_S + max(GNSS_TIMES_S))
        self.site = Site(LAT_DEG, 100.0)
        world = World(self.site, self.traj, TableMotion(power_on_deg=0.0, ringing_amplitude_deg=None))
        n = int(round(self.traj.duration_s * rate_hz))
        self.dth, self.dv = world.increments(0.0, n, 1.0 / rate_hz)
        self.t_fix = np.arange(1, int(np.floor(self.traj.duration_s * gnss_rate_hz)) + 1) / gnss_rate_hz
        self.pos, self.vel = self.traj.antenna_enu(self.t_fix, LEVER_TRUTH_M)

    def config(self, prior_std_deg: float | None) -> GnssAlignConfig:
        """The filter as the CLI's simulated run sets it up: lever arm 0 ± 1 m, the prior, and the IMU
        noise of the grade (`noise` "grade": the simulated run knows it) or the conservative defaults."""
        return GnssAlignConfig.for_imu_grade(
            self.grade if self.noise == "grade" else None,
            heading_std_deg=prior_std_deg,
            lever_arm_b_m=(0.0, 0.0, 0.0),
            lever_arm_std_m=1.0,
        )

    def heading_deg(self, t_s) -> np.ndarray:
        return np.rad2deg(self.traj.heading_rad(np.asarray(t_s, float))[0])

    def data(self, seed: int) -> tuple[ImuSeries, GnssSeries]:
        """IMU samples through the grade's error models with drawn biases, noisy antenna fixes."""
        ss = np.random.SeedSequence(seed).spawn(4)
        gb, ab = drawn_biases(self.grade, np.random.default_rng(ss[3]))
        dth = GyroModel(gyro_errors(self.grade, **gb), self.rate_hz, np.random.default_rng(ss[0])).apply(
            self.dth, self.dv  # the true specific force drives the gyros' g-sensitivity, as on the device
        )
        dv = AccelModel(accel_errors(self.grade, **ab), self.rate_hz, np.random.default_rng(ss[1])).apply(
            self.dv
        )
        rng = np.random.default_rng(ss[2])
        pos = self.pos + rng.standard_normal(self.pos.shape) * np.asarray(GNSS_POS_STD_M)
        vel = self.vel + rng.standard_normal(self.vel.shape) * GNSS_VEL_STD_M_S
        n = len(self.t_fix)
        gnss = GnssSeries(
            self.t_fix,
            pos,
            vel,
            np.tile(GNSS_POS_STD_M, (n, 1)),
            np.full((n, 3), GNSS_VEL_STD_M_S),
            (self.site.latitude_deg, 0.0, self.site.height_m),
        )
        return ImuSeries.from_increments(dth, dv, self.rate_hz), gnss


def gnss_run(bench: GnssBench, seed: int, prior_std_deg: float | None) -> dict:
    """One seed: error and σ at the report times, and the time from which |error| < 1° stays."""
    imu, gnss = bench.data(seed)
    rng = np.random.default_rng([seed, 7])
    e0 = float(rng.uniform(-180.0, 180.0) if prior_std_deg is None else rng.normal(0.0, prior_std_deg))
    res = align_gnss(imu, gnss, float(bench.heading_deg(0.0)) + e0, bench.config(prior_std_deg))
    h = res.history
    err = np.asarray(wrap_deg_180(h.heading_deg - bench.heading_deg(h.t_s)), float)
    idx = [min(int(np.searchsorted(h.t_s, MOTION_START_S + t - 1e-6)), len(h.t_s) - 1) for t in GNSS_TIMES_S]
    return {
        "seed": seed,
        "initial_error_deg": e0,
        "err_deg": err[idx].tolist(),
        "std_deg": h.heading_std_deg[idx].tolist(),
        "max_z_after_1deg": _max_z_converged(h.heading_std_deg, err),
    }


def time_to_1deg(bench: GnssBench, seed: int, e0_deg: float, prior_std_deg: float | None) -> float | None:
    """Seconds after motion start from which |error| < 1° to the end (None: never)."""
    imu, gnss = bench.data(seed)
    h = align_gnss(imu, gnss, float(bench.heading_deg(0.0)) + e0_deg, bench.config(prior_std_deg)).history
    err = np.asarray(wrap_deg_180(h.heading_deg - bench.heading_deg(h.t_s)), float)
    bad = np.nonzero(np.abs(err) >= 1.0)[0]
    if len(bad) and bad[-1] == len(err) - 1:
        return None
    return float((h.t_s[bad[-1] + 1] if len(bad) else h.t_s[0]) - MOTION_START_S)


def ttc_table(bench: GnssBench, seeds: range) -> str:
    """Time to < 1° from 10/45/90/180° with the prior given (σ = the initial error) and unknown."""
    lines = [
        "| initial error | prior | " + " | ".join(f"seed {s}" for s in seeds) + " | median |",
        "|---:|---|" + "---:|" * (len(seeds) + 1),
    ]
    for e0 in (10.0, 45.0, 90.0, 180.0):
        for label, sd in ((f"{e0:g}°", e0), ("unknown", None)):
            t = [time_to_1deg(bench, s, e0, sd) for s in seeds]
            cells = ["never" if v is None else f"{v:.1f}" for v in t]
            med = float(np.median([np.inf if v is None else v for v in t]))
            lines.append(f"| {e0:g}° | {label} | " + " | ".join(cells) + f" | {med:.1f} |")
            print(lines[-1], flush=True)
    return "\n".join(lines)


def _max_z_converged(std: np.ndarray, err: np.ndarray) -> float | None:
    """Largest |error|/σ once σ < 1° (the "4.9σ just after convergence" check)."""
    ok = std < 1.0
    return float(np.max(np.abs(err[ok]) / std[ok])) if ok.any() else None


# ---------------------------------------------------------------------------------------------
# Swaying
# ---------------------------------------------------------------------------------------------
def sway_run(grade: str, seed: int, rate_hz: float) -> dict:
    """One seed: a random heading and sway phases, the estimate on the first T s for each T."""
    rng = np.random.default_rng([seed, 11])
    heading = float(rng.uniform(0.0, 360.0))
    ph = rng.uniform(0.0, 360.0, 4)
    plat = SwayingPlatform(
        heading_deg=heading,
        roll=(Sinusoid(10.0, 8.0, ph[0]),),
        pitch=(Sinusoid(5.0, 6.0, ph[1]),),
        yaw=(Sinusoid(3.0, 10.0, ph[2]),),
        heave=(Sinusoid(0.5, 7.0, ph[3]),),
    )
    world = World(Site(LAT_DEG), plat, TableMotion(power_on_deg=0.0))
    n = int(round(max(SWAYING_TIMES_S) * rate_hz))
    dth, dv = world.increments(0.0, n, 1.0 / rate_hz, SWAY_LEVER_M)
    ss = np.random.SeedSequence(seed).spawn(3)
    gb, ab = drawn_biases(grade, np.random.default_rng(ss[2]))
    gyro = GyroModel(gyro_errors(grade, **gb), rate_hz, ss[0]).apply(dth, dv) * rate_hz
    accel = AccelModel(accel_errors(grade, **ab), rate_hz, ss[1]).apply(dv) * rate_hz / STANDARD_GRAVITY_M_S2
    errs, stds = [], []
    prior = grade_bias_prior(grade)
    for t in SWAYING_TIMES_S:
        k = int(round(t * rate_hz))
        s = align_swaying(
            gyro[:k], accel[:k], rate_hz, LAT_DEG, max_sway_period_s=min(10.0, t / 8.0), **prior
        )
        c, _, _ = world.attitude(np.array([t]))
        errs.append(float(wrap_deg_180(s.heading_deg - math.degrees(euler_from_dcm(c[0])[0]))))
        stds.append(s.heading_std_deg)
    return {"seed": seed, "err_deg": errs, "std_deg": stds}


# ---------------------------------------------------------------------------------------------
# Table
# ---------------------------------------------------------------------------------------------
def table(title: str, times: tuple[float, ...], runs: list[dict], time_label: str) -> tuple[str, list[dict]]:
    err = np.array([r["err_deg"] for r in runs])
    std = np.array([r["std_deg"] for r in runs])
    lines = [
        f"### {title} ({len(runs)} seeds)",
        "",
        f"| {time_label} | ≤1σ [%] (68.3) | ≤2σ [%] (95.4) | ≤3σ [%] (99.7) | worst diff [pp] | "
        "rms error [°] | rms σ [°] | σ < 1° [%] | within ±10 pp |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]
    rows = []
    for i, t in enumerate(times):
        cov = coverage(err[:, i], std[:, i])
        diff = [100.0 * (c - e) for c, e in zip(cov, EXPECTED, strict=True)]
        worst = max(diff, key=abs)
        ok = all(abs(d) <= TOLERANCE_PP for d in diff)
        row = {
            "t_s": t,
            "coverage": cov,
            "diff_pp": diff,
            "ok": ok,
            "rms_error_deg": float(np.sqrt(np.mean(err[:, i] ** 2))),
            "rms_std_deg": float(np.sqrt(np.mean(std[:, i] ** 2))),
            "converged_fraction": float(np.mean(std[:, i] < 1.0)),
        }
        rows.append(row)
        lines.append(
            f"| {t:.0f} | {100 * cov[0]:.1f} | {100 * cov[1]:.1f} | {100 * cov[2]:.1f} | {worst:+.1f} | "
            f"{row['rms_error_deg']:.4f} | {row['rms_std_deg']:.4f} | "
            f"{100 * row['converged_fraction']:.0f} | {'ok' if ok else 'NO'} |"
        )
    return "\n".join(lines), rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out_dir", type=Path)
    ap.add_argument(
        "--mode",
        choices=("gnss", "swaying", "both", "gnss-ttc"),
        default="both",
        help="gnss-ttc: time to < 1° from 10/45/90/180° with and without the prior instead",
    )
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--seed0", type=int, default=1000)
    ap.add_argument("--grade", default="kvh1760", help="GNSS mode's IMU grade")
    ap.add_argument("--swaying-grade", default="nav")
    ap.add_argument("--swaying-rate", type=float, default=100.0)
    ap.add_argument(
        "--gnss-noise",
        choices=("grade", "default"),
        default="grade",
        help="GNSS filter's IMU noise: the grade's data-sheet figures (as a simulated run) or the defaults",
    )
    ap.add_argument("--gnss-prior", default="unknown", help="'unknown' or the prior's 1σ in degrees")
    args = ap.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    seeds = range(args.seed0, args.seed0 + args.seeds)
    out, md = {"args": {k: str(v) for k, v in vars(args).items()}}, []
    t_wall = time.perf_counter()
    if args.mode == "gnss-ttc":
        md.append(ttc_table(GnssBench(args.grade, noise=args.gnss_noise), seeds))
    if args.mode in ("gnss", "both"):
        prior = None if args.gnss_prior == "unknown" else float(args.gnss_prior)
        bench = GnssBench(args.grade, noise=args.gnss_noise)
        runs = []
        for s in seeds:
            runs.append(gnss_run(bench, s, prior))
            if len(runs) % 10 == 0:
                print(
                    f"  gnss: {len(runs)} seeds ({time.perf_counter() - t_wall:.0f} s)",
                    file=sys.stderr,
                    flush=True,
                )
        zs = [r["max_z_after_1deg"] for r in runs if r["max_z_after_1deg"] is not None]
        prior_text = "unknown (uniform initial error)" if prior is None else f"{prior:g}°"
        title = (
            f"GNSS, {args.grade}, filter noise {args.gnss_noise}, prior {prior_text}"
            f"; largest |error|/σ once σ < 1°: median {np.median(zs):.1f}, max {np.max(zs):.1f}"
        )
        text, rows = table(title, GNSS_TIMES_S, runs, "s after motion")
        print(text, flush=True)
        md.append(text)
        out["gnss"] = {"rows": rows, "runs": runs}
    if args.mode in ("swaying", "both"):
        runs = []
        for s in seeds:
            runs.append(sway_run(args.swaying_grade, s, args.swaying_rate))
            if len(runs) % 10 == 0:
                print(
                    f"  swaying: {len(runs)} seeds ({time.perf_counter() - t_wall:.0f} s)",
                    file=sys.stderr,
                    flush=True,
                )
        text, rows = table(
            f"swaying, cone, {args.swaying_grade}, {args.swaying_rate:g} Hz",
            SWAYING_TIMES_S,
            runs,
            "window [s]",
        )
        print(text, flush=True)
        md.append(text)
        out["swaying"] = {"rows": rows, "runs": runs}
    (args.out_dir / "coverage.json").write_text(json.dumps(out, indent=1))
    (args.out_dir / "coverage.md").write_text("\n\n".join(md) + "\n")
    print(f"wrote {args.out_dir}/coverage.md, coverage.json ({time.perf_counter() - t_wall:.0f} s wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
