"""firmware_sim CAN accelerometer node: golden frames, and its behaviour on python-can `virtual` buses.

The node is driven by calling `advance(t)` with device times chosen here, so every count below is
a property of device time, not of the wall clock.
"""

from __future__ import annotations

import itertools
import math
import struct

import can
import numpy as np
import pytest

from firmware_sim.devices import canopen_accel as ca
from firmware_sim.devices.canopen_accel import CanAccelNode

G0 = 9.80665
NODE = 0x10
HB, TPDO1, TPDO2, EMCY = 0x700 + NODE, 0x180 + NODE, 0x280 + NODE, 0x080 + NODE
_channels = itertools.count()


# ---------------------------------------------------------------------------------------------
# Stand-ins for the physics helper's World / AccelModel (documented signatures only)
# ---------------------------------------------------------------------------------------------
class StandInWorld:
    """Specific force f_b(t) = f0 + a·sin(2π·f_sway·t) on x; `increments` integrates it exactly."""

    def __init__(self, f0_m_s2=(0.0, 0.0, 9.80), sway_m_s2: float = 0.0, sway_hz: float = 0.7):
        self.f0 = np.asarray(f0_m_s2, dtype=float)
        self.sway = sway_m_s2
        self.w = 2 * math.pi * sway_hz
        self.lever_arms: list[tuple[float, ...]] = []
        self.calls: list[tuple[float, int, float]] = []

    def increments(self, t0_s, n, dt_s, lever_arm_b_m):
        self.lever_arms.append(tuple(np.asarray(lever_arm_b_m, dtype=float)))
        self.calls.append((t0_s, n, dt_s))
        ta = t0_s + np.arange(n) * dt_s
        tb = ta + dt_s
        dv = np.tile(self.f0 * dt_s, (n, 1))
        if self.sway:
            dv[:, 0] += self.sway * (np.cos(self.w * ta) - np.cos(self.w * tb)) / self.w
        return np.zeros((n, 3)), dv


class PerfectAccel:
    """An error-free accelerometer model."""

    def __init__(self):
        self.samples = 0

    def apply(self, dv):
        self.samples += len(dv)
        return np.array(dv, dtype=float)


def buses():
    """Two python-can virtual buses on a fresh channel: (the node's, a client's)."""
    channel = f"sim-can-test-{next(_channels)}"
    return can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)


def drain(bus) -> list[can.Message]:
    out = []
    while (m := bus.recv(timeout=0)) is not None:
        out.append(m)
    return out


def run(node, times) -> None:
    for t in times:
        node.advance(float(t))


def nmt(client, command, node=NODE):
    client.send(can.Message(arbitration_id=0, data=[command, node], is_extended_id=False))


def tpdo_pairs(frames):
    """[(TPDO1, TPDO2)] for each TPDO1 immediately followed by its TPDO2."""
    return [
        (a, b)
        for a, b in itertools.pairwise(frames)
        if a.arbitration_id == TPDO1 and b.arbitration_id == TPDO2
    ]


@pytest.fixture
def bench():
    node_bus, client = buses()
    world, model = StandInWorld(), PerfectAccel()
    node = CanAccelNode(node_bus, world, model, node_id=NODE, rate_hz=100.0, lever_arm_b_m=(0.1, 0.0, 0.05))
    yield node, client, world, model
    node.close()
    node_bus.shutdown()
    client.shutdown()


# ---------------------------------------------------------------------------------------------
# Codec against the golden vectors
# ---------------------------------------------------------------------------------------------
def test_golden_canopen_frames(golden):
    node = golden["canopen"]["node_id"]
    for v in golden["canopen"]["frames"]:
        want = (v["id"], bytes.fromhex(v["data"]))
        name = v["name"]
        if name.startswith("NMT"):
            cmd, target = want[1]
            assert ca.encode_nmt(cmd, target) == want
            assert ca.decode_nmt(want[1]) == (cmd, target)
        elif name.startswith("heartbeat"):
            assert ca.encode_heartbeat(node, v["state"]) == want
        elif name.startswith("TPDO1"):
            assert ca.encode_tpdo1(node, v["accel_x_ug"], v["accel_y_ug"]) == want
        elif name.startswith("TPDO2"):
            args = (v["accel_z_ug"], v["temperature_centi_c"], v["counter"], v["status"])
            assert ca.encode_tpdo2(node, *args) == want
            # the vectorized encoder the node actually uses gives the same bytes
            _, p2 = ca.encode_samples(np.array([[0, 0, args[0]]]), args[1], np.array([args[2]]),
                                      np.array([args[3]]))
            assert p2[0] == want[1]
        elif name.startswith("EMCY"):
            assert ca.encode_emcy(node, v["error_code"], v["error_register"]) == want
        else:
            pytest.fail(f"golden CANopen vector not covered: {name}")


