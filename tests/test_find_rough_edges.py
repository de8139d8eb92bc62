"""The find's rough edges a newcomer met (issue 12 item 7), each pinned:

- a failed start (bad config, bad latitude, bad port) leaves no run directory behind; Ctrl-C
  before the first position leaves one that replay and --resume explain;
- a raw log cut short says "imu.raw ends inside position k (n of m samples)" and exits 4, not 2
  (a usage error) and not an estimator's "NaN or inf";
- report.png has error bars on the position means, a legend and a radius unit on the polar plot,
  and no two text labels overlap;
- `--seed` has help text.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers import northfinder_line, read_events, run_cli, sigint_when, start_cli

USAGE_EXIT, DEVICE_EXIT, DAMAGED_EXIT = 2, 3, 4
FAST = ("--simulate", "--positions", "3", "--dwell", "2", "--no-report")


def _bench_on_no_port(tmp_path: Path) -> Path:
    """A valid bench.toml whose turntable port does not exist."""
    bench = tmp_path / "bench.toml"
    bench.write_text(
        f'[turntable]\nport = "{tmp_path / "ttyNONE"}"\n[imu]\nport = "{tmp_path / "ttyIMU"}"\n'
        f'[accelerometer]\ninterface = "virtual"\nchannel = "{tmp_path.name}"\n[site]\nlatitude_deg = 40.0\n',
        encoding="utf-8",
    )
    return bench


def test_bad_config_bad_latitude_and_bad_port_leave_no_run_directory(tmp_path):
    out = tmp_path / "run"
    missing = run_cli("find", "--config", str(tmp_path / "nope.toml"), "--out", str(out), cwd=tmp_path)
    assert missing.returncode == USAGE_EXIT and "nope.toml" in northfinder_line(missing.stderr)
    lat = run_cli("find", "--simulate", "--latitude", "95", "--out", str(out), cwd=tmp_path)
    assert lat.returncode == USAGE_EXIT and "--latitude 95" in northfinder_line(lat.stderr)
    port = run_cli("find", "--config", str(_bench_on_no_port(tmp_path)), "--out", str(out), cwd=tmp_path)
    line = northfinder_line(port.stderr)
    assert port.returncode == DEVICE_EXIT and "turntable" in line and "ttyNONE" in line, port.stderr
    assert not out.exists(), sorted(p.name for p in out.iterdir())


def test_an_existing_out_directory_is_never_removed_by_a_failed_start(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("the user's", encoding="utf-8")
    proc = run_cli("find", "--config", str(_bench_on_no_port(tmp_path)), "--out", str(out), cwd=tmp_path)
    assert proc.returncode == DEVICE_EXIT
    assert (out / "notes.txt").read_text(encoding="utf-8") == "the user's"


@pytest.mark.parametrize("argv", [("find", "--simulate"), ("align", "--mode", "gnss", "--simulate"),
                                  ("align", "--mode", "swaying", "--simulate")])
def test_out_onto_a_directory_holding_a_run_is_refused_and_the_run_left_as_it_was(tmp_path, argv):
    """A second run written into the first's directory would append its events to the first's and
    replace its raw logs: neither could be replayed. One line names the directory; nothing changes."""
    out = tmp_path / "run"
    out.mkdir()
    events = '{"event": "start", "session": 1}\n'
    (out / "events.jsonl").write_text(events, encoding="utf-8")
    proc = run_cli(*argv, "--out", str(out), cwd=tmp_path)
    line = northfinder_line(proc.stderr)
    assert proc.returncode == USAGE_EXIT and str(out) in line and "already holds a run" in line, line
    assert ("--resume" in line) == (argv[0] == "find")
    assert sorted(p.name for p in out.iterdir()) == ["events.jsonl"]
    assert (out / "events.jsonl").read_text(encoding="utf-8") == events


def test_ctrl_c_before_the_first_position_leaves_a_run_that_replay_and_resume_explain(tmp_path):
    out = tmp_path / "run"
    proc = start_cli("find", *FAST, "--out", str(out), cwd=tmp_path)
    started = lambda: any(e.get("event") == "start" for e in read_events(out))  # noqa: E731
    _, err = sigint_when(proc, [(started, "the start event")], timeout_s=60)
    assert proc.returncode == 130 and "after 0 of 3 positions" in northfinder_line(err)
    again = run_cli("replay", str(out), cwd=tmp_path)
    assert again.returncode == 1
    assert "incomplete run, 0 of 3 positions" in again.stdout and "needs at least 3" in again.stdout


@pytest.fixture(scope="module")
def short_run(tmp_path_factory) -> Path:
    """One short simulated find (3 positions, 2 s dwells), its run directory."""
    tmp = tmp_path_factory.mktemp("short")
    out = tmp / "run"
    proc = run_cli("find", *FAST, "--out", str(out), cwd=tmp, timeout_s=120)
    assert proc.returncode == 0, proc.stderr
    return out


def _cut_at(data: bytes, sample_index: int) -> int:
    """The shortest prefix of a raw IMU log that holds the frame with `sample_index` (bisection
    over the length: the decoder's last index only grows with the prefix)."""
    from northfinder.codecs.kvh import decode_imu_stream

    lo, hi = 0, len(data)
    while lo < hi:
        mid = (lo + hi) // 2
        block, _ = decode_imu_stream(data[:mid])
        if len(block) and int(block.sample_index[-1]) >= sample_index:
            hi = mid
        else:
            lo = mid + 1
    return lo


def test_a_cut_short_imu_log_names_the_position_and_the_samples_and_exits_4(short_run, tmp_path):
    damaged = tmp_path / "damaged"
    shutil.copytree(short_run, damaged)
    positions = [e for e in read_events(damaged) if e["event"] == "position"]
    last = positions[-1]["imu"]
    raw = damaged / "imu.raw"
    data = raw.read_bytes()
    raw.write_bytes(data[:_cut_at(data, (last["first_index"] + last["last_index"]) // 2)])
    proc = run_cli("replay", str(damaged), cwd=tmp_path)
    line = northfinder_line(proc.stderr)
    assert proc.returncode == DAMAGED_EXIT, proc.stderr
    m = last["last_index"] - last["first_index"] + 1 - last["lost"]
    assert f"imu.raw ends inside position {len(positions)} (" in line and f" of {m} samples)" in line, line
    assert "NaN" not in line
    n = int(line.split(f"position {len(positions)} (")[1].split(" of ")[0])
    assert 0 < n < m


def test_report_has_error_bars_a_polar_legend_with_a_radius_unit_and_no_overlapping_labels(short_run):
    from matplotlib.container import ErrorbarContainer

    from northfinder.report import draw_report, mean_std_errors

    result = json.loads((short_run / "result.json").read_text())
    gyro_se, _ = mean_std_errors(result["positions"])
    p0 = result["positions"][0]
    assert gyro_se[0][1] == pytest.approx(p0["gyro_std_dph"][1] / p0["samples"] ** 0.5)
    fig = draw_report(result)
    axes = fig.get_axes()
    bars = [c for ax in axes for c in ax.containers if isinstance(c, ErrorbarContainer)]
    assert len(bars) >= 6 * 2  # every axis: the means and the residuals
    polar = [ax for ax in axes if ax.name == "polar"][0]
    legend = polar.get_legend()
    assert legend is not None and "[deg]" in legend.get_title().get_text()
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    texts = [t for ax in axes for t in (ax.title, ax.xaxis.label, ax.yaxis.label) if t.get_text()]
    texts += [t for t in polar.get_yticklabels() + polar.get_xticklabels() if t.get_text()]
    texts += list(legend.get_texts())
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in texts]
    overlaps = [(a, b) for i, (a, ba) in enumerate(boxes) for b, bb in boxes[i + 1:] if ba.overlaps(bb)]
    assert not overlaps, overlaps


def test_seed_has_help_text(tmp_path):
    proc = run_cli("find", "--help", cwd=tmp_path)
    text = " ".join(proc.stdout.split())
    assert "--seed N the simulator's random seed" in text


def test_plan_goal_mistakes_are_one_line_and_leave_no_run_directory(tmp_path, capsys):
    """--target-std/--time-budget: combined with the plan's own flags, without a grade on a real
    bench, out of range or out of reach — each one line naming the flag, exit 2, nothing written."""
    from northfinder.cli import main

    out = tmp_path / "run"
    cases = [
        (["--simulate", "--target-std", "0.05", "--positions", "4"], "give either the goal or the plan"),
        (["--config", str(_bench_on_no_port(tmp_path)), "--target-std", "0.05"], "give --grade"),
        (["--simulate", "--target-std", "-1"], "--target-std -1"),
        (["--simulate", "--time-budget", "5"], "no plan fits in 5 s"),
        (["--simulate", "--grade", "consumer", "--target-std", "0.0001"], "no plan reaches"),
    ]
    for argv, expected in cases:
        assert main(["find", *argv, "--out", str(out)]) == USAGE_EXIT, argv
        err = capsys.readouterr().err
        assert expected in northfinder_line(err), (argv, err)
        assert not out.exists()
