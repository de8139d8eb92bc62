"""The second models' pure codecs against tests/golden/models.json, both sides, and fuzzed.

APT vectors are the byte examples of Thorlabs' protocol Issue 28; STIM vectors are made by
tools/make_golden_vectors.py (a third implementation: zlib-derived CRC) from TS1524 rev.31's
tables, which print no datagram; CiA 410 vectors from DS 410's default TPDO and CiA 301's SDO.
The simulator's own encoders (firmware_sim.devices.*) must produce the same bytes. Fuzzing:
random and mutated streams never raise from the stream decoders, and every byte is accounted for.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from firmware_sim.devices import apt as sim_apt
from firmware_sim.devices import stim as sim_stim
from northfinder.codecs import apt, cia410, stim

ROOT = Path(__file__).resolve().parent.parent
MODELS = json.loads((ROOT / "tests" / "golden" / "models.json").read_text())


def test_golden_file_is_what_the_generator_writes():
    spec = importlib.util.spec_from_file_location("mgv", ROOT / "tools" / "make_golden_vectors.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert MODELS == json.loads(json.dumps(mod.build_models()))


# ---------------------------------------------------------------------------------------------
# Thorlabs APT
# ---------------------------------------------------------------------------------------------
def _apt_by_name(prefix: str) -> dict:
    return next(v for v in MODELS["apt"] if v["name"].startswith(prefix))


def test_apt_encoders_match_the_protocol_examples():
    assert apt.hw_req_info(dest=0x11).hex() == _apt_by_name("HW_REQ_INFO")["hex"]
    assert apt.set_channel_enable(True, 1, dest=0x22).hex() == _apt_by_name("MOD_SET")["hex"]
    assert apt.move_home(1, dest=0x22).hex() == _apt_by_name("MOT_MOVE_HOME ")["hex"]
    assert apt.move_absolute(200000, 1, dest=0x22).hex() == _apt_by_name("MOT_MOVE_ABSOLUTE")["hex"]
    assert apt.ack_status(dest=0x21).hex() == _apt_by_name("MOT_ACK")["hex"]
    assert sim_apt.header(0x0444, 1, 0, dest=0x01, source=0x22).hex() == _apt_by_name("MOT_MOVE_HOMED")["hex"]


def test_apt_decoder_reads_every_example_and_the_info_fields():
    stream = b"".join(bytes.fromhex(v["hex"]) for v in MODELS["apt"])
    dec = apt.AptDecoder()
    msgs = dec.feed(stream)
    assert [m.raw.hex() for m in msgs] == [v["hex"] for v in MODELS["apt"]]
    assert dec.stats.skipped_bytes == 0 and dec.pending_bytes == 0
    v = _apt_by_name("HW_GET_INFO")
    info = apt.parse_hw_info(msgs[-1].data)
    got = (info.serial_number, info.model, info.hw_type, list(info.firmware), info.hw_version,
           info.mod_state, info.channels)
    keys = ("serial_number", "model", "hw_type", "firmware", "hw_version", "mod_state", "channels")
    assert got == tuple(v[k] for k in keys)
    assert apt.parse_hw_info(apt.encode_hw_info(info)) == info
    sim_packet = sim_apt.packet(0x0006, apt.encode_hw_info(info), dest=0x01, source=0x22)
    assert sim_packet.hex().startswith("06005400")


def test_apt_prm1z8_scaling_is_the_protocol_table():
    # APT §8 p. 39: PRM1-Z8 velocity 42941.66 per °/s, acceleration 14.66 per °/s²
    assert apt.velocity_from_deg_s(1.0) == 42942 and apt.acceleration_from_deg_s2(100.0) == 1466
    assert math.isclose(apt.deg_s_from_velocity(apt.velocity_from_deg_s(10.0)), 10.0, rel_tol=1e-5)
    assert apt.counts_from_deg(360.0) == 691071
    assert math.isclose(apt.deg_from_counts(691071), 360.0, abs_tol=1e-3)
    assert sim_apt.VEL_SCALE == pytest.approx(42941.66, abs=0.01)
    assert sim_apt.ACC_SCALE == pytest.approx(14.66, abs=0.01)


def test_apt_status_structure_round_trip_and_names():
    s = apt.MotorStatus(1, -123456, 42, -5, apt.SB_HOMED | apt.SB_SETTLED | apt.SB_ENABLED)
    assert apt.parse_status(apt.encode_status(s)) == s
    assert s.homed and s.enabled and not s.moving and not s.fault
    assert apt.describe_status(s.status_bits) == "homed, settled, enabled"


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.binary(max_size=400), st.lists(st.integers(0, 399), max_size=8))
def test_apt_decoder_never_raises_and_accounts_for_every_byte(noise, cuts):
    stream = noise + b"".join(bytes.fromhex(v["hex"]) for v in MODELS["apt"]) + noise[:37]
    dec = apt.AptDecoder()
    got = 0
    consumed = 0
    pieces = sorted(set(c % (len(stream) + 1) for c in cuts))
    for a, b in zip([0, *pieces], [*pieces, len(stream)], strict=True):
        for m in dec.feed(stream[a:b]):
            consumed += len(m.raw)
            got += 1
    assert consumed + dec.stats.skipped_bytes + dec.pending_bytes == len(stream)
    assert got == dec.stats.messages


# ---------------------------------------------------------------------------------------------
# STIM
# ---------------------------------------------------------------------------------------------
def test_stim_layout_is_tables_5_12_and_5_22():
    for ident, length in MODELS["stim"]["lengths"].items():
        assert stim.datagram_length(int(ident, 16)) == length
    for ident, dummies in MODELS["stim"]["dummies"].items():
        assert stim.layout(int(ident, 16))["dummies"] == dummies
    check = MODELS["stim"]["check"]
    assert stim.stim_crc(check["ascii"].encode()[:8]) == stim.crc32_mpeg2(b"12345678")
    assert stim.crc32_mpeg2(check["ascii"].encode()) == int(check["crc"], 16)
    assert sim_stim.crc32(check["ascii"].encode()) == int(check["crc"], 16)


@pytest.mark.parametrize("k", [0, 1])
def test_stim_golden_datagrams_both_sides(k):
    v = MODELS["stim"]["datagrams"][k]
    raw = bytes.fromhex(v["hex"])
    assert len(raw) == v["length"]
    units = stim.StimUnits(gyro="rate", accel="acceleration")
    dec = stim.StimDecoder(v["id"], units, rate_hz=2000)
    s = dec.feed(raw)
    assert len(s) == 1 and dec.stats.crc_errors == 0
    assert s.gyro[0].tolist() == [g / 2**14 for g in v["gyro_raw"]]
    if "acc_raw" in v:
        assert s.accel[0].tolist() == [a / 2**19 for a in v["acc_raw"]]
        assert s.incl[0].tolist() == [i / 2**22 for i in v["incl_raw"]]
    assert int(s.counter[0]) == v["counter"] and int(s.latency_us[0]) == v["latency_us"]
    assert s.status[0, : len(v["status"])].tolist() == v["status"]
    # both encoders give the same bytes
    enc = stim.encode_datagrams(v["id"], s.gyro, v["status"][0], v["counter"], v["latency_us"], units,
                                accel=s.accel, status_accel=0, incl=s.incl, status_incl=0)
    assert enc == raw
    body = np.frombuffer(raw[: len(raw) - 4], dtype=np.uint8)
    assert sim_stim.seal(body.tobytes()) == raw


def test_stim_status_gives_per_axis_validity():
    valid = stim.status_valid(np.array([0x00, 0x41, 0x09, 0x14, 0x80, 0x02], dtype=np.uint8))
    assert valid.tolist() == [[True] * 3, [False] * 3, [False, True, True], [True, True, False],
                              [False] * 3, [True] * 3]  # 0x02 alone: a channel bit without bit 3/4


def test_stim_serial_datagram_and_service_listing():
    v = MODELS["stim"]["serial_datagram"]
    assert stim.encode_serial_datagram(v["serial"]).hex() == v["hex"]
    assert stim.parse_serial_datagram(bytes.fromhex(v["hex"])) == v["serial"]
    imu = object.__new__(sim_stim.StimImu)
    assert imu.serial_datagram().hex() == v["hex"]
    listing = ("SERIAL NUMBER = N25582405002002\r\nPRODUCT = STIM300\r\n"
               "PART NUMBER = 84167-4400003-321 REV K\r\n"
               "SAMPLE RATE [samples/s] = 2000\r\n")
    ident = stim.identity_from_listing(listing)
    assert (ident.product, ident.serial_number, ident.sample_rate_hz) == ("STIM300", "N25582405002002", 2000)
    with pytest.raises(ValueError, match="PRODUCT"):
        stim.identity_from_listing("SERIAL NUMBER = N1\r\n")


def test_stim_decoder_counts_counter_gaps_and_identity_datagrams():
    units = stim.StimUnits("increment", "increment")
    g = np.zeros((5, 3))
    counters = np.array([4, 8, 16, 20, 24])  # one datagram (4 internal samples) missing after 8
    raw = stim.encode_datagrams(0x93, g, 0, counters, 500, units, accel=g, incl=g)
    serial = bytes.fromhex(MODELS["stim"]["serial_datagram"]["hex"])
    dec = stim.StimDecoder(0x93, units, rate_hz=500)
    s = dec.feed(raw[:76] + serial + raw[76:])
    assert len(s) == 5 and dec.stats.counter_gaps == 4 and dec.stats.identity_datagrams == 1


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
@given(st.binary(max_size=300), st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), max_size=6),
       st.integers(1, 97))
def test_stim_decoder_never_raises_and_accounts_for_every_byte(noise, flips, chunk):
    units = stim.StimUnits("increment", "increment")
    g = np.random.default_rng(len(noise)).normal(size=(6, 3)) * 1e-3
    good = stim.encode_datagrams(0x93, g, 0, np.arange(6) * 4, 500, units, accel=g, incl=g)
    stream = bytearray(noise[:50] + good + noise[50:])
    for pos, val in flips:
        stream[pos % len(stream)] ^= val
    dec = stim.StimDecoder(0x93, units, rate_hz=500)
    n = 0
    for i in range(0, len(stream), chunk):
        n += len(dec.feed(bytes(stream[i : i + chunk])))
    assert n == dec.stats.datagrams
    assert (n * 38 + dec.stats.identity_datagrams * 20 + dec.stats.skipped_bytes + dec.pending_bytes
            == len(stream))
    if not flips:
        assert n >= 6


# ---------------------------------------------------------------------------------------------
# CiA 410
# ---------------------------------------------------------------------------------------------
def test_cia410_tpdo_and_operating_parameter():
    for v in MODELS["cia410"]["tpdo1"]:
        assert cia410.encode_slopes(v["long"], v["lateral"]).hex() == v["hex"]
        assert cia410.decode_slopes(bytes.fromhex(v["hex"])) == (v["long"], v["lateral"])
    inv = MODELS["cia410"]["inversion"]
    assert cia410.apply_operating_parameter(inv["physical"], inv["operating"]) == inv["shown"]
    assert cia410.apply_operating_parameter(1000, 0x02, offset=-300, diff_offset=50) == 750
    assert cia410.apply_operating_parameter(1000, 0x03, offset=-300) == -1300
    assert cia410.preset_offset(0, 1000) == -1000  # zeroing: the shown slope becomes the preset
    counts, bad = cia410.decode_slope_frames([bytes.fromhex("e803"), bytes.fromhex("e80330f8")])
    assert counts.tolist() == [[1000, -2000]] and bad == 1


def test_cia410_sdo_upload_vector_against_the_simulated_dictionary():
    from firmware_sim.devices.canopen_accel import STATE_PRE_OPERATIONAL, SdoServer
    from firmware_sim.devices.cia410 import build_od

    v = MODELS["cia410"]["sdo_upload_resolution"]
    server = SdoServer(build_od(0x20), lambda *a: None)
    assert server.handle(bytes.fromhex(v["request"]), STATE_PRE_OPERATIONAL).hex() == v["response"]


def test_cia410_slopes_to_specific_force_is_exact_at_large_tilt():
    g = 9.80665
    for theta_deg, gamma_deg in ((0.0, 0.0), (2.0, -1.0), (20.0, 30.0), (-45.0, 10.0)):
        th, ga = math.radians(theta_deg), math.radians(gamma_deg)
        f_true = g * np.array([-math.sin(ga) * math.cos(th), math.sin(th), math.cos(ga) * math.cos(th)])
        long_deg, lat_deg = cia410.slopes_from_specific_force(f_true)
        f = cia410.specific_force_from_slopes(long_deg, lat_deg, g)[0]
        assert np.allclose(f, f_true, atol=1e-12 * g)
    assert cia410.quantization_ug(1) == pytest.approx(17.45, abs=0.01)