def test_vectorized_tpdo_encoder_matches_struct():
    rng = np.random.default_rng(3)
    ug = rng.integers(-8_000_000, 8_000_000, size=(50, 3))
    counters = np.arange(250, 300) & 0xFF
    status = rng.choice([0x07, 0x87], size=50)
    p1, p2 = ca.encode_samples(ug, -350, counters, status)
    for i in range(50):
        assert p1[i] == struct.pack("<ii", ug[i, 0], ug[i, 1])
        assert p2[i] == struct.pack("<ihBB", ug[i, 2], -350, counters[i], status[i])


# ---------------------------------------------------------------------------------------------
# NMT and heartbeat
# ---------------------------------------------------------------------------------------------
def test_bootup_then_preoperational_heartbeat_every_second(bench):
    node, client, _, _ = bench
    node.advance(0.0)
    boot = drain(client)
    assert [(m.arbitration_id, bytes(m.data)) for m in boot] == [(HB, b"\x00")]
    run(node, np.arange(1, 350) * 0.01)  # up to 3.49 s device time
    frames = drain(client)
    assert [(m.arbitration_id, bytes(m.data)) for m in frames] == [(HB, b"\x7f")] * 3
    assert node.state == ca.STATE_PRE_OPERATIONAL


def test_tpdo_pairs_at_configured_rate_after_start_and_none_after_stop(bench):
    node, client, world, model = bench
    run(node, [0.0, 0.5, 1.2])
    drain(client)
    nmt(client, ca.NMT_START)
    node.advance(2.0)  # the start is acted on at device time 2.0
    # uneven steps: the node must emit what is due whatever the loop's cadence
    steps = np.cumsum(np.resize([0.0137, 0.003, 0.051, 0.0004], 400))
    run(node, [t for t in 2.0 + steps if t < 5.0] + [5.0])
    frames = drain(client)
    pairs = tpdo_pairs(frames)
    tpdo = [m for m in frames if m.arbitration_id in (TPDO1, TPDO2)]
    # samples ending in (2.0, 5.0] s at 100 Hz
    assert len(pairs) == round((5.0 - 2.0) * 100.0)
    assert len(tpdo) == 2 * len(pairs)  # every frame paired
    hb = [bytes(m.data) for m in frames if m.arbitration_id == HB]
    assert hb == [b"\x7f"] + [b"\x05"] * 3  # at 2 s (due as the start arrived), then 3, 4, 5 s
    counters = [m.data[6] for _, m in pairs]
    assert counters == [i & 0xFF for i in range(len(pairs))]
    # level, perfect sensor: z = 9.80 m/s² in standard g, x = y = 0; status xyz valid
    z_ug = round(9.80 / G0 * 1e6)
    for m1, m2 in pairs:
        assert struct.unpack("<ii", m1.data) == (0, 0)
        z, temp, _, status = struct.unpack("<ihBB", m2.data)
        assert (z, temp, status) == (z_ug, 2500, 0x07)
    assert set(world.lever_arms) == {(0.1, 0.0, 0.05)}
    # the sensor ran from power-on, also while pre-operational: one model sample per 10 ms
    assert model.samples == round(5.0 * 100.0)

    nmt(client, ca.NMT_STOP)
    node.advance(5.005)
    run(node, 5.005 + np.arange(1, 301) * 0.01)  # to 8.005 s
    after = drain(client)
    assert [m.arbitration_id for m in after] == [HB, HB, HB]
    assert [bytes(m.data) for m in after] == [b"\x04"] * 3


