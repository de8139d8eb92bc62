#!/usr/bin/env python3
"""Record one fixed stream of the accelerometer node's frames three ways, as the driver logs it:

- `vcan.asc`: the frames sent by another process on a vcan, read with python-can's socketcan
  (the kernel flags them as sent from this host: python-can logs them `Tx`);
- `kernel-slcan.asc`: sent through firmware_sim's emulated USB-CAN adapter on a pty, with the
  kernel's slcan driver attached (`slcand -o -c -s6 PTY slcan-rec`), read with socketcan (`Rx`);
- `python-slcan.asc`: through the same emulated adapter, read with python-can's own `slcan` (`Rx`).

Needs a kernel with CAN and root: run it in the guest,
`python3 tools/vcan_guest.py -- python3 tools/record_can_logs.py tests/data/can-logs`.
tests/test_socketcan_logs.py replays the three stored logs and checks they decode identically.
"""

from __future__ import annotations

import argparse
import select
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(REPO), str(REPO / "tests")]

import can  # noqa: E402

from northfinder.codecs.canopen import CanCodec  # noqa: E402

NODE_ID = 0x10
SAMPLES = 40
SKIPPED_COUNTER = 23  # one sample the node "lost": the replay must count it, whatever the transport
FRAME_GAP_S = 0.002


def node_frames() -> list[tuple[int, bytes]]:
    """The stream: boot-up heartbeat, then SAMPLES samples (TPDO1 + TPDO2, one counter skipped),
    a heartbeat every 10 samples and one EMCY; values are fixed functions of the counter."""
    codec = CanCodec(NODE_ID)
    out = [codec.encode("HEARTBEAT", {"state": 0x05})]
    for c in range(SAMPLES + 1):
        if c == SKIPPED_COUNTER:
            continue
        out.append(codec.encode("TPDO1", {"accel_x": 1000 * c - 17, "accel_y": -2000 + 37 * c}))
        out.append(codec.encode("TPDO2", {"accel_z": 1_000_000 - 3 * c, "temperature": 2500 + c,
                                          "counter": (200 + c) % 256, "status": 7}))
        if c % 10 == 9:
            out.append(codec.encode("HEARTBEAT", {"state": 0x05}))
        if c == 30:
            out.append(codec.encode("EMCY", {"error_code": 0x8110, "error_register": 0x11, "vendor": 0}))
    return out


def send(bus: can.BusABC) -> None:
    for can_id, data in node_frames():
        bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        time.sleep(FRAME_GAP_S)


def _pump(adapter, stop: threading.Event) -> None:
    """Drive firmware_sim's adapter as its simulator loop does: answer the client, forward frames."""
    while not stop.is_set():
        fd = adapter.fileno()
        if fd is not None and select.select([fd], [], [], 0.002)[0]:
            adapter.on_readable(0.0)
        elif fd is None:
            time.sleep(0.002)
        adapter.advance(0.0)


def _record(interface: str, channel: str, log: Path, feed, **options) -> None:
    from northfinder.drivers.accelerometer import Accelerometer

    log.unlink(missing_ok=True)
    with Accelerometer(interface, channel, log_path=log, bus_options=options) as acc:
        time.sleep(0.3)  # python-can's slcan and the notifier are up
        feed()
        expected = SAMPLES  # SAMPLES + 1 counters, one skipped
        deadline = time.monotonic() + 20
        while acc.stats.pairs < expected and time.monotonic() < deadline:
            time.sleep(0.05)
        print(f"{log.name}: {acc.stats.pairs} samples, {acc.stats.lost_samples} lost", flush=True)
        time.sleep(0.3)


def _adapter() -> Iterator:
    from firmware_sim.devices.slcan_adapter import SlcanAdapter

    channel = f"record-{time.monotonic_ns()}"
    internal = can.Bus(interface="virtual", channel=channel)
    peer = can.Bus(interface="virtual", channel=channel)
    adapter = SlcanAdapter(internal)
    stop = threading.Event()
    thread = threading.Thread(target=_pump, args=(adapter, stop), daemon=True)
    thread.start()
    try:
        yield adapter, peer
    finally:
        stop.set()
        thread.join(5)
        adapter.close()
        internal.shutdown()
        peer.shutdown()


def main(argv: list[str] | None = None) -> int:
    import contextlib

    from socketcan_bus import kernel_slcan, own_vcan

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out", type=Path, help="directory for vcan.asc, kernel-slcan.asc, python-slcan.asc")
    p.add_argument("--send", metavar="CHANNEL", help=argparse.SUPPRESS)  # the other process on the vcan
    args = p.parse_args(argv)
    if args.send:
        with can.Bus(interface="socketcan", channel=args.send) as bus:
            send(bus)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    with own_vcan("vcan-rec") as channel:
        def other_process() -> None:
            subprocess.run([sys.executable, __file__, str(args.out), "--send", channel], check=True,
                           stdin=subprocess.DEVNULL, timeout=60)
        _record("socketcan", channel, args.out / "vcan.asc", other_process)
    adapter_pair = contextlib.contextmanager(_adapter)
    with adapter_pair() as (adapter, peer), kernel_slcan(adapter.slave_path, "slcan-rec"):
        _record("socketcan", "slcan-rec", args.out / "kernel-slcan.asc", lambda: send(peer))
    with adapter_pair() as (adapter, peer):
        _record("slcan", adapter.slave_path, args.out / "python-slcan.asc", lambda: send(peer),
                sleep_after_open=0)
    return 0


if __name__ == "__main__":
    sys.exit(main())
