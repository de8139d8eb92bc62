"""CANopen SDO (PROTOCOLS.md §3.1): firmware_sim's SDO server on the device side, and the driver on
python-canopen configuring a node and decoding samples by the mapping the node reports.

Device-side tests speak raw frames on a python-can `virtual` bus (no northfinder, no canopen
library). Driver tests run the simulated node on a device clock in a thread (`virtual` bus).
"""

from __future__ import annotations

import itertools
import os
import re
import struct
import sys
import threading
import time
from pathlib import Path

import can
import canopen
import cantools
import numpy as np
import pytest

from firmware_sim.devices import canopen_accel as ca
from firmware_sim.devices.canopen_accel import CanAccelNode
from northfinder.codecs.canopen import DEFAULT_DBC_PATH, default_layout
from northfinder.drivers.accelerometer import DEFAULT_EDS_PATH, Accelerometer, layout_from_node
from northfinder.errors import DeviceError

sys.path.insert(0, os.path.dirname(__file__))
from test_sim_can import PerfectAccel, StandInWorld  # noqa: E402

NODE = 0x10
SWAPPED_EDS = Path(__file__).parent / "data" / "accel_swapped.eds"
F0_M_S2 = (0.8, -1.7, 9.6)  # distinct x, y, z so that an axis mix-up shows
G0 = 9.80665
_channels = itertools.count()


def _record_send_times(node: CanAccelNode) -> list[tuple[float, int]]:
    """(device time, id) of every frame the node sends (the virtual bus stamps host time)."""
    sent: list[tuple[float, int]] = []
    send = node._send

    def spy(t_s, arbitration_id, data):
        sent.append((t_s, arbitration_id))
        send(t_s, arbitration_id, data)

    node._send = spy
    return sent


def _buses():
    ch = f"sdo-test-{os.getpid()}-{next(_channels)}"
    return ch, can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)


# ---------------------------------------------------------------------------------------------
# Device side: raw SDO frames against the node
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def raw_node():
    _, node_bus, client = _buses()
    node = CanAccelNode(node_bus, StandInWorld(), PerfectAccel(), node_id=NODE, rate_hz=100.0)
    sent = _record_send_times(node)
    node.advance(0.0)
    while client.recv(timeout=0) is not None:
        pass
    clock = {"t": 0.0}

    def ask(payload: bytes, dt_s: float = 0.001) -> can.Message | None:
        client.send(can.Message(arbitration_id=0x600 + NODE, data=payload, is_extended_id=False))
        t_req = clock["t"] + dt_s
        clock["t"] = t_req
        node.advance(t_req)
        for msg in iter(lambda: client.recv(timeout=0), None):
            if msg.arbitration_id == 0x580 + NODE:
                t_answer = [t for t, i in sent if i == 0x580 + NODE][-1]
                assert 0 <= t_answer - (t_req - dt_s) <= 0.010  # answered within 10 ms of device time
                return msg
        return None

    yield node, client, ask
    node.close()
    node_bus.shutdown()
    client.shutdown()


def _abort(msg: can.Message) -> tuple[int, int, int]:
    cmd, index, sub, code = struct.unpack("<BHBI", bytes(msg.data))
    assert cmd == 0x80 and len(msg.data) == 8
    return index, sub, code


def test_expedited_and_segmented_upload(raw_node):
    node, _, ask = raw_node
    r = ask(ca.sdo_upload_request(0x1018, 1))
    assert bytes(r.data) == struct.pack("<BHBI", 0x43, 0x1018, 1, ca.VENDOR_ID)
    r = ask(ca.sdo_upload_request(0x2100, 0))
    assert bytes(r.data[:6]) == struct.pack("<BHBH", 0x4B, 0x2100, 0, 100)
    r = ask(ca.sdo_upload_request(0x1008, 0))
    name = ca.DEVICE_NAME.encode()
    assert bytes(r.data) == struct.pack("<BHBI", 0x41, 0x1008, 0, len(name))
    got, toggle = b"", 0
    while True:
        r = ask(bytes((0x60 | toggle << 4,)) + bytes(7))
        head = r.data[0]
        assert head >> 4 & 1 == toggle and head >> 5 == 0
        got += bytes(r.data[1 : 8 - (head >> 1 & 7)])
        toggle ^= 1
        if head & 1:
            break
    assert got == name
    r = ask(bytes((0x60 | toggle << 4,)) + bytes(7))  # no transfer going on any more
    assert _abort(r)[2] == ca.ABORT_COMMAND


