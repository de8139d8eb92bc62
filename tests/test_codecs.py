"""Codecs against the golden byte vectors (tests/golden/vectors.json) and their own invariants."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from northfinder.codecs import canopen, kvh, smc100

# ------------------------------------------------------------------------------------ SMC100


def test_smc100_replies_golden(golden):
    for v in golden["smc100"]["replies"]:
        line = bytes.fromhex(v["hex"])
        reply = smc100.parse_reply(line)
        assert reply.address == v["address"]
        if "state" in v:
            assert smc100.parse_ts(line) == (v["errors"], v["state"])
        elif "error_letter" in v:
            assert smc100.parse_te(line) == v["error_letter"]
        elif "position" in v:
            assert smc100.parse_position(line) == v["position"]
        else:
            assert smc100.parse_position(line, reply.command) == v["soft_limit"]


def test_smc100_commands_golden(golden):
    for v in golden["smc100"]["commands"]:
        data = bytes.fromhex(v["hex"])
        cmd = smc100.parse_command(data)
        assert (cmd.address, cmd.command, cmd.value) == (v["address"], v["command"], v["value"])
        assert cmd.query == v.get("query", False)
        # encoding the parsed command gives the golden bytes, or the shortest spelling of them
        encoded = smc100.encode_command(cmd.address, cmd.command, cmd.value, cmd.query)
        assert smc100.parse_command(encoded) == cmd
    assert smc100.encode_command(1, "PA", 90.0) == b"1PA90\r\n"
    assert smc100.encode_command(1, "PR", -45.5) == b"1PR-45.5\r\n"
    assert smc100.encode_command(1, "TP", query=True) == b"1TP?\r\n"
    assert smc100.encode_command(12, "TS") == b"12TS\r\n"


def test_smc100_exchange_sends_are_encodable(golden):
    for step in golden["smc100"]["exchange"]:
        if "send" in step:
            cmd = smc100.parse_command(step["send"].encode() + b"\r\n")
            wire = step["send"].encode() + b"\r\n"
            assert smc100.encode_command(cmd.address, cmd.command, cmd.value) == wire


def test_smc100_names():
    assert smc100.state_name(0x0A) == "NOT REFERENCED after reset"
    assert smc100.state_name(0x0F) == "NOT REFERENCED"
    assert smc100.state_name(0x1E) == "HOMING"
    assert smc100.state_name(0x28) == "MOVING"
    assert smc100.state_name(0x33) == "READY from MOVING"
    assert smc100.state_name(0x3D) == "DISABLE from MOVING"
    assert smc100.state_name(0x46) == "JOGGING"
    assert smc100.state_name(0x14) == "CONFIGURATION"
    assert [smc100.is_ready(s) for s in (0x32, 0x33, 0x34, 0x35, 0x28, 0x0A)] == [True] * 4 + [False] * 2
    assert smc100.error_names(0x0020) == ["following error"]
    assert smc100.error_names(0x0201) == ["negative end of run", "80 W output power exceeded"]
    assert smc100.TE_MEANINGS["N"] == "position beyond soft limit"
    assert smc100.TE_MEANINGS["H"] == "not allowed in NOT REFERENCED"


@pytest.mark.parametrize("line", [b"", b"hello\r\n", b"\xfe\x81\xff\x55\r\n", b"1T\r\n", b"TS000033\r\n"])
def test_smc100_rejects_non_replies(line):
    with pytest.raises(smc100.ProtocolError):
        smc100.parse_reply(line)


def test_smc100_reply_checks():
    with pytest.raises(smc100.ProtocolError):
        smc100.parse_ts(b"1TS0033\r\n")  # too few digits
    with pytest.raises(smc100.ProtocolError):
        smc100.parse_reply(b"2TS000033\r\n", expect="TS", address=1)
    with pytest.raises(smc100.ProtocolError):
        smc100.parse_reply(b"1TP90\r\n", expect="TS")
    with pytest.raises(ValueError):
        smc100.encode_command(32, "PA", 1.0)


# ------------------------------------------------------------------------------------ KVH


def test_crc_golden(golden):
    for v in golden["crc32_mpeg2"]:
        data = v["ascii"].encode() if "ascii" in v else bytes.fromhex(v["hex"])
        assert kvh.crc32_mpeg2(data) == int(v["crc"], 16)
        if data:
            rows = np.frombuffer(data, np.uint8)[None, :]
            assert int(kvh.crc32_mpeg2_rows(rows)[0]) == int(v["crc"], 16)


def test_crc_rows_match_scalar_on_random_frames():
    rows = np.random.default_rng(7).integers(0, 256, size=(64, 32), dtype=np.uint8)
    vec = kvh.crc32_mpeg2_rows(rows)
    assert vec.dtype == np.uint32
    assert [int(c) for c in vec] == [kvh.crc32_mpeg2(r.tobytes()) for r in rows]


def test_kvh_frames_golden(golden):
    for v in golden["kvh_format_a"]:
        msg = bytes.fromhex(v["hex"])
        encoded = kvh.encode_frame(v["gyro"], v["accel_g"], v["status"], v["sequence"], v["temperature_c"])
        assert encoded == msg
        dec = kvh.KvhDecoder()
        out = dec.feed(msg)
        assert len(out) == 1 and dec.stats.frames == 1 and dec.stats.bad_crc == 0
        f = out.frames[0]
        assert f["gyro"].tolist() == v["gyro_f32"]
        assert f["accel"].tolist() == v["accel_f32"]
        assert (int(f["status"]), int(f["sequence"]), int(f["temperature"])) == (
            v["status"], v["sequence"], v["temperature_c"])
        assert int(f["crc"]) == int(v["crc"], 16)


def _stream(n: int, start_seq: int = 0, seed: int = 1) -> tuple[bytes, np.ndarray]:
    gyro = np.random.default_rng(seed).normal(scale=1e-5, size=(n, 3))
    data = kvh.encode_frames(gyro, np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, 0x77),
                             np.arange(start_seq, start_seq + n), np.full(n, 25))
    return data, gyro.astype(np.float32)


def test_decoder_sequence_wrap_into_monotonic_index():
    data, gyro = _stream(300, start_seq=120)
    dec = kvh.KvhDecoder()
    out = dec.feed(data)
    assert out.sample_index.tolist() == list(range(300))
    assert np.array_equal(out.frames["gyro"], gyro)
    s = dec.stats
    assert (s.frames, s.sequence_gaps, s.lost_samples, s.resyncs) == (300, 0, 0, 0)


def test_decoder_counts_each_perturbation_exactly():
    data, _ = _stream(40)
    F = kvh.FRAME_SIZE
    frames = [data[i * F:(i + 1) * F] for i in range(40)]
    bad_crc = bytearray(frames[10])
    bad_crc[-1] ^= 0x01
    frames[10] = bytes(bad_crc)
    frames[20] = frames[20][:12] + frames[20][15:]  # 3 bytes dropped inside frame 20
    del frames[30:32]  # two whole frames dropped: a sequence gap, no resync
    stream = b"".join(frames[:5]) + b"\x00garbage\r\n" + b"".join(frames[5:])
    dec = kvh.KvhDecoder()
    out = dec.feed(stream)
    s = dec.stats
    assert s.frames == 40 - 1 - 1 - 2
    assert s.bad_crc == 2  # the corrupted CRC and the frame with dropped bytes
    assert s.resyncs == 3  # after the garbage, the bad CRC and the short frame
    assert s.sequence_gaps == 3 and s.lost_samples == 4
    expected = [i for i in range(40) if i not in (10, 20, 30, 31)]
    assert out.sample_index.tolist() == expected
    # frames 10 and 20 arrived (corrupted): their gaps are exact; 30–31's bytes never came
    assert s.unknown_gaps == 1 and dec.unknown_gap_indices == [32]


def test_decoder_marks_a_gap_whose_bytes_never_came_as_unknown_even_when_it_aliases():
    """130 frames lost on the line look like 2 to the 7-bit sequence: the decoder counts 2 (all it
    can) but marks the gap unknown, because 128·k more may be missing; a corrupted frame of the
    same stream, whose bytes did come, is an exact gap."""
    data, _ = _stream(300)
    F = kvh.FRAME_SIZE
    corrupt = bytearray(data[5 * F:6 * F])
    corrupt[20] ^= 0x10
    stream = data[:5 * F] + bytes(corrupt) + data[6 * F:100 * F] + data[230 * F + 7:]
    dec = kvh.KvhDecoder()
    out = dec.feed(stream)
    assert dec.stats.lost_samples == 1 + 2 + 1  # frame 5, 100–229 counted as 2, frame 230 cut
    assert dec.stats.unknown_gaps == 1
    (k,) = dec.unknown_gap_indices
    assert k == 231 - 128  # the index the decoder gave frame 231: one wrap short of the truth
    assert k in out.sample_index
    block, _ = kvh.decode_imu_stream(stream)
    assert block.unknown_gaps == (k,)


def test_decoder_fake_header_in_garbage_is_one_bad_crc():
    data, _ = _stream(4)
    stream = data[:72] + kvh.HEADER + bytes(40) + data[72:]
    dec = kvh.KvhDecoder()
    assert len(dec.feed(stream)) == 4
    assert (dec.stats.bad_crc, dec.stats.resyncs, dec.stats.lost_samples) == (1, 1, 0)


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(min_value=0, max_value=36 * 12 + 30), max_size=12))
def test_decoder_output_does_not_depend_on_chunking(cuts):
    data, _ = _stream(12, start_seq=125)
    stream = bytearray(b"xx" + data[:100] + b"\x00\x01" + data[100:200] + data[203:] + b"\xfe\x81")
    stream[150] ^= 0xFF
    whole = kvh.KvhDecoder()
    ref = whole.feed(bytes(stream))
    chunked = kvh.KvhDecoder()
    pieces, last = [], 0
    for cut in sorted(set(cuts)) + [len(stream)]:
        pieces.append(chunked.feed(bytes(stream[last:cut])))
        last = cut
    idx = np.concatenate([p.sample_index for p in pieces])
    frames = np.concatenate([p.frames for p in pieces])
    assert np.array_equal(idx, ref.sample_index)
    for name in kvh.FRAME_DTYPE.names:
        assert np.array_equal(frames[name], ref.frames[name])
    assert chunked.stats == whole.stats
    assert chunked.unknown_gap_indices == whole.unknown_gap_indices


def test_gyro_scale():
    assert kvh.gyro_scale_to_rad_s(1000, "DELTA", "RAD") == 1000.0
    assert kvh.gyro_scale_to_rad_s(1000, "RATE", "RAD") == 1.0
    assert kvh.gyro_scale_to_rad_s(100, "RATE", "DEG") == np.pi / 180
    assert kvh.gyro_scale_to_rad_s(100, "delta", "deg") == 100 * np.pi / 180
    with pytest.raises(ValueError):
        kvh.gyro_scale_to_rad_s(100, "ANGLE", "RAD")


def test_kvh_config_lines():
    assert kvh.encode_set("CONFIG", 1) == b"=CONFIG,1\n"
    assert kvh.encode_set("DR", 1000) == b"=DR,1000\n"
    assert kvh.encode_set("rotfmt", "RATE") == b"=ROTFMT,RATE\n"
    assert kvh.encode_query("DR") == b"?DR\n"
    assert kvh.parse_config_reply(b"DR,1000\n") == ("DR", "1000")
    assert kvh.parse_config_reply(b"ROTUNITS,DEG\r\n") == ("ROTUNITS", "DEG")
    with pytest.raises(ValueError):
        kvh.parse_config_reply(b"DR 1000\n")
    found = kvh.find_config_replies(b"\xfe\x81junkDR,250\nROTFMT,DELTA\n")
    assert [(k, v) for k, v, _ in found] == [("DR", "250"), ("ROTFMT", "DELTA")]


# ------------------------------------------------------------------------------------ CANopen


def test_canopen_frames_golden(golden):
    codec = canopen.CanCodec(golden["canopen"]["node_id"])
    for v in golden["canopen"]["frames"]:
        data = bytes.fromhex(v["data"])
        name, sig = codec.decode(v["id"], data)
        if name == "NMT":
            assert codec.encode_nmt(sig["command"], sig["node_id"]) == (v["id"], data)
        elif name == "HEARTBEAT":
            assert sig["state"] == v["state"]
        elif name == "TPDO1":
            assert (sig["accel_x"], sig["accel_y"]) == (v["accel_x_ug"], v["accel_y_ug"])
        elif name == "TPDO2":
            assert (sig["accel_z"], sig["temperature"], sig["counter"], sig["status"]) == (
                v["accel_z_ug"], v["temperature_centi_c"], v["counter"], v["status"])
        elif name == "EMCY":
            assert (sig["error_code"], sig["error_register"]) == (v["error_code"], v["error_register"])
        else:
            pytest.fail(f"unexpected frame {name}")
        if name != "NMT":
            assert codec.encode(name, sig) == (v["id"], data)
    assert codec.encode_nmt("start") == (0, bytes.fromhex("0110"))
    assert codec.encode_nmt("start", 0) == (0, bytes.fromhex("0100"))
    assert codec.encode_nmt("stop") == (0, bytes.fromhex("0210"))


def test_canopen_other_node_ids_by_offset():
    codec = canopen.CanCodec(0x22)
    assert codec.ids == {"EMCY": 0xA2, "TPDO1": 0x1A2, "TPDO2": 0x2A2, "HEARTBEAT": 0x722}
    assert codec.decode(0x190, bytes(8)) is None  # node 0x10's TPDO1 is not ours
    assert codec.decode(0x722, b"\x05") == ("HEARTBEAT", {"state": 5})
    assert codec.encode_nmt("start") == (0, b"\x01\x22")
    with pytest.raises(ValueError):
        canopen.CanCodec(0)
    assert canopen.load_database().get_message_by_name("TPDO2").frame_id == 0x290


def test_config_reply_after_binary_data_that_looks_like_letters():
    """A reply straight after a data message: the preceding byte may be an upper-case letter."""
    from northfinder.codecs import kvh

    assert kvh.find_config_reply(b"\x12\x99QDR,100\n", "DR") == ("100", 10)
    assert kvh.find_config_reply(b"\x00ZROTUNITS,DEG\r\n", "ROTUNITS") == ("DEG", 16)
    assert kvh.find_config_reply(b"DR,100", "DR") is None  # incomplete line
