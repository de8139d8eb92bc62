"""`northfinder align` as a user meets it: the help text, and a failed start that leaves nothing
behind (issue 12's rough edges on the align side)."""

from __future__ import annotations

import os

import pytest
from helpers import northfinder_line

from northfinder.cli import main
from northfinder.devices import registry
from northfinder.devices.registry import ModelSpec
from northfinder.errors import DeviceError


def test_align_help_describes_both_modes_and_every_simulator_flag(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["align", "--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())  # argparse wraps to the terminal width
    assert "Find true north with a strapdown IMU and no turntable" in text
    assert "--mode swaying the IMU alone on a swaying base" in text
    assert "--mode gnss the IMU and an NMEA GNSS receiver" in text
    assert "--seed N the simulator's random seed: the same seed draws the same sensor noise (default 1)" in (
        text
    )
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


def test_the_bench_file_sets_the_align_defaults_and_flags_override_them(tmp_path, capsys):
    """[swaying] and [gnss_alignment] are read by the one configuration; a value there is used
    (a too-short window is named by file and key) and the flag wins over it."""
    cfg = tmp_path / "bench.toml"
    port = tmp_path / "no-such-tty"
    head = f'[imu]\nport = "{port}"\n[site]\nlatitude_deg = 40.0\n'
    out = tmp_path / "run"
    sway = ["align", "--mode", "swaying", "--config", str(cfg), "--out", str(out)]
    cfg.write_text(head + "[swaying]\nduration_s = 50.0\nsway_period_s = 10.0\n")
    assert main(sway) == 2
    line = northfinder_line(capsys.readouterr().err)
    assert f"{cfg}: [swaying] duration_s = 50: too short for the swaying alignment" in line
    assert "needs at least 80 device seconds" in line
    # the flag overrides the file: past the checks, the (missing) port is the next mistake
    assert main([*sway, "--duration", "90"]) == 3
    assert str(port) in northfinder_line(capsys.readouterr().err)
    assert not out.exists()
    cfg.write_text(head + '[swaying]\nmethod = "kalman"\n')
    assert main(sway) == 2
    line = northfinder_line(capsys.readouterr().err)
    assert "[swaying] method = 'kalman' is not allowed; use one of cone" in line
    cfg.write_text(f'[imu]\nport = "{port}"\n[gnss]\nport = "{port}-g"\n[gnss_alignment]\nduration_s = 5.0\n')
    assert main(["align", "--mode", "gnss", "--config", str(cfg), "--out", str(out)]) == 2
    line = northfinder_line(capsys.readouterr().err)
    assert "[gnss_alignment] duration_s = 5.0 is not allowed; use at least 10 device seconds" in line


# -- the models bench.toml names reach the align runs on hardware ------------------------------------
class _ProbeImu:
    """An IMU model that opens (so the GNSS receiver is opened next) and does nothing else."""

    def __init__(self, options):
        self._transport = options.get("transport")

    def configure_for_run(self, rate_hz):
        """Nothing to configure."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._transport is not None:
            self._transport.close()


def _open_probe(role: str, succeed: bool):
    def open_(section, log_path, options):
        if succeed:
            return _ProbeImu(options)
        port = section["port"] if isinstance(section, dict) else section.port  # a dict or a config section
        raise DeviceError(role, port, f"the probe-{role} model was opened")

    return open_


PROBE_SWAYING_IMU = ModelSpec("imu", "probe-imu", _open_probe("imu", succeed=False))
PROBE_GNSS_IMU = ModelSpec("imu", "probe-imu", _open_probe("imu", succeed=True))
PROBE_GNSS = ModelSpec("gnss", "probe-gnss", _open_probe("gnss", succeed=False))


@pytest.fixture
def probe_models(monkeypatch):
    """Register this module's probe models as built-ins for one test (the registry loads a built-in
    by import path; this test module is importable by its name from tests/)."""
    def register(role: str, name: str, attr: str) -> None:
        monkeypatch.setitem(registry.BUILTIN, f"{role}/{name}", f"{__name__}:{attr}")

    yield register
    monkeypatch.undo()
    registry.refresh()


def test_align_swaying_on_hardware_opens_the_imu_model_of_bench_toml(tmp_path, capsys, probe_models):
    probe_models("imu", "probe-imu", "PROBE_SWAYING_IMU")
    cfg = tmp_path / "bench.toml"
    cfg.write_text(f'[imu]\nmodel = "probe-imu"\nport = "{tmp_path / "imu"}"\n[site]\nlatitude_deg = 40.0\n')
    assert main(["align", "--mode", "swaying", "--config", str(cfg), "--out", str(tmp_path / "run")]) == 3
    assert "the probe-imu model was opened" in northfinder_line(capsys.readouterr().err)


def test_align_gnss_on_hardware_opens_the_imu_and_gnss_models_of_bench_toml(tmp_path, capsys, probe_models):
    probe_models("imu", "probe-imu", "PROBE_GNSS_IMU")
    probe_models("gnss", "probe-gnss", "PROBE_GNSS")
    fds = [os.openpty() for _ in range(2)]  # real ports: the run opens its stamped transports on them
    try:
        imu_port, gnss_port = (os.ttyname(slave) for _, slave in fds)
        cfg = tmp_path / "bench.toml"
        cfg.write_text(f'[imu]\nmodel = "probe-imu"\nport = "{imu_port}"\n'
                       f'[gnss]\nmodel = "probe-gnss"\nport = "{gnss_port}"\n')
        assert main(["align", "--mode", "gnss", "--config", str(cfg), "--out", str(tmp_path / "run")]) == 3
    finally:
        for fd in (fd for pair in fds for fd in pair):
            os.close(fd)
    assert "the probe-gnss model was opened" in northfinder_line(capsys.readouterr().err)
