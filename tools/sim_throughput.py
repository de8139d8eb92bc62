#!/usr/bin/env python3
"""Measure firmware-sim's IMU stream: wall time and simulator CPU for N device seconds.

Starts `python -m firmware_sim` as its own process (as a user would), reads the KVH pty with
pyserial until it has `--device-s` × rate messages, and prints: the wall time, the CPU time
the simulator process used (from /proc/<pid>/stat, user + system), the client's CPU, the
messages, CRC failures and sequence gaps. Nothing is asserted: these are measured figures.

    python3 tools/sim_throughput.py                 # time scale 50, 60 s device at 1000 Hz
    python3 tools/sim_throughput.py --time-scale 20 --device-s 30
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import serial

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from firmware_sim.devices.kvh import HEADER, MESSAGE_BYTES, unpack_messages  # noqa: E402


def proc_cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--time-scale", type=float, default=50.0)
    p.add_argument("--device-s", type=float, default=60.0)
    p.add_argument("--rate-hz", type=int, default=1000, help="the simulator's default IMU rate")
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args()

    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t_launch = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "firmware_sim", "--time-scale", repr(args.time_scale),
         "--seed", str(args.seed)],
        cwd=ROOT, env=env, stdout=subprocess.PIPE,
    )
    try:
        endpoints = json.loads(proc.stdout.readline())
        t_endpoints = time.monotonic() - t_launch
        n = int(round(args.device_s * args.rate_hz))
        want = MESSAGE_BYTES * (n + 1)
        port = serial.Serial(endpoints["imu"], 921600, timeout=0.5)
        # The clock starts with the simulator's loop (about when the endpoints line comes): measure
        # the stream from its first bytes, and say how long they took to come.
        t_open = time.monotonic()
        raw = bytearray(port.read(1))
        while not raw and time.monotonic() < t_open + 30.0:
            raw += port.read(1)
        t_first = time.monotonic() - t_open
        cpu0_sim, cpu0_client = proc_cpu_s(proc.pid), time.process_time()
        t0 = time.monotonic()
        deadline = t0 + 10.0 * args.device_s / args.time_scale + 10.0
        while len(raw) < want and time.monotonic() < deadline:
            raw += port.read(want - len(raw))
        wall = time.monotonic() - t0
        cpu_sim, cpu_client = proc_cpu_s(proc.pid) - cpu0_sim, time.process_time() - cpu0_client
        port.close()
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=10)

    start = bytes(raw).find(HEADER)
    msgs = unpack_messages(bytes(raw[start:]))[:n]
    seq = msgs["sequence"].astype(int)
    gaps = int(np.count_nonzero(np.diff(seq) % 128 != 1))
    print(f"endpoints printed after     {t_endpoints:.2f} s (launch to JSON line)")
    print(f"first IMU bytes after       {t_first:.2f} s (port open to data)")
    print(f"device time                 {args.device_s:g} s at {args.rate_hz} Hz, "
          f"time scale {args.time_scale:g} (ideal wall {args.device_s / args.time_scale:.2f} s)")
    print(f"messages read               {len(msgs)} of {n}")
    print(f"CRC failures                {int(np.count_nonzero(~msgs['crc_ok']))}")
    print(f"sequence gaps               {gaps}")
    print(f"wall time                   {wall:.3f} s")
    print(f"simulator CPU (user+sys)    {cpu_sim:.3f} s  ({100.0 * cpu_sim / wall:.0f} % of one core)")
    print(f"client CPU (this process)   {cpu_client:.3f} s")
    print(f"firmware-sim exit code      {code}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
