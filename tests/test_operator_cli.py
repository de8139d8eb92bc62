"""What the operator sees at the terminal: tables that fit 80 columns (numbers never cut), plain
lines when piped, one clear line per mistake (the bad-input table), `check --simulate`,
`--version`, and the same flag meaning the same thing in every subcommand."""

from __future__ import annotations

import argparse
import collections
import fcntl
import json
import os
import pty
import re
import struct
import subprocess
import sys
import termios
import time
from pathlib import Path

import pytest

from tests.helpers import run_cli, subprocess_env

DATA = Path(__file__).resolve().parent / "data" / "reports"
ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")
QUICK_FIND = ("find", "--simulate", "--positions", "4", "--dwell", "2", "--time-scale", "20", "--no-report")


# -- tables at 80 and 200 columns ----------------------------------------------------------------
def _summary_at(width: int) -> str:
    from rich.console import Console

    from northfinder.cli._summary import print_summary

    result = json.loads((DATA / "find-r5" / "result.json").read_text())
    console = Console(width=width, force_terminal=False, color_system=None)
    with console.capture() as cap:
        print_summary(result, console=console)
    return cap.get()


@pytest.mark.parametrize("width", [80, 200])
def test_summary_fits_the_width_and_every_number_is_whole(width):
    out = _summary_at(width)
    assert max(len(line) for line in out.splitlines()) <= width
    assert "…" not in out
    result = json.loads((DATA / "find-r5" / "result.json").read_text())
    for p in result["positions"]:  # every mean as printed, whole
        for v in p["gyro_dph"]:
            assert f"{v:+.4f}" in out
        for v in p["accel_g"]:
            assert f"{v * 1e3:+.3f}" in out
    assert ("positions (continued)" in out) == (width == 80)  # 80: split in two; 200: one table


def test_split_columns_repeats_the_key_and_keeps_order():
    from northfinder.cli._tables import split_columns

    assert split_columns([1, 7, 8, 8, 8], 80) == [[0, 1, 2, 3, 4]]
    assert split_columns([1, 7, 8, 8, 8, 8, 8, 8], 80) == [[0, 1, 2, 3, 4, 5, 6], [0, 7]]  # 81 wide: split
    groups = split_columns([1, 7, 8, 8, 7, 7, 7, 8, 7, 4, 5, 5], 80)  # 80 wide, then the counts
    assert groups == [[0, 1, 2, 3, 4, 5, 6, 7], [0, 8, 9, 10, 11]]
    assert split_columns([1, 100], 80) == [[0, 1]]  # a column wider than the screen still shows


def test_piped_find_prints_one_plain_line_per_event(tmp_path):
    proc = run_cli(*QUICK_FIND, "--out", str(tmp_path / "run"), cwd=tmp_path, timeout_s=180)
    assert proc.returncode == 0, proc.stderr
    err = proc.stderr
    assert "\r" not in err and "\x1b[" not in err and "\x1b[" not in proc.stdout
    lines = err.splitlines()
    assert lines[0] == "referencing the stage"
    for k in range(1, 5):
        # a position measured again (the host loaded: samples lost) moves again: ≥ 1
        assert sum(line.startswith(f"position {k} of 4: moving to") for line in lines) >= 1
        assert sum(line.startswith(f"position {k} of 4: measured at") for line in lines) == 1
    assert "returning to the start" in lines
    assert "…" not in proc.stdout