@pytest.mark.parametrize("payload, code", [
    (ca.sdo_upload_request(0x2200, 0), ca.ABORT_NO_OBJECT),
    (ca.sdo_upload_request(0x1018, 9), ca.ABORT_NO_SUBINDEX),
    (ca.sdo_download_request(0x1018, 1, b"\1\0\0\0"), ca.ABORT_READ_ONLY),
    (ca.sdo_download_request(0x2100, 0, b"\x32\0\0\0"), ca.ABORT_LENGTH),  # u16 written with 4 bytes
    (ca.sdo_download_request(0x2100, 0, struct.pack("<H", 1001)), ca.ABORT_RANGE),
    (ca.sdo_download_request(0x2100, 0, struct.pack("<H", 0)), ca.ABORT_RANGE),
    # CiA 301 §7.5.2.38: no mapping change while the PDO is valid
    (ca.sdo_download_request(0x1A00, 1, struct.pack("<I", 0x20020008)), ca.ABORT_UNSUPPORTED),
    (ca.sdo_download_request(0x1A00, 0, b"\x01"), ca.ABORT_UNSUPPORTED),
    # §7.5.2.37: the CAN-ID of a valid PDO does not change; 241…251 are reserved types
    (ca.sdo_download_request(0x1800, 1, struct.pack("<I", 0x191)), ca.ABORT_RANGE),
    (ca.sdo_download_request(0x1800, 2, bytes((241,))), ca.ABORT_RANGE),
    (ca.sdo_download_request(0x1800, 3, struct.pack("<H", 10)), ca.ABORT_RANGE),  # inhibit while valid
    (ca.sdo_upload_request(0x1800, 4), ca.ABORT_NO_SUBINDEX),  # sub 4 reserved
    (bytes((0xE0,)) + bytes(7), ca.ABORT_COMMAND),
])
def test_aborts(raw_node, payload, code):
    node, _, ask = raw_node
    index, sub = struct.unpack_from("<HB", payload, 1)
    assert _abort(ask(payload)) == (index, sub, code)
    assert node.od[(0x2100, 0)].value == 100  # nothing changed


def test_segmented_download(raw_node):
    node, _, ask = raw_node
    r = ask(struct.pack("<BHBI", 0x21, 0x2100, 0, 2))  # initiate, size indicated, 2 bytes follow
    assert bytes(r.data) == struct.pack("<BHB4x", 0x60, 0x2100, 0)
    r = ask(bytes((0x00 | (7 - 2) << 1 | 1,)) + struct.pack("<H", 40) + bytes(5))  # toggle 0, last
    assert bytes(r.data) == bytes((0x20,)) + bytes(7) and node.rate_hz == 40.0
    ask(struct.pack("<BHBI", 0x21, 0x2100, 0, 2))
    r = ask(bytes((0x10 | (7 - 2) << 1 | 1,)) + struct.pack("<H", 30) + bytes(5))  # wrong toggle
    assert _abort(r) == (0x2100, 0, ca.ABORT_TOGGLE) and node.rate_hz == 40.0


