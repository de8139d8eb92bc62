"""Clients written from the manuals alone (not northfinder's drivers) against firmware-sim.

- SMC100: the user manual's start-up (RS, PW1, ZT, ID?, SL?/SR?, PW0, OR), moves and a bare ST,
  over a real pty with pyserial, each step checked by TS/TE as the manual says a host should.
- CANopen: the `canopen` library as a standard master over python-can's slcan client to
  firmware-sim's emulated adapter (a real pty): `pdo.read()`, a remap and re-time by the CiA 301
  procedure with `pdo.save()`, and the remapped TPDOs received (event timer and SYNC-driven).

Decisions are made in device terms (states, counters, SYNC counts); host time only bounds waits.
Run with `-s` to see the dialogue each client had (printed as it goes).
"""

from __future__ import annotations

import struct
import threading
import time

import can
import canopen
import pytest
import serial

from firmware_sim.config import SimConfig
from firmware_sim.simulator import Simulator
from northfinder.drivers.accelerometer import DEFAULT_EDS_PATH  # the node's EDS file (data, not code)

NODE = 0x10
WAIT_S = 20.0  # host-time bound for anything the simulator does in device time


# ---------------------------------------------------------------------------------------------
# SMC100
# ---------------------------------------------------------------------------------------------
class ManualSmc100:
    """The SMC100 manual's host: `xxAAnn\\r\\n` out, one line back for a query, TE after a set."""

    def __init__(self, path: str) -> None:
        self.port = serial.Serial(path, 57600, timeout=10.0, xonxoff=True)
        self.log: list[str] = []

    def send(self, text: str) -> None:
        self.log.append(f"> {text}")
        self.port.write(text.encode("ascii") + b"\r\n")

    def line(self) -> str:
        raw = self.port.readline()
        assert raw.endswith(b"\r\n"), f"no complete line: {raw!r}"
        text = raw[:-2].decode("ascii")
        self.log.append(f"< {text}")
        return text

    def ask(self, text: str) -> str:
        self.send(text)
        return self.line()

    def ok(self, text: str) -> None:
        """A set/move command, then TE: the manual's way to know it was accepted."""
        self.send(text)
        assert self.ask("1TE") == "1TE@", self.log[-4:]

    def state(self) -> int:
        reply = self.ask("1TS")
        assert reply.startswith("1TS") and len(reply) == 9, reply
        return int(reply[7:9], 16)

    def wait_state(self, *states: int) -> int:
        deadline = time.monotonic() + WAIT_S
        while time.monotonic() < deadline:
            if (s := self.state()) in states:
                return s
            time.sleep(0.02)
        raise AssertionError(f"state never in {states}")


def test_smc100_manual_start_up_moves_and_bare_st():
    sim = Simulator(SimConfig(seed=3, time_scale=20.0, accel_enabled=False))
    ep = sim.start()
    host = ManualSmc100(ep["turntable"])
    try:
        host.send("1RS")
        assert host.wait_state(0x0A) == 0x0A  # NOT REFERENCED from reset
        host.ok("1PW1")
        assert host.state() == 0x14  # CONFIGURATION
        host.send("1ZT")
        dump = [host.line()]  # the manual's example (p. 67): 1PW1, the parameters, 1PW1
        while len(dump) == 1 or dump[-1] != "1PW1":
            dump.append(host.line())
        assert dump[0] == "1PW1" and len(dump) > 10
        assert {line[1:3] for line in dump} >= {"AC", "VA", "SL", "SR", "SU", "ZX"}
        stage_id = host.ask("1ID?")
        assert stage_id.startswith("1ID") and len(stage_id) > 3
        low, high = float(host.ask("1SL?")[3:]), float(host.ask("1SR?")[3:])
        assert low < 0.0 < high
        host.ok("1PW0")
        assert host.state() == 0x0C  # NOT REFERENCED from CONFIGURATION
        host.ok("1OR")
        assert host.wait_state(0x32) == 0x32  # READY from HOMING
        host.ok("1PA90")
        assert host.wait_state(0x33) == 0x33
        assert abs(float(host.ask("1TP")[3:]) - 90.0) < 1e-3
        host.ok("1PR-45")
        host.wait_state(0x33)
        assert abs(float(host.ask("1TP")[3:]) - 45.0) < 1e-3
        host.send(f"1PA{high + 1:g}")  # the manual: a target beyond the software limit is G
        assert host.ask("1TE") == "1TEG"
        assert host.ask("1PT90").startswith("1PT")
        host.ok("1PA300")
        assert host.state() == 0x28  # MOVING
        host.send("ST")  # no address: the manual stops every controller
        assert host.wait_state(0x33) == 0x33
        stopped = float(host.ask("1TP")[3:])
        assert 45.0 < stopped < 300.0
        assert host.ask("1TE") == "1TE@"  # bare ST is not an error
        host.ok("1PA10")  # and the next command runs
        host.wait_state(0x33)
    finally:
        print("\n".join(host.log))
        host.port.close()
        sim.stop()


