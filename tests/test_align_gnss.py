"""`northfinder align --mode gnss` end to end: firmware-sim's vehicle (IMU pty + GNSS pty) in a
subprocess, the run directory, replay bit for bit, bad NMEA, Ctrl-C, user mistakes; and the host
receive-stamp time alignment against an exact identity.

Tolerances: the heading error against 3× the filter's own 1σ; the lever arm within 0.1 m and the
position within 2 m (the issue's bounds); NMEA fault counts within 5σ of the binomial count the
injected rates give.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest
import serial
from helpers import northfinder_line, only_line, read_events, sigint_when, start_cli

from northfinder.cli import main
from northfinder.cli.replay import differences
from northfinder.rundir import EVENTS, RESULT
from northfinder.runs import gnss as gr

TIME_SCALE = 25.0
"""firmware-sim's vehicle kept up with 25× real time on this shared 2-core host (60 device s in 2.45 s
of wall time; 30× took 4.2 s, 40× fell far behind). A simulator that falls behind delays the data,
it does not lose it: the test would take longer, not fail."""
E2E_DURATION_S = 300.0
"""The whole default drive: the issue's bounds (lever arm within 0.1 m, position under 2 m) are for
it; at 120 s the lever arm's forward component was still 0.09 m (3.3 of its claimed σ) off."""


def _run_cli(*argv: str, capsys) -> tuple[int, str, str]:
    rc = main(["align", "--mode", "gnss", *argv])
    out, err = capsys.readouterr()
    return rc, out, err


# ---------------------------------------------------------------------------------------------
# End to end through firmware-sim
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def e2e_run(tmp_path_factory):
    """One simulated alignment from a 90° initial heading error (the CLI in this process).

    No --link-latency here: firmware-sim's shaped links (the GNSS formats each epoch on its own,
    ~20 ms of CPU) fall behind at 25× on this loaded host and the host then overruns the IMU
    (3774 samples lost in one try); the 150 ± 20 ms run is docs/gnss-alignment.md's, at 2×. The
    host stamps of this run are off by 0.1–0.7 s anyway (the reader polls the GNSS between IMU
    reads): the data estimate starts from them."""
    out = tmp_path_factory.mktemp("align_gnss") / "run"
    json_path = out.parent / "x.json"
    t0 = time.monotonic()
    rc = main(
        [
            "align",
            "--mode",
            "gnss",
            "--simulate",
            "--duration",
            str(E2E_DURATION_S),
            "--heading-error",
            "90",
            "--heading-std",
            "90",
            "--time-scale",
            str(TIME_SCALE),
            "--seed",
            "3",
            "--out",
            str(out),
            "--json",
            str(json_path),
        ]
    )
    wall_s = time.monotonic() - t0
    return rc, out, json.loads(json_path.read_text()), wall_s


def test_simulated_alignment_from_90_deg_is_within_3_sigma_of_the_truth(e2e_run):
    rc, out, result, wall_s = e2e_run
    assert rc == 0
    assert result["kind"] == gr.KIND and result["complete"] is True
    assert result["method"] == "sincos"
    # the IMU–GNSS offset from the data (the hardware path), against the truth log's exact one:
    # within 3 of its σ and within the 10 ms, from wherever the host stamps put it
    ta = result["time_alignment"]
    assert ta["method"] == "data"
    assert abs(ta["data_minus_truth_s"]) <= 3.0 * ta["data"]["std_s"]
    assert 3.0 * ta["data"]["std_s"] <= 0.010
    # the filter started 90° off the truth at the start
    start = result["truth"]["heading_at_start_deg"]
    assert math.isclose((result["initial_heading_deg"] - start) % 360.0, 90.0, abs_tol=1e-9)
    assert result["initial_heading_std_deg"] == 90.0  # the prior (truth + --heading-error) ± --heading-std
    assert abs(result["error_deg"]) <= 3.0 * result["heading_std_deg"]
    assert result["converged_after_s"] is not None
    # No line fault is injected, but a host loaded enough to overrun the line (the simulator, like a
    # UART, drops what its client leaves unread) cuts the window at the first gap whose length the
    # 7-bit sequence cannot tell (test_a_gap_of_unknown_length_cuts_the_window…); the heading bound
    # above holds either way, the whole drive's bounds below only for the whole drive.
    if "imu_unknown_gap" not in result:
        assert result["duration_device_s"] == pytest.approx(E2E_DURATION_S)
        assert result["lever_arm_error_m"] < 0.1
        assert result["position_error_m"] < 2.0
    for key in (
        "heading_deg",
        "heading_std_deg",
        "lever_arm_m",
        "converged_after_s",
        "duration_device_s",
        "method",
        "position_error_m",
    ):
        assert key in result
    assert set(result["methods"]) == {"sincos", "small_angle"}
    assert (out / "report.png").stat().st_size > 10_000
    for name in ("imu.raw", "gnss.nmea", "imu.rx", "gnss.rx", "truth.jsonl", "config.json", EVENTS, RESULT):
        assert (out / name).exists(), name


