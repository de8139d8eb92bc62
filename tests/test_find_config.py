"""bench.toml parsing and validation, the position plan, and CLI flag mistakes (no devices needed)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from northfinder import config as bench
from northfinder.errors import ConfigError

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "docs" / "bench.example.toml"


def test_example_config_loads_with_its_documented_values():
    cfg = bench.load(EXAMPLE)
    assert cfg.turntable.port == "/dev/ttyUSB0"
    assert cfg.imu.rate_hz == 1000
    assert cfg.accelerometer.node_id == 16
    assert cfg.site.latitude_deg == 40.0
    assert cfg.run.positions == 8 and cfg.run.dwell_s == 30.0
    assert cfg.estimator.method == "exact"
    bench.require_ports(cfg)
    # the same file serves both align modes (one configuration, one validation)
    assert cfg.gnss.port == "/dev/ttyUSB2" and cfg.gnss.lever_arm_m == (0.5, 1.5, 1.2)
    assert cfg.imu.rot_format == "DELTA" and cfg.imu.rot_units == "RAD"
    assert bench.require_align(cfg, "swaying") == 40.0 and bench.require_align(cfg, "swaying", -12.5) == -12.5
    assert math.isnan(bench.require_align(cfg, "gnss"))
    assert (cfg.swaying.duration_s, cfg.swaying.method, cfg.swaying.sway_period_s) == (300.0, "cone", 10.0)
    assert cfg.gnss_alignment.duration_s == 300.0


@pytest.mark.parametrize(
    ("table", "key", "value", "needle"),
    [
        ("run", "positions", "2", "[run] positions = 2"),
        ("run", "dwell_s", "0", "[run] dwell_s = 0.0"),
        ("run", "dwell_s", "-5.0", "[run] dwell_s = -5.0"),
        ("run", "order", '"random"', "[run] order = 'random'"),
        ("imu", "rate_hz", "333", "[imu] rate_hz = 333"),
        ("accelerometer", "node_id", "200", "[accelerometer] node_id = 200"),
        ("accelerometer", "bitrate", "123", "[accelerometer] bitrate = 123"),
        ("turntable", "address", "0", "[turntable] address = 0"),
        ("site", "latitude_deg", "90.0", "[site] latitude_deg = 90.0"),
        ("estimator", "method", '"magic"', "[estimator] method = 'magic'"),
        ("run", "positions", '"eight"', "[run] positions = 'eight'"),
        ("turntable", "allow_home", '"yes"', "[turntable] allow_home = 'yes'"),
    ],
)
def test_out_of_range_values_name_key_value_and_what_is_allowed(tmp_path, table, key, value, needle):
    p = tmp_path / "bench.toml"
    p.write_text(f"[{table}]\n{key} = {value}\n")
    with pytest.raises(ConfigError) as err:
        bench.load(p)
    msg = str(err.value)
    assert needle in msg and str(p) in msg
    assert "\n" not in msg
    assert "use" in msg  # says what is allowed


def test_toml_syntax_error_names_file_and_line(tmp_path):
    p = tmp_path / "bench.toml"
    p.write_text("[turntable]\nport = /dev/ttyUSB0\n")
    with pytest.raises(ConfigError) as err:
        bench.load(p)
    assert str(p) in str(err.value) and "line 2" in str(err.value)


def test_unknown_table_and_key_are_named(tmp_path):
    p = tmp_path / "bench.toml"
    p.write_text("[turntabel]\nport = 'x'\n")
    with pytest.raises(ConfigError, match=r"unknown table \[turntabel\]"):
        bench.load(p)
    p.write_text("[run]\ndwell = 3\n")
    with pytest.raises(ConfigError, match=r"unknown key \[run\] dwell"):
        bench.load(p)


def test_a_retired_key_of_an_older_bench_file_is_read_and_ignored(tmp_path):
    p = tmp_path / "bench.toml"
    p.write_text("[imu]\nport = '/dev/ttyUSB1'\nlink_timeout_s = 1.0\n")
    cfg = bench.load(p)
    assert cfg.imu.port == "/dev/ttyUSB1" and not hasattr(cfg.imu, "link_timeout_s")
    assert "link_timeout_s" not in cfg.to_dict()["imu"]


def test_missing_file_is_one_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="no such configuration file"):
        bench.load(tmp_path / "nope.toml")


def test_same_port_for_two_devices_is_refused(tmp_path):
    p = tmp_path / "bench.toml"
    p.write_text(
        "[turntable]\nport = '/dev/ttyUSB1'\n[imu]\nport = '/dev/ttyUSB1'\n"
        "[accelerometer]\nchannel = '/dev/ttyACM0'\n[site]\nlatitude_deg = 40.0\n"
    )
    cfg = bench.load(p)
    with pytest.raises(ConfigError, match=r"\[imu\] port = '/dev/ttyUSB1' is also \[turntable\] port"):
        bench.require_ports(cfg)


def test_missing_latitude_is_refused_for_a_real_run(tmp_path):
    p = tmp_path / "bench.toml"
    p.write_text("[turntable]\nport = 'a'\n[imu]\nport = 'b'\n[accelerometer]\nchannel = 'c'\n")
    with pytest.raises(ConfigError, match=r"\[site\] latitude_deg is missing"):
        bench.require_ports(bench.load(p))


@pytest.mark.parametrize("n", [3, 4, 5, 8, 12])
@pytest.mark.parametrize("order", bench.ORDERS)
def test_position_plan_visits_every_equally_spaced_angle_once(n, order):
    plan = bench.position_plan_deg(n, 10.0, order)
    assert sorted(plan) == pytest.approx([10.0 + k * 360.0 / n for k in range(n)])
    assert plan[0] == 10.0


def test_alternating_order_visits_opposite_pairs():
    plan = bench.position_plan_deg(8, 0.0, "alternating")
    assert plan[:4] == [0.0, 180.0, 45.0, 225.0]


def _cli(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run(
        [sys.executable, "-m", "northfinder", *argv],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=60,
        env=env,
    )


def _one_line_error(proc: subprocess.CompletedProcess[str]) -> str:
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    return lines[0]


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--simulate", "--positions", "2"], "--positions 2: use at least 3 positions"),
        (["--simulate", "--dwell", "0"], "--dwell 0: use a dwell greater than 0 s"),
        (["--simulate", "--dwell", "-1"], "--dwell -1: use a dwell greater than 0 s"),
    ],
)
def test_cli_flag_mistakes_are_one_line(tmp_path, argv, needle):
    line = _one_line_error(_cli("find", *argv, "--out", str(tmp_path / "run"), cwd=tmp_path))
    assert needle in line


def test_cli_malformed_bench_toml_is_one_line(tmp_path):
    p = tmp_path / "bench.toml"
    p.write_text("[run]\npositions = = 3\n")
    line = _one_line_error(_cli("find", "--config", str(p), cwd=tmp_path))
    assert str(p) in line and "line 2" in line


def test_cli_bench_toml_with_n_below_3_is_one_line(tmp_path):
    p = tmp_path / "bench.toml"
    p.write_text("[run]\npositions = 2\n")
    line = _one_line_error(_cli("check", "--config", str(p), cwd=tmp_path))
    assert "[run] positions = 2" in line
