"""The second model of each role (issue 24): Thorlabs APT stage, Sensonor STIM IMU, CiA 410
inclinometer — their drivers' pure parts (status bits, the STIM listing, counter and gaps, fuzzing
of the STIM stream, the CiA 410 slopes) and `check` on firmware-sim. The finds are in
tests/test_models_second_finds.py.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers import run_cli, start_sim

from northfinder.codecs import apt, stim
from northfinder.devices import registry
from northfinder.errors import DeviceError
from northfinder.models.apt import state_from_bits
from northfinder.models.cia410 import SATURATED, SlopeDecoder, slopes_to_block
from northfinder.models.stim import StimConfig, StimStream, config_from_listing, listing_text

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
    # datagrams still in flight (or left in the port by an earlier session) run into the first line;
    # a CRC ending in "A " once made its key "A SERIAL NUMBER"
    for glued in (b"\x93\x00\x05=\xff", b"\x93\x00\x41 ", b"\x93Z-"):
        assert config_from_listing(listing_text(glued + LISTING.encode()))[1] == cfg
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
def test_check_and_find_config_on_a_bench_toml_naming_the_second_models(tmp_path):
    """`check` names each model and the identity it reports; `find --config` on the same bench.toml
    runs them (3 × 1 s on the stiffer stage) and its result names each model."""
    fast = tmp_path / "fast.toml"
    fast.write_text("stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n")
    sim = start_sim("--stage", "apt", "--imu", "stim", "--tilt", "cia410", "--grade", "stim300",
                    "--time-scale", "5", "--accel-rate", "50", "--config", str(fast))
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
        found = run_cli("find", "--config", str(bench), "--positions", "3", "--dwell", "1", "--no-report",
                        "--out", str(tmp_path / "run"), cwd=tmp_path, timeout_s=120)
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
    assert found.returncode == 0, found.stderr[-1500:]
    devices = json.loads((tmp_path / "run" / "result.json").read_text())["devices"]
    assert {r: d["model"] for r, d in devices.items()} == {
        "turntable": "apt", "imu": "stim", "accelerometer": "cia410"}


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
