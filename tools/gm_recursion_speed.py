#!/usr/bin/env python3
"""Per-call cost of the sensor models' Gauss–Markov recursion: firmware_sim's numpy
`FirstOrderRecursion` against scipy.signal.lfilter (what it replaced), for calls of n samples × 3
axes as the simulator's loop makes them (a few per tick at real time, ~10^5 at high time scales).
Prints the best-of-5 mean time per call in µs; nothing is asserted.

    python tools/gm_recursion_speed.py
"""

from __future__ import annotations

import math
import sys
import timeit
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from firmware_sim.physics.sensors import FirstOrderRecursion  # noqa: E402


def per_call_s(call, n: int) -> float:
    """Best-of-5 mean wall time of one call."""
    number = max(5, 20_000 // n)
    return min(timeit.repeat(call, number=number, repeat=5)) / number


def main() -> int:
    phi = math.exp(-1e-3 / 300.0)  # kvh1760's bias instability (τ = 300 s) at 1000 samples/s
    rng = np.random.default_rng(0)
    print(f"φ = {phi:.12f}; µs per call of n samples × 3 axes (best of 5)")
    print("       n     numpy   lfilter")
    for n in (1, 5, 50, 500, 5000, 100_000):
        x = rng.standard_normal((n, 3))
        rec, zi = FirstOrderRecursion(phi, np.zeros(3)), np.zeros((1, 3))
        ours = per_call_s(lambda rec=rec, x=x: rec.apply(x), n)
        theirs = per_call_s(lambda x=x, zi=zi: lfilter([1.0], [1.0, -phi], x, axis=0, zi=zi), n)
        print(f"{n:8d}  {ours * 1e6:8.1f}  {theirs * 1e6:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