def test_mapping_follows_the_cia301_procedure_and_the_rate_the_state(raw_node):
    node, client, ask = raw_node

    def ok(index, sub, data):
        r = ask(ca.sdo_download_request(index, sub, data))
        assert bytes(r.data) == struct.pack("<BHB4x", 0x60, index, sub), (hex(index), sub, bytes(r.data))

    # §7.5.2.38: invalidate the PDO, count 0, then the entries, then the count, then validate
    ok(0x1800, 1, struct.pack("<I", ca.PDO_NOT_VALID | 0x190))
    ok(0x1A00, 0, b"\0")
    assert _abort(ask(ca.sdo_download_request(0x1A00, 1, struct.pack("<I", 0x20020020))))[2] == \
        ca.ABORT_NOT_MAPPABLE  # an 8-bit object as 32 bits
    assert _abort(ask(ca.sdo_download_request(0x1A00, 1, struct.pack("<I", 0x22000020))))[2] == \
        ca.ABORT_NO_OBJECT
    ok(0x1A00, 3, struct.pack("<I", 0x20000320))
    assert _abort(ask(ca.sdo_download_request(0x1A00, 0, b"\x03")))[2] == ca.ABORT_PDO_LENGTH  # 96 bits
    ok(0x1A00, 2, struct.pack("<I", 0x20010010))  # x, temperature, counter: 56 bits
    ok(0x1A00, 3, struct.pack("<I", 0x20020008))
    ok(0x1A00, 0, b"\x03")
    assert _abort(ask(ca.sdo_download_request(0x1A00, 1, struct.pack("<I", 0x20000120))))[2] == \
        ca.ABORT_UNSUPPORTED  # an entry only while the count is 0
    ok(0x1800, 3, struct.pack("<H", 20))  # inhibit time: only while not valid
    ok(0x1800, 1, struct.pack("<I", 0x190))
    assert node.od[(0x1A00, 0)].value == 3 and ca.pdo_valid(node.od, 0)
    r = ask(ca.sdo_download_request(0x2100, 0, struct.pack("<H", 50)))
    assert bytes(r.data) == struct.pack("<BHB4x", 0x60, 0x2100, 0) and node.rate_hz == 50.0
    client.send(can.Message(arbitration_id=0, data=[0x01, NODE], is_extended_id=False))
    assert _abort(ask(ca.sdo_download_request(0x2100, 0, struct.pack("<H", 25))))[2] == ca.ABORT_STATE
    assert node.rate_hz == 50.0
    ok(0x1800, 5, struct.pack("<H", 100))  # the event timer: in every state
    r = ask(ca.sdo_download_request(0x1017, 0, struct.pack("<H", 500)))  # rw in every state
    assert r.data[0] == 0x60 and node.heartbeat_period_s == 0.5


def test_rate_write_moves_the_device_clock_of_the_samples():
    _, node_bus, client = _buses()
    node = CanAccelNode(node_bus, StandInWorld(), PerfectAccel(), node_id=NODE, rate_hz=100.0)
    sent = _record_send_times(node)
    node.advance(0.0)
    client.send(can.Message(arbitration_id=0x600 + NODE, data=ca.sdo_download_request(0x2100, 0, b"\x19\0"),
                            is_extended_id=False))
    node.advance(0.0105)
    client.send(can.Message(arbitration_id=0, data=[0x01, NODE], is_extended_id=False))
    node.advance(0.02)
    for t in np.arange(0.03, 1.0, 0.01):
        node.advance(float(t))
    times = np.array([t for t, i in sent if i == 0x290])
    assert len(times) >= 20 and np.allclose(np.diff(times), 1 / 25)
    node_bus.shutdown()
    client.shutdown()


def test_swapped_mapping_frames():
    _, node_bus, client = _buses()
    world = StandInWorld(F0_M_S2)
    node = CanAccelNode(node_bus, world, PerfectAccel(), node_id=NODE, rate_hz=100.0, mapping="swapped")
    node.advance(0.0)
    client.send(can.Message(arbitration_id=0, data=[0x01, NODE], is_extended_id=False))
    node.advance(0.001)
    node.advance(0.031)
    frames = [m for m in iter(lambda: client.recv(timeout=0), None) if m.arbitration_id in (0x190, 0x290)]
    z, x = struct.unpack("<ii", bytes(frames[0].data))
    y, status, counter, temp = struct.unpack("<iBBh", bytes(frames[1].data))
    want = np.rint(np.asarray(F0_M_S2) / G0 * 1e7)
    assert (x, y, z) == tuple(int(v) for v in want) and (status, counter, temp) == (7, 0, 2500)
    node_bus.shutdown()
    client.shutdown()


# ---------------------------------------------------------------------------------------------
# The EDS, the simulator's dictionary and the DBC agree
# ---------------------------------------------------------------------------------------------
_KINDS = {0x5: "u8", 0x6: "u16", 0x7: "u32", 0x3: "i16", 0x4: "i32", 0x9: "vs"}


@pytest.mark.parametrize("eds, mapping, rate",
                         [(DEFAULT_EDS_PATH, "default", 100), (SWAPPED_EDS, "swapped", 25)])
