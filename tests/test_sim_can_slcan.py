"""firmware_sim slcan adapter on a real pty, and the CAN node reached across processes.

In one process: a real pyserial client on the adapter's pty (golden command replies and frame
lines). Across processes: python-can's own `slcan` interface in a subprocess talks to the node
through the adapter while a small loop here drives both with a scaled device clock.
"""

from __future__ import annotations

import itertools
import json
import os
import select
import subprocess
import sys
import textwrap
import threading
import time

import can
import pytest
import serial

from firmware_sim.clock import DeviceClock
from firmware_sim.devices import canopen_accel as ca
from firmware_sim.devices import slcan_adapter as sa
from firmware_sim.devices.canopen_accel import CanAccelNode
from firmware_sim.devices.slcan_adapter import SlcanAdapter

sys.path.insert(0, os.path.dirname(__file__))
from test_sim_can import PerfectAccel, StandInWorld  # noqa: E402

NODE = 0x10
HB, TPDO1, TPDO2 = 0x700 + NODE, 0x180 + NODE, 0x280 + NODE
_channels = itertools.count()


def _virtual_pair():
    channel = f"sim-slcan-test-{os.getpid()}-{next(_channels)}"
    return can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)


def _read_exactly(port: serial.Serial, n: int) -> bytes:
    data = port.read(n)
    assert len(data) == n, f"expected {n} bytes from the adapter, got {data!r}"
    return data


@pytest.fixture
def adapter_and_client():
    internal, peer = _virtual_pair()
    adapter = SlcanAdapter(internal)
    port = serial.Serial(adapter.endpoint()["channel"], baudrate=115200, timeout=2.0)
    yield adapter, port, peer
    port.close()
    adapter.close()
    internal.shutdown()
    peer.shutdown()


# ---------------------------------------------------------------------------------------------
# Codec and command replies against the golden vectors
# ---------------------------------------------------------------------------------------------
def test_golden_slcan_lines_both_ways(golden):
    for v in golden["slcan"]["frames"]:
        data = bytes.fromhex(v["data"])
        msg = can.Message(arbitration_id=v["id"], data=data, is_extended_id=v["extended"])
        assert sa.encode_frame(msg) == v["line"].encode()
        back = sa.decode_frame(v["line"].encode())
        assert (back.arbitration_id, bytes(back.data), back.is_extended_id) == (v["id"], data, v["extended"])


def test_remote_frames_and_malformed_lines():
    for line, ext in ((b"r1232\r", False), (b"R1ABCDEF08\r", True)):
        msg = sa.decode_frame(line)
        assert msg.is_remote_frame and msg.is_extended_id == ext
        assert sa.encode_frame(msg) == line
    for bad in (b"t12", b"t1232AA", b"t8001", b"t1239" + b"00" * 9, b"tXYZ0", b"x1230"):
        with pytest.raises(ValueError):
            sa.decode_frame(bad)


def test_golden_command_replies_over_the_pty(adapter_and_client, golden):
    adapter, port, _ = adapter_and_client
    assert adapter.endpoint() == {"interface": "slcan", "channel": port.port}
    for v in golden["slcan"]["commands"]:
        port.write(v["send"].encode())
        port.flush()
        _wait_readable(adapter)
        adapter.on_readable(0.0)
        assert _read_exactly(port, len(v["reply"])) == v["reply"].encode(), v["send"]
    assert adapter.bitrate == 500_000


def _wait_readable(adapter, timeout_s=2.0):
    r, _, _ = select.select([adapter.fileno()], [], [], timeout_s)
    assert r, "adapter pty never became readable"


def test_frames_both_ways_only_while_open(adapter_and_client, golden):
    adapter, port, peer = adapter_and_client
    frame = golden["slcan"]["frames"][6]  # a TPDO1
    msg = can.Message(arbitration_id=frame["id"], data=bytes.fromhex(frame["data"]), is_extended_id=False)

    # closed: bus frames are dropped, a client frame is refused with BEL
    peer.send(msg)
    adapter.advance(0.0)
    assert adapter.stats.dropped_closed == 1
    port.write(b"t00020110\r")
    _wait_readable(adapter)
    adapter.on_readable(0.0)
    assert _read_exactly(port, 1) == b"\x07"
    assert peer.recv(timeout=0) is None

    port.write(b"S6\rO\r")
    _wait_readable(adapter)
    adapter.on_readable(0.0)
    assert _read_exactly(port, 2) == b"\r\r"
    peer.send(msg)
    adapter.advance(0.0)
    line = frame["line"].encode()
    assert _read_exactly(port, len(line)) == line

    for v in golden["slcan"]["frames"]:
        port.write(v["line"].encode())
        port.flush()
        _wait_readable(adapter)
        adapter.on_readable(0.0)
        assert _read_exactly(port, 2) == (b"Z\r" if v["extended"] else b"z\r")
        got = peer.recv(timeout=1.0)
        assert (got.arbitration_id, bytes(got.data), got.is_extended_id) == (
            v["id"], bytes.fromhex(v["data"]), v["extended"])

    # listen-only: bus frames still arrive, client frames are refused
    port.write(b"C\rL\rt1230\r")
    _wait_readable(adapter)
    adapter.on_readable(0.0)
    assert _read_exactly(port, 3) == b"\r\r\x07"
    assert peer.recv(timeout=0) is None