def _run_on_pty(argv: list[str], cwd: Path, columns: int, timeout_s: float = 180.0) -> tuple[int, str]:
    """ARGV with stdout and stderr on a pseudo-terminal `columns` wide; (exit code, output)."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 50, columns, 0, 0))
    env = {**subprocess_env(), "COLUMNS": str(columns), "TERM": "xterm"}
    proc = subprocess.Popen([sys.executable, "-m", "northfinder", *argv], stdin=subprocess.DEVNULL,
                            stdout=slave, stderr=slave, cwd=cwd, env=env)
    os.close(slave)
    chunks = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            data = os.read(master, 65536)
        except OSError:  # EIO: the child closed the terminal
            break
        if not data:
            break
        chunks.append(data)
    os.close(master)
    code = proc.wait(timeout=30)
    return code, b"".join(chunks).decode("utf-8", "replace")


def test_find_on_an_80_column_terminal_cuts_no_number(tmp_path):
    code, out = _run_on_pty([*QUICK_FIND, "--out", str(tmp_path / "run")], tmp_path, 80)
    assert code == 0, out[-2000:]
    summary = ANSI.sub("", out[out.index("northfinder result"):]).replace("\r", "")
    assert "…" not in summary
    assert max(len(line) for line in summary.splitlines()) <= 80
    assert "positions (continued)" in summary
    result = json.loads((tmp_path / "run" / "result.json").read_text())
    for p in result["positions"]:
        assert f"{p['gyro_dph'][1]:+.4f}" in summary


def test_history_at_80_columns_and_piped(tmp_path):
    import shutil

    shutil.copytree(DATA / "find-r5", tmp_path / "runs" / "find-r5")
    db = str(tmp_path / "h.sqlite")
    assert run_cli("history", "--db", db, "--rebuild", str(tmp_path / "runs"), cwd=tmp_path).returncode == 0
    code, out = _run_on_pty(["history", "--db", db], tmp_path, 80, timeout_s=60)
    text = ANSI.sub("", out).replace("\r", "")
    assert code == 0 and "…" not in text, text
    assert max(len(line) for line in text.splitlines()) <= 80
    for number in ("36.9529", "0.0567", "-0.0471", "40.000", "2026-11-25 22:16:22", "8 × 5 s"):
        assert number in text, number
    piped = run_cli("history", "--db", db, cwd=tmp_path)
    assert "…" not in piped.stdout and "\x1b[" not in piped.stdout and "(continued)" not in piped.stdout


# -- the bad-input table: command → exit code → one line -----------------------------------------
BAD_INPUT = [
    # (argv, exit code, words the one line must hold)
    (["find", "--simulate", "--out", "/proc/self"], 2, ["--out /proc/self", "cannot write into it"]),
    (["find", "--simulate", "--fault", "bogus=1"], 2,
     ["--simulate", "unknown fault 'bogus'", "known faults"]),
    (["find", "--simulate", "--grade", "bogus"], 2, ["--simulate", "grade", "use one of nav"]),
    (["find", "--simulate", "--time-scale", "-1"], 2, ["--time-scale -1", "greater than 0"]),
    (["find", "--simulate", "--fault", "imu-silence=x"], 2,
     ["--simulate", "imu-silence=x", "START_S:DURATION_S"]),
    (["find", "--simulate", "--heading", "400"], 2, ["--heading", "400", "between -360 and 360"]),
    (["align", "--mode", "swaying", "--simulate", "--heading", "400"], 2, ["--heading", "400"]),
    (["campaign", "--simulate", "--repeat", "1", "--heading", "400"], 2,
     ["--heading 400", "more than a turn"]),
    (["find", "--simulate", "--positions", "x"], 2, ["--positions", "invalid int value", "--help"]),
    (["check"], 2, ["one of the arguments --config --simulate is required"]),
    ([], 2, ["COMMAND", "northfinder --help"]),
    (["align", "--mode", "swaying", "--simulate", "--sway-method", "bogus"], 2, ["--sway-method", "cone"]),
]


@pytest.mark.parametrize("argv,code,words", BAD_INPUT, ids=[" ".join(a) or "(none)" for a, _, _ in BAD_INPUT])
def test_bad_input_is_one_line_and_its_exit_code(tmp_path, argv, code, words):
    proc = run_cli(*argv, cwd=tmp_path, timeout_s=120)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == code, proc.stderr
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not any(tmp_path.glob("runs/*")), "a refused start leaves no run directory"


def test_version_and_check_simulate(tmp_path):
    proc = run_cli("--version", cwd=tmp_path)
    assert proc.returncode == 0 and re.fullmatch(r"northfinder \d+\.\d+\.\d+\n", proc.stdout), proc
    proc = run_cli("check", "--simulate", cwd=tmp_path, timeout_s=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    assert [line.split()[0] for line in lines] == ["note", "ok", "ok", "ok", "note"], lines
    assert lines[1].startswith("ok    turntable on /dev/pts/") and "SMC100" in lines[1]
    assert lines[2].startswith("ok    imu on ") and "1000 Hz" in lines[2]
    assert lines[3].startswith("ok    accelerometer node 0x10 on slcan")
    assert lines[-1] == "note  firmware-sim stopped (exit code 0)"


# -- one flag, one meaning --------------------------------------------------------------------
def _subparsers() -> dict[str, argparse.ArgumentParser]:
    from northfinder.cli import build_parser

    (sub,) = [a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def _meaning(action: argparse.Action) -> tuple:
    """What a flag means across commands: its kind of action, its choices and its unit (metavar; a
    list of the unit and any *_DIR directory count as the same)."""
    metavar = action.metavar or ""
    metavar = re.sub(r"^(\w+)\[,\1…\]$", r"\1", metavar)  # DEG[,DEG…]: a list of DEG
    metavar = re.sub(r"^\w*_DIR$", "DIR", metavar)
    kind = type(action).__name__
    return kind, tuple(action.choices) if action.choices else None, metavar


def test_every_flag_has_help_and_a_shared_flag_means_the_same_everywhere():
    seen: dict[str, list[tuple[str, tuple]]] = collections.defaultdict(list)
    for command, parser in _subparsers().items():
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            assert action.help, f"{command} {action.option_strings or action.dest}: no help"
            for flag in action.option_strings:
                seen[flag].append((command, _meaning(action)))
    shared = {flag: uses for flag, uses in seen.items() if len(uses) > 1}
    must = {"--seed", "--grade", "--time-scale", "--fault", "--json", "--heading", "--latitude"}
    assert must <= set(shared)
    for flag, uses in shared.items():
        meanings = {m for _, m in uses}
        assert len(meanings) == 1, f"{flag}: {uses}"


def test_every_command_that_runs_a_measurement_takes_json_and_fault():
    parsers = _subparsers()
    for command in ("find", "align", "campaign"):
        flags = set(parsers[command]._option_string_actions)
        assert {"--json", "--fault", "--seed", "--grade", "--time-scale", "--out"} <= flags, command