def test_eds_matches_the_simulated_dictionary(eds, mapping, rate):
    od = canopen.import_od(str(eds), NODE)
    sim = ca.build_object_dictionary(NODE, mapping, rate)
    seen = set()
    for obj in od.values():
        subs = [obj] if isinstance(obj, canopen.objectdictionary.ODVariable) else list(obj.values())
        for var in subs:
            key = (var.index, var.subindex)
            seen.add(key)
            assert key in sim, f"{var.index:04X}:{var.subindex} in the EDS, not in the node"
            entry = sim[key]
            assert _KINDS[var.data_type] == entry.kind, key
            assert var.writable == (entry.access != "ro"), key
            if not entry.mappable:
                assert var.default == entry.value, key
    assert seen == set(sim)  # and nothing in the node that the EDS does not describe


def test_dbc_matches_the_eds_mapping():
    """The DBC (for raw CAN logs in common tools) says what the EDS's default mapping says."""
    node = canopen.RemoteNode(NODE, str(DEFAULT_EDS_PATH))
    canopen.Network().add_node(node)  # no bus: the mapping comes from the EDS defaults
    node.tpdo.read(from_od=True)
    layout = layout_from_node(node)
    assert layout == default_layout(NODE)
    db = cantools.database.load_file(str(DEFAULT_DBC_PATH))
    for tpdo in layout.tpdos:
        msg = db.get_message_by_frame_id(tpdo.cob_id)
        assert msg.length == tpdo.length
        start = 0
        for obj, sig in zip(tpdo.objects, msg.signals, strict=True):
            assert (sig.start, sig.length, sig.is_signed) == (start, obj.bits, obj.signed)
            scale = sig.scale if sig.unit in ("g", "degC") else 1.0
            assert scale == pytest.approx(obj.scale), sig.name
            start += obj.bits


# ---------------------------------------------------------------------------------------------
# The driver against the simulated node
# ---------------------------------------------------------------------------------------------
class _Clocked:
    """The node advanced on a device clock (1× host time) in a thread."""

    def __init__(self, **kw):
        self.channel, self.bus, self.extra = _buses()
        self.extra.shutdown()
        self.world = StandInWorld(F0_M_S2)
        self.node = CanAccelNode(self.bus, self.world, PerfectAccel(), node_id=NODE, **kw)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self):
        t0 = time.monotonic()
        while not self._stop.is_set():
            self.node.advance(time.monotonic() - t0)
            time.sleep(0.001)

    def close(self):
        self._stop.set()
        self._thread.join(2)
        self.bus.shutdown()


@pytest.fixture
def clocked(request):
    sims = []

    def make(**kw):
        sims.append(_Clocked(**kw))
        return sims[-1]

    yield make
    for s in sims:
        s.close()


def _line(exc: DeviceError) -> str:
    text = str(exc)
    assert "\n" not in text
    return text


@pytest.mark.parametrize("mapping, eds", [("default", None), ("swapped", SWAPPED_EDS)])
def test_driver_configures_and_decodes_by_the_nodes_mapping(clocked, mapping, eds):
    sim = clocked(rate_hz=100.0 if mapping == "default" else 25.0, mapping=mapping)
    events = []
    with Accelerometer("virtual", sim.channel, eds_path=eds) as acc:
        acc.wait_heartbeat(timeout_s=3)
        info = acc.configure(rate_hz=None, log=events.append)
        assert info["identity"] == {"vendor_id": ca.VENDOR_ID, "product_code": ca.PRODUCT_CODE,
                                    "revision": ca.REVISION, "serial_number": ca.SERIAL_NUMBER,
                                    "device_name": ca.DEVICE_NAME}
        assert acc.rate_hz == sim.node.rate_hz  # read from the node, not assumed
        acc.start_node()
        block = acc.read(10, timeout_s=5)
    assert [e["step"] for e in events] == ["nmt", "identity", "mapping", "rate", "heartbeat"]
    resolution_g = 1e-6 if mapping == "default" else 1e-7
    want = np.asarray(F0_M_S2) / G0
    assert np.all(np.abs(block.accel_g - want) <= resolution_g / 2 + 1e-12)
    assert block.lost_samples == 0 and np.all(block.temperature_c == 25.0) and np.all(block.status == 7)
    assert np.all(np.diff(block.counter) == 1)


def test_driver_writes_rate_and_heartbeat(clocked):
    sim = clocked(rate_hz=100.0)
    with Accelerometer("virtual", sim.channel) as acc:
        acc.wait_heartbeat(timeout_s=3)
        info = acc.configure(rate_hz=40, heartbeat_ms=500)
    assert (info["rate_hz"], info["heartbeat_ms"]) == (40.0, 500)
    assert sim.node.rate_hz == 40.0 and sim.node.heartbeat_period_s == 0.5