# ---------------------------------------------------------------------------------------------
# CANopen with the canopen library
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def can_bench():
    sim = Simulator(SimConfig(seed=4, time_scale=5.0, accel_rate_hz=100.0))
    ep = sim.start()
    network = canopen.Network()
    network.connect(interface=ep["can"]["interface"], channel=ep["can"]["channel"],
                    bitrate=ep["can"]["bitrate"])
    node = canopen.RemoteNode(NODE, str(DEFAULT_EDS_PATH))
    network.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 5.0
    yield sim, network, node
    network.disconnect()
    sim.stop()


class Frames(can.Listener):
    """Every frame the master sees, by COB-ID."""

    def __init__(self) -> None:
        self.by_id: dict[int, list[bytes]] = {}
        self.lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self.lock:
            self.by_id.setdefault(msg.arbitration_id, []).append(bytes(msg.data))

    def count(self, cob_id: int) -> int:
        with self.lock:
            return len(self.by_id.get(cob_id, []))

    def wait(self, cob_id: int, n: int) -> list[bytes]:
        deadline = time.monotonic() + WAIT_S
        while self.count(cob_id) < n and time.monotonic() < deadline:
            time.sleep(0.01)
        with self.lock:
            got = list(self.by_id.get(cob_id, []))
        assert len(got) >= n, f"0x{cob_id:03X}: {len(got)} frames, wanted {n}"
        return got


def test_canopen_library_reads_remaps_and_retimes_the_node(can_bench):
    sim, network, node = can_bench
    node.nmt.state = "PRE-OPERATIONAL"
    node.tpdo.read()
    t1, t2 = node.tpdo[1], node.tpdo[2]
    print(f"\nread: TPDO1 0x{t1.cob_id:03X} type {t1.trans_type} "
          f"{[(v.index, v.subindex, v.length) for v in t1.map]}; "
          f"TPDO2 0x{t2.cob_id:03X} type {t2.trans_type} {[(v.index, v.subindex, v.length) for v in t2.map]}")
    assert (t1.cob_id, t1.enabled, t1.trans_type) == (0x180 + NODE, True, 254)
    assert [(v.index, v.subindex) for v in t1.map] == [(0x2000, 1), (0x2000, 2)]
    assert [(v.index, v.subindex) for v in t2.map] == [(0x2000, 3), (0x2001, 0), (0x2002, 0), (0x2003, 0)]

    # remap TPDO1 to z + counter, timer-driven every 50 ms; TPDO2 to x + counter on every 2nd SYNC
    t1.clear()
    t1.add_variable(0x2000, 3)
    t1.add_variable(0x2002, 0)
    t1.trans_type, t1.event_timer, t1.enabled = 254, 50, True
    t1.save()  # CiA 301: invalidate, count 0, entries, count, validate
    t2.clear()
    t2.add_variable(0x2000, 1)
    t2.add_variable(0x2002, 0)
    t2.trans_type, t2.enabled = 2, True
    t2.save()
    node.tpdo.read()  # what the node now says
    assert [(v.index, v.subindex) for v in t1.map] == [(0x2000, 3), (0x2002, 0)]
    assert (t1.trans_type, t1.event_timer, t2.trans_type) == (254, 50, 2)

    frames = Frames()
    network.notifier.add_listener(frames)
    node.nmt.state = "OPERATIONAL"
    got1 = frames.wait(0x180 + NODE, 6)
    counters = [data[4] for data in got1[:6]]
    steps = {(b - a) % 256 for a, b in zip(counters[:-1], counters[1:], strict=True)}
    z_ug = struct.unpack("<i", got1[0][:4])[0]
    print(f"TPDO1 (z, counter) every 50 ms at 100 Hz: counters {counters}, z {z_ug} µg")
    assert all(len(d) == 5 for d in got1) and steps == {5}  # 50 ms = 5 samples, in device time
    assert 0.5e6 < abs(z_ug) < 1.5e6  # z sees about 1 g

    assert frames.count(0x280 + NODE) == 0  # SYNC-driven: nothing without SYNC
    for k in range(6):
        network.send_message(0x080, b"")  # SYNC (COB-ID 1005h), no counter
        frames.wait(0x280 + NODE, k // 2)
        time.sleep(0.05)
    got2 = frames.wait(0x280 + NODE, 3)
    print(f"TPDO2 (x, counter) after 6 SYNCs with type 2: {len(got2)} frames")
    assert len(got2) == 3 and all(len(d) == 5 for d in got2)
    node.nmt.state = "PRE-OPERATIONAL"
