"""A lab's own model through the `northfinder.models` entry-point group, end to end.

tests/oot_stage is a package out of northfinder's tree (its own pyproject.toml, its own serial code
for a stage), installed into a temporary directory (package + dist-info with its entry points); a
find then runs on firmware-sim with `[turntable] model = "labstage"`, which northfinder can only
find through the package's entry point.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from helpers import read_events, subprocess_env

from northfinder.devices import registry
from northfinder.simulate import SimSettings, SimulatorProcess

PACKAGE = Path(__file__).parent / "oot_stage"
TIME_SCALE = 10.0
FAST_STAGE_TOML = "stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """tests/oot_stage installed into a folder the way a wheel installs: the package, and a
    `labstage-0.1.0.dist-info` with METADATA and the entry points its pyproject.toml declares — what
    importlib.metadata (and so the registry) finds on sys.path. (Not pip: the test venv has no
    `wheel` for setuptools to build one offline.)"""
    target = tmp_path_factory.mktemp("oot") / "site"
    shutil.copytree(PACKAGE / "labstage", target / "labstage")
    project = tomllib.loads((PACKAGE / "pyproject.toml").read_text())["project"]
    info = target / f"{project['name']}-{project['version']}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\n"
                                   f"Version: {project['version']}\n")
    lines = [f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items())
             for group, entries in project["entry-points"].items()]
    (info / "entry_points.txt").write_text("\n".join(lines))
    (info / "top_level.txt").write_text("labstage\n")
    return target


def _env(site: Path) -> dict[str, str]:
    env = subprocess_env()
    env["PYTHONPATH"] = os.pathsep.join([str(site), env["PYTHONPATH"]])
    return env


def test_the_model_is_unknown_until_its_package_is_installed():
    with pytest.raises(Exception, match="labstage"):
        registry.spec("turntable", "labstage")


def test_find_on_a_stage_model_from_another_package(tmp_path, site):
    listed = subprocess.run(
        [sys.executable, "-c",
         "from northfinder.devices import registry; print(registry.available('turntable'))"],
        capture_output=True, text=True, env=_env(site), timeout=60)
    assert "labstage" in listed.stdout, listed.stderr
    sim_toml = tmp_path / "sim.toml"
    sim_toml.write_text(FAST_STAGE_TOML)
    with SimulatorProcess(SimSettings(heading_deg=37.0, time_scale=TIME_SCALE, config=str(sim_toml))) as ep:
        bench = tmp_path / "bench.toml"
        bench.write_text(
            f"[turntable]\nmodel = 'labstage'\nport = '{ep['turntable']}'\n[imu]\nport = '{ep['imu']}'\n"
            f"[accelerometer]\ninterface = 'slcan'\nchannel = '{ep['can']['channel']}'\n"
            "bus_options = {sleep_after_open = 0.05}\n"
            "[site]\nlatitude_deg = 40.0\n[run]\npositions = 4\ndwell_s = 2.0\nplan = 'positions'\n"
        )
        run = tmp_path / "run"
        argv = ["find", "--config", str(bench), "--out", str(run), "--no-report"]
        proc = subprocess.run([sys.executable, "-m", "northfinder", *argv], capture_output=True, text=True,
                              cwd=tmp_path, env=_env(site), timeout=300)
    assert proc.returncode == 0, proc.stderr
    start = next(e for e in read_events(run) if e["event"] == "start")
    assert start["turntable"]["model"] == "labstage"
    assert json.loads((run / "config.json").read_text())["bench"]["turntable"]["model"] == "labstage"
    result = json.loads((run / "result.json").read_text())
    assert result["complete"] and result["positions_measured"] == 4
    assert "> 1PA" in (run / "turntable.log").read_text()  # the lab's own code drove the stage
    print(f"find on labstage: heading {result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}° "
          f"(truth 37°)")
    replay = subprocess.run([sys.executable, "-m", "northfinder", "replay", str(run), "--quiet"],
                            capture_output=True, text=True, env=_env(site), timeout=120)
    assert replay.returncode == 0 and "identical" in replay.stdout, replay.stdout + replay.stderr