def test_sdo_aborts_are_one_line_naming_node_object_and_code(clocked, tmp_path):
    sim = clocked(rate_hz=100.0)
    wrong = tmp_path / "wrong_type.eds"  # a user EDS that calls the rate a u32: the node says length
    text = DEFAULT_EDS_PATH.read_text()
    wrong.write_text(re.sub(r"(\[2100\]\nParameterName=Sample rate\nObjectType=0x7\nDataType=)0x0006",
                            r"\g<1>0x0007", text))
    with Accelerometer("virtual", sim.channel, eds_path=wrong) as acc:
        acc.wait_heartbeat(timeout_s=3)
        with pytest.raises(DeviceError) as unknown:
            acc.sdo_read(0x2200, 0, need_eds=False)
        with pytest.raises(DeviceError) as length:
            acc.configure(rate_hz=50)
        acc.start_node()  # nothing lost: the node and the driver go on
        block = acc.read(5, timeout_s=5)
    assert re.search(r"node 0x10: .*object 2200:0 aborted with 0x06020000", _line(unknown.value))
    assert re.search(r"node 0x10: .*object 2100:0 \(Sample rate\) aborted with 0x06070010",
                     _line(length.value))
    assert len(block) == 5 and block.lost_samples == 0 and sim.node.rate_hz == 100.0


def test_sdo_timeout_with_the_node_silent(clocked):
    sim = clocked(rate_hz=100.0, faults={"accel-sdo-silent": 0.0})
    with Accelerometer("virtual", sim.channel, sdo_timeout_s=0.3) as acc:
        acc.wait_heartbeat(timeout_s=3)
        t0 = time.monotonic()
        with pytest.raises(DeviceError) as exc:
            acc.configure()
        assert 0.25 <= time.monotonic() - t0 < 3.0
        acc.start_node()
        block = acc.read(5, timeout_s=5)  # NMT and TPDOs still work: nothing lost
    assert re.search(r"node 0x10: .*object 1018:1 \(Vendor-ID\) within 0.3 s \(abort 0x05040000",
                     _line(exc.value))
    assert len(block) == 5 and sim.node.stats.sdo_ignored >= 1


def test_eds_without_a_needed_object_is_one_line(clocked, tmp_path):
    sim = clocked(rate_hz=100.0)
    eds = tmp_path / "no_rate.eds"
    text = DEFAULT_EDS_PATH.read_text().replace("5=0x2100\n", "").replace("SupportedObjects=5\n",
                                                                            "SupportedObjects=4\n")
    eds.write_text(text[: text.index("[2100]")])
    with Accelerometer("virtual", sim.channel, eds_path=eds) as acc:
        acc.wait_heartbeat(timeout_s=3)
        with pytest.raises(DeviceError) as exc:
            acc.configure()
    assert "has no object 2100:0" in _line(exc.value)


# ---------------------------------------------------------------------------------------------
# Golden SDO vectors (tests/golden/vectors.json) on both sides
# ---------------------------------------------------------------------------------------------
def test_golden_sdo_device_side(golden):
    """firmware_sim's SDO server answers each golden request with the golden response."""
    for ex in golden["canopen_sdo"]["exchanges"]:
        _, node_bus, client = _buses()
        node = CanAccelNode(node_bus, StandInWorld(), PerfectAccel(), node_id=NODE, rate_hz=100.0)
        node.advance(0.0)
        if ex.get("state") == "operational":
            node.state = ca.STATE_OPERATIONAL
        for step in ex.get("setup", []) + ex["steps"]:
            got = node.sdo.handle(bytes.fromhex(step["request"]), node.state)
            assert got.hex() == step["response"], ex["name"]
        node_bus.shutdown()
        client.shutdown()


