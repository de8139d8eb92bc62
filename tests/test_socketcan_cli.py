"""`firmware-sim --can INTERFACE[:CHANNEL]` and `northfinder find --simulate --can …` (issue 21, item 3);
on a real kernel CAN bus they run in tests/test_socketcan.py (the guest)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from helpers import subprocess_env

from firmware_sim.cli import build_parser, config_from_args, parse_can
from firmware_sim.config import ConfigError
from northfinder.simulate import SimSettings


@pytest.mark.parametrize(("text", "want"), [
    ("socketcan:vcan0", {"can_interface": "socketcan", "can_channel": "vcan0"}),
    ("slcan", {"can_interface": "slcan"}),
    ("Virtual: bench ", {"can_interface": "virtual", "can_channel": "bench"}),
])
def test_parse_can(text, want):
    assert parse_can(text) == want


@pytest.mark.parametrize("text", ["socketcan", "virtual", "pcan:PCAN_USBBUS1", ""])
def test_a_bad_can_flag_names_the_flag_and_an_example(text):
    with pytest.raises(ConfigError, match=r"--can .*e\.g\. --can socketcan:vcan0"):
        parse_can(text)


def test_the_flag_overrides_the_toml(tmp_path):
    toml = tmp_path / "sim.toml"
    toml.write_text('can_interface = "virtual"\ncan_channel = "bench"\n')
    cfg = config_from_args(build_parser().parse_args(["--config", str(toml), "--can", "socketcan:vcan-x"]))
    assert (cfg.can_interface, cfg.can_channel) == ("socketcan", "vcan-x")


def test_firmware_sim_puts_its_node_where_can_says():
    proc = subprocess.Popen([sys.executable, "-m", "firmware_sim", "--can", "virtual:cli-test-bench"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=subprocess_env())
    try:
        endpoints = json.loads(proc.stdout.readline())
        assert endpoints["can"]["interface"] == "virtual" and endpoints["can"]["channel"] == "cli-test-bench"
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    bad = subprocess.run([sys.executable, "-m", "firmware_sim", "--can", "socketcan"], capture_output=True,
                         text=True, env=subprocess_env(), timeout=60)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "--can socketcan" in bad.stderr


def test_find_simulate_passes_can_on_to_firmware_sim():
    argv = SimSettings(can="socketcan:vcan0").argv()
    assert argv[argv.index("--can") + 1] == "socketcan:vcan0"
    assert "--can" not in SimSettings().argv()
