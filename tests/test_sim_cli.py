"""The firmware-sim command: endpoints JSON, clean exit on SIGTERM/SIGINT, one-line user errors."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from firmware_sim.cli import build_parser, config_from_args
from firmware_sim.config import ConfigError, SimConfig

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "firmware_sim" / "data" / "example.toml"


def _run(*args: str) -> subprocess.Popen[bytes]:
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen([sys.executable, "-m", "firmware_sim", *args], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _endpoints(proc: subprocess.Popen[bytes], timeout_s: float = 30.0) -> dict:
    t0 = time.monotonic()
    ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
    assert ready, "firmware-sim printed nothing"
    line = proc.stdout.readline()
    print(f"\nfirmware-sim printed its endpoints {time.monotonic() - t0:.2f} s after start")
    return json.loads(line)


def _hung_up(client: serial.Serial) -> bool:
    """True when the other end of the client's pty has gone (read gives EOF or EIO)."""
    while True:
        try:
            data = os.read(client.fileno(), 4096)
        except BlockingIOError:  # nothing to read, but the pty is alive
            return False
        except OSError:
            return True
        if not data:
            return True


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_command_prints_endpoints_runs_and_exits_0_leaving_nothing(sig):
    proc = _run("--heading", "37", "--pitch", "1.5", "--roll", "-0.8", "--latitude", "40", "--grade", "nav",
                "--seed", "1", "--time-scale", "10", "--fault", "imu-disconnect=1000:1")
    try:
        ep = _endpoints(proc)
        assert set(ep) == {"turntable", "imu", "can"}
        assert ep["can"] == {"interface": "slcan", "channel": ep["can"]["channel"], "bitrate": 500000,
                             "node_id": 16}
        stage = serial.Serial(ep["turntable"], 57600, timeout=2.0)
        stage.write(b"1TS\r\n")
        assert stage.readline() == b"1TS00000A\r\n"
        # device time starts with the loop; the first frame may still take a while on a loaded machine
        imu = serial.Serial(ep["imu"], 921600, timeout=15.0)
        assert b"\xfe\x81\xff\x55" in imu.read(200)
        imu_link_dir = os.path.dirname(ep["imu"])  # the disconnect fault puts the IMU behind a link
        assert os.path.islink(ep["imu"])
        proc.send_signal(sig)
        assert proc.wait(timeout=10) == 0
        assert proc.stderr.read() == b""
        assert _hung_up(stage) and _hung_up(imu)  # its masters are closed
        stage.close()
        imu.close()
        assert not os.path.exists(imu_link_dir)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize("args, words", [
    (["--fault", "imu-silence=5"], "imu-silence"),
    (["--fault", "warp-drive=1"], "warp-drive"),
    (["--fault", "imu-crc-rate"], "NAME=VALUE"),
    (["--config", "/nonexistent/bench.toml"], "/nonexistent/bench.toml"),
    (["--latitude", "123"], "latitude_deg"),
    (["--time-scale", "0"], "time_scale"),
    (["--grade", "unobtainium"], "grade"),
    (["--sway", "roll=abc"], "--sway roll=abc"),
    (["--scenario", "boat"], "scenario"),
    (["--lever-arm", "1,2"], "--lever-arm 1,2"),
    (["--imu-rate", "333"], "imu_rate_hz"),
    (["--scenario", "vehicle", "--fault", "gnss-nofix=5"], "gnss-nofix"),
])
def test_user_mistakes_give_one_line_and_exit_2(args, words):
    proc = _run(*args)
    out, err = proc.communicate(timeout=30)
    lines = err.decode().strip().splitlines()
    assert proc.returncode == 2 and out == b""
    assert len(lines) == 1 and words in lines[0] and "Traceback" not in lines[0], lines


def test_bad_toml_key_names_the_key(tmp_path):
    bad = tmp_path / "bench.toml"
    bad.write_text('heading_deg = 10\nimu_rate = 100\n')
    proc = _run("--config", str(bad))
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 2 and "imu_rate" in err.decode() and len(err.decode().strip().splitlines()) == 1


def test_example_toml_and_flags_merge():
    argv = ["--config", str(EXAMPLE), "--heading", "12.5", "--fault", "stage-stall=2"]
    args = build_parser().parse_args(argv)
    cfg = config_from_args(args)
    assert cfg.heading_deg == 12.5 and cfg.pitch_deg == 1.5 and cfg.imu_lever_arm_m == (0.05, 0.0, 0.10)
    assert cfg.faults.stage_stall == 2
    with pytest.raises(ConfigError, match="imu_variant"):
        SimConfig(imu_variant="x")


def test_grade_names_checked_early_are_the_physics_presets():
    from firmware_sim.config import GRADES
    from firmware_sim.physics.sensors import ACCEL_PRESETS, GYRO_PRESETS

    assert set(GRADES) == set(GYRO_PRESETS) == set(ACCEL_PRESETS)


def test_sway_table_builds_a_swaying_world():
    from firmware_sim.physics.world import SwayingPlatform
    from firmware_sim.simulator import build_world

    world = build_world(SimConfig(sway={"roll": [[2.0, 8.0], [0.5, 3.1, 40.0]],
                                        "heave": [{"amplitude": 0.3, "period_s": 7.0}]}))
    assert isinstance(world.platform, SwayingPlatform) and len(world.platform.roll) == 2
    with pytest.raises(ConfigError, match="sway.wobble"):
        build_world(SimConfig(sway={"wobble": [[1.0, 2.0]]}))


def test_disturbance_fault_reaches_the_world():
    from firmware_sim.simulator import build_world

    world = build_world(SimConfig(faults=["disturbance=20:0.5:0.1"]))
    assert [(d.start_s, d.duration_s, d.amplitude_deg) for d in world.disturbances] == [(20.0, 0.5, 0.1)]
    assert build_world(SimConfig()).disturbances == []