def test_golden_sdo_canopen_library_side(golden):
    """python-canopen's SDO client (what the driver uses) sends the golden requests, byte for
    byte, and reads the golden responses as the value or the abort code."""
    from canopen.sdo.exceptions import SdoAbortedError

    vectors = golden["canopen_sdo"]
    _, lib_bus, dev_bus = _buses()
    network = canopen.Network(lib_bus)
    network.notifier = can.Notifier(lib_bus, network.listeners, 0.05)
    node = canopen.RemoteNode(NODE, str(DEFAULT_EDS_PATH))
    network.add_node(node)
    script: list[dict] = []
    seen: list[tuple[str, str]] = []
    stop = threading.Event()

    def device():
        while not stop.is_set():
            msg = dev_bus.recv(timeout=0.05)
            if msg is None or msg.arbitration_id != vectors["request_id"] or not script:
                continue
            step = script.pop(0)
            seen.append((bytes(msg.data).hex(), step["request"]))
            reply = bytes.fromhex(step["response"])
            dev_bus.send(can.Message(arbitration_id=vectors["response_id"], data=reply, is_extended_id=False))

    thread = threading.Thread(target=device, daemon=True)
    thread.start()
    try:
        for ex in vectors["exchanges"]:
            script[:] = ex.get("setup", []) + ex["steps"]
            for step in ex.get("setup", []):
                request = bytes.fromhex(step["request"])
                index, sub = struct.unpack_from("<HB", request, 1)
                node.sdo.download(index, sub, request[4 : 8 - (request[0] >> 2 & 3)])
            upload = bytes.fromhex(ex["steps"][0]["request"])[0] == 0x40
            if "abort" in ex:
                with pytest.raises(SdoAbortedError) as info:
                    if upload:
                        node.sdo.upload(ex["index"], ex["sub"])
                    else:
                        node.sdo.download(ex["index"], ex["sub"], bytes.fromhex(ex["value"]))
                assert info.value.code == ex["abort"], ex["name"]
            elif upload:
                assert node.sdo.upload(ex["index"], ex["sub"]).hex() == ex["value"], ex["name"]
            else:
                node.sdo.download(ex["index"], ex["sub"], bytes.fromhex(ex["value"]))
            assert not script, ex["name"]
    finally:
        stop.set()
        thread.join(2)
        network.notifier.stop()
        lib_bus.shutdown()
        dev_bus.shutdown()
    assert seen and all(sent == want for sent, want in seen), [s for s in seen if s[0] != s[1]]


# ---------------------------------------------------------------------------------------------
# End to end: find on a node with another mapping and rate (set only in the node and its EDS)
# ---------------------------------------------------------------------------------------------
def test_find_follows_a_swapped_mapping_and_the_nodes_own_rate(tmp_path):
    """The simulator's node maps z, x | y, status, counter, temperature at 0.1 µg and runs at
    25 Hz; the bench config names only the user's EDS (rate_hz 0: keep the node's rate). The
    heading is within 3σ of the noise limit (CONVENTIONS.md), the tilt from the accelerometer
    within its own noise/bias-instability/misalignment bound, and every dwell has 25 Hz samples.
    firmware-sim runs as its own process (over slcan): in this one it shared the interpreter with
    the find, and on a loaded CI host the IMU's pty once took no command for 1 s, once lost samples."""
    from helpers import LOADED_HOST_SIM_TOML
    from test_e2e_find import (
        DWELL_S,
        FAST_STAGE_TOML,
        POSITIONS,
        TIME_SCALE,
        TRUTHS,
        _check_replay,
        _noise_limit_deg,
    )

    from firmware_sim.physics.sensors import ACCEL_PRESETS
    from northfinder.rundir import RunDir
    from northfinder.runs.find import measure
    from northfinder.simulate import SimSettings, SimulatorProcess, bench_config

    truth = TRUTHS[0]
    rate_hz = 25.0
    sim_toml = tmp_path / "sim.toml"
    sim_toml.write_text(LOADED_HOST_SIM_TOML + FAST_STAGE_TOML
                        + f'accel_rate_hz = {rate_hz:g}\naccel_mapping = "swapped"\n')
    settings = SimSettings(**truth, time_scale=TIME_SCALE, config=str(sim_toml))
    run_dir = tmp_path / "run"
    with SimulatorProcess(settings) as endpoints:
        assert endpoints["can"]["interface"] == "slcan"
        cfg = bench_config(endpoints, truth["latitude_deg"])
        cfg.accelerometer.eds = str(SWAPPED_EDS)
        cfg.run.positions, cfg.run.dwell_s = POSITIONS, DWELL_S
        assert cfg.validate().accelerometer.rate_hz == 0.0  # nothing about the rate on our side
        result = measure(cfg, RunDir(run_dir), settings=settings, report=False,
                         can_kwargs={"sleep_after_open": 0.05})
    assert result["complete"]
    n = int(DWELL_S * rate_hz)  # the node's rate; an early move leaves ≥ 90 % (accel_min_fraction)
    assert all(0.9 * n <= p["accel_samples"] + p["accel_lost_samples"] <= n for p in result["positions"])
    limit = _noise_limit_deg(truth, result["duration_device_s"])
    assert abs(result["error_deg"]) < 3.0 * limit, (result["error_deg"], limit)
    acc = ACCEL_PRESETS[truth["grade"]]
    t_total = POSITIONS * DWELL_S
    tol_deg = np.rad2deg(3e-6 * (max(acc.noise_ug_rt_hz) / np.sqrt(t_total) + max(acc.bias_instability_ug))
                         + 1e-6 * max(np.abs(acc.misalignment_urad)))
    assert abs(result["tilt"]["pitch_deg"] - truth["pitch_deg"]) < tol_deg, (result["tilt"], tol_deg)
    assert abs(result["tilt"]["roll_deg"] - truth["roll_deg"]) < tol_deg, (result["tilt"], tol_deg)
    _check_replay(run_dir)  # the can.asc replays by the mapping the run read from the node


