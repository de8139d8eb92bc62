"""`northfinder align` as a user meets it: the help text, and a failed start that leaves nothing
behind (issue 12's rough edges on the align side)."""

from __future__ import annotations

import pytest
from helpers import northfinder_line

from northfinder.cli import main


def test_align_help_describes_both_modes_and_every_simulator_flag(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["align", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps to the terminal width
    assert "Find true north with a strapdown IMU and no turntable" in text
    assert "--mode swaying the IMU alone on a swaying base" in text
    assert "--mode gnss the IMU and an NMEA GNSS receiver" in text
    assert "--seed SEED simulator noise seed (default 1)" in text
    assert "--time-scale K simulated device time runs K× the wall clock (default: 40 swaying, 20 gnss)" in (
        text
    )


@pytest.mark.parametrize("mode", ["swaying", "gnss"])
def test_a_port_that_does_not_exist_leaves_no_run_directory(mode, tmp_path, capsys):
    """The run directory is made before the devices open; when the IMU's port is not there, the
    one-line error is all that is left (config.json and an empty raw log are removed with it)."""
    cfg = tmp_path / "bench.toml"
    missing = tmp_path / "no-such-tty"
    cfg.write_text(
        f'[imu]\nport = "{missing}"\n[gnss]\nport = "{missing}-gnss"\n[site]\nlatitude_deg = 40.0\n'
    )
    out = tmp_path / "runs" / "run"
    assert main(["align", "--mode", mode, "--config", str(cfg), "--out", str(out)]) == 3
    line = northfinder_line(capsys.readouterr().err)
    assert "imu" in line and str(missing) in line
    assert not out.exists()
    assert (tmp_path / "runs").exists()  # only the directory this run made is removed


def test_an_existing_directory_given_as_out_is_never_removed(tmp_path, capsys):
    """--out naming a directory that was there before (the user's own) stays, whatever it holds."""
    cfg = tmp_path / "bench.toml"
    cfg.write_text(f'[imu]\nport = "{tmp_path / "no-such-tty"}"\n[site]\nlatitude_deg = 40.0\n')
    out = tmp_path / "mine"
    out.mkdir()
    assert main(["align", "--mode", "swaying", "--config", str(cfg), "--out", str(out)]) == 3
    capsys.readouterr()
    assert out.is_dir()
