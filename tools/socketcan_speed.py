#!/usr/bin/env python3
"""How fast a find over socketcan can run before the accelerometer loses samples (issue 21, item 4).

For each time scale K: firmware-sim in its own process with its node on a vcan of its own, then
`northfinder find --config` on socketcan (3 positions × 4 s, no report). Prints per K: the node's
frames per wall second (the vcan's rx_packets over the find's wall time), the socket receive buffer
the driver asked for and got, the samples lost inside the kept dwells and in the stream, the drops
the kernel counted on the driver's socket (SO_RXQ_OVFL, in the run's faults table), re-measured
positions, and the find process's CPU time per wall second (user + system of the child).

Needs a kernel with CAN and root: run it in the guest,
`python3 tools/vcan_guest.py -- python3 tools/socketcan_speed.py 2 4 6 8 10`.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(REPO), str(REPO / "tests")]

from northfinder.simulate import SimSettings, SimulatorProcess  # noqa: E402

FAST_STAGE_TOML = "stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n"
POSITIONS, DWELL_S = 3, 4.0
DRIVER_BUFFER_BYTES = 0  # the driver's own receive buffer request, read when first needed


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def one_find(work: Path, scale: float, imu_rate_hz: int) -> dict:
    from socketcan_bus import interface_stats, own_vcan

    work.mkdir(parents=True, exist_ok=True)
    sim_toml = work / "sim.toml"
    sim_toml.write_text(FAST_STAGE_TOML + f"imu_rate_hz = {imu_rate_hz}\n")
    with own_vcan("vcan-speed") as channel, SimulatorProcess(SimSettings(
            time_scale=scale, seed=21, config=str(sim_toml), can=f"socketcan:{channel}")) as ep:
        bench = work / "bench.toml"
        bench.write_text(f'[turntable]\nport = "{ep["turntable"]}"\nspeed_deg_s = 90.0\n[imu]\nport = '
                         f'"{ep["imu"]}"\nrate_hz = {imu_rate_hz}\n'
                         f'[accelerometer]\ninterface = "socketcan"\nchannel = "{channel}"\n'
                         '[site]\nlatitude_deg = 40.0\n')
        run = work / "run"
        before, cpu0, t0 = interface_stats(channel), _children_cpu_s(), time.monotonic()
        found = subprocess.run([sys.executable, "-m", "northfinder", "find", "--config", str(bench),
                                "--positions", str(POSITIONS), "--dwell", str(DWELL_S), "--no-report",
                                "--out", str(run)], capture_output=True, text=True, stdin=subprocess.DEVNULL,
                               timeout=600, cwd=work, env={**os.environ, "PYTHONPATH": str(REPO)})
        wall_s, cpu_s, after = time.monotonic() - t0, _children_cpu_s() - cpu0, interface_stats(channel)
    events = [json.loads(line) for line in (run / "events.jsonl").read_text().splitlines()] \
        if (run / "events.jsonl").exists() else []
    stats = [e for e in events if e.get("event") == "stats"]
    kept = [e for e in events if e.get("event") == "position"]
    return {
        "scale": scale, "rc": found.returncode, "wall_s": wall_s, "cpu_per_s": cpu_s / wall_s,
        "frames_per_s": (after["rx_packets"] - before["rx_packets"]) / wall_s,
        "lost_in_dwells": sum(int(e["accel"]["lost"]) for e in kept),
        "lost_in_stream": sum(int(e.get("accel", {}).get("lost_samples", 0)) for e in stats),
        "kernel_drops": sum(int(e.get("accel", {}).get("kernel_drops", 0)) for e in stats),
        "remeasured": sum(e.get("event") == "remeasure" for e in events),
        "error": found.stderr.strip().splitlines()[-1:] if found.returncode else [],
    }


def accel_only(work: Path, scale: float, buffer_bytes: int | None, seconds: float = 10.0) -> dict:
    """The receive path alone: firmware-sim's node on a vcan at `scale`, the driver reading it for
    `seconds` of device time (no IMU reader, no find). `buffer_bytes` None: the driver's own
    receive buffer; else that size (e.g. the kernel default) — the drop counter works either way."""
    from socketcan_bus import interface_stats, own_vcan

    import northfinder.drivers.accelerometer as accelerometer
    from northfinder.drivers.accelerometer import Accelerometer

    work.mkdir(parents=True, exist_ok=True)
    sim_toml = work / "sim.toml"
    sim_toml.write_text("imu_rate_hz = 1\n")  # the IMU's pty is not read here: keep it quiet
    global DRIVER_BUFFER_BYTES
    DRIVER_BUFFER_BYTES = DRIVER_BUFFER_BYTES or accelerometer.RECEIVE_BUFFER_BYTES
    accelerometer.RECEIVE_BUFFER_BYTES = buffer_bytes or DRIVER_BUFFER_BYTES
    with own_vcan("vcan-speed") as channel, SimulatorProcess(SimSettings(
            time_scale=scale, seed=21, config=str(sim_toml), can=f"socketcan:{channel}")), \
            Accelerometer("socketcan", channel) as acc:
        acc.wait_heartbeat(timeout_s=30)
        acc.configure(rate_hz=100)
        buffer = acc._drops.receive_buffer_bytes
        before, cpu0, t0 = interface_stats(channel), time.process_time(), time.monotonic()
        acc.start_node()
        samples = int(100 * seconds)
        got = 0
        while got < samples and time.monotonic() - t0 < 10 * seconds:
            got += len(acc.read(min(100, samples - got), timeout_s=10 * seconds))
        wall_s, cpu_s, after = time.monotonic() - t0, time.process_time() - cpu0, interface_stats(channel)
        acc.stop_node()
        stats = acc.stats
    frames_per_s = (after["rx_packets"] - before["rx_packets"]) / wall_s
    return {"scale": scale, "buffer": buffer, "frames_per_s": frames_per_s,
            "samples": got, "lost": stats.lost_samples, "kernel_drops": stats.kernel_drops,
            "cpu_per_s": cpu_s / wall_s, "wall_s": wall_s}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scales", type=float, nargs="+", help="time scales to try, e.g. 2 4 6 8 10")
    p.add_argument("--work", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "socketcan-speed")
    p.add_argument("--imu-rate", type=int, default=1000, metavar="HZ",
                   help="the IMU's rate in the finds (1000; 100 leaves the guest's CPU to the CAN path)")
    p.add_argument("--accel-only", action="store_true",
                   help="the receive path alone, with the kernel's default buffer and with the driver's")
    args = p.parse_args(argv)
    if args.accel_only:
        default = int(Path("/proc/sys/net/core/rmem_default").read_text())
        for scale in args.scales:
            for buffer in (default // 2, None):  # the kernel doubles what it is asked for
                r = accel_only(args.work / f"a{scale:g}", scale, buffer)
                print(f"x{scale:<4g} receive buffer {r['buffer']:8d} B  frames/s {r['frames_per_s']:6.0f}  "
                      f"samples {r['samples']}  lost {r['lost']:5d}  kernel drops {r['kernel_drops']:5d}  "
                      f"reader CPU {r['cpu_per_s']:.2f} s/s  wall {r['wall_s']:.1f} s", flush=True)
        return 0
    rmem = Path("/proc/sys/net/core/rmem_default").read_text().strip()
    print(f"socket receive buffer default {rmem} B (net.core.rmem_default); {POSITIONS} positions × "
          f"{DWELL_S:g} s, accelerometer 100 Hz, IMU {args.imu_rate} Hz", flush=True)
    for scale in args.scales:
        r = one_find(args.work / f"x{scale:g}", scale, args.imu_rate)
        print(f"x{scale:<4g} exit {r['rc']}  wall {r['wall_s']:6.1f} s  frames/s {r['frames_per_s']:7.0f}  "
              f"lost in dwells {r['lost_in_dwells']:4d}  lost in stream {r['lost_in_stream']:5d}  "
              f"kernel drops {r['kernel_drops']:5d}  re-measured {r['remeasured']}  "
              f"find CPU {r['cpu_per_s']:.2f} s/s  {' '.join(r['error'])}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
