#!/usr/bin/env python3
"""IMU–GNSS time offset from the data on late, jittery links (issue 16 part 4), at the estimator level.

    python3 tools/time_offset_links.py [--seeds 3] [--duration 300] [--no-heading]

For each seed, one drive on firmware_sim physics (the default drive, kvh1760, 250 Hz, GNSS 10 Hz,
lever arm (0.5, 1.5, 1.2) m; IMU sample 0 starts at GNSS time 0). For each link latency L in
0, 50, 100, 150, 200 ms with ±20 ms jitter (firmware_sim.link's seeded delay process), the host's
lower-envelope start (min IMU chunk delay − min GNSS epoch delay, chunks of 10 samples) for two
link set-ups — both links L ± 20 ms, and the IMU link L ± 20 ms with the GNSS on time (the host
stamps' worst case) — and the data estimate refined from it (northfinder.align.time_offset).

Prints per latency: the host error, the data error, its σ and error/σ, worst over seeds. Then,
unless --no-heading, the heading of the δsin/δcos filter (lever arm prior 0 ± 1 m, heading unknown)
on each seed's drive with the true start and with the data estimate of the 150 ms IMU-only case:
the heading difference against the filter's σ ("heading unaffected beyond its σ").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from firmware_sim.link import LinkShaper, LinkSpec  # noqa: E402
from firmware_sim.physics.vehicle import VehicleTrajectory, simulate_drive  # noqa: E402
from northfinder.align.gnss_ins import GnssAlignConfig, GnssSeries, ImuSeries, align_gnss  # noqa: E402
from northfinder.align.time_offset import NoTimeInformation, estimate_time_offset  # noqa: E402

LATENCIES_MS = (0, 50, 100, 150, 200)
JITTER_MS = 20.0
CHUNK = 10
LATITUDE_DEG = 40.0
G = 9.80665


def coarse_t0(drive, imu_ms: float, gnss_ms: float, seed: int) -> float:
    """The host stamps' start of sample 0 (truth 0) with firmware_sim's link delay processes."""
    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2)]
    jit = JITTER_MS / 1e3
    imu = LinkShaper(LinkSpec(imu_ms / 1e3, jit if imu_ms else 0.0), rngs[0])
    gnss = LinkShaper(LinkSpec(gnss_ms / 1e3, jit if gnss_ms else 0.0), rngs[1])
    ends = np.arange(CHUNK, len(drive.dtheta_rad) + 1, CHUNK) / drive.rate_hz
    return float(imu.delay_s(ends).min() - gnss.delay_s(drive.gnss_t_s).min())


def estimate(drive, coarse: float):
    gyro = drive.dtheta_rad * drive.rate_hz
    accel = drive.dv_m_s * drive.rate_hz / G
    return estimate_time_offset(
        gyro, accel, None, drive.rate_hz, drive.gnss_t_s, drive.gnss_vel_enu_m_s, LATITUDE_DEG, coarse
    )


def heading(drive, t0_s: float) -> tuple[float, float, float]:
    """(heading error [deg], 1σ [deg], truth at the end) of the sin/cos filter with IMU start t0_s."""
    imu = ImuSeries.from_increments(drive.dtheta_rad, drive.dv_m_s, drive.rate_hz, t0_s)
    n = len(drive.gnss_t_s)
    gnss = GnssSeries(drive.gnss_t_s, drive.gnss_pos_enu_m, drive.gnss_vel_enu_m_s,
                      np.tile(drive.gnss_pos_std_m, (n, 1)), np.tile(drive.gnss_vel_std_m_s, (n, 1)),
                      (LATITUDE_DEG, 0.0, drive.site.height_m))
    cfg = GnssAlignConfig(lever_arm_b_m=(0.0, 0.0, 0.0), lever_arm_std_m=1.0)
    res = align_gnss(imu, gnss, 0.0, cfg)
    t_last = float(res.history.t_s[-1])
    truth = float(np.rad2deg(drive.trajectory.heading_rad(np.array([t_last]))[0][0]))
    err = (res.heading_deg - truth + 180.0) % 360.0 - 180.0
    return err, res.heading_std_deg, truth


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--duration", type=float, default=300.0)
    p.add_argument("--no-heading", action="store_true")
    args = p.parse_args(argv)
    t_wall = time.monotonic()
    drives = [simulate_drive(VehicleTrajectory(duration_s=args.duration), seed=s) for s in range(args.seeds)]
    print(f"{args.seeds} drives of {args.duration:g} s; IMU sample 0 at GNSS time 0 (truth)\n")
    print("| links | latency [ms] | host error [ms] (worst) | data error [ms] (worst) | σ [ms] | "
          "worst |error|/σ | 3σ ≤ 10 ms |")
    print("|---|---|---|---|---|---|---|")
    data_150 = {}
    for setup in ("both", "imu-only"):
        for lat in LATENCIES_MS:
            host_e, data_e, sig = [], [], []
            for s, d in enumerate(drives):
                gnss_ms = lat if setup == "both" else 0.0
                c = coarse_t0(d, lat, gnss_ms, seed=1000 * s + lat)
                try:
                    est = estimate(d, c)
                except NoTimeInformation as exc:
                    print(f"seed {s}: {exc}")
                    continue
                host_e.append(c * 1e3)
                data_e.append(est.t0_s * 1e3)
                sig.append(est.std_s * 1e3)
                if setup == "imu-only" and lat == 150:
                    data_150[s] = est.t0_s
            he, de, sg = np.array(host_e), np.array(data_e), np.array(sig)
            worst = lambda a: a[np.argmax(np.abs(a))]  # noqa: E731
            label = f"{lat} ± {JITTER_MS:g}" if lat else "0"
            print(f"| {setup} | {label} | {worst(he):+.1f} | {worst(de):+.2f} | "
                  f"{sg.min():.2f}–{sg.max():.2f} | {np.max(np.abs(de) / sg):.2f} | "
                  f"{'yes' if np.all(3 * sg <= 10.0) else 'NO'} |")
    if not args.no_heading:
        print("\nheading of the δsin/δcos filter, true start vs the data estimate (IMU link 150 ± 20 ms):")
        print("| seed | data − truth start [ms] | error, true start [deg] | error, data start [deg] | "
              "σ [deg] | |difference|/σ |")
        print("|---|---|---|---|---|---|")
        for s, t0 in data_150.items():
            e_true, _, _ = heading(drives[s], 0.0)
            e_data, sig, _ = heading(drives[s], t0)
            print(f"| {s} | {t0 * 1e3:+.2f} | {e_true:+.4f} | {e_data:+.4f} | {sig:.4f} | "
                  f"{abs(e_data - e_true) / sig:.3f} |")
    print(f"\nwall time {time.monotonic() - t_wall:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
