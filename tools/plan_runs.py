"""End-to-end runs of the find's plans through firmware-sim (issue 13): σ, bias and σ / limit of
the elapsed device time per plan, and a run planned for a target σ against its prediction.

    python3 tools/plan_runs.py [--runs 5] [--seed0 1] [--grade nav] [--latitude 40] [--target-std 0.05]

Part 1: `--runs` finds with `northfinder find --simulate` defaults (8 × 20 s, every sim motion error
on: misalignment, scale-factor asymmetry, g-sensitivity, wobble, speed ripple), seeds seed0…; each
run gives both plans on the same data: the dwell means (plan "positions") and every sample
(plan "positions+motion"). Per plan: the mean error (bias), the rms error, the mean reported σ,
and σ over the white-noise limit of the elapsed time: of the fit's span (the first dwell's start to
the rest after the return), of the IMU stream from the first dwell's start to its end, and of the
plan model's elapsed time (from the start angle: a sweep's turn to its first rest included).
Part 2: `--runs` finds with `--target-std`: the plan the model chose, its predicted σ and elapsed
time against what the runs reported.
Part 3: `--runs` sweeps (`find --simulate --plan sweep`, `--sweep-rests` rests) whose dwell the plan
model solves so that the sweep lasts as long as part 1's 8 × 20 s (the same elapsed device time):
the same figures as part 1.
Every run is a real subprocess simulator on ptys and python-can's slcan client (as `find --simulate`).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from northfinder.estimators.limits import noise_limit_heading_std_deg  # noqa: E402
from northfinder.estimators.plan import GRADES  # noqa: E402


def find(out: Path, seed: int, extra: list[str]) -> dict:
    """One `northfinder find --simulate` in its own process; its result.json."""
    cmd = [sys.executable, "-m", "northfinder", "find", "--simulate", "--seed", str(seed), "--no-report",
           "--out", str(out), "--json", str(out) + ".json", *extra]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"find failed (seed {seed}): {done.stderr[-2000:]}")
    return json.loads(Path(str(out) + ".json").read_text())


def stream_s(run_dir: Path) -> float:
    """Device time of the whole IMU stream in the run's raw log (opening, homing, … the return)."""
    from northfinder.codecs.kvh import decode_imu_stream

    start = next(e for e in map(json.loads, (run_dir / "events.jsonl").read_text().splitlines())
                 if e.get("event") == "start")
    imu = start["imu"]
    block, _ = decode_imu_stream((run_dir / "imu.raw").read_bytes(), imu["rate_hz"], imu["rot_format"],
                                 imu["rot_units"])
    return float(block.sample_index[-1] - block.sample_index[0] + 1) / float(imu["rate_hz"])


def limit_deg(grade: str, elapsed_s: float, lat: float, tilt_deg: float) -> float:
    return float(noise_limit_heading_std_deg(GRADES[grade].arw_deg_rt_h, elapsed_s, lat, tilt_deg, 90.0, 2))


def summarize(name: str, err: np.ndarray, std: np.ndarray, lim_span: np.ndarray, lim_stream: np.ndarray,
              lim_planned: float) -> None:
    rms = float(np.sqrt(np.mean(err**2)))
    print(f"{name:18s} bias {np.mean(err):+.4f}° (±{np.std(err, ddof=1) / math.sqrt(len(err)):.4f})  "
          f"rms err {rms:.4f}°  mean σ {np.mean(std):.4f}°  "
          f"rms |err|/σ {np.sqrt(np.mean((err / std) ** 2)):.2f}  "
          f"σ/limit: fit span {np.mean(std / lim_span):.3f}, "
          f"first dwell → end {np.mean(std / lim_stream):.3f}, "
          f"planned elapsed {np.mean(std) / lim_planned:.3f}")


def planned_limit_deg(args, spec) -> tuple[float, float]:
    """(the plan model's elapsed time of `spec` — from the start angle, the turn to the first rest
    included —, the limit of it) at the bench's 2° tilt."""
    from northfinder.estimators import plan as P

    elapsed = P.predict(spec, GRADES[args.grade], args.latitude, 2.0, P.Stage()).elapsed_s
    return elapsed, limit_deg(args.grade, elapsed, args.latitude, 2.0)


def spans(args, r: dict, run_dir: Path) -> tuple[float, float, float, float]:
    """(fit span s, span with the return s, and the limit of each) of a run with its motion fit."""
    m = r["motion_fit"]
    assert m["available"], m
    tilt = r["truth"]["pitch_deg"], r["truth"]["roll_deg"]
    tilt_deg = math.degrees(math.acos(math.cos(math.radians(tilt[0])) * math.cos(math.radians(tilt[1]))))
    span = m["samples"]["fit_span_device_s"]
    stream = stream_s(run_dir) - m["samples"]["before_first_dwell_s"]  # + the return
    return (span, stream, limit_deg(args.grade, span, args.latitude, tilt_deg),
            limit_deg(args.grade, stream, args.latitude, tilt_deg))