def test_nmt_for_all_nodes_other_nodes_and_preoperational(bench):
    node, client, _, _ = bench
    node.advance(0.0)
    nmt(client, ca.NMT_START, node=0x11)  # someone else's node
    run(node, [0.5, 1.0])
    assert node.state == ca.STATE_PRE_OPERATIONAL
    assert not any(m.arbitration_id == TPDO1 for m in drain(client))
    nmt(client, ca.NMT_START, node=0)  # all nodes
    run(node, [1.0, 1.5])
    assert node.state == ca.STATE_OPERATIONAL
    assert len(tpdo_pairs(drain(client))) == 50
    nmt(client, ca.NMT_PRE_OPERATIONAL)
    run(node, [1.5, 2.0])
    frames = drain(client)
    assert [bytes(m.data) for m in frames] == [b"\x7f"]


def test_counter_wraps_and_reset_node_boots_again(bench):
    node, client, _, _ = bench
    node.advance(0.0)
    nmt(client, ca.NMT_START)
    run(node, np.linspace(0.0, 3.0, 37))
    pairs = tpdo_pairs(drain(client))
    counters = [m.data[6] for _, m in pairs]
    assert len(counters) == 300
    assert counters == [i & 0xFF for i in range(300)]  # …, 254, 255, 0, 1, …
    assert counters[255:258] == [255, 0, 1]

    nmt(client, ca.NMT_RESET_NODE)
    node.advance(3.25)
    frames = drain(client)
    assert [(m.arbitration_id, bytes(m.data)) for m in frames][-1] == (HB, b"\x00")
    assert node.state == ca.STATE_PRE_OPERATIONAL
    run(node, [4.0, 4.25])  # heartbeat period restarts from the reset
    assert [(m.arbitration_id, bytes(m.data)) for m in drain(client)] == [(HB, b"\x7f")]
    nmt(client, ca.NMT_START)
    run(node, [4.25, 4.3])
    assert [m.data[6] for _, m in tpdo_pairs(drain(client))] == [0, 1, 2, 3, 4]  # counter restarted


def test_samples_do_not_depend_on_the_loop_cadence():
    payloads = []
    for times in (np.arange(0, 401) * 0.005, np.r_[0.0, 0.3333, 0.77, 1.0001, 1.6, 2.0]):
        node_bus, client = buses()
        world = StandInWorld(sway_m_s2=0.3, sway_hz=1.3)
        node = CanAccelNode(node_bus, world, PerfectAccel())
        node.advance(0.0)
        nmt(client, ca.NMT_START)
        run(node, times)
        payloads.append([(m.arbitration_id, bytes(m.data)) for m in drain(client)])
        node_bus.shutdown()
        client.shutdown()
    assert payloads[0] == payloads[1]
    # and the x channel carries the sway, averaged over each 10 ms interval
    x_ug = [struct.unpack("<i", d[:4])[0] for i, d in payloads[0] if i == TPDO1]
    w = 2 * math.pi * 1.3
    ta = np.arange(len(x_ug)) * 0.01
    expect = 0.3 * (np.cos(w * ta) - np.cos(w * (ta + 0.01))) / (w * 0.01) / G0 * 1e6
    assert np.max(np.abs(np.array(x_ug) - expect)) <= 0.5 + 1e-6  # rounding to 1 µg


def test_over_range_sets_bit7_and_clips_to_full_scale():
    node_bus, client = buses()
    node = CanAccelNode(node_bus, StandInWorld(f0_m_s2=(0.0, -12.0 * G0, 9.8)), PerfectAccel(),
                        full_scale_g=8.0, temperature_c=-3.5)
    node.advance(0.0)
    nmt(client, ca.NMT_START)
    run(node, [0.0, 0.05])
    pairs = tpdo_pairs(drain(client))
    assert len(pairs) == 5
    for m1, m2 in pairs:
        assert struct.unpack("<ii", m1.data) == (0, -8_000_000)
        z, temp, _, status = struct.unpack("<ihBB", m2.data)
        assert (temp, status) == (-350, 0x87)
    node_bus.shutdown()
    client.shutdown()


# ---------------------------------------------------------------------------------------------
# Faults
# ---------------------------------------------------------------------------------------------
def _faulted_run(faults, seed, t_end=20.0):
    node_bus, client = buses()
    node = CanAccelNode(node_bus, StandInWorld(), PerfectAccel(), faults=faults, rng=seed)
    node.advance(0.0)
    nmt(client, ca.NMT_START)
    run(node, np.arange(0, int(t_end * 20) + 1) * 0.05)
    frames = drain(client)
    node_bus.shutdown()
    client.shutdown()
    return node, frames


