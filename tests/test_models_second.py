"""The second model of each role (issue 24): Thorlabs APT stage, Sensonor STIM IMU, CiA 410
inclinometer — their drivers' pure parts, `check` on firmware-sim, and finds on firmware-sim (each
model with the others at their defaults, and the mixed bench), with the faults that apply.

Finds are short in device time (4 × 3 s) at time scale 10 on the stiffer simulated stage; the
accuracy tolerances come from the noise limit of docs/CONVENTIONS.md for the grade's ARW in
northfinder's own grade table (estimators.plan.GRADES), never from a printed run.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli, start_sim

from northfinder.codecs import apt, stim
from northfinder.devices import registry
from northfinder.errors import DeviceError
from northfinder.estimators.limits import noise_limit_heading_std_deg
from northfinder.estimators.plan import GRADES
from northfinder.models.apt import state_from_bits
from northfinder.models.cia410 import SATURATED, SlopeDecoder, slopes_to_block
from northfinder.models.stim import StimConfig, StimStream, config_from_listing
from northfinder.rotations import tilt_and_azimuth
from northfinder.rundir import RESULT, jsonable
from northfinder.runs.find import replay

POSITIONS, DWELL_S, TIME_SCALE = 4, 3.0, 10.0
FAST_STAGE_TOML = "stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n"
SIGMA_TOLERANCE = 0.20

LISTING = (
    "SERIAL NUMBER = N25582405002002\r\nPRODUCT = STIM300\r\nPART NUMBER = 84167-4400003-321 REV K\r\n"
    "GYRO OUTPUT UNIT = [°] – INCREMENTAL ANGLE\r\n"
    "ACCELEROMETER OUTPUT UNIT = [m/s] – INCREMENTAL VELOCITY\r\n"
    "SAMPLE RATE [samples/s] = 500\r\nACCELEROMETER RANGE:\r\n X-AXIS: ± 10g\r\n Y-AXIS: ± 10g\r\n"
    " Z-AXIS: ± 10g\r\nDATAGRAM = 0x93\r\n"
)


# -- pure parts ---------------------------------------------------------------------------------
def test_the_registry_knows_each_second_model_by_the_name_firmware_sim_uses():
    assert registry.available("turntable")[:2] == ["smc100", "apt"]
    assert registry.available("imu")[:2] == ["kvh", "stim"]
    assert registry.available("accelerometer")[:2] == ["nf-accel", "cia410"]
    assert registry.decoder_for("imu", "stim") is not None
    assert registry.decoder_for("accelerometer", "cia410") is not None


def test_apt_status_bits_map_to_the_stage_role():
    homed = apt.SB_ENABLED | apt.SB_HOMED | apt.SB_SETTLED | apt.SB_CONNECTED
    st = state_from_bits(homed)
    assert st.ready and st.referenced and not st.moving and st.fault is None
    # a move just commanded: not ready until MOVE_COMPLETED, even before the in-motion bits show
    assert not state_from_bits(homed, apt.MOT_MOVE_COMPLETED).ready
    assert state_from_bits(homed, apt.MOT_MOVE_HOMED).homing
    stalled = state_from_bits(apt.SB_HOMED | apt.SB_POSITION_ERROR | apt.SB_ERROR)
    assert not stalled.ready and stalled.fault == "position error, error"
    assert state_from_bits(apt.SB_HOMED).fault == "channel disabled"


def test_stim_listing_gives_units_rate_datagram_and_refuses_what_cannot_be_scaled():
    ident, cfg = config_from_listing(LISTING)
    assert ident.describe() == "Sensonor STIM300 s/n N25582405002002 p/n 84167-4400003-321 REV K"
    assert cfg == StimConfig(0x93, "increment", "increment", 10, 500)
    with pytest.raises(ValueError, match="AVERAGE"):
        config_from_listing(LISTING.replace("[°] – INCREMENTAL ANGLE", "[°/s] – AVERAGE ANGULAR RATE"))
    with pytest.raises(ValueError, match="range"):
        config_from_listing(LISTING.replace(" Z-AXIS: ± 10g", " Z-AXIS: ± 30g"))


def _datagrams(cfg: StimConfig, n: int, first: int = 1) -> list[bytes]:
    step = stim.INTERNAL_RATE_HZ // cfg.rate_hz
    k = first + np.arange(n)
    raw = stim.encode_datagrams(
        cfg.datagram_id, np.full((n, 3), 1e-4), 0, k * step, 500, cfg.units, accel=np.full((n, 3), 0.001)
    )
    size = stim.datagram_length(cfg.datagram_id)
    return [raw[i * size : (i + 1) * size] for i in range(n)]


def test_stim_counter_gives_the_index_a_spoiled_datagram_is_an_exact_gap_a_silence_an_unknown_one():
    cfg = StimConfig(0x93, "increment", "increment", 10, 500)  # counter steps 4: wraps every 64 datagrams
    dg = _datagrams(cfg, 200)
    spoiled = bytearray(dg[10])
    spoiled[5] ^= 0xFF
    stream_bytes = (
        b"".join(dg[:10]) + bytes(spoiled) + b"".join(dg[11:100]) + b"".join(dg[170:])
    )  # 70 never came
    whole = StimStream(cfg)
    index, s = whole.feed(stream_bytes)
    assert list(index[:3]) == [1, 2, 3] and 11 not in index and index[10] == 12
    assert whole.decoder.stats.crc_errors == 1 and whole.lost_samples >= 1
    assert whole.unknown_gaps == [
        int(index[99])
    ]  # after the silence: the counter alone cannot tell 70 from 6
    assert index[99] - index[98] == 71 % 64  # what the counter shows: 71 steps, seen as 7
    chunked = StimStream(cfg)  # the same indices whatever the chunks (live reads ≠ replay's one read)
    rng = np.random.default_rng(3)
    cuts = np.sort(rng.integers(0, len(stream_bytes), 25))
    parts = [
        chunked.feed(stream_bytes[a:b])[0]
        for a, b in zip([0, *cuts], [*cuts, len(stream_bytes)], strict=True)
    ]
    assert np.array_equal(np.concatenate(parts), index) and chunked.unknown_gaps == whole.unknown_gaps


def test_stim_stream_never_raises_on_bad_bytes_and_counts_them():
    cfg = StimConfig(0x93, "rate", "acceleration", 10, 1000)
    rng = np.random.default_rng(24)
    good = b"".join(_datagrams(cfg, 50))
    for _ in range(30):
        noise = rng.integers(0, 256, int(rng.integers(0, 400)), dtype=np.uint8).tobytes()
        data = bytearray(noise + good + noise)
        for pos in rng.integers(0, len(data), 5):
            data[pos] = int(rng.integers(0, 256))
        st = StimStream(cfg)
        index, s = st.feed(bytes(data))
        counters = st.stats()
        assert counters["frames"] == len(index) <= 50 and np.all(np.diff(index) > 0)
        assert counters["skipped_bytes"] + counters["frames"] * st.size + st.decoder.pending_bytes == len(
            data
        )


def test_cia410_slopes_counter_saturation_and_malformed_frames():
    dec = SlopeDecoder(0x10)
    frames = [
        (0x190, (1000).to_bytes(2, "little", signed=True) + (-500).to_bytes(2, "little", signed=True)),
        (0x190, b"\x01\x02\x03"),  # malformed: counted, no sample
        (0x710, b"\x05"),  # a heartbeat: not a sample
        (0x190, (32767).to_bytes(2, "little", signed=True) + (0).to_bytes(2, "little", signed=True)),
    ]
    assert [dec.feed(i, d) for i, d in frames] == [True, False, False, True]
    assert dec.stats.malformed == 1 and dec.stats.frames == 2
    counter, counts = dec.drain()
    block = slopes_to_block(counter, counts, 1)
    assert list(block.counter) == [0, 1]
    f = block.accel_g[0]
    assert f == pytest.approx(
        [
            np.sin(np.radians(1.0)),
            np.sin(np.radians(-0.5)),
            np.sqrt(1 - np.sin(np.radians(1.0)) ** 2 - np.sin(np.radians(0.5)) ** 2),
        ]
    )
    assert block.status[1] == SATURATED and np.isnan(block.accel_g[1, 0]) and np.isnan(block.accel_g[1, 2])


# -- on firmware-sim ------------------------------------------------------------------------------
def test_check_names_each_second_model_and_the_identity_it_reports(tmp_path):
    sim = start_sim(
        "--stage", "apt", "--imu", "stim", "--tilt", "cia410", "--grade", "stim300", "--time-scale", "5"
    )
    try:
        ep = json.loads(sim.stdout.readline())
        can = ep["can"]
        bench = tmp_path / "bench.toml"
        bench.write_text(
            f'[turntable]\nmodel = "apt"\nport = "{ep["turntable"]}"\n'
            f'[imu]\nmodel = "stim"\nport = "{ep["imu"]}"\n'
            f'[accelerometer]\nmodel = "cia410"\ninterface = "slcan"\nchannel = "{can["channel"]}"\n'
            f"node_id = {can['node_id']}\nbus_options = {{sleep_after_open = 0.05}}\n"
            "[site]\nlatitude_deg = 40.0\n"
        )
        out = run_cli("check", "--config", str(bench), cwd=tmp_path, timeout_s=90)
    finally:
        sim.terminate()
        sim.wait(timeout=10)
    assert out.returncode == 0, out.stderr
    stage, imu, acc = out.stdout.splitlines()[:3]
    assert (
        stage.startswith("ok") and "Thorlabs KDC101 s/n 27000001" in stage and stage.endswith("[model apt]")
    )
    assert (
        "Sensonor STIM300 s/n N25582405002002" in imu
        and "datagram 0x93" in imu
        and imu.endswith("[model stim]")
    )
    assert (
        "CiA 410 inclinometer (device type 0x0000019A)" in acc and "6010:0 (16 bit), 6020:0 (16 bit)" in acc
    )
    assert acc.endswith("[model cia410]")


def _limit_deg(result: dict, grade: str) -> float:
    t = result["truth"]
    tilt, tilt_az = tilt_and_azimuth(*np.deg2rad([t["heading_deg"], t["pitch_deg"], t["roll_deg"]]))
    motion = result["motion_fit"]
    used_s = motion["samples"]["used_device_s"] if motion["available"] else result["duration_device_s"]
    return float(
        noise_limit_heading_std_deg(
            GRADES[grade].arw_deg_rt_h,
            used_s,
            result["latitude_deg"],
            np.rad2deg(tilt),
            np.rad2deg(tilt_az),
            gyro_axes=2,
        )
    )


def _find(tmp_path: Path, models: dict[str, str], grade: str, *faults: str) -> tuple[dict, Path]:
    sim_toml = tmp_path / "fast.toml"
    sim_toml.write_text(FAST_STAGE_TOML)
    run_dir = tmp_path / "run"
    argv = [
        "find",
        "--simulate",
        "--positions",
        str(POSITIONS),
        "--dwell",
        str(DWELL_S),
        "--time-scale",
        str(TIME_SCALE),
        "--grade",
        grade,
        "--sim-config",
        str(sim_toml),
        "--no-report",
        "--out",
        str(run_dir),
    ]
    for role, name in models.items():
        argv += [f"--{role}", name]
    for fault in faults:
        argv += ["--fault", fault]
    out = run_cli(*argv, cwd=tmp_path, timeout_s=240)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads((run_dir / RESULT).read_text()), run_dir


def _check(result: dict, run_dir: Path, grade: str, models: dict[str, str]) -> None:
    assert result["complete"] and result["positions_measured"] == POSITIONS
    roles = {"stage": "turntable", "imu": "imu", "tilt": "accelerometer"}
    assert {roles[r]: m for r, m in models.items()}.items() <= {
        r: d["model"] for r, d in result["devices"].items()
    }.items()
    err = (result["heading_deg"] - result["truth"]["heading_deg"] + 180.0) % 360.0 - 180.0
    sigma, limit = result["heading_std_deg"], _limit_deg(result, grade)
    assert abs(err) < 3.0 * sigma, (err, sigma)
    assert abs(sigma / limit - 1.0) < SIGMA_TOLERANCE, (sigma, limit)
    again = replay(run_dir)
    assert json.loads(json.dumps(jsonable(again.result))) == json.loads((run_dir / RESULT).read_text())


@pytest.mark.slow
def test_apt_stage_finds_north_and_a_stall_is_retried_after_re_enabling(tmp_path):
    models = {"stage": "apt"}
    result, run_dir = _find(tmp_path, models, "nav", "stage-stall=2")
    _check(result, run_dir, "nav", models)
    assert result["devices"]["turntable"]["identity"]["controller"].startswith("Thorlabs KDC101")
    errors = result["faults"]["stage_errors"]
    assert len(errors) == 1 and "position error, error" in errors[0]["error"], errors


@pytest.mark.slow
def test_stim_finds_north_with_corrupt_and_flagged_datagrams_counted(tmp_path):
    models = {"imu": "stim"}
    result, run_dir = _find(tmp_path, models, "stim300", "imu-crc-rate=0.002", "imu-invalid-rate=0.002")
    _check(result, run_dir, "stim300", models)
    imu = result["faults"]["imu"]
    assert imu["bad_crc"] > 0 and imu["lost_samples"] >= imu["bad_crc"], imu
    assert sum(imu["invalid_samples"].values()) > 0 and sum(imu["invalid_in_dwells"].values()) > 0, imu
    assert result["devices"]["imu"]["identity"]["unit"].startswith("Sensonor STIM300")


@pytest.mark.slow
def test_cia410_inclinometer_gives_the_tilt(tmp_path):
    models = {"tilt": "cia410"}
    result, run_dir = _find(tmp_path, models, "nav")
    _check(result, run_dir, "nav", models)
    assert result["tilt"]["pitch_deg"] == pytest.approx(result["truth"]["pitch_deg"], abs=0.01)
    assert result["tilt"]["roll_deg"] == pytest.approx(result["truth"]["roll_deg"], abs=0.01)


@pytest.mark.slow
def test_mixed_bench_apt_stim_cia410_in_one_find(tmp_path):
    models = {"stage": "apt", "imu": "stim", "tilt": "cia410"}
    result, run_dir = _find(tmp_path, models, "stim300")
    _check(result, run_dir, "stim300", models)
    assert json.loads((run_dir / "config.json").read_text())["simulate"]["models"] == {
        "stage": "apt",
        "imu": "stim",
        "tilt": "cia410",
    }


def test_a_stim_asked_for_another_rate_is_one_line(tmp_path):
    sim = start_sim("--imu", "stim", "--imu-rate", "500", "--time-scale", "5")
    try:
        ep = json.loads(sim.stdout.readline())
        spec = registry.spec("imu", "stim")
        with (
            spec.open({"port": ep["imu"]}, None, {}) as imu,
            pytest.raises(DeviceError, match="set rate_hz = 500"),
        ):
            imu.configure_for_run(1000)
    finally:
        sim.terminate()
        sim.wait(timeout=10)
