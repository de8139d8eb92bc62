#!/usr/bin/env python3
"""find's memory against device time: is it flat in run length? (issue 27, item 5)

Runs ``northfinder find --simulate`` as a user does and samples, every `--every-s` of wall, the
find process's resident set (VmRSS) and peak (VmHWM) from /proc, against the device time the run
has reached: the IMU samples in its raw log (imu.raw grows as bytes arrive; 36 bytes a frame at
the IMU's rate, codecs.kvh.FRAME_SIZE). Printed: a table of device s, IMU samples, RSS and peak,
then the peak RSS of the run, its growth per IMU sample (least squares slope of RSS over the
samples after the first position, where start-up allocations are done) and the load average.

    python3 tools/rss_vs_time.py                                  # 8 × 120 s at 50×
    python3 tools/rss_vs_time.py --positions 8 --dwell 60 --time-scale 80 --every-s 1
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from a checkout without installing

from northfinder.codecs.kvh import FRAME_SIZE  # noqa: E402
from northfinder.rundir import IMU_RAW  # noqa: E402

ENV = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
MIB = 1024.0 * 1024.0


def status_kib(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process [KiB] (Linux /proc/<pid>/status)."""
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key = line.split(":", 1)[0]
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(line.split()[1])
    except OSError:
        pass
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--positions", type=int, default=8)
    p.add_argument("--dwell", type=float, default=120.0, help="device seconds per position")
    p.add_argument("--time-scale", type=float, default=50.0)
    p.add_argument("--imu-rate-hz", type=float, default=1000.0, help="the simulated IMU's rate (sim default)")
    p.add_argument("--every-s", type=float, default=0.5, help="wall seconds between samples")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--timeout-s", type=float, default=900.0)
    args = p.parse_args()

    out = Path(tempfile.mkdtemp(prefix="nf-rss-"))
    run_dir = out / "run"
    argv = [sys.executable, "-m", "northfinder", "find", "--simulate", "--positions", str(args.positions),
            "--dwell", f"{args.dwell:g}", "--time-scale", f"{args.time_scale:g}", "--seed", str(args.seed),
            "--no-report", "--json", str(out / "result.json"), "--out", str(run_dir)]
    load0 = " ".join(f"{x:.2f}" for x in os.getloadavg())
    t0 = time.monotonic()
    proc = subprocess.Popen(argv, cwd=out, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    rows: list[tuple[float, int, float, float]] = []  # wall s, IMU samples, RSS MiB, peak MiB
    peak_kib = 0
    try:
        while proc.poll() is None and time.monotonic() - t0 < args.timeout_s:
            mem = status_kib(proc.pid)
            raw = run_dir / IMU_RAW
            samples = raw.stat().st_size // FRAME_SIZE if raw.exists() else 0
            if mem:
                peak_kib = max(peak_kib, mem.get("VmHWM", 0))
                rows.append((time.monotonic() - t0, samples, mem.get("VmRSS", 0) / 1024.0, peak_kib / 1024.0))
            time.sleep(args.every_s)
        if proc.poll() is None:
            proc.kill()
        code = proc.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    wall = time.monotonic() - t0
    err = proc.stderr.read().decode("utf-8", "replace").strip().splitlines() if proc.stderr else []
    result = json.loads((out / "result.json").read_text()) if (out / "result.json").exists() else {}
    shutil.rmtree(out, ignore_errors=True)

    print(f"find {args.positions} × {args.dwell:g} s at time scale {args.time_scale:g}: exit {code}, "
          f"{wall:.1f} s wall; load avg {load0} at start, "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} at the end")
    if code != 0 and err:
        print(f"  {err[-1]}")
    print(f"{'wall s':>7} {'device s':>9} {'IMU samples':>12} {'RSS MiB':>8} {'peak MiB':>9}")
    step = max(1, len(rows) // 40)
    for wall_s, n, rss, hwm in rows[::step] + rows[-1:]:
        print(f"{wall_s:7.1f} {n / args.imu_rate_hz:9.1f} {n:12,d} {rss:8.0f} {hwm:9.0f}")
    if not rows:
        return 1
    n = np.array([r[1] for r in rows], dtype=float)
    rss = np.array([r[2] for r in rows])
    late = n >= args.dwell * args.imu_rate_hz  # after the first position: start-up is done
    slope = None
    if np.unique(n[late]).size > 2:
        slope = float(np.polyfit(n[late], rss[late] * MIB, 1)[0])
    total = int(n.max())
    print(f"peak RSS {peak_kib / 1024.0:.0f} MiB over {total:,d} IMU samples "
          f"({total / args.imu_rate_hz:.0f} device s in the raw log; result says "
          f"{result.get('duration_device_s', 'n/a')} device s)")
    if slope is not None:
        print(f"RSS growth after the first position: {slope:.0f} bytes per IMU sample (least squares)")
    print(f"peak RSS per IMU sample: {peak_kib * 1024.0 / max(total, 1):.0f} bytes")
    return 0 if code == 0 else 2


if __name__ == "__main__":
    sys.exit(main())