def test_slow_client_loses_whole_frames_never_half_lines():
    internal, peer = _virtual_pair()
    adapter = SlcanAdapter(internal, backlog_bytes=1000)
    port = serial.Serial(adapter.slave_path, timeout=0.2)
    try:
        port.write(b"O\r")
        _wait_readable(adapter)
        adapter.on_readable(0.0)
        assert _read_exactly(port, 1) == b"\r"
        n = 3000  # 66 kB of TPDO lines, far more than the kernel's pty buffer plus the backlog
        for i in range(n):
            data = i.to_bytes(4, "little") * 2
            peer.send(can.Message(arbitration_id=TPDO1, data=data, is_extended_id=False))
        adapter.advance(0.0)
        assert adapter.stats.overruns > 0
        assert adapter.stats.to_client + adapter.stats.overruns == n
        received = bytearray()
        while chunk := port.read(65536):
            received += chunk
            adapter.advance(0.0)  # push the backlog as the client drains the pty
        lines = bytes(received).split(b"\r")
        assert lines[-1] == b""
        frames = [sa.decode_frame(line) for line in lines[:-1]]  # every line whole
        assert len(frames) == adapter.stats.to_client
        counts = [int.from_bytes(f.data[:4], "little") for f in frames]
        assert counts == sorted(counts)  # in order; the lost ones are the newest, as on an overrun
    finally:
        port.close()
        adapter.close()
        internal.shutdown()
        peer.shutdown()


# ---------------------------------------------------------------------------------------------
# Across processes: python-can's slcan interface in a subprocess
# ---------------------------------------------------------------------------------------------
class _Loop:
    """What the Simulator does for these two devices: one device clock, poll the pty, advance.

    The node powers on when the client opens the CAN channel, as on a bench where the adapter is
    connected first, so the client can see the boot-up heartbeat.
    """

    def __init__(self, time_scale: float, rate_hz: float = 100.0) -> None:
        self.node_bus, self.adapter_bus = _virtual_pair()
        self.adapter = SlcanAdapter(self.adapter_bus)
        self.node = CanAccelNode(self.node_bus, StandInWorld(), PerfectAccel(), node_id=NODE, rate_hz=rate_hz)
        self.clock = DeviceClock(time_scale)
        self.powered = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="can-loop", daemon=True)
        self.error: BaseException | None = None

    def __enter__(self) -> _Loop:
        self.clock.start()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5.0)
        self.node.close()
        self.adapter.close()
        self.node_bus.shutdown()
        self.adapter_bus.shutdown()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                fd = self.adapter.fileno()  # None while no client has the port open
                readable, _, _ = select.select([fd] if fd is not None else [], [], [], 0.001)
                t = self.clock.now()
                if readable:
                    self.adapter.on_readable(t)
                if self.powered or self.adapter.is_open:
                    self.powered = True
                    self.node.advance(t)
                self.adapter.advance(t)
        except BaseException as exc:  # surfaced by the test
            self.error = exc


CLIENT = textwrap.dedent(
    """
    import json, sys, time
    import can

    NODE = 0x10
    HB = 0x700 + NODE
    bus = can.Bus(interface="slcan", channel=sys.argv[1], bitrate=500000, sleep_after_open=0)
    log = []

    def heartbeat(timeout_s=10.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            m = bus.recv(timeout=0.1)
            if m is None:
                continue
            log.append([m.arbitration_id, m.data.hex()])
            if m.arbitration_id == HB:
                return m.data[0]
        bus.shutdown()
        sys.exit(f"no heartbeat within {timeout_s} s; got {log[-5:]}")

    def nmt(command):
        log.append(["nmt", command])
        bus.send(can.Message(arbitration_id=0, data=[command, NODE], is_extended_id=False))

    version = bus.get_version(2.0)
    serial_number = bus.get_serial_number(2.0)
    heartbeat(); heartbeat()              # boot-up, then pre-operational
    nmt(0x01)
    while heartbeat() != 0x05:
        pass
    for _ in range(3):                    # three whole seconds of device time, operational
        heartbeat()
    nmt(0x02)
    while heartbeat() != 0x04:
        pass
    heartbeat(); heartbeat()              # two whole seconds, stopped
    nmt(0x81)
    while heartbeat() != 0x00:
        pass
    heartbeat()
    bus.shutdown()
    print(json.dumps({"version": version, "serial": serial_number, "log": log}))
    """
)


