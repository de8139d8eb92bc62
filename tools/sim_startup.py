#!/usr/bin/env python3
"""Measure one firmware-sim start: wall and CPU to the endpoints line, then to the IMU's first byte.

Starts `PYTHON -m firmware_sim ARGS…` as its own process in a scratch directory (so the
interpreter's own install is what runs: `--python python3` measures that install), reads the
endpoints line, opens the IMU pty with pyserial and waits for its first byte (device time must
have started for it to come), then lets the process idle for `--idle-s` and stops it. Prints the
wall time from launch to each of those points and the simulator process's CPU (user + system,
/proc/<pid>/stat) at each, and whether the process imported scipy (from `-X importtime`, which
the interpreter writes to stderr). Nothing is asserted: these are measured figures.

    python tools/sim_startup.py                          # the bench, 3 starts
    python tools/sim_startup.py --python python3 -- --scenario vehicle --time-scale 25
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import serial


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def one_start(python: str, sim_args: list[str], idle_s: float) -> dict[str, float | bool]:
    """Launch, endpoints, IMU's first byte, idle: wall [s] and CPU [s] at each point."""
    with tempfile.TemporaryDirectory() as scratch:
        err_path = Path(scratch) / "stderr"
        with open(err_path, "wb") as err:
            t0 = time.monotonic()
            proc = subprocess.Popen([python, "-X", "importtime", "-m", "firmware_sim", *sim_args],
                                    cwd=scratch, stdout=subprocess.PIPE, stderr=err)
            try:
                endpoints = json.loads(proc.stdout.readline())
                out: dict[str, float | bool] = {"endpoints_wall_s": time.monotonic() - t0,
                                                "endpoints_cpu_s": proc_cpu_s(proc.pid)}
                port = serial.Serial(endpoints["imu"], 921600, timeout=0.2)
                deadline = time.monotonic() + 30.0
                while not port.read(1) and time.monotonic() < deadline:
                    pass
                out["first_byte_wall_s"] = time.monotonic() - t0
                out["first_byte_cpu_s"] = proc_cpu_s(proc.pid)
                port.close()
                time.sleep(idle_s)
                out["idle_end_cpu_s"] = proc_cpu_s(proc.pid)
            finally:
                proc.send_signal(signal.SIGTERM)
                proc.wait(timeout=10)
        out["scipy_imported"] = any(line.split("|")[-1].strip() == "scipy"
                                    for line in err_path.read_text(errors="replace").splitlines()
                                    if line.startswith("import time:"))
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--python", default=sys.executable, help="the interpreter whose firmware_sim runs")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--idle-s", type=float, default=2.0, help="wall time to idle after the first byte")
    p.add_argument("sim_args", nargs="*", help="firmware-sim's own arguments (after --)")
    args = p.parse_args()
    where = subprocess.run([args.python, "-c", "import firmware_sim; print(firmware_sim.__file__)"],
                           capture_output=True, text=True, cwd=tempfile.gettempdir()).stdout.strip()
    print(f"{args.python} -m firmware_sim {' '.join(args.sim_args)}  ({where})")
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f}")
    print("run  endpoints wall/CPU [s]  first IMU byte wall/CPU [s]  CPU after idle [s]  scipy")
    for i in range(args.runs):
        r = one_start(args.python, args.sim_args, args.idle_s)
        print(f"{i + 1:3d}  {r['endpoints_wall_s']:7.3f} / {r['endpoints_cpu_s']:5.2f}"
              f"        {r['first_byte_wall_s']:7.3f} / {r['first_byte_cpu_s']:5.2f}"
              f"           {r['idle_end_cpu_s']:5.2f}  (+{args.idle_s:g} s)   {r['scipy_imported']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
