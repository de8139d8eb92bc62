"""Role × model on firmware-sim: each model's `check` line, one find (default 8 × 20 s), error, σ,
σ / noise limit of its grade, replay identical — and the mixed bench (APT + STIM + CiA 410).

    python tools/second_models_table.py [--positions 8] [--dwell 20] [--time-scale 10] [--only NAME]

Each row runs firmware-sim with the row's models, writes a bench.toml with `model =` keys for
`northfinder check`, then `northfinder find --simulate` with the same models and `northfinder
replay` of its run directory. The limit is docs/CONVENTIONS.md's (northfinder.estimators.limits,
with the tilt factor and both horizontal gyros) for the grade's ARW from northfinder's own grade
table (estimators.plan.GRADES), over the device time the reported fit used.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from northfinder.estimators.limits import noise_limit_heading_std_deg
from northfinder.estimators.plan import GRADES
from northfinder.rotations import tilt_and_azimuth

ROWS = {  # name: (stage, imu, tilt, grade)
    "smc100+kvh+nf-accel": ("smc100", "kvh", "nf-accel", "nav"),
    "apt": ("apt", "kvh", "nf-accel", "nav"),
    "stim": ("smc100", "stim", "nf-accel", "stim300"),
    "cia410": ("smc100", "kvh", "cia410", "nav"),
    "mixed apt+stim+cia410": ("apt", "stim", "cia410", "stim300"),
}
CLI = [sys.executable, "-m", "northfinder"]


def model_flags(stage: str, imu: str, tilt: str, grade: str) -> list[str]:
    """The model and grade flags, which firmware-sim and `northfinder find --simulate` both take."""
    return ["--stage", stage, "--imu", imu, "--tilt", tilt, "--grade", grade]


def check_lines(stage: str, imu: str, tilt: str, grade: str, tmp: Path) -> list[str]:
    """firmware-sim with these models, a bench.toml naming them, `northfinder check` → its lines."""
    sim = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "firmware_sim",
            *model_flags(stage, imu, tilt, grade),
            "--time-scale",
            "5",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        ep = json.loads(sim.stdout.readline())
        can = ep["can"]
        bench = tmp / f"bench-{stage}-{imu}-{tilt}.toml"
        bench.write_text(
            f'[turntable]\nmodel = "{stage}"\nport = "{ep["turntable"]}"\n'
            f'[imu]\nmodel = "{imu}"\nport = "{ep["imu"]}"\n'
            f'[accelerometer]\nmodel = "{tilt}"\ninterface = "{can["interface"]}"\n'
            f'channel = "{can["channel"]}"\n'
            f"node_id = {can['node_id']}\nbus_options = {{sleep_after_open = 0.05}}\n"
            "[site]\nlatitude_deg = 40.0\n"
        )
        out = subprocess.run(
            [*CLI, "check", "--config", str(bench)], capture_output=True, text=True, timeout=120
        )
        return out.stdout.strip().splitlines() + [ln for ln in out.stderr.strip().splitlines() if ln]
    finally:
        sim.terminate()
        sim.wait(timeout=10)


def one_find(stage: str, imu: str, tilt: str, grade: str, args: argparse.Namespace, out: Path) -> dict:
    cmd = [
        *CLI,
        "find",
        "--simulate",
        *model_flags(stage, imu, tilt, grade),
        "--positions",
        str(args.positions),
        "--dwell",
        str(args.dwell),
        "--time-scale",
        str(args.time_scale),
        "--seed",
        str(args.seed),
        "--no-report",
        "--out",
        str(out),
    ]
    t0 = time.monotonic()
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    wall = time.monotonic() - t0
    if run.returncode:
        return {"failed": (run.stderr.strip().splitlines() or ["?"])[-1]}
    result = json.loads((out / "result.json").read_text())
    replay = subprocess.run([*CLI, "replay", str(out)], capture_output=True, text=True, timeout=600)
    first = (replay.stdout.strip().splitlines() or [""])[0]
    truth = result["truth"]
    tilt_rad, tilt_az = tilt_and_azimuth(
        *np.deg2rad([truth["heading_deg"], truth["pitch_deg"], truth["roll_deg"]])
    )
    motion = result.get("motion_fit") or {}
    used_s = motion["samples"]["used_device_s"] if motion.get("available") else result["duration_device_s"]
    limit = float(
        noise_limit_heading_std_deg(
            GRADES[grade].arw_deg_rt_h,
            used_s,
            result["latitude_deg"],
            np.rad2deg(tilt_rad),
            np.rad2deg(tilt_az),
            gyro_axes=2,
        )
    )
    err = (result["heading_deg"] - truth["heading_deg"] + 180.0) % 360.0 - 180.0
    pos = result["positions"]
    return {
        "heading": result["heading_deg"],
        "error": err,
        "sigma": result["heading_std_deg"],
        "limit": limit,
        "used_s": used_s,
        "wall_s": wall,
        "replay_identical": "identical to the live result.json" in first,
        "devices": {r: d["model"] for r, d in result.get("devices", {}).items()},
        "lost_imu": sum(p["lost_samples"] for p in pos),
        "lost_accel": sum(p["accel_lost_samples"] for p in pos),
        "bad_crc": result["faults"]["imu"]["bad_crc"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--positions", type=int, default=8)
    ap.add_argument("--dwell", type=float, default=20.0)
    ap.add_argument("--time-scale", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", action="append", choices=list(ROWS))
    ap.add_argument("--no-check", action="store_true")
    args = ap.parse_args()
    os.environ.setdefault("PYTHONUNBUFFERED", "1")
    with tempfile.TemporaryDirectory(prefix="second-models-") as d:
        tmp = Path(d)
        for name in args.only or list(ROWS):
            stage, imu, tilt, grade = ROWS[name]
            print(f"== {name}: --stage {stage} --imu {imu} --tilt {tilt} --grade {grade}", flush=True)
            if not args.no_check:
                for line in check_lines(stage, imu, tilt, grade, tmp):
                    print(f"   check: {line}", flush=True)
            r = one_find(stage, imu, tilt, grade, args, tmp / name.replace(" ", "_").replace("+", "_"))
            if "failed" in r:
                print(f"   find FAILED: {r['failed']}", flush=True)
                continue
            print(
                f"   find {args.positions} x {args.dwell:g} s at {args.time_scale:g}x "
                f"({r['wall_s']:.0f} s wall): "
                f"devices {r['devices']}; heading {r['heading']:.4f}°, error {r['error']:+.4f}°, "
                f"σ {r['sigma']:.4f}°, |error|/σ {abs(r['error']) / r['sigma']:.2f}, limit ({grade}, "
                f"{r['used_s']:.1f} s) {r['limit']:.4f}°, σ/limit {r['sigma'] / r['limit']:.3f}; "
                f"replay identical: {r['replay_identical']}; IMU lost {r['lost_imu']} "
                f"(bad CRC {r['bad_crc']}), "
                f"accel lost {r['lost_accel']}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