def test_loss_rate_drops_tpdo_frames_deterministically():
    p = 0.1
    node, frames = _faulted_run({"accel-loss-rate": str(p)}, seed=7)
    _, again = _faulted_run({"accel-loss-rate": p}, seed=7)
    assert [(m.arbitration_id, bytes(m.data)) for m in frames] == [
        (m.arbitration_id, bytes(m.data)) for m in again
    ]
    n = node.stats.samples
    assert n == 2000
    tpdo = [m for m in frames if m.arbitration_id in (TPDO1, TPDO2)]
    dropped = 2 * n - len(tpdo)
    assert dropped == node.stats.tpdo_dropped
    sigma = math.sqrt(2 * n * p * (1 - p))
    assert abs(dropped - 2 * n * p) < 5 * sigma
    pairs = tpdo_pairs(frames)
    assert len(pairs) < n  # the client sees unpaired frames …
    counters = np.array([m.data[6] for _, m in pairs])
    assert np.any((np.diff(counters) & 0xFF) > 1)  # … and counter gaps
    assert [bytes(m.data) for m in frames if m.arbitration_id == HB] == [b"\x00"] + [b"\x05"] * 20


def test_emcy_and_heartbeat_loss_at_device_times():
    node, frames = _faulted_run({"accel-emcy": ["1.5", "2.25:0x8110"], "accel-heartbeat-loss": 3.5,
                                 "imu-crc-rate": 0.5}, seed=1, t_end=6.0)
    emcy = [(i, m) for i, m in enumerate(frames) if m.arbitration_id == EMCY]
    assert [bytes(m.data) for _, m in emcy] == [bytes.fromhex("0050010000000000"),
                                                bytes.fromhex("1081010000000000")]
    # in device-time order; at one instant heartbeat, then EMCY, then data: the EMCY at 1.5 s
    # follows the samples that ended before 1.5 s (149 of them) and precedes the one ending at it
    i_emcy = emcy[0][0]
    before = [m for m in frames[:i_emcy] if m.arbitration_id == TPDO2]
    assert len(before) == 149
    hb = [bytes(m.data) for m in frames if m.arbitration_id == HB]
    assert hb == [b"\x00", b"\x05", b"\x05", b"\x05"]  # boot-up, 1, 2, 3 s; none from 3.5 s on
    assert node.stats.tpdo_dropped == 0


def test_no_faults_draw_nothing_from_the_rng():
    rng = np.random.default_rng(5)
    state = rng.bit_generator.state
    node_bus, client = buses()
    node = CanAccelNode(node_bus, StandInWorld(), PerfectAccel(), faults={}, rng=rng)
    node.advance(0.0)
    nmt(client, ca.NMT_START)
    run(node, [0.0, 2.0])
    assert rng.bit_generator.state == state
    assert len(tpdo_pairs(drain(client))) == 200
    node_bus.shutdown()
    client.shutdown()


@pytest.mark.parametrize("kwargs, key", [({"node_id": 0}, "node_id"), ({"rate_hz": 0}, "rate_hz")])
def test_bad_settings_name_the_key(kwargs, key):
    node_bus, _ = buses()
    with pytest.raises(ValueError, match=key):
        CanAccelNode(node_bus, StandInWorld(), PerfectAccel(), **kwargs)
    node_bus.shutdown()


def test_bad_fault_value_names_the_fault():
    with pytest.raises(ValueError, match="accel-emcy"):
        ca.AccelFaults.from_spec({"accel-emcy": "soon"})
    with pytest.raises(ValueError, match="accel-loss-rate"):
        ca.AccelFaults.from_spec({"accel-loss-rate": 1.5})


def test_faults_from_the_simulators_fault_specs():
    from firmware_sim.faults import parse_faults

    faults = parse_faults(["accel-loss-rate=0.25", "accel-emcy=3:0x8130", "accel-heartbeat-loss=4",
                           "imu-crc-rate=0.1"])
    for spec in (faults, faults.for_accel()):
        got = ca.AccelFaults.from_spec(spec)
        assert (got.loss_rate, got.emcy, got.heartbeat_loss_at_s) == (0.25, [(3.0, 0x8130)], 4.0)
    assert ca.AccelFaults.from_spec(parse_faults([])) == ca.AccelFaults()