def part1(args, tmp: Path) -> None:
    rows = []
    for k in range(args.runs):
        site = ["--grade", args.grade, "--latitude", str(args.latitude)]
        r = find(tmp / f"defaults{k}", args.seed0 + k, site)
        m = r["motion_fit"]
        span, stream, lim_span, lim_stream = spans(args, r, tmp / f"defaults{k}")
        dwell_err = (r["dwell_fit"]["heading_deg"] - r["truth"]["heading_deg"] + 180) % 360 - 180
        rows.append((dwell_err, r["dwell_fit"]["heading_std_deg"], r["error_deg"], r["heading_std_deg"],
                     lim_span, lim_stream, span, stream))
        print(f"seed {args.seed0 + k}: dwells {dwell_err:+.4f} ± {rows[-1][1]:.4f}°, every sample "
              f"{r['error_deg']:+.4f} ± {r['heading_std_deg']:.4f}°, span {span:.1f} s, "
              f"stream {stream:.1f} s, "
              f"misalignment {m['misalignment_dph_per_dps']}", flush=True)
    a = np.array(rows)
    from northfinder.estimators.plan import PlanSpec

    elapsed, lim = planned_limit_deg(args, PlanSpec("positions+motion", 8, 20.0))
    print(f"\n{args.runs} runs, {args.grade}, {args.latitude}° N, 8 × 20 s (find --simulate defaults, "
          f"planned {elapsed:.0f} s):")
    summarize("positions", a[:, 0], a[:, 1], a[:, 4], a[:, 5], lim)
    summarize("positions+motion", a[:, 2], a[:, 3], a[:, 4], a[:, 5], lim)


def part3(args, tmp: Path) -> None:
    from northfinder.estimators import plan as P

    elapsed = P.predict(P.PlanSpec("positions", 8, 20.0), GRADES[args.grade], args.latitude, 2.0,
                        P.Stage()).elapsed_s
    dwell = round(P.sweep_dwell_for(elapsed, args.sweep_rests, P.Stage()), 1)
    rows = []
    for k in range(args.runs):
        extra = ["--grade", args.grade, "--latitude", str(args.latitude), "--plan", "sweep",
                 "--positions", str(args.sweep_rests), "--dwell", str(dwell)]
        r = find(tmp / f"sweep{k}", args.seed0 + k, extra)
        m = r["motion_fit"]
        span, stream, lim_span, lim_stream = spans(args, r, tmp / f"sweep{k}")
        rows.append((r["error_deg"], r["heading_std_deg"], lim_span, lim_stream))
        print(f"seed {args.seed0 + k}: sweep {args.sweep_rests} rests × {dwell:g} s: {r['error_deg']:+.4f} ± "
              f"{r['heading_std_deg']:.4f}°, span {span:.1f} s, stream {stream:.1f} s, "
              f"misalignment {m['misalignment_dph_per_dps']}", flush=True)
    a = np.array(rows)
    print(f"\n{args.runs} sweeps, {args.grade}, {args.latitude}° N, {args.sweep_rests} rests × {dwell:g} s "
          f"(planned to last {elapsed:.0f} s like 8 × 20 s):")
    _, lim = planned_limit_deg(args, P.PlanSpec("sweep", args.sweep_rests, dwell, "zigzag"))
    summarize("sweep", a[:, 0], a[:, 1], a[:, 2], a[:, 3], lim)


def part2(args, tmp: Path) -> None:
    rows = []
    for k in range(args.runs):
        r = find(tmp / f"target{k}", args.seed0 + k, ["--grade", args.grade, "--latitude", str(args.latitude),
                                                      "--target-std", str(args.target_std)])
        p = r["plan_prediction"]
        motion = r.get("motion_fit", {})
        span = motion["samples"]["fit_span_device_s"] if motion.get("available") else None
        rows.append((r["error_deg"], r["heading_std_deg"], p["predicted_std_deg"], p["predicted_elapsed_s"]))
        print(f"seed {args.seed0 + k}: plan {p['kind']} {p['positions']} × {p['dwell_s']:g} s, predicted "
              f"{p['predicted_std_deg']:.4f}° in {p['predicted_elapsed_s']:.0f} s; "
              f"run σ {r['heading_std_deg']:.4f}° "
              f"(ratio {r['heading_std_deg'] / p['predicted_std_deg']:.3f}), error {r['error_deg']:+.4f}°, "
              f"fit span {span} s", flush=True)
    a = np.array(rows)
    print(f"\n--target-std {args.target_std}: mean reported σ / predicted {np.mean(a[:, 1] / a[:, 2]):.3f}, "
          f"rms error / predicted {np.sqrt(np.mean(a[:, 0] ** 2)) / a[0, 2]:.3f} ({args.runs} runs)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--seed0", type=int, default=1)
    ap.add_argument("--grade", default="nav")
    ap.add_argument("--latitude", type=float, default=40.0)
    ap.add_argument("--target-std", type=float, default=0.05)
    ap.add_argument("--sweep-rests", type=int, default=4)
    ap.add_argument("--part", choices=("1", "2", "3", "both", "all"), default="all")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        if args.part in ("1", "both", "all"):
            part1(args, Path(d))
        if args.part in ("2", "both", "all"):
            part2(args, Path(d))
        if args.part in ("3", "all"):
            part3(args, Path(d))


if __name__ == "__main__":
    main()
