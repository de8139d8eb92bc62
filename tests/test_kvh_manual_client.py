"""A KVH 1775 client written from the manual alone (no northfinder code), run against firmware-sim's
IMU on a real pty with pyserial: the manual's start-up dialogue with echoes (§7), then data.

The manual's rules it relies on: commands end in CR and/or LF, are case-insensitive, and are
echoed without their '='; queries are answered "KEY,value" (§7); Configuration Mode stops the
binary data (§3.3); format A is 36 bytes, header FE 81 FF 55, CRC-32 poly 0x04C11DB7, init
0xFFFFFFFF, no reflection, no final xor (Tables 5-1, 5-9); sequence 0..127 (Table 5-2).
"""

from __future__ import annotations

import struct
import time

import serial
from helpers import crc32_mpeg2_bitwise

from firmware_sim.config import SimConfig
from firmware_sim.simulator import Simulator

HEADER = b"\xfe\x81\xff\x55"


class ManualClient:
    """What a bench engineer writes from §7: send a line, read until the expected reply line."""

    def __init__(self, port: str):
        self.port = serial.Serial(port, 921600, timeout=0.2)
        self.buffer = bytearray()
        self.transcript: list[str] = []

    def _read_until(self, wanted: bytes, timeout_s: float = 15.0) -> bytes:
        deadline = time.monotonic() + timeout_s
        while wanted not in self.buffer:
            assert time.monotonic() < deadline, f"no {wanted!r} within {timeout_s} s"
            self.buffer += self.port.read(4096)
        at = self.buffer.index(wanted)
        before = bytes(self.buffer[:at])
        del self.buffer[:at + len(wanted)]
        return before

    def command(self, line: str, expect: str) -> None:
        self.port.write(line.encode("ascii") + b"\r\n")
        self._read_until(expect.encode("ascii") + b"\r\n")
        self.transcript.append(f"{line} -> {expect}")

    def query(self, key: str) -> str:
        self.port.write(f"?{key}\r\n".encode("ascii"))
        self._read_until(f"{key.upper()},".encode("ascii"))
        value = self._read_until(b"\r\n").decode("ascii")
        self.transcript.append(f"?{key} -> {key.upper()},{value}")
        return value

    def frames(self, n: int) -> list[tuple[int, int, float]]:
        """n format-A messages (status, sequence, gyro y) with a good CRC, from the stream."""
        out = []
        deadline = time.monotonic() + 20.0
        while len(out) < n:
            assert time.monotonic() < deadline
            self.buffer += self.port.read(4096)
            while (at := self.buffer.find(HEADER)) >= 0 and len(self.buffer) >= at + 36:
                msg = bytes(self.buffer[at:at + 36])
                if crc32_mpeg2_bitwise(msg[:32]) == struct.unpack(">I", msg[32:])[0]:
                    gy = struct.unpack(">f", msg[8:12])[0]
                    out.append((msg[28], msg[29], gy))
                    del self.buffer[:at + 36]
                else:
                    del self.buffer[:at + 1]
        return out[:n]


def test_manual_start_up_dialogue_against_firmware_sim():
    with Simulator(SimConfig(seed=2, time_scale=5.0, accel_enabled=False)) as ep:
        client = ManualClient(ep["imu"])
        try:
            assert len(client.frames(10)) == 10  # Normal Mode: binary data
            client.command("=config,1", "CONFIG,1")  # lower case in, upper case echo out
            client.buffer.clear()
            assert client.query("CONFIG") == "1"
            assert client.query("IS").isdigit()
            assert client.query("DR") == "1000"
            assert client.query("ROTFMT") == "DELTA"
            assert client.query("ROTUNITS") == "RAD"
            assert client.query("TEMPUNITS") == "C"
            assert client.query("BAUD") == "921600"
            client.command("=DR,100", "DR,100")
            assert client.query("DR") == "100"
            client.command("=ROTFMT,RATE", "ROTFMT,RATE")
            client.command("=CONFIG,0", "CONFIG,0")
            frames = client.frames(60)
        finally:
            client.port.close()
    print("\n".join(client.transcript))
    seq = [s for _, s, _ in frames]
    assert all((b - a) % 128 == 1 for a, b in zip(seq, seq[1:], strict=False))
    assert [st for st, _, _ in frames[:2]] == [0, 0]  # the first 2 after =DR carry no valid data
    assert [st for st, _, _ in frames[2:]] == [0x77] * 58
    rate_rad_s = sum(g for _, _, g in frames[2:]) / 58  # RATE now: rad/s, the Earth rate's share
    assert abs(rate_rad_s) < 1e-3