# ---------------------------------------------------------------------------------------------
# With the physics helper's World and AccelModel (expected values from northfinder's own,
# independently written rotations and normal gravity)
# ---------------------------------------------------------------------------------------------
def test_node_reports_the_worlds_specific_force_in_standard_g():
    from firmware_sim.physics.sensors import AccelErrors, AccelModel
    from firmware_sim.physics.world import World
    from northfinder.constants import normal_gravity_m_s2
    from northfinder.rotations import dcm_from_euler, rot_z

    lat, heading, pitch, roll = 40.0, 30.0, 2.0, -1.0
    world = World.static(lat, heading, pitch, roll)
    model = AccelModel(AccelErrors(), 100.0, np.random.default_rng(1))  # error-free
    node_bus, client = buses()
    node = CanAccelNode(node_bus, world, model)
    node.advance(0.0)
    nmt(client, ca.NMT_START)
    run(node, [0.0, 0.5])
    pairs = tpdo_pairs(drain(client))
    assert len(pairs) == 50
    alpha = float(np.squeeze(world.table.kinematics(0.0)[0]))  # the table stands where it powered on
    c_bn = (dcm_from_euler(np.radians(heading), np.radians(pitch), np.radians(roll)) @ rot_z(alpha)).T
    g = normal_gravity_m_s2(lat)
    f_b = c_bn @ np.array([0.0, 0.0, g])
    want_ug = f_b / G0 * 1e6
    for m1, m2 in pairs:
        got = np.array(struct.unpack("<ii", m1.data) + struct.unpack("<i", m2.data[:4]), dtype=float)
        # Earth-rate centripetal and Coriolis terms are < 0.01 µg here; rounding to 1 µg
        assert np.all(np.abs(got - want_ug) <= 0.5 + 0.05)
    node_bus.shutdown()
    client.shutdown()


def test_nav_preset_noise_reaches_the_wire():
    """Per-sample spread of z equals the preset's noise density times √rate (white noise)."""
    from firmware_sim.physics.sensors import ACCEL_PRESETS, AccelModel
    from firmware_sim.physics.world import World

    errors = ACCEL_PRESETS["nav"]
    rate_hz = 100.0
    node_bus, client = buses()
    node = CanAccelNode(node_bus, World.static(40.0), AccelModel(errors, rate_hz, np.random.default_rng(11)),
                        rate_hz=rate_hz)
    node.advance(0.0)
    nmt(client, ca.NMT_START)
    run(node, np.arange(0, 41) * 0.5)  # 20 s: 2000 samples
    z = np.array([struct.unpack("<i", m2.data[:4])[0] for _, m2 in tpdo_pairs(drain(client))], dtype=float)
    assert len(z) == 2000
    sigma_ug = float(np.max(errors.noise_ug_rt_hz)) * math.sqrt(rate_hz)
    # first differences cancel bias and slow drift; their sample std has relative standard error
    # √(1 + 2ρ²)/√(2n) with lag-1 correlation ρ = −1/2; allow 5 of them, + 1 µg of rounding
    rel = 5 * math.sqrt(1.5) / math.sqrt(2 * (len(z) - 1))
    assert abs(np.std(np.diff(z)) / math.sqrt(2) - sigma_ug) < rel * sigma_ug + 1.0
    node_bus.shutdown()
    client.shutdown()


def test_sampling_starts_at_power_on():
    """Powered on late (the simulator powers the node when the adapter's channel opens): the
    sensor does not make up for the time it was off, and its grid starts at power-on."""
    node_bus, client = buses()
    world, model = StandInWorld(), PerfectAccel()
    node = CanAccelNode(node_bus, world, model)
    node.advance(7.3)
    nmt(client, ca.NMT_START)
    run(node, [7.3, 7.8, 8.3])
    frames = drain(client)
    assert (frames[0].arbitration_id, bytes(frames[0].data)) == (HB, b"\x00")
    assert len(tpdo_pairs(frames)) == 100
    assert model.samples == 100
    assert world.calls[0][0] == pytest.approx(7.3, abs=1e-12)
    t_next = [t0 + n * dt for t0, n, dt in world.calls]
    assert [t0 for t0, _, _ in world.calls[1:]] == pytest.approx(t_next[:-1], abs=1e-9)  # contiguous
    node_bus.shutdown()
    client.shutdown()
