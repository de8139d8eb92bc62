"""Measured speed of the NMEA path: firmware_sim's receiver formatting epochs, northfinder's decoder
(pynmeagps per sentence) and the vectorized ENU conversion, for one default 300 s drive at 10 Hz.

Why: the GNSS/INS replay decodes a whole NMEA log and a time-scaled bench sends epochs faster
than real time; this prints how much headroom there is (no assertion: figures, not a test).

    python3 tools/nmea_speed.py [--seconds 300] [--repeat 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from firmware_sim.devices.gnss import GnssReceiver  # noqa: E402
from firmware_sim.physics.vehicle import VehicleTrajectory  # noqa: E402
from firmware_sim.physics.world import Site, World  # noqa: E402
from northfinder.codecs.nmea import fixes_to_arrays  # noqa: E402
from northfinder.drivers.gnss import decode_nmea_log  # noqa: E402


def _best(fn, repeat: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=300.0, help="drive length in device seconds")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure; the fastest is printed")
    args = ap.parse_args(argv)
    traj = VehicleTrajectory(duration_s=args.seconds)
    world = World(Site(40.0, 100.0), traj)
    n_epochs = int(args.seconds * 10) + 1

    def encode() -> bytes:
        rx = GnssReceiver(world, rng=1)
        try:
            return rx.epoch_bytes(np.arange(n_epochs))
        finally:
            rx.close()

    t_enc, data = _best(encode, args.repeat)
    t_dec, (fixes, stats) = _best(lambda: decode_nmea_log(data), args.repeat)
    t_arr, _ = _best(lambda: fixes_to_arrays(fixes), args.repeat)
    n_sent = stats.sentences
    print(f"drive: {args.seconds:g} s at 10 Hz = {n_epochs} epochs, {n_sent} sentences, {len(data)} bytes")
    print(f"firmware_sim encode: {t_enc:.3f} s  ({n_epochs / t_enc:,.0f} epochs/s, "
          f"{args.seconds / t_enc:,.0f}x real time)")
    print(f"northfinder decode:  {t_dec:.3f} s  ({n_sent / t_dec:,.0f} sentences/s, "
          f"{1e6 * t_dec / n_sent:.0f} us/sentence, {args.seconds / t_dec:,.0f}x real time)")
    print(f"fixes_to_arrays:     {t_arr * 1e3:.1f} ms for {len(fixes)} fixes")
    print(f"counters: {stats.as_dict()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
