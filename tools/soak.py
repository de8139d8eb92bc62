"""Soak: one long `find` with every fault at a low rate, time-scaled; prints what it measured.

firmware_sim runs in this process (its accelerometer on python-can's `virtual` bus), the whole
northfinder stack on top (drivers on real ptys, sequencer, run directory, estimator). Faults:
corrupt and cut IMU frames, lost CAN frames at low rates for the whole run; one stage stall,
one EMCY, heartbeats lost for the last part, the IMU port unplugged and back; the IMU silent for
2 s and a knock, each injected by the simulator in the middle of a dwell (at a device time read
from its clock when the dwell has run 5 s).

Prints: device duration, wall time, the faults injected (simulator side) and what the drivers
counted, per-position accounting (received + lost = the device counter span, received = the
dwell), RSS at start, along the run and at the end, and the heading error against the truth in
units of its σ. Exit 1 if any check fails (no crash, accounting exact, heading within 3σ).

    python3 tools/soak.py                      # 24 × 72 s ≈ 30 min device time at K = 10
    python3 tools/soak.py --positions 8 --dwell 20 --time-scale 10   # a short one
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
import uuid
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def rss_mib() -> float:
    """Resident set size of this process [MiB] (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--positions", type=int, default=24)
    ap.add_argument("--dwell", type=float, default=72.0, help="dwell per position [device s]")
    ap.add_argument("--time-scale", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--out", help="run directory (default: a temporary one)")
    args = ap.parse_args(argv)

    from firmware_sim.config import SimConfig
    from firmware_sim.faults import parse_faults
    from firmware_sim.simulator import Simulator
    from northfinder.errors import NorthfinderError
    from northfinder.rundir import RunDir, jsonable
    from northfinder.runs.find import measure, replay
    from northfinder.simulate import SimSettings, bench_config

    truth = {"heading_deg": 123.4, "pitch_deg": 2.0, "roll_deg": -1.2, "latitude_deg": 48.0}
    per_pos_s = args.dwell + 4.0  # move + settle, about, on this stage
    total_s = args.positions * per_pos_s
    faults = [
        "imu-crc-rate=0.001",
        "imu-drop-byte-rate=0.0005",
        "accel-loss-rate=0.005",
        f"stage-stall={max(2, args.positions // 3)}",
        f"accel-emcy={0.5 * per_pos_s + 3.0:.1f}",  # in position 0's dwell (no EMCY while stopped)
        f"accel-heartbeat-loss={0.85 * total_s:.1f}",
        f"imu-disconnect={0.3 * total_s:.1f}:1",
    ]
    silence_at, bump_at = max(2, args.positions // 2), max(3, (3 * args.positions) // 4)
    injected: dict[str, float] = {}

    sim_cfg = SimConfig(
        **truth,
        grade="nav",
        seed=args.seed,
        time_scale=args.time_scale,
        stage_speed_dps=90.0,
        stage_accel_dps2=360.0,
        stage_ringing_decay_s=0.1,
        accel_rate_hz=50.0,
        can_interface="virtual",
        can_channel=f"soak-{uuid.uuid4().hex[:8]}",
        faults=parse_faults(faults),
    )
    sim = Simulator(sim_cfg)
    rss: list[tuple[int, float]] = []

    def on_progress(p) -> None:
        if p.phase == "measured":
            rss.append((p.position, rss_mib()))
        if p.phase != "dwell" or p.dwell_done_s < 5.0:
            return
        if p.position == silence_at and "imu-silence" not in injected:
            injected["imu-silence"] = sim.clock.now() + 0.2
            sim.imu.silence = (injected["imu-silence"], 2.0)
        if p.position == bump_at and "disturbance" not in injected:
            injected["disturbance"] = sim.clock.now() + 0.2
            sim.world.add_disturbance(injected["disturbance"], 0.5, 0.01)

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="northfinder-soak-")) / "run"
    rss0 = rss_mib()
    t0 = time.monotonic()
    failed: list[str] = []
    result = None
    with sim as endpoints:
        cfg = bench_config(endpoints, truth["latitude_deg"])
        cfg.accelerometer.rate_hz = 50.0
        cfg.run.positions = args.positions
        cfg.run.dwell_s = args.dwell
        cfg.validate()
        rss_start = rss_mib()
        try:
            settings = SimSettings(**truth, time_scale=args.time_scale)
            result = measure(cfg, RunDir(out), settings=settings, report=False,
                             seq_kwargs={"on_progress": on_progress})
        except NorthfinderError as exc:
            failed.append(f"the run stopped: {exc}")
        device_s = sim.clock.now()
        kvh, node, stage = sim.imu, sim.accelerometer, sim.turntable
        sim_side = {
            "imu messages sent": int(getattr(kvh, "messages_sent", -1)),
            "CAN TPDO frames dropped": int(getattr(getattr(node, "stats", None), "tpdo_dropped", -1)),
            "CAN EMCY sent": int(getattr(getattr(node, "stats", None), "emcy", -1)),
            "stage moves": int(getattr(stage, "moves", -1)),
        }
    wall_s = time.monotonic() - t0
    rss_end = rss_mib()

    print(f"run directory      {out}")
    print(f"device time        {device_s:.1f} s ({device_s / 60:.1f} min) at K = {args.time_scale:g}; "
          f"wall {wall_s:.1f} s")
    print(f"faults (cmd line)  {' '.join(faults)}")
    t_sil, t_bump = injected.get("imu-silence", float("nan")), injected.get("disturbance", float("nan"))
    print(f"faults (mid-dwell) imu-silence 2 s at {t_sil:.2f} s (position {silence_at}), "
          f"disturbance 0.5 s × 0.01° at {t_bump:.2f} s (position {bump_at})")
    print("simulator side     " + ", ".join(f"{k} {v}" for k, v in sim_side.items()))
    if result is None:
        for f in failed:
            print("FAIL", f)
        return 1
    fa = result["faults"]
    print("imu (driver)       " + ", ".join(f"{k} {v}" for k, v in fa["imu"].items()))
    acc = {k: v for k, v in fa["accel"].items() if k != "emergencies"}
    print("accel (driver)     " + ", ".join(f"{k} {v}" for k, v in acc.items()))
    print(f"emergencies        {fa['accel']['emergencies']}")
    print(f"stage errors       {[e['error'] for e in fa['stage_errors']]}")
    for r in fa["remeasured"]:
        print(f"re-measured        position {r['index'] + 1} attempt {r['attempt']}: {r['reason'][:110]}")

    events = [json.loads(x) for x in (out / "events.jsonl").read_text().splitlines() if x.strip()]
    kept = [e for e in events if e["event"] == "position"]
    imu_rx = imu_lost = acc_rx = acc_lost = 0
    for e in kept:
        i, a = e["imu"], e["accel"]
        imu_rx, imu_lost = imu_rx + i["samples"], imu_lost + i["lost"]
        acc_rx, acc_lost = acc_rx + a["samples"], acc_lost + a["lost"]
        if i["samples"] + i["lost"] != i["last_index"] - i["first_index"] + 1:
            failed.append(f"position {e['index'] + 1}: IMU received + lost != counter span")
        if i["samples"] != round(args.dwell * 1000.0):
            failed.append(f"position {e['index'] + 1}: IMU received {i['samples']} != dwell")
        if a["samples"] + a["lost"] != a["last_counter"] - a["first_counter"] + 1:
            failed.append(f"position {e['index'] + 1}: accel received + lost != counter span")
    print(f"accounting         {len(kept)} positions kept: IMU {imu_rx} received + {imu_lost} lost = "
          f"{imu_rx + imu_lost} (device counter spans); accel {acc_rx} + {acc_lost} = {acc_rx + acc_lost}")
    lo, hi = min(r for _, r in rss), max(r for _, r in rss)
    print(f"RSS                start {rss_start:.1f} MiB (before the simulator {rss0:.1f}), "
          f"along the run {lo:.1f}…{hi:.1f} MiB, end {rss_end:.1f} MiB")
    err, sig = result["error_deg"], result["heading_std_deg"]
    print(f"heading            {result['heading_deg']:.4f}° ± {sig:.4f}° (truth {truth['heading_deg']}°): "
          f"error {err:+.4f}° = {abs(err) / sig:.2f} σ")
    again = replay(out)
    same = json.loads(json.dumps(jsonable(again.result))) == json.loads((out / "result.json").read_text())
    print(f"replay             {'identical to the live result' if same else 'DIFFERS'}")
    if not result["complete"]:
        failed.append("the run is incomplete")
    if abs(err) > 3.0 * sig:
        failed.append(f"heading error {abs(err) / sig:.2f} σ > 3 σ")
    if not same:
        failed.append("replay differs from the live result")
    if len(rss) > 4:  # flat: the second half grows by less than 20 MiB
        half = [r for _, r in rss[len(rss) // 2:]]
        if half[-1] - half[0] > 20.0:
            failed.append(f"RSS grew {half[-1] - half[0]:.1f} MiB over the second half")
    for f in failed:
        print("FAIL", f)
    print("soak", "FAILED" if failed else "passed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