def test_python_can_slcan_client_in_another_process():
    time_scale = 5.0
    with _Loop(time_scale) as loop:
        proc = subprocess.run(
            [sys.executable, "-c", CLIENT, loop.adapter.endpoint()["channel"]],
            capture_output=True, text=True, timeout=60,
        )
        assert loop.error is None, loop.error
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["version"] == [10, 13]
    assert result["serial"] == "A123"
    log = [tuple(e) for e in result["log"]]

    # boot-up heartbeat first, then pre-operational, no data before the start
    i_start = log.index(("nmt", 1))
    assert log[0] == (HB, "00")
    assert [e for e in log[:i_start] if e[0] == HB] == [(HB, "00"), (HB, "7f")]
    assert not [e for e in log[:i_start] if e[0] in (TPDO1, TPDO2)]

    # operational: between consecutive operational heartbeats (1 s of device time) 100 pairs
    i_stop = log.index(("nmt", 2))
    running = log[i_start:i_stop]
    hb_idx = [i for i, e in enumerate(running) if e == (HB, "05")]
    assert len(hb_idx) == 4
    counters = []
    for a, b in itertools.pairwise(hb_idx):
        seg = running[a + 1 : b]
        assert [e[0] for e in seg] == [TPDO1, TPDO2] * 100  # 100 Hz, every frame paired
        counters += [int(e[1][12:14], 16) for e in seg if e[0] == TPDO2]
    assert counters == [(counters[0] + i) & 0xFF for i in range(300)]  # no gap across 3 s

    # stopped: from the first stopped heartbeat on, heartbeats only
    i_reset = log.index(("nmt", 0x81))
    stopped = log[i_stop:i_reset]
    first_04 = stopped.index((HB, "04"))
    assert stopped[first_04:] == [(HB, "04")] * 3

    # reset node: boot-up again, then pre-operational, no data
    after = log[i_reset + 1 :]
    hbs = [e for e in after if e[0] == HB]
    assert hbs[-2:] == [(HB, "00"), (HB, "7f")]
    assert not [e for e in after if e[0] in (TPDO1, TPDO2)]


@pytest.mark.socketcan
def test_node_on_socketcan_vcan0():
    """On a vcan of its own (tests/socketcan_bus.py; runs in tools/vcan_guest.py's guest)."""
    from socketcan_bus import own_vcan

    with own_vcan("vcan-node") as channel:
        _node_on_socketcan(channel)


def _node_on_socketcan(channel: str) -> None:
    node_bus = can.Bus(interface="socketcan", channel=channel)
    client = can.Bus(interface="socketcan", channel=channel)
    try:
        node = CanAccelNode(node_bus, StandInWorld(), PerfectAccel())
        node.advance(0.0)
        client.send(can.Message(arbitration_id=0, data=[ca.NMT_START, NODE], is_extended_id=False))
        time.sleep(0.05)  # let the kernel deliver the NMT frame; not a timing assertion
        node.advance(0.0)
        node.advance(0.5)
        frames = []
        while (m := client.recv(timeout=0.2)) is not None:
            frames.append(m)
        assert (frames[0].arbitration_id, bytes(frames[0].data)) == (HB, b"\x00")
        ids = [m.arbitration_id for m in frames[1:]]
        assert ids == [TPDO1, TPDO2] * 50
    finally:
        node_bus.shutdown()
        client.shutdown()


def test_channel_opened_at_the_wrong_bitrate_passes_nothing():
    internal, peer = _virtual_pair()
    adapter = SlcanAdapter(internal, bus_bitrate=500_000)
    port = serial.Serial(adapter.slave_path, timeout=0.2)
    try:
        msg = can.Message(arbitration_id=HB, data=b"\x7f", is_extended_id=False)
        for setting, passes in ((b"S4\rO\r", False), (b"C\rS6\rO\r", True)):
            port.write(setting)
            _wait_readable(adapter)
            adapter.on_readable(0.0)
            port.read(setting.count(b"\r"))
            peer.send(msg)
            adapter.advance(0.0)
            port.write(b"t00020110\r")
            _wait_readable(adapter)
            adapter.on_readable(0.0)
            got = port.read(64)
            assert (b"t71017F\r" in got) == passes, setting
            assert (peer.recv(timeout=0.2) is not None) == passes, setting
        assert adapter.stats.wrong_bitrate == 2
    finally:
        port.close()
        adapter.close()
        internal.shutdown()
        peer.shutdown()


