"""End to end with the KVH unit's whole dialogue in the stream (issue 23): firmware-sim with the
imu-dialogue-rate fault puts echoes, query replies, INVALID lines and BIT messages between the
data messages, and sends each new client the power-up BIT message first. `northfinder check`
reports that BIT; an 8-position find counts exactly the samples the raw IMU log, scanned
independently of northfinder's decoder (every header, every CRC), shows lost: none on a quiet
host, and never one for a line of text or a BIT message."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import run_cli

from northfinder.codecs import kvh
from northfinder.rundir import RunDir
from northfinder.simulate import SimSettings, SimulatorProcess, bench_config

pytestmark = pytest.mark.slow

DIALOGUE_RATE = 0.003  # per message: ~3 text lines or BIT messages per device second at 1 kHz
FAST_STAGE_TOML = "stage_speed_dps = 90.0\nstage_accel_dps2 = 360.0\nstage_ringing_decay_s = 0.1\n"


def _scan_frames(raw: bytes) -> np.ndarray:
    """Sequence numbers of every good frame in `raw`, found by brute force (every header position,
    the byte-loop reference CRC): a loss count that does not lean on KvhDecoder."""
    seqs, p = [], raw.find(kvh.HEADER)
    while p >= 0 and p + 36 <= len(raw):
        frame = raw[p:p + 36]
        if kvh.crc32_mpeg2(frame[:32]) == int.from_bytes(frame[32:], "big"):
            seqs.append(frame[29])
            p = raw.find(kvh.HEADER, p + 36)
        else:
            p = raw.find(kvh.HEADER, p + 1)
    return np.array(seqs, dtype=np.int64)


def _truth_events(path: Path, name: str) -> list[dict]:
    out = []
    for line in path.read_text().splitlines():
        rec = json.loads(line)
        if rec.get("event") == name:
            out.append(rec)
    return out


def test_check_and_find_with_the_dialogue_in_the_stream(tmp_path):
    from northfinder.runs.find import measure

    truth_log = tmp_path / "truth.jsonl"
    sim_toml = tmp_path / "sim.toml"
    sim_toml.write_text(FAST_STAGE_TOML + "accel_rate_hz = 50.0\n" + f"truth_log = '{truth_log}'\n")
    settings = SimSettings(time_scale=10.0, seed=5, config=str(sim_toml),
                           faults=(f"imu-dialogue-rate={DIALOGUE_RATE}",))
    run_dir = tmp_path / "run"
    with SimulatorProcess(settings) as ep:
        toml = tmp_path / "bench.toml"
        toml.write_text(
            f"[turntable]\nport = '{ep['turntable']}'\n[imu]\nport = '{ep['imu']}'\n"
            f"[accelerometer]\ninterface = 'slcan'\nchannel = '{ep['can']['channel']}'\n"
            "bus_options = {sleep_after_open = 0.05}\n[site]\nlatitude_deg = 40.0\n")
        check = run_cli("check", "--config", str(toml), cwd=tmp_path)
        assert check.returncode == 0, check.stdout + check.stderr
        imu_line = next(ln for ln in check.stdout.splitlines() if f"imu on {ep['imu']}" in ln)
        print(imu_line)
        assert "power-up BIT 7F 7F 7F 7F 7F 7F: all passed" in imu_line

        cfg = bench_config(ep, settings.latitude_deg)
        cfg.accelerometer.rate_hz = 50.0
        cfg.run.positions = 8
        cfg.run.dwell_s = 3.0
        result = measure(cfg.validate(), RunDir(run_dir), settings=settings, report=False,
                         can_kwargs={"sleep_after_open": 0.05})
    assert result["complete"] and result["positions_measured"] == 8
    imu = result["faults"]["imu"]
    # the bytes the counters saw: imu.raw goes on past the result (the reader runs until the close),
    # and a loaded host can overrun the pty there (a 91-step gap after the last counted frame, once)
    counted = [e for e in RunDir(run_dir, create=False).events() if e.get("event") == "stats"][-1]["imu"]
    raw = (run_dir / "imu.raw").read_bytes()[:counted["bytes"]]
    seq = _scan_frames(raw)
    assert len(seq) == imu["frames"] == counted["frames"]
    step = np.diff(seq) % 128
    step[step == 0] = 128  # the same number again: a whole wrap went missing
    true_lost = int((step - 1).sum())  # what the line really lost (a loaded host can overrun the pty)
    dialogue = _truth_events(truth_log, "imu_dialogue")
    inserted = sum(e.get("lines", e.get("fields", {}).get("lines", 0)) for e in dialogue)
    bit_in_raw = len(kvh.find_bit_messages(raw))
    print(f"find: counted lost {imu['lost_samples']} (in dwells {imu['lost_in_dwells']}), truly lost in "
          f"the raw log's counted bytes {true_lost}; {len(seq)} frames, {inserted} dialogue insertions "
          f"by the sim (whole run), {bit_in_raw} BIT messages and {raw.count(b'INVALID,')} INVALID lines in "
          f"imu.raw, {imu['resyncs']} resyncs, {imu['skipped_bytes']} skipped bytes")
    assert inserted > 0 and bit_in_raw > 0 and b"INVALID,=FOO\r\n" in raw  # the dialogue was there
    assert imu["lost_samples"] == true_lost and imu["bad_crc"] == 0  # nothing counted lost that was not
    assert sum(p["lost_samples"] for p in result["positions"]) == imu["lost_in_dwells"] <= true_lost
    for p in result["positions"]:
        assert p["samples"] == 3000