def test_bad_nmea_is_counted_and_skipped_and_ctrl_c_keeps_the_data_and_exits_130(tmp_path):
    """One simulator run with NMEA faults, stopped by SIGINT after 30 s of device time: the faults
    are counted (binomial 5σ of the injected rates), no-fix epochs are not used, nothing crashes;
    the data read is aligned, saved as incomplete, and `replay_gnss_run` recomputes it bit for bit
    from imu.raw + gnss.nmea + events alone (the replay check lives here rather than on the 300 s
    run: same code path, a sixth of the filter time, and the harder case — faults, cut short)."""
    run_dir = tmp_path / "run"
    rate = 0.05
    proc = start_cli(
        "align",
        "--mode",
        "gnss",
        "--simulate",
        "--time-scale",
        str(TIME_SCALE),
        "--seed",
        "4",
        "--fault",
        f"gnss-bad-checksum-rate={rate}",
        "--fault",
        f"gnss-truncate-rate={rate}",
        "--fault",
        "gnss-nofix=15:3",
        "--out",
        str(run_dir),
        cwd=tmp_path,
    )
    _, err = sigint_when(
        proc,
        [
            (lambda: any(e["event"] == "start" for e in read_events(run_dir)), "a start event"),
            # 30 s of device time read
            (lambda: (run_dir / "imu.raw").stat().st_size >= 36 * 250 * 30, "30 s of IMU data"),
        ],
        timeout_s=60.0,
    )
    assert proc.returncode == 130, err
    line = northfinder_line(err)
    assert "SIGINT" in line and str(run_dir) in line
    end = [e for e in read_events(run_dir) if e["event"] == "end"]
    assert len(end) == 1 and end[0]["complete"] is False
    partial = json.loads((run_dir / RESULT).read_text())
    assert partial["complete"] is False
    assert 30.0 <= partial["duration_device_s"] < 300.0
    assert math.isfinite(partial["heading_deg"]) and math.isfinite(partial["heading_std_deg"])

    s = partial["gnss"]["stats"]
    total = s["sentences"] + s["bad_checksum"] + s["truncated"] + s["malformed"] + s["unknown"]
    # truncation is drawn first; a checksum is corrupted only in a sentence left whole
    for count, p in ((s["truncated"], rate), (s["bad_checksum"], rate * (1 - rate))):
        assert abs(count - total * p) <= 5 * math.sqrt(total * p * (1 - p)), (count, total, p)
    # 3 s without a fix: 30 epochs of no-fix sentences (minus the faulted ones), none used
    assert 0 < s["no_fix"] <= 90
    assert s["malformed"] == 0
    assert partial["gnss"]["updates"] < partial["gnss"]["fixes"]

    again, complete = gr.replay_gnss_run(run_dir)
    assert complete is False
    assert differences(partial, again) == []


