"""Monte Carlo of three turntable plans at the same elapsed device time (issue 13, estimator level).

    python3 tools/plan_vs_limit.py [--trials 200] [--elapsed 240] [--seed 13] [--rate-hz 100]

Per plan — stop-and-go (today: dwell means), stop-and-go using its motion samples (every gyro
sample at its z-gyro angle, misalignment estimated), and a sweep (whole revolutions, both
directions) — it draws per-sample data from its own forward model (CONVENTIONS.md frames:
C_p^n = Rz(−ψ)Rx(θ)Ry(γ), C_b^p = Rz(α); Earth rate and gravity in b; white noise at the grade's
ARW, Gauss–Markov bias instability, rate random walk, scale factors, the horizontal input axes
tilted by δ toward the table axis, a z gyro with scale factor and asymmetry; trapezoid moves),
runs the estimators and prints σ, bias, σ / limit(elapsed) and the planner's predicted σ.
It also runs the motion-sample fit that ignores the motion terms (the biased one).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from northfinder.estimators import plan as P  # noqa: E402
from northfinder.estimators.harmonic import fit_harmonic  # noqa: E402
from northfinder.estimators.heading import solve_batch  # noqa: E402
from northfinder.estimators.motion_fit import fit_motion, heading_from_rates, table_angle_from_z  # noqa: E402

OMEGA_E = 7.2921150e-5  # rad/s, WGS-84 (CONVENTIONS.md)
DPH = math.pi / 180.0 / 3600.0


@dataclass(frozen=True)
class MotionErrors:
    """What a moving table adds: δ_x, δ_y [rad] (input axis toward the table axis), scale factors
    [ppm] of x, y and z, the z gyro's scale-factor asymmetry [ppm], turn-on biases [°/h]."""

    delta_x: float = 2e-4
    delta_y: float = -1.5e-4
    sf_xy_ppm: float = 50.0
    sf_z_ppm: float = 300.0
    sf_z_asym_ppm: float = 100.0
    bias_dph: tuple[float, float, float] = (0.004, -0.003, 0.002)


def g_local_g(lat_deg: float) -> float:
    """WGS-84 normal gravity at sea level (Somigliana) in g."""
    s2 = math.sin(math.radians(lat_deg)) ** 2
    e2 = 6.69437999014e-3
    return 9.7803253359 * (1 + 0.00193185265241 * s2) / math.sqrt(1 - e2 * s2) / 9.80665


def _c_pn(psi: float, theta: float, gamma: float) -> np.ndarray:
    """C_p^n = Rz(−ψ)·Rx(θ)·Ry(γ) (CONVENTIONS.md), written out here, independent of northfinder."""
    cz, sz = math.cos(-psi), math.sin(-psi)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1.0]])
    rx = np.array([[1, 0, 0], [0, math.cos(theta), -math.sin(theta)], [0, math.sin(theta), math.cos(theta)]])
    ry = np.array([[math.cos(gamma), 0, math.sin(gamma)], [0, 1, 0], [-math.sin(gamma), 0, math.cos(gamma)]])
    return rz @ rx @ ry


def truth_platform(heading_deg: float, tilt_deg: float, tilt_az_deg: float, lat_deg: float):
    """Earth rate [rad/s] and specific force [g] in p for tilt ε toward azimuth ζ at heading ψ."""
    e, d = math.radians(tilt_deg), math.radians(tilt_az_deg - heading_deg)
    theta = math.atan2(-math.sin(e) * math.cos(d), math.cos(e))
    gamma = math.asin(math.sin(e) * math.sin(d))
    c_np = _c_pn(math.radians(heading_deg), theta, gamma).T
    lat = math.radians(lat_deg)
    w_p = c_np @ np.array([0.0, OMEGA_E * math.cos(lat), OMEGA_E * math.sin(lat)])
    f_p = c_np @ np.array([0.0, 0.0, g_local_g(lat_deg)])
    return w_p, f_p


def _gm(rng, shape, sigma: float, tau_s: float, dt: float) -> np.ndarray:
    """Stationary first-order Gauss–Markov samples along axis 1 (exact AR(1))."""
    from scipy.signal import lfilter

    phi = math.exp(-dt / tau_s)
    w = rng.standard_normal(shape) * sigma * math.sqrt(1 - phi**2)
    w[:, 0] = sigma * rng.standard_normal(shape[0:1] + shape[2:])
    return lfilter([1.0], [1.0, -phi], w, axis=1)


