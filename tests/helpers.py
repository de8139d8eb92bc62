"""Helpers several test files share: bytes into a pty, the CLI as a subprocess (run, or stopped
with Ctrl-C at a chosen point), a run's events, the one-line error checks, and the in-test
transport that pins a driver's write/reply pairs (ExpectedProtocol)."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import serial

from northfinder.rundir import EVENTS

REPO = Path(__file__).resolve().parents[1]

LOADED_HOST_SIM_TOML = "client_stall_wall_s = 10.0\n"
"""firmware-sim config for an end-to-end test whose checks map the host's IMU sample indices onto
the truth log: the IMU's pty holds 10 s of wall time for a reader kept off the CPU (default 1 s).
On a CI host at load 9 on 2 cores the default lost bytes in 4 of 6 slow-stage finds at 10×; a gap of
128 samples or more cannot be counted from the 7-bit sequence, and the indices no longer map to
device time (the margins read as a dwell inside a move). With 10 s: 6 of 6 lossless. These tests are
about the settle and the fit, not about the link's overrun (test_faults and test_sim_devices are)."""


class ExpectedProtocol:
    """An in-test transport (pymeasure's expected_protocol style): asserts each write the driver
    makes, in order, and serves the reply that goes with it. It pins the protocol; it is not a
    device model.

    `pairs`: (what the driver must write, the reply or None); a str gets `terminator` appended
    (b"\r\n" for the SMC100's lines), bytes are taken as they are. `initial`: bytes readable
    before any write (a streaming IMU). Serves both driver surfaces: the line transport's
    `read_until` and the byte stream's `read_available`.
    """

    def __init__(self, pairs: Sequence[tuple[str | bytes, str | bytes | None]], *, terminator: bytes = b"",
                 initial: bytes = b"", url: str = "expected://device"):
        self.url = url
        self._terminator = terminator
        self._pairs = [(self._bytes(send), None if reply is None else self._bytes(reply))
                       for send, reply in pairs]
        self._rx: queue.Queue[bytes] = queue.Queue()
        if initial:
            self._rx.put(initial)
        self.closed = False

    def _bytes(self, item: str | bytes) -> bytes:
        return item if isinstance(item, bytes) else item.encode() + self._terminator

    def write(self, data: bytes) -> None:
        assert self._pairs, f"unexpected write {data!r}: the protocol is finished"
        send, reply = self._pairs.pop(0)
        assert data == send, f"wrote {data!r}, expected {send!r}"
        if reply:
            self._rx.put(reply)

    def read_until(self, terminator: bytes = b"\r\n", size: int | None = None) -> bytes:
        try:
            return self._rx.get_nowait()
        except queue.Empty:
            return b""

    def read_available(self, max_bytes: int = 1 << 16) -> bytes:
        try:
            return self._rx.get(timeout=0.02)
        except queue.Empty:
            return b""

    def reset_input_buffer(self) -> None:
        while not self._rx.empty():
            self._rx.get_nowait()

    def note(self, text: str) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        assert not self._pairs, f"the driver did not send {self._pairs}"


