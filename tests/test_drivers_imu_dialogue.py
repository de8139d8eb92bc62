"""The IMU driver and the unit's whole dialogue (KVH 1775 manual §7): each configuration command
confirmed by its echo, a refusal named from the unit's INVALID/USAGE line, and echoes, query
replies and BIT messages inside the binary stream skipped without counting a sample lost."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import ExpectedProtocol

from northfinder.codecs import kvh
from northfinder.drivers.imu import Imu
from northfinder.errors import DeviceError


def _frames(n: int, start_seq: int = 0) -> list[bytes]:
    rng = np.random.default_rng(7)
    raw = kvh.encode_frames(rng.normal(size=(n, 3)) * 1e-6, rng.normal(size=(n, 3)), np.full(n, 0x77),
                            np.arange(start_seq, start_seq + n), np.full(n, 25))
    return [raw[i * 36:(i + 1) * 36] for i in range(n)]


def test_a_refused_command_is_one_line_naming_the_port_and_the_command():
    proto = ExpectedProtocol([
        (b"=CONFIG,1\n", b"CONFIG,1\r\n"),
        (b"=ROTFMT,RATE\n", b"USAGE,=ROTFMT,<DELTA|RATE>\r\n"),  # as if the unit had no RATE
        (b"=CONFIG,0\n", b"CONFIG,0\r\n"),
    ], url="expected://kvh")
    with Imu("expected://kvh", transport=proto, wait_for_data=False, timeout_s=2) as imu:
        with pytest.raises(DeviceError) as err:
            imu.configure(rot_format="RATE")
    proto.assert_done()
    message = str(err.value)
    assert message.startswith("imu on expected://kvh: the IMU refused =ROTFMT,RATE")
    assert "USAGE,=ROTFMT,<DELTA|RATE>" in message and "\n" not in message


def test_an_invalid_line_is_a_refusal_too():
    proto = ExpectedProtocol([
        (b"=CONFIG,1\n", b"CONFIG,1\r\n"),
        (b"=DR,100\n", b"INVALID,=DR,100\r\n"),
        (b"=CONFIG,0\n", b"CONFIG,0\r\n"),
    ])
    with Imu("expected://kvh", transport=proto, wait_for_data=False, timeout_s=2) as imu:
        with pytest.raises(DeviceError, match=r"refused =DR,100 \(it answered 'INVALID,=DR,100'\)"):
            imu.configure(rate_hz=100)
    proto.assert_done()


def test_no_echo_is_a_timeout_naming_the_command():
    proto = ExpectedProtocol([(b"=CONFIG,1\n", None)])
    with Imu("expected://kvh", transport=proto, wait_for_data=False, timeout_s=0.3) as imu:
        with pytest.raises(DeviceError, match=r"no echo of =CONFIG,1"):
            imu.query("DR")


def test_text_and_bit_messages_in_the_stream_cost_no_sample():
    """Frames 0..199 with a power-up BIT message first and, between frames, echoes, query replies,
    an INVALID line and a ?BIT answer: all 200 samples arrive, none counted lost."""
    frames = _frames(200)
    bit = kvh.encode_bit_message()
    extras = {10: b"CONFIG,0\r\n", 50: b"DR,1000\r\n", 51: b"INVALID,=FOO\r\n", 120: bit,
              121: b"ROTFMT,DELTA\r\n"}
    stream = bit + b"".join(f + extras.get(i, b"") for i, f in enumerate(frames))
    proto = ExpectedProtocol([], initial=stream)
    with Imu("expected://kvh", transport=proto, timeout_s=2) as imu:
        block = imu.read(200, timeout_s=5)
        stats = imu.stats
        test, source = imu.built_in_test()
        assert len(imu.bit_messages) == 2
    assert block.sample_index.tolist() == list(range(200)) and block.lost_samples == 0
    assert stats.lost_samples == 0 and stats.sequence_gaps == 0 and stats.bad_crc == 0
    assert source == "power-up" and test.healthy and test.describe() == "BIT 7F 7F 7F 7F 7F 7F: all passed"


def test_built_in_test_asks_with_query_bit_when_the_power_up_message_was_missed():
    frames = _frames(20)
    failed = kvh.encode_bit_message(bytes([0x7F, 0x7D, 0x7F, 0x7F, 0x7F, 0x7F]))
    proto = ExpectedProtocol([(b"?BIT\n", frames[10] + failed + frames[11])], initial=b"".join(frames[:10]))
    with Imu("expected://kvh", transport=proto, timeout_s=2) as imu:
        test, source = imu.built_in_test()
    proto.assert_done()
    assert source == "?BIT" and not test.healthy and "byte 1 bits 0x02" in test.describe()


def test_bit_checksum_covers_the_header_as_in_the_manual_example():
    assert kvh.encode_bit_message() == bytes.fromhex("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23")
    (message, start), = kvh.find_bit_messages(b"\x00\x01" + bytes.fromhex("FE 81 00 AA 7F 7F 7F 7F 7F 7F 24"))
    assert start == 2 and not message.checksum_ok


def test_another_commands_refusal_is_not_taken_for_this_one():
    """An INVALID line for another input (a second terminal's) before the echo: the echo counts."""
    proto = ExpectedProtocol([
        (b"=CONFIG,1\n", b"INVALID,=FOO\r\nCONFIG,1\r\n"),
        (b"?DR\n", b"DR,1000\r\n"),
        (b"=CONFIG,0\n", b"CONFIG,0\r\n"),
    ])
    with Imu("expected://kvh", transport=proto, wait_for_data=False, timeout_s=2) as imu:
        assert imu.query("DR") == "1000"
    proto.assert_done()
    assert kvh.find_refusal(b"INVALID,=FOO\r\nUSAGE,=DR,<1|5>\r\n", "DR") == ("USAGE,=DR,<1|5>", 31)
    assert kvh.find_refusal(b"INVALID,=FOO\r\n", "DR") is None