def simulate_samples(
    rng,
    trials: int,
    sch: P.Schedule,
    sensor: P.Sensor,
    err: MotionErrors,
    heading_deg: float,
    lat_deg: float,
    tilt_deg: float,
    tilt_az_deg: float,
):
    """Per-sample gyro (T, m, 3) [°/h] and accelerometer (T, m, 3) [g] on the schedule's grid."""
    dt, m = sch.dt_s, sch.alpha_deg.size
    w_p, f_p = truth_platform(heading_deg, tilt_deg, tilt_az_deg, lat_deg)
    a = np.deg2rad(sch.alpha_deg)
    c, s = np.cos(a), np.sin(a)
    w_tab = np.deg2rad(sch.omega_dps)
    wb = np.stack([w_p[0] * c + w_p[1] * s, -w_p[0] * s + w_p[1] * c, w_p[2] + w_tab], axis=-1) / DPH
    sf = np.array([err.sf_xy_ppm, -err.sf_xy_ppm, 0.0]) * 1e-6
    sf_z = (err.sf_z_ppm + err.sf_z_asym_ppm * np.sign(w_tab)) * 1e-6
    meas = wb * (1.0 + sf)
    meas[:, 2] = wb[:, 2] * (1.0 + sf_z)
    meas[:, 0] += err.delta_x * wb[:, 2]
    meas[:, 1] += err.delta_y * wb[:, 2]
    gyro = np.broadcast_to(meas + np.asarray(err.bias_dph), (trials, m, 3)).copy()
    gyro += sensor.arw_deg_rt_h * 60.0 / math.sqrt(dt) * rng.standard_normal((trials, m, 3))
    if sensor.bias_instability_dph > 0:
        gyro += _gm(rng, (trials, m, 3), sensor.bias_instability_dph, sensor.bi_correlation_s, dt)
    if sensor.rrw_dph_rt_h > 0:
        gyro += (
            np.cumsum(rng.standard_normal((trials, m, 3)), axis=1)
            * sensor.rrw_dph_rt_h
            / 60.0
            * math.sqrt(dt)
        )
    fb = np.stack([f_p[0] * c + f_p[1] * s, -f_p[0] * s + f_p[1] * c, np.full(m, f_p[2])], axis=-1)
    accel = fb + sensor.accel_noise_ug_rt_hz * 1e-6 / math.sqrt(dt) * rng.standard_normal((trials, m, 3))
    return gyro, accel


def _up_vector(alpha_deg, accel, lat_deg: float) -> np.ndarray:
    """Up vector u^p from a harmonic fit of accelerometer samples (T, m, 3) at their angles (eq 5, 9)."""
    fit = fit_harmonic(np.deg2rad(alpha_deg), accel[..., :2], ("x", "y"))
    fx, fy = fit.coef("v_x"), fit.coef("v_y")
    g = g_local_g(lat_deg)
    return np.stack([fx, fy, np.sqrt(g**2 - fx**2 - fy**2)], axis=-1) / g


def _encoder(sch: P.Schedule) -> np.ndarray:
    """Encoder at rest (NaN while moving), quantized to 1e-4° like the SMC100 stage."""
    return np.where(sch.rest, np.round(sch.alpha_deg, 4), np.nan)


def headings_positions(sch, gyro, accel, sensor, lat):
    """Today's estimator: dwell means → solve_batch (x, y, z gyro; exact method)."""
    used = sch.gyro_used.astype(np.int8)
    edges = np.flatnonzero(np.diff(np.r_[0, used, 0]))
    segs = list(zip(edges[::2], edges[1::2], strict=True))
    ang = np.array([np.round(sch.alpha_deg[a], 4) for a, _ in segs])
    g = np.stack([gyro[:, a:b].mean(axis=1) for a, b in segs], axis=1)
    f = np.stack([accel[:, a:b].mean(axis=1) for a, b in segs], axis=1)
    dwell = (segs[0][1] - segs[0][0]) * sch.dt_s
    std = np.full((len(segs), 3), sensor.arw_deg_rt_h * 60.0 / math.sqrt(dwell))
    sol = solve_batch(ang, g, f, lat, gyro_std_dph=std)
    return sol.heading_deg


def headings_motion(sch, gyro, accel, sensor, lat, terms=("misalignment",)):
    """Every sample at its z-gyro angle pinned to the encoder at rest (eq M1–M4), as the run: from
    the first rest on (a sweep first turns to it), the tilt from the accelerometer at rest."""
    first = int(np.argmax(sch.rest))
    enc, acc, used = _encoder(sch)[first:], sch.rest[first:], sch.gyro_used[first:]
    out = np.empty(gyro.shape[0])
    for t in range(gyro.shape[0]):
        alpha, omega = table_angle_from_z(gyro[t, first:, 2], sch.dt_s, enc)
        up = _up_vector(alpha[acc], accel[t : t + 1, first:][:, acc], lat)[0]
        fit = fit_motion(alpha[used], omega[used], gyro[t, first:][used, :2], ("x", "y"), terms=terms)
        out[t] = heading_from_rates(fit.coef("v_x")[0], fit.coef("v_y")[0], up, lat)[0]
    return out


def stats(err_deg: np.ndarray) -> tuple[float, float, float]:
    """(σ, bias, RMS) of heading errors [deg]."""
    e = (err_deg + 180.0) % 360.0 - 180.0
    return float(np.std(e, ddof=1)), float(np.mean(e)), float(np.sqrt(np.mean(e**2)))