def test_no_client_no_fd_to_watch_and_a_vanished_client_closes_the_channel():
    internal, peer = _virtual_pair()
    adapter = SlcanAdapter(internal)
    try:
        assert adapter.fileno() is None  # a client-less master polls hang-up: not watched
        port = serial.Serial(adapter.slave_path, timeout=0.5)
        assert adapter.fileno() is not None
        port.write(b"O\r")
        _wait_readable(adapter)
        adapter.on_readable(0.0)
        assert adapter.is_open
        port.close()  # gone without `C`
        peer.send(can.Message(arbitration_id=HB, data=b"\x05", is_extended_id=False))
        adapter.advance(0.0)
        assert not adapter.is_open and adapter.stats.dropped_closed == 1
        assert adapter.fileno() is None
        port = serial.Serial(adapter.slave_path, timeout=0.2)  # the next client starts clean
        assert port.read(16) == b""
        port.close()
    finally:
        adapter.close()
        internal.shutdown()
        peer.shutdown()


def test_the_bench_loop_puts_what_the_node_sends_in_a_tick_on_the_wire_in_that_tick():
    """firmware_sim's bench, built but not running: its client opens the slcan channel, the node is
    started over NMT, and ONE pass of the loop's device order (every device's `advance(t)`) brings
    the node's first samples onto the adapter's pty — the adapter comes after the node, as a real
    adapter forwards a frame when it is sent (before it, every frame waited a tick: 0.6 device s
    at 120×)."""
    from firmware_sim.config import SimConfig
    from firmware_sim.simulator import Simulator

    sim = Simulator(SimConfig(seed=5))
    sim._build()
    try:
        adapter = sim.can_adapter
        port = serial.Serial(adapter.endpoint()["channel"], baudrate=115200, timeout=2.0)
        try:
            port.write(b"S6\rO\r")
            _wait_readable(adapter)
            adapter.on_readable(0.0)
            assert _read_exactly(port, 2) == b"\r\r"
            for device in sim.devices:  # power on: boot-up, pre-operational
                device.advance(0.0)
            port.reset_input_buffer()
            port.write(b"t000201%02X\r" % NODE)  # NMT start node
            _wait_readable(adapter)
            adapter.on_readable(0.0)
            assert _read_exactly(port, 2) == b"z\r"
            for device in sim.devices:
                device.advance(0.05)  # the node acts on the start at 50 ms
            for device in sim.devices:
                device.advance(0.1)  # 50 ms more: five samples at 100 Hz, sent in this pass
            port.timeout = 0.5
            lines = port.read_until(b"t%03X" % TPDO1)
            assert lines.endswith(b"t%03X" % TPDO1), lines
        finally:
            port.close()
    finally:
        sim._close_all()


def test_a_node_on_the_wire_acts_on_an_nmt_stop_when_its_line_came_in_not_at_the_next_tick():
    """The adapter stamps a client's frame with the device time its line arrived, and the node on
    firmware_sim's wire acts on it then (can_wire.arrival_s): a stop in at 1.005 s, handed on by
    the tick at 1.1 s, ends the TPDOs at the sample due by 1.005 s (none of 1.01…1.1 s), as a real
    node does — at a tick's time the sensor sent on while the table, moved by a command sent after
    the stop, had begun to turn. On a python-can bus (wall-clock stamps) the tick's time stands."""
    from firmware_sim.can_wire import arrival_s, wire

    node_bus, adapter_bus = wire("arrival-test")
    adapter = SlcanAdapter(adapter_bus)
    node = CanAccelNode(node_bus, StandInWorld(), PerfectAccel(), node_id=NODE, rate_hz=100.0)
    try:
        adapter.on_input(b"S6\rO\r", 0.0)
        node.advance(0.0)  # power-on: boot-up, pre-operational
        adapter.on_input(b"t000201%02X\r" % NODE, 0.0)  # NMT start
        node.advance(1.0)
        tpdo_ids = {0x180 + NODE, 0x280 + NODE}
        while adapter_bus.recv(timeout=0) is not None:
            pass
        adapter.on_input(b"t000202%02X\r" % NODE, 1.005)  # NMT stop, in at 1.005 s
        node.advance(1.1)
        after = [m for m in iter(lambda: adapter_bus.recv(timeout=0), None) if m.arbitration_id in tpdo_ids]
        assert after == []
    finally:
        node.close()
        adapter.close()
        node_bus.shutdown()
        adapter_bus.shutdown()
    other = can.Message(arbitration_id=0, data=b"\x02\x10", timestamp=1.7e9)
    virtual = can.Bus(interface="virtual", channel=f"arrival-{os.getpid()}")
    try:
        assert arrival_s(virtual, other, 1.0, 1.1) == 1.1
    finally:
        virtual.shutdown()