def crc32_mpeg2_bitwise(data: bytes) -> int:
    """Reference CRC-32/MPEG-2, one bit at a time (poly 0x04C11DB7, init FFFFFFFF, not reflected, no
    final XOR): the KVH format A check (PROTOCOLS.md §2, the KVH manual's Table 5-9) and the STIM300
    datagram check (TS1524 rev.31 Table 5-22). Written from the definition, not from either codec."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte << 24
        for _ in range(8):
            crc = ((crc << 1) ^ 0x04C11DB7) & 0xFFFFFFFF if crc & 0x80000000 else (crc << 1) & 0xFFFFFFFF
    return crc


def recv_frames(bus, ids: Sequence[int], n: int, timeout_s: float) -> list:
    """Up to `n` frames whose arbitration id is in `ids`, received from the python-can `bus` within
    `timeout_s` host seconds (a bound only: the caller decides on what arrived)."""
    frames = []
    deadline = time.monotonic() + timeout_s
    while len(frames) < n and time.monotonic() < deadline:
        msg = bus.recv(timeout=1.0)
        if msg is not None and msg.arbitration_id in ids:
            frames.append(msg)
    return frames


def write_all(fd: int, data: bytes) -> None:
    """os.write until every byte is in (a pty takes a few KiB at a time)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def subprocess_env() -> dict[str, str]:
    """This environment with the checkout first on PYTHONPATH (northfinder and firmware_sim found
    from any working directory)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def read_events(run_dir: Path) -> list[dict]:
    """events.jsonl of a run directory ([] before it exists)."""
    p = run_dir / EVENTS
    if not p.exists():
        return []
    return [json.loads(ln) for ln in p.read_text().splitlines() if ln.strip()]


def run_cli(*argv: str, cwd: Path, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    """`python -m northfinder ARGV` to the end, output captured."""
    return subprocess.run(
        [sys.executable, "-m", "northfinder", *argv],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=subprocess_env(),
        timeout=timeout_s,
    )


def start_cli(*argv: str, cwd: Path) -> subprocess.Popen[str]:
    """`python -m northfinder ARGV` started in the background, output piped."""
    return subprocess.Popen(
        [sys.executable, "-m", "northfinder", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=subprocess_env(),
    )


def sigint_when(
    proc: subprocess.Popen[str], steps: Sequence[tuple[Callable[[], bool], str]], timeout_s: float
) -> tuple[str, str]:
    """Wait until each condition of `steps` holds in turn (the process still running, all within
    `timeout_s` of wall time), then Ctrl-C it; its (stdout, stderr). Killed if it outlives this."""
    try:
        deadline = time.monotonic() + timeout_s
        for ready, what in steps:
            while not ready():
                assert proc.poll() is None, proc.communicate()
                assert time.monotonic() < deadline, f"{what} not within {timeout_s:g} s"
                time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def only_line(err: str) -> str:
    """stderr is exactly one non-blank line and no traceback: that line."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def northfinder_line(err: str) -> str:
    """The one `northfinder:` line of stderr (a progress bar may have drawn above it), no traceback."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("northfinder:")]
    assert len(lines) == 1, err
    return lines[0]


def start_sim(*argv: str) -> subprocess.Popen[str]:
    """`python -m firmware_sim ARGV` in its own session (a test's Ctrl-C does not reach it); its
    first stdout line is the endpoints JSON."""
    return subprocess.Popen(
        [sys.executable, "-m", "firmware_sim", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=subprocess_env(),
        start_new_session=True,
    )


def load_tool(name: str):
    """tools/<name>.py as a module (tools are scripts, not a package), registered in sys.modules
    under its name so that its dataclasses can look their module up."""
    import importlib.util

    spec = importlib.util.spec_from_file_location(name, REPO / "tools" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(name, mod)
    spec.loader.exec_module(mod)
    return mod


def advance_and_read(sim, client, t_s: float, out: bytearray) -> None:
    """Advance an in-process simulator's IMU to device time t_s and read what it wrote from the
    client side of its pty, pushing its backlog through until none is left."""
    sim.imu.advance(float(t_s))
    while sim.imu.port.pending:
        sim.imu.port.flush()
        out += client.read(client.in_waiting or 1)
    out += client.read(client.in_waiting)


class SerialKeepingInput(serial.Serial):
    """pyserial whose open() keeps what arrived meanwhile: pyserial flushes the input when it opens
    a port, and the simulator delivers the IMU's first frame CONNECT_GRACE_WALL_S (50 ms) after it
    sees the client, so a host loaded by a CPU hog that took longer to open flushed that frame
    unseen. Tests that count every frame from the connect on use this; the flush is a client's choice."""

    def _reset_input_buffer(self) -> None:
        if self.is_open:  # (False until open() returns)
            super()._reset_input_buffer()