def run_plan(name, spec, estimator, args, sensor, err, stage, rng, terms=None):
    """Monte Carlo of one plan in chunks; returns the table row."""
    sch = P.schedule(spec, stage, 1.0 / args.rate_hz)
    pred = P.predict(spec, sensor, args.latitude, args.tilt, stage)
    errs = []
    for start in range(0, args.trials, args.chunk):
        k = min(args.chunk, args.trials - start)
        gyro, accel = simulate_samples(rng, k, sch, sensor, err, args.heading, args.latitude, args.tilt, 90.0)
        if estimator == "positions":
            h = headings_positions(sch, gyro, accel, sensor, args.latitude)
        else:
            h = headings_motion(sch, gyro, accel, sensor, args.latitude, terms)
        errs.append(h - args.heading)
    sigma, bias, rms = stats(np.concatenate(errs))
    limit = pred.limit_deg
    return dict(
        plan=name,
        spec=spec.describe(),
        elapsed=sch.elapsed_s,
        used=sch.used_s,
        sigma=sigma,
        bias=bias,
        rms=rms,
        ratio=sigma / limit,
        pred=pred.sigma_deg,
        limit=limit,
    )


def plans(elapsed_s: float, stage: P.Stage, n: int, revolutions: int):
    """(name, spec, estimator, motion terms, stage) per row, every plan lasting elapsed_s."""
    d = P.positions_dwell_for(elapsed_s, n, stage)
    one_way = P.Stage(stage.speed_deg_s, stage.accel_deg_s2, stage.settle_s, stage.turnaround_s, False)
    d1 = P.positions_dwell_for(elapsed_s, n, one_way)
    sweep = P.PlanSpec("sweep", revolutions, P.sweep_dwell_for(elapsed_s, revolutions, stage), "zigzag")
    pm, pm1 = P.PlanSpec("positions+motion", n, d), P.PlanSpec("positions+motion", n, d1)
    full = ("misalignment",)
    return [
        ("stop-and-go (today)", P.PlanSpec("positions", n, d), "positions", None, stage),
        ("stop-and-go + motion samples", pm, "motion", full, stage),
        ("  same, motion terms ignored", pm, "motion", (), stage),
        ("stop-and-go + motion, no return move", pm1, "motion", full, one_way),
        ("  same, motion terms ignored", pm1, "motion", (), one_way),
        ("sweep (rests the long way round)", sweep, "motion", full, stage),
        ("  same, motion terms ignored", sweep, "motion", (), stage),
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--elapsed", type=float, default=240.0, help="elapsed device time of every plan [s]")
    ap.add_argument("--seed", type=int, default=13)
    ap.add_argument("--rate-hz", type=float, default=100.0, help="IMU sample rate of the synthetic data")
    ap.add_argument("--latitude", type=float, default=40.0)
    ap.add_argument("--tilt", type=float, default=2.0, help="tilt [deg], toward the east (worst case)")
    ap.add_argument(
        "--heading", type=float, default=37.0, help="true heading [deg] (fixed: bias is per truth)"
    )
    ap.add_argument("--positions", type=int, default=8)
    ap.add_argument("--revolutions", type=int, default=4)
    ap.add_argument("--chunk", type=int, default=25)
    args = ap.parse_args(argv)
    sensor, err, stage = P.GRADES["nav"], MotionErrors(), P.Stage()
    rng = np.random.default_rng(args.seed)
    print(
        f"nav grade (plan.GRADES: ARW {sensor.arw_deg_rt_h} °/√h, BI {sensor.bias_instability_dph} °/h, "
        f"RRW {sensor.rrw_dph_rt_h} °/h/√h), {args.latitude}° N, tilt {args.tilt}° E, "
        f"δ = ({err.delta_x:g}, {err.delta_y:g}) rad, SF xy ±{err.sf_xy_ppm:g} ppm, z {err.sf_z_ppm:g} ± "
        f"{err.sf_z_asym_ppm:g} ppm, {args.trials} trials, {args.rate_hz:g} Hz, seed {args.seed}"
    )
    hdr = (
        "plan",
        "schedule",
        "elapsed s",
        "gyro used s",
        "σ MC °",
        "bias °",
        "abs(bias)/σ",
        "σ/limit(elapsed)",
        "σ predicted °",
        "MC/pred",
    )
    print("| " + " | ".join(hdr) + " |\n|" + "---|" * len(hdr))
    t0 = time.time()
    for name, spec, est, terms, st in plans(args.elapsed, stage, args.positions, args.revolutions):
        r = run_plan(name, spec, est, args, sensor, err, st, rng, terms)
        print(
            f"| {r['plan']} | {r['spec']} | {r['elapsed']:.1f} | {r['used']:.1f} | {r['sigma']:.4f} | "
            f"{r['bias']:+.4f} | {abs(r['bias']) / r['sigma']:.2f} | {r['ratio']:.3f} | {r['pred']:.4f} | "
            f"{r['sigma'] / r['pred']:.3f} |",
            flush=True,
        )
    se = 1.0 / math.sqrt(2 * (args.trials - 1))
    print(
        f"limit(elapsed) = N/(Ωe cos L)·√(2/T)/√2·(1/cos ε); σ MC's own 1σ sampling error ≈ {se:.1%}; "
        f"bias 1σ ≈ σ/√{args.trials} = {1 / math.sqrt(args.trials):.3f}σ; {time.time() - t0:.0f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
