"""The KVH conformance table (docs/conformance/kvh.md) is what firmware-sim answers now, and its rows
hold the manual's own examples (1775 technical manual §7, §8, §5.3)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest
import serial

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tools"))

import conformance_kvh  # noqa: E402

from firmware_sim.config import SimConfig  # noqa: E402
from firmware_sim.simulator import Simulator  # noqa: E402

DOC = Path(__file__).resolve().parent.parent / "docs" / "conformance" / "kvh.md"


@pytest.fixture(scope="module")
def rows():
    """(mode, line) → the reply of its first occurrence in the table."""
    out: dict[tuple[str, str], bytes] = {}
    for r, reply in conformance_kvh.run_rows():
        out.setdefault((r.mode, r.line), reply)
    return out


def test_the_table_on_disk_is_what_firmware_sim_answers_now():
    text, rows = conformance_kvh.table()
    assert DOC.read_text() == text, "run python tools/conformance_kvh.py"
    assert all(conformance_kvh._agrees(r, reply) for r, reply in rows)
    assert "not as tabulated" not in text


def test_the_manuals_own_examples(rows):
    # §8.17.3: "?FILTTYPE,A" → "FILTTYPE,A,CHEBY"
    assert rows[("config", "?FILTTYPE,A")] == b"FILTTYPE,A,CHEBY\r\n"
    # §8.1.3: the default alignment's reply
    assert rows[("config", "?AXES")] == (b"AXES,+1.000000E+00,+0.000000E+00,+0.000000E+00,+0.000000E+00,"
                                         b"+1.000000E+00,+0.000000E+00,+0.000000E+00,+0.000000E+00,+1.000000E+00\r\n")
    # BIT, normal status: "FE 81 00 AA 7F 7F 7F 7F 7F 7F 23"
    assert rows[("config", "?BIT")] == bytes.fromhex("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23")
    # §7: a command is echoed without its "=", input case-insensitive, reply upper case
    assert rows[("normal", "=config,1")] == b"CONFIG,1\r\n"
    assert rows[("config", "=DR,100")] == b"DR,100\r\n" and rows[("config", "?DR")] == b"DR,100\r\n"
    # §7: unknown input in Configuration Mode → "INVALID," + the echo; ignored in Normal Mode
    assert rows[("config", "=FOO")] == b"INVALID,=FOO\r\n"
    assert rows[("normal", "=FOO")] == b"" and rows[("normal", "?DR")] == b""
    # §7: invalid parameters to a known keyword → a prompt; §7.1: an integer sent as a float too
    assert rows[("config", "=DR,333")].startswith(b"USAGE,=DR,<1|5|10|25|50|100|250|500|750|1000")
    assert rows[("config", "=DR,100.0")].startswith(b"USAGE,=DR,")
    # §8.10/§8.11: the echo counter
    assert [rows[("config", line)] for line in ("=ECHO", "=ECHO,5", "?ECHO", "=ECHO,Reset")] == [
        b"ECHO,1\r\n", b"ECHO,5\r\n", b"ECHO,6\r\n", b"ECHO,0\r\n"]
    # §8.25.3: the log layout of the manual's example
    logs = rows[("config", "?LOGS")].decode().split("\r\n")
    assert logs[:5] == ["Start of log entries!", "Log 1:", "Source - ?BIT", "Format - BIT Status",
                        "Data - 0x7F7F7F7F7F7F7F7F"] and logs[-2:] == ["End of log entries!", ""]
    assert rows[("normal", "?LOGS")] == b""  # tech. manual p. 24: a Configuration mode command


def test_bit2_checksum_rule_gives_the_icds_own_example():
    """ICD §5.3.2: `FE 81 00 AB 7F 7F 7F 7F 7F 7F 37 7F DA` — Table 5-11's rule (sum mod 256, header
    included) reproduces its last byte; with all bytes healthy it gives 0x22."""
    from firmware_sim.devices.kvh import bit_message

    example = bytes.fromhex("FE 81 00 AB 7F 7F 7F 7F 7F 7F 37 7F DA")
    assert bit_message(extended=True, data=example[4:-1]) == example
    assert bit_message(extended=True)[-1] == 0x22


def test_query_bit_in_normal_mode_follows_the_next_data_message_on_a_pty():
    """§8.5: in Normal Mode the BIT message is sent right after a data message, data going on."""
    with Simulator(SimConfig(seed=4, time_scale=5.0, accel_enabled=False)) as ep:
        port = serial.Serial(ep["imu"], 921600, timeout=0.5)
        try:
            time.sleep(0.3)
            port.reset_input_buffer()
            port.write(b"?BIT\r\n")
            got = bytearray()
            deadline = time.monotonic() + 20.0
            while bytes.fromhex("FE 81 00 AA") not in got[:-60] and time.monotonic() < deadline:
                got += port.read(4096)
        finally:
            port.close()
    data = bytes(got)
    at = data.find(bytes.fromhex("FE 81 00 AA 7F 7F 7F 7F 7F 7F 23"))
    assert at >= 0, "no BIT message within 20 s"
    frame_start = data.rfind(b"\xfe\x81\xff\x55", 0, at)
    assert frame_start >= 0 and at - frame_start == 36  # right after one whole data message
    assert data[at + 11:at + 15] == b"\xfe\x81\xff\x55"  # and the data go on