# ---------------------------------------------------------------------------------------------
# User mistakes: one line, non-zero exit
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--simulate", "--lever-arm", "1,2"], "--lever-arm 1,2"),
        (["--simulate", "--lever-arm", "1,2,x"], "--lever-arm 1,2,x"),
        (["--simulate", "--duration", "0"], "--duration 0"),
        (["--duration", "60"], "--config"),
        (["--config", "bench.toml", "--heading-error", "10"], "--heading-error"),
        (["--simulate", "--heading-std", "5"], "--heading-std needs a heading"),
        (["--simulate", "--heading-error", "10", "--heading-std", "abc"], "--heading-std abc"),
        (["--simulate", "--heading-error", "10", "--heading-std", "0"], "--heading-std 0"),
        (["--config", "bench.toml", "--heading-std", "5"], "--heading-std needs a heading"),
        (["--config", "bench.toml", "--heading", "10", "--initial-heading", "20"], "--initial-heading"),
        (["--simulate", "--link-latency", "abc"], "--link-latency abc"),
        (["--simulate", "--link-latency", "10,20"], "--link-latency 10,20: the latency must be"),
        (["--simulate", "--link-latency", "cpu=10:1"], "name the link imu or gnss"),
        (["--config", "bench.toml", "--link-latency", "150,20"], "--link-latency is for --simulate"),
    ],
)
def test_flag_mistakes_are_one_line(argv, needle, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rc, _, err = _run_cli(*argv, "--out", str(tmp_path / "run"), capsys=capsys)
    assert rc == 2
    assert needle in only_line(err)


def test_missing_gnss_port_in_the_bench_config_is_one_line(tmp_path, capsys):
    cfg = tmp_path / "bench.toml"
    cfg.write_text('[imu]\nport = "/dev/ttyUSB1"\nrate_hz = 250\n')
    rc, _, err = _run_cli("--config", str(cfg), "--out", str(tmp_path / "run"), capsys=capsys)
    assert rc == 2
    line = only_line(err)
    assert "[gnss] port" in line and str(cfg) in line


def test_a_port_that_does_not_exist_is_one_line_naming_it(tmp_path, capsys):
    cfg = tmp_path / "bench.toml"
    missing = str(tmp_path / "no-such-tty")
    cfg.write_text(f'[imu]\nport = "{missing}"\nrate_hz = 250\n[gnss]\nport = "{missing}-gnss"\n')
    rc, _, err = _run_cli("--config", str(cfg), "--out", str(tmp_path / "run"), capsys=capsys)
    assert rc == 3
    line = only_line(err)
    assert "imu" in line and missing in line


def test_bench_config_keys_are_checked(tmp_path):
    """[imu] and [gnss] are read by northfinder.config, the one configuration every mode uses."""
    from northfinder import config

    def load(text: str) -> config.BenchConfig:
        cfg.write_text(text)
        bench = config.load(cfg)
        config.require_align(bench, "gnss")
        return bench

    cfg = tmp_path / "bench.toml"
    with pytest.raises(config.ConfigError, match=r"unknown key \[gnss\] lever_arm;"):
        load('[imu]\nport = "/dev/a"\n[gnss]\nport = "/dev/b"\nlever_arm = [1, 2, 3]\n')
    with pytest.raises(config.ConfigError, match=r"\[gnss\] lever_arm_m = \[1, 2\] is not allowed"):
        load('[imu]\nport = "/dev/a"\n[gnss]\nport = "/dev/b"\nlever_arm_m = [1, 2]\n')
    with pytest.raises(config.ConfigError, match="both /dev/a"):
        load('[imu]\nport = "/dev/a"\n[gnss]\nport = "/dev/a"\n')
    with pytest.raises(config.ConfigError, match=r"\[imu\] rot_format = 'ANGLE' is not allowed; use one"):
        load('[imu]\nport = "/dev/a"\nrot_format = "ANGLE"\n[gnss]\nport = "/dev/b"\n')
    with pytest.raises(config.ConfigError, match=r"\[gnss\] latency_s = 2.0 is not allowed; use 0 … 1 s"):
        load('[imu]\nport = "/dev/a"\n[gnss]\nport = "/dev/b"\nlatency_s = 2.0\n')
    bench = load(
        '[imu]\nport = "/dev/a"\nrate_hz = 250\n[gnss]\nport = "/dev/b"\nlever_arm_m = [0.5, 1.5, 1.2]\n'
    )
    assert bench.gnss.lever_arm_m == (0.5, 1.5, 1.2) and bench.imu.rate_hz == 250


# ---------------------------------------------------------------------------------------------
# Host receive-stamp alignment (real hardware): an exact identity on synthetic arrivals
# ---------------------------------------------------------------------------------------------
def test_host_stamp_alignment_recovers_the_offset_up_to_the_smallest_delays():
    """IMU index 0 starts at GNSS time t0. Chunks arrive after random delays; the lower-envelope
    estimate must equal t0 + (smallest IMU delay − smallest GNSS delay) to rounding."""
    from firmware_sim.devices.gnss import format_gga, format_rmc, format_vtg
    from firmware_sim.devices.kvh import pack_messages

    rng = np.random.default_rng(7)
    rate, k_scale, t0, host0 = 250.0, 20.0, 3.137, 1234.5
    utc_ref = 1795348800.0  # 2026-11-22T12:00:00Z
    n = 250 * 60
    raw = pack_messages(np.zeros((n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)), 0x77, np.arange(n) & 0x7F, 25)
    ends = np.sort(rng.choice(np.arange(1, n), size=300, replace=False))
    ends = np.append(ends, n)  # last sample in each chunk (count), i.e. index ends−1
    imu_delay = rng.uniform(0.002, 0.3, len(ends))  # device seconds
    imu_host = host0 + (t0 + ends / rate + imu_delay) / k_scale
    import datetime as dt

    epochs = np.arange(0, 600)  # 10 Hz, 60 s
    sentences, u = [], []
    for k in epochs:
        when = dt.datetime(2026, 11, 22, 12, tzinfo=dt.UTC) + dt.timedelta(milliseconds=100 * int(k))
        s = (
            format_gga(when, 40.0, 116.3, 0.0)
            + format_rmc(when, 40.0, 116.3, 0.0, 0.0)
            + format_vtg(0.0, 0.0)
        )
        sentences.append(s)
        u.append(k / 10.0)
    # a corrupted GGA claiming a later time would fake an early arrival: it must be skipped
    bad = format_gga(dt.datetime(2026, 11, 22, 12, 5, 0, tzinfo=dt.UTC), 40.0, 116.3, 0.0)
    bad = bad[:-4] + b"00\r\n" if not bad.endswith(b"00\r\n") else bad[:-4] + b"01\r\n"
    sentences.insert(10, bad)
    u.insert(10, None)
    nmea, totals, hosts, gnss_delay = b"", [], [], []
    for s, ui in zip(sentences, u, strict=True):
        nmea += s
        if ui is None:
            continue
        d = rng.uniform(0.004, 0.5)
        gnss_delay.append(d)
        totals.append(len(nmea))
        hosts.append(host0 + (ui + d) / k_scale)
    est = gr.host_offsets(
        raw, (imu_host, ends * 36), nmea, (np.array(hosts), np.array(totals)), rate, utc_ref, k_scale
    )
    expect = t0 + imu_delay.min() - min(gnss_delay)
    assert est["t0_s"] == pytest.approx(expect, abs=1e-6)
    assert est["gnss_epochs"] == len(epochs)


def test_hardware_path_on_a_moving_vehicle_refuses_with_one_line(tmp_path, capsys):
    """`--config` (the real-hardware path: IMU configuration read back, host receive stamps) against
    firmware-sim's vehicle once it is driving: levelling needs a still start, so one line says so.
    The host-stamp time alignment of that run is computed and finite."""
    from northfinder.rundir import RunDir
    from northfinder.runs.gnss_live import VehicleSim, VehicleSimProcess

    truth_log = tmp_path / "truth.jsonl"
    with VehicleSimProcess(VehicleSim(time_scale=TIME_SCALE, truth_log=str(truth_log))) as endpoints:
        starter = serial.Serial(endpoints["gnss"])  # the vehicle's device time waits for a client
        deadline = time.monotonic() + 30.0
        while True:  # wait until the vehicle drives (it starts at 10 s, 10 m/s from 18 s)
            rows = truth_log.read_text().splitlines() if truth_log.exists() else []
            if any('"type": "truth"' in r and json.loads(r)["t_device_s"] > 20.0 for r in rows[-3:]):
                break
            assert time.monotonic() < deadline, "firmware-sim did not reach 20 s of device time"
            time.sleep(0.05)
        starter.close()
        cfg = tmp_path / "bench.toml"
        cfg.write_text(
            f'[imu]\nport = "{endpoints["imu"]}"\nrate_hz = 250\n[gnss]\nport = "{endpoints["gnss"]}"\n'
            "lever_arm_m = [0.6, 1.4, 1.1]\n"
        )
        run_dir = tmp_path / "run"
        rc, _, err = _run_cli("--config", str(cfg), "--duration", "20", "--out", str(run_dir), capsys=capsys)
    assert rc == 2
    assert "standing still" in northfinder_line(err)  # after the progress bar
    rd = RunDir(run_dir, create=False)
    events = rd.events()
    start, end = events[0], events[-1]
    assert start["kind"] == gr.KIND and start["imu"]["rate_hz"] == 250.0 and end["complete"] is True
    block, fixes = gr.window_from_logs(rd, start, end)
    assert len(block) == end["imu"]["samples"] and len(fixes) == end["gnss"]["fixes"]
    t0, info = gr.time_alignment(rd, start, end, None, fixes[-1].time_s - end["utc_ref_s"])
    assert info["method"] == "host" and math.isfinite(t0)
    assert info["imu_chunks"] > 0 and info["gnss_epochs"] > 0


def test_a_gap_of_unknown_length_cuts_the_window_and_keeps_the_heading_honest(tmp_path):
    """The IMU falls silent for 3 device seconds (750 samples at 250 Hz: five whole turns of the 7-bit
    sequence and 110): the sequence shows a gap of 110, so every later sample would be placed 2.56 s
    early against the GNSS and the heading end far off with a small σ. The decoder sees that the gap's
    bytes never came, the run keeps the part before it, says so, and its heading is within 3σ of
    the truth; replay gives the same."""
    out = tmp_path / "run"
    rc = main(["align", "--mode", "gnss", "--simulate", "--duration", "60", "--heading-error", "90",
               "--heading-std", "90", "--time-scale", str(TIME_SCALE), "--seed", "3",
               "--fault", "imu-silence=40:3", "--out", str(out)])
    assert rc == 0
    result = json.loads((out / RESULT).read_text())
    cut = result["imu_unknown_gap"]
    assert cut["unknown_gaps"] == 1
    assert result["imu"]["stats"]["unknown_gaps"] == 1
    assert result["imu"]["lost_samples"] == 750 % 128  # all the sequence can count
    t_first = result["imu"]["window_s"][0]  # the window's first sample in GNSS time
    assert cut["kept_s"] == pytest.approx(40.0 - t_first, abs=0.1)  # the silence began at 40 s
    assert cut["at_s"] == pytest.approx(cut["kept_s"] + 110 / 250.0, abs=0.01)  # where the count puts it
    assert result["duration_device_s"] == pytest.approx(cut["kept_s"])
    assert abs(result["error_deg"]) <= 3.0 * result["heading_std_deg"]
    replayed, complete = gr.replay_gnss_run(out)
    assert complete and differences(replayed, result) == []


def test_unknown_gaps_are_kept_by_the_window_selection_and_cut_at_the_first():
    from northfinder.codecs.kvh import ImuBlock
    from northfinder.runs.base import before_unknown_gap, select_samples

    idx = np.array([0, 1, 2, 5, 6, 7, 20, 21])
    n = len(idx)
    block = ImuBlock(idx, np.zeros((n, 3)), np.zeros((n, 3)), np.full(n, 0x77, np.uint8), np.zeros(n), 13,
                     10.0, (5, 20))
    assert select_samples(block, 1, 7).unknown_gaps == (5,)
    assert select_samples(block, 5, 21).unknown_gaps == (20,)  # a gap before the first sample is not in it
    kept, cut = before_unknown_gap(block)
    assert kept.sample_index.tolist() == [0, 1, 2] and kept.unknown_gaps == ()
    assert cut["at_index"] == 5 and cut["at_s"] == 0.5 and cut["kept_s"] == 0.3
    assert cut["dropped_samples"] == 5 and cut["unknown_gaps"] == 2
    assert before_unknown_gap(select_samples(block, 0, 2)) [1] is None


def test_the_summary_says_which_start_was_used():
    """A prior is named with its σ and that it is held while standing; no σ says 'unknown'."""
    from northfinder.cli._align_summary import start_text

    assert "prior 40.00° ± 5° (1σ), held while standing still" == start_text(
        {"initial_heading_deg": 40.0, "initial_heading_std_deg": 5.0}
    )
    unknown = start_text({"initial_heading_deg": 0.0, "initial_heading_std_deg": None})
    assert unknown.startswith("heading unknown")


def test_the_summary_counts_converged_and_below_1deg_from_the_same_start(e2e_run):
    """'converged after' (result: from the filter start) and '<1° after' (from the first IMU sample)
    are printed from the same start, the first IMU sample, and the summary says so: the converged
    time shown is the result's plus filter_start_s (the levelling), for both filters."""
    from rich.console import Console

    from northfinder.cli._align_summary import print_gnss_summary as print_summary

    _, _, result, _ = e2e_run
    assert result["filter_start_s"] >= 5.0  # the levelling is counted in the shift
    console = Console(record=True, width=160)
    print_summary(result, console=console)
    text = console.export_text()
    shown = result["converged_after_s"] + result["filter_start_s"]
    assert f"converged after  {shown:.1f} s (1σ < 1° from then on; from the first IMU sample" in text
    assert "times from the first IMU sample" in text
    rows = {line.split("│")[1].strip(" *"): line for line in text.splitlines() if line.count("│") == 8}
    for name, m in result["methods"].items():
        cells = [c.strip() for c in rows[name].split("│")[1:-1]]
        assert float(cells[3]) == pytest.approx(m["converged_after_s"] + result["filter_start_s"], abs=0.051)
        if m["time_below_1deg_s"] is None:  # the true error did not stay below 1° to the end
            assert cells[5] == "—"
        else:
            assert float(cells[5]) == pytest.approx(m["time_below_1deg_s"], abs=0.051)
