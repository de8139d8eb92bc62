"""The align estimators' latitude limit (northfinder.align.limits): one constant, one message, in
every align mode and on every path (flag, bench file, estimator), and nothing left behind."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import northfinder_line

from northfinder import config
from northfinder.align.coarse import coarse_align
from northfinder.align.limits import LATITUDE_ADVICE, LATITUDE_LIMIT_DEG, latitude_problem
from northfinder.align.swaying import align_swaying
from northfinder.cli import main
from northfinder.errors import InputError
from northfinder.estimators.heading import MAX_ABS_LATITUDE_DEG


def test_the_limit_is_inclusive_and_refuses_non_numbers():
    assert latitude_problem(LATITUDE_LIMIT_DEG) is None and latitude_problem(-LATITUDE_LIMIT_DEG) is None
    for bad in (np.nextafter(LATITUDE_LIMIT_DEG, 90.0), -90.0, 95.0, float("nan"), float("inf")):
        assert latitude_problem(bad) == LATITUDE_ADVICE
    assert LATITUDE_LIMIT_DEG < MAX_ABS_LATITUDE_DEG  # gyrocompassing on a moving base needs more


@pytest.mark.parametrize("mode", ["swaying", "gnss"])
def test_both_align_modes_refuse_the_same_latitude_with_the_same_line(mode, tmp_path, capsys):
    """`align --latitude 95` (the simulator itself would answer "[-90, 90]") stops before anything
    starts, with the align estimators' words, and leaves no run directory."""
    out = tmp_path / "run"
    rc = main(["align", "--mode", mode, "--simulate", "--latitude", "95", "--out", str(out)])
    assert rc == 2
    assert northfinder_line(capsys.readouterr().err).endswith(f"--latitude 95: {LATITUDE_ADVICE}")
    assert not out.exists()


def test_a_bench_file_latitude_beyond_the_align_limit_gives_the_same_advice(tmp_path, capsys):
    """87° is a valid site for the turntable find ([site] passes config's own check) but not for the
    swaying alignment: one line naming the file and key, with the same advice as --latitude."""
    cfg = tmp_path / "bench.toml"
    cfg.write_text('[imu]\nport = "/dev/ttyUSB7"\n[site]\nlatitude_deg = 87.0\n')
    assert config.load(cfg).site.latitude_deg == 87.0
    out = tmp_path / "run"
    assert main(["align", "--mode", "swaying", "--config", str(cfg), "--out", str(out)]) == 2
    line = northfinder_line(capsys.readouterr().err)
    assert f"{cfg}: [site] latitude_deg = 87.0 is not allowed; {LATITUDE_ADVICE}" in line
    with pytest.raises(config.ConfigError, match="use −89…89"):  # beyond the find's own limit
        config.from_dict({"site": {"latitude_deg": 89.5}})


def test_the_estimators_check_again_with_the_same_words():
    """A caller that skips the CLI (a tool, a test) still gets the estimator's own refusal."""
    n = 2000
    gyro = np.tile([1e-5, 0.0, 5e-5], (n, 1))
    accel = np.tile([0.0, 0.0, 1.0], (n, 1))
    with pytest.raises(InputError, match="latitude 87: use −85…85"):
        coarse_align(gyro, accel, 100.0, 87.0)
    with pytest.raises(InputError) as exc:
        align_swaying(gyro, accel, 100.0, -87.0)
    assert str(exc.value) == f"latitude -87: {LATITUDE_ADVICE}"
