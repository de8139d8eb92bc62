#!/usr/bin/env python3
"""slcan receive throughput: python-can's stock client against northfinder's ChunkedSlcanBus.

Both clients read the same bytes from a real pty: TPDO1/TPDO2 lines as firmware_sim's slcan
adapter sends them (22 bytes each), written as fast as the pty takes them by a thread. Printed:
frames per second of wall and of CPU time (this process, every thread, the writer included), the
multiple of the 200 frames/s a 100 Hz accelerometer sends in real time (a find at time scale K
needs 200·K), and the pyserial read calls per frame. Best of `--repeats`; the load average is
printed with the figures because the machine may be shared.

    python3 tools/slcan_speed.py                 # 20,000 frames, best of 3
    python3 tools/slcan_speed.py --frames 100000
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run from a checkout without installing

import can  # noqa: E402
from can.interfaces.slcan import slcanBus  # noqa: E402

from northfinder.transport import ChunkedSlcanBus  # noqa: E402

TPDO_LINES = b"t1908E803000030F8FFFF\r" + b"t290840420F00D0090707\r"
REAL_TIME_FRAMES_S = 200.0


@contextlib.contextmanager
def slcan_client_on_pty(bus_class: type[slcanBus], count_reads: bool = True
                        ) -> Iterator[tuple[int, slcanBus, list[int]]]:
    """`bus_class` opened on the slave end of a fresh raw pty, with what it sent on open (C, S6, O)
    already read off the master end. Yields the master fd (blocking) to write the adapter's bytes
    into, the bus, and a one-item list counting the bus's pyserial read calls (left at 0 when
    `count_reads` is off: the counting wrapper costs a Python call per read). Shut and closed on exit."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    bus = bus_class(channel=os.ttyname(slave), bitrate=500000, sleep_after_open=0)
    calls = [0]
    if count_reads:
        port_read = bus.serialPortOrig.read

        def counting_read(size: int = 1) -> bytes:
            calls[0] += 1
            return port_read(size)

        bus.serialPortOrig.read = counting_read
    try:
        with contextlib.suppress(BlockingIOError):
            os.set_blocking(master, False)
            os.read(master, 4096)  # the C / S6 / O the client sent on open
        os.set_blocking(master, True)
        yield master, bus, calls
    finally:
        bus.shutdown()
        os.close(master)
        os.close(slave)


def tpdo_payload(n_frames: int) -> bytes:
    """`n_frames` TPDO1/TPDO2 lines in turn, as firmware_sim's adapter sends them."""
    return TPDO_LINES * (n_frames // 2) + TPDO_LINES[:22] * (n_frames % 2)


def receive(bus_class: type[slcanBus], payload: bytes, n_frames: int, count_reads: bool = True
            ) -> tuple[int, float, float, int]:
    """Frames received, wall s, CPU s and pyserial read calls for `n_frames` slcan lines in
    `payload`, written into the pty by a thread as fast as it takes them."""
    with slcan_client_on_pty(bus_class, count_reads) as (master, bus, calls):
        writer = threading.Thread(target=lambda: os.write(master, payload), daemon=True)
        got = 0
        w0, c0 = time.perf_counter(), time.process_time()
        writer.start()
        while got < n_frames and bus.recv(timeout=5.0) is not None:
            got += 1
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        writer.join(5)
    return got, wall, cpu, calls[0]


def measure(bus_class: type[slcanBus], n_frames: int, repeats: int) -> dict:
    best = None
    for _ in range(repeats):
        got, wall, cpu, calls = receive(bus_class, tpdo_payload(n_frames), n_frames)
        if got != n_frames:
            raise SystemExit(f"{bus_class.__name__}: received {got} of {n_frames} frames")
        if best is None or wall < best["wall"]:
            best = {"wall": wall, "cpu": cpu, "calls": calls}
    return best


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=20_000)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"python-can {can.__version__}; {args.frames} frames, best of {args.repeats}; "
          f"load avg {load} at start")
    rows = []
    clients = (("stock slcanBus", slcanBus), ("ChunkedSlcanBus", ChunkedSlcanBus))
    for label, cls in clients:
        r = measure(cls, args.frames, args.repeats)
        rate, cpu_rate = args.frames / r["wall"], args.frames / r["cpu"]
        rows.append(rate)
        print(f"{label:16s} {rate:>11,.0f} frames/s wall = {rate / REAL_TIME_FRAMES_S:>6,.0f}× real time; "
              f"CPU {cpu_rate:>11,.0f} frames/s; {r['calls'] / args.frames:5.2f} reads/frame")
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"ChunkedSlcanBus / stock: {rows[1] / rows[0]:.1f}× (wall); load avg {load} at the end")
    return 0


if __name__ == "__main__":
    sys.exit(main())