def test_find_on_a_node_silent_on_sdo_is_one_line_and_keeps_the_run_directory(tmp_path):
    """The CLI: a node that never answers SDO stops `find` with one line (node, object, abort
    code) after the 5 s of §3.1; the run directory keeps its config, events and raw logs."""
    from helpers import northfinder_line, read_events, run_cli
    from test_e2e_find import _bench_toml

    from northfinder.simulate import SimSettings, SimulatorProcess

    with SimulatorProcess(SimSettings(time_scale=5.0, faults=("accel-sdo-silent=0",))) as ep:
        toml = _bench_toml(tmp_path / "bench.toml", ep["turntable"], ep["imu"], ep["can"]["channel"])
        proc = run_cli("find", "--config", str(toml), "--out", str(tmp_path / "run"), "--no-report",
                       cwd=tmp_path)
    assert proc.returncode == 3, proc.stderr
    line = northfinder_line(proc.stderr)
    assert re.search(r"node 0x10: no SDO answer to the read of object 1018:1 \(Vendor-ID\) within 5 s "
                     r"\(abort 0x05040000", line), line
    assert {"config.json", "events.jsonl", "can.asc"} <= {p.name for p in (tmp_path / "run").iterdir()}
    assert read_events(tmp_path / "run")[0] == {"event": "accel_config", "step": "nmt",
                                                "state": "pre-operational"}


def test_check_prints_the_identity_read_over_sdo(tmp_path):
    """`northfinder check` names the node that answered: identity, device name, mapping, rate —
    all read over SDO from firmware_sim's node (here with the swapped mapping at 25 Hz and the
    user's EDS), nothing written."""
    from helpers import run_cli
    from test_e2e_find import _bench_toml

    from northfinder.simulate import SimSettings, SimulatorProcess

    sim_toml = tmp_path / "sim.toml"
    sim_toml.write_text('accel_mapping = "swapped"\naccel_rate_hz = 25\n')
    with SimulatorProcess(SimSettings(time_scale=1.0, config=str(sim_toml))) as ep:
        toml = _bench_toml(tmp_path / "bench.toml", ep["turntable"], ep["imu"], ep["can"]["channel"])
        toml.write_text(toml.read_text().replace("[site]", f"eds = '{SWAPPED_EDS}'\n[site]"))
        proc = run_cli("check", "--config", str(toml), cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (line,) = [ln for ln in proc.stdout.splitlines() if "accelerometer" in ln]
    assert line.startswith("ok ")
    for text in (f"'{ca.DEVICE_NAME}'", f"vendor ID 0x{ca.VENDOR_ID:08X}",
                 f"product code 0x{ca.PRODUCT_CODE:08X}", f"revision 0x{ca.REVISION:08X}",
                 f"serial number 0x{ca.SERIAL_NUMBER:08X}",
                 "rate 25 Hz (2100:0)", "TPDO1 0x190: 2004:3 Acceleration z (0.1 ug), 2004:1 Acceleration x",
                 "TPDO2 0x290: 2004:2 Acceleration y (0.1 ug), 2003:0 Status, 2002:0 Sample counter"):
        assert text in line, (text, line)
