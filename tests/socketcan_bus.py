"""A kernel CAN bus of a test's own: a vcan made for one test and removed after it, and the kernel's
slcan driver (`slcand`, can-utils) attached to a serial port.

A test that asserts on "the first frame" must own its bus (under pytest-xdist three tests on one
vcan0 saw each other's NMT frames and heartbeats). These need a kernel with CAN and the right to add
links (root): the User-Mode Linux guest of tools/vcan_guest.py has both; elsewhere the tests skip,
and the guest's run (CI) counts a skip as a failure. Commands as in docs/can-on-linux.md.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

IFNAMSIZ = 15  # a Linux interface name is at most 15 characters
COMMAND_TIMEOUT_S = 20.0


def _run(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(argv, capture_output=True, text=True, stdin=subprocess.DEVNULL,
                          timeout=COMMAND_TIMEOUT_S, check=False)


def _why_not_here() -> str | None:
    if not Path("/proc/net/can").exists():
        return "this kernel has no CAN (AF_CAN): run these in the guest, python3 tools/vcan_guest.py"
    if shutil.which("ip") is None:
        return "no `ip` (iproute2) here"
    return None


@contextlib.contextmanager
def own_vcan(name: str) -> Iterator[str]:
    """`ip link add dev NAME type vcan; ip link set up NAME` for the block, deleted after it."""
    assert len(name) <= IFNAMSIZ, name
    why = _why_not_here()
    if why:
        pytest.skip(why)
    _run("ip", "link", "del", "dev", name)  # left over from an interrupted run
    made = _run("ip", "link", "add", "dev", name, "type", "vcan")
    if made.returncode:
        pytest.skip(f"cannot add vcan {name}: {made.stderr.strip()} (needs the vcan module and root)")
    try:
        up = _run("ip", "link", "set", "up", name)
        assert up.returncode == 0, up.stderr
        yield name
    finally:
        _run("ip", "link", "del", "dev", name)


@contextlib.contextmanager
def kernel_slcan(tty: str, name: str, bitrate_code: str = "s6") -> Iterator[str]:
    """The kernel's slcan driver on serial port `tty` as interface `name`, the way a CANable or USBtin
    is attached: `slcand -o -c -s6 TTY NAME; ip link set up NAME` (-s6: 500 kbit/s; -o open, -c close
    the channel on the adapter). slcand is stopped (and the link goes) after the block."""
    assert len(name) <= IFNAMSIZ, name
    why = _why_not_here()
    if why:
        pytest.skip(why)
    if shutil.which("slcand") is None:
        pytest.skip("no slcand here (apt-get install can-utils)")
    proc = subprocess.Popen(["slcand", "-F", "-o", "-c", f"-{bitrate_code}", tty, name],
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + COMMAND_TIMEOUT_S
        while not Path(f"/sys/class/net/{name}").exists():
            assert proc.poll() is None, f"slcand exited: {proc.stdout.read().decode(errors='replace')}"
            assert time.monotonic() < deadline, f"slcand made no {name} in {COMMAND_TIMEOUT_S:g} s"
            time.sleep(0.05)
        up = _run("ip", "link", "set", "up", name)
        assert up.returncode == 0, up.stderr
        yield name
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=COMMAND_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def interface_stats(name: str) -> dict[str, int]:
    """The interface's counters from /sys/class/net/NAME/statistics (rx_dropped, rx_over_errors…)."""
    base = Path(f"/sys/class/net/{name}/statistics")
    return {p.name: int(p.read_text()) for p in base.iterdir()} if base.is_dir() else {}


def in_guest() -> bool:
    """True inside tools/vcan_guest.py's guest."""
    return os.environ.get("NORTHFINDER_VCAN_GUEST") == "1"
