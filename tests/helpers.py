"""Helpers several test files share: bytes into a pty, the CLI as a subprocess (run, or stopped
with Ctrl-C at a chosen point), a run's events, and the one-line error checks."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from northfinder.rundir import EVENTS

REPO = Path(__file__).resolve().parents[1]


def write_all(fd: int, data: bytes) -> None:
    """os.write until every byte is in (a pty takes a few KiB at a time)."""
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def subprocess_env() -> dict[str, str]:
    """This environment with the checkout first on PYTHONPATH (northfinder and firmware_sim found
    from any working directory)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p)
    return env


def read_events(run_dir: Path) -> list[dict]:
    """events.jsonl of a run directory ([] before it exists)."""
    p = run_dir / EVENTS
    if not p.exists():
        return []
    return [json.loads(ln) for ln in p.read_text().splitlines() if ln.strip()]


def run_cli(*argv: str, cwd: Path, timeout_s: float = 60.0) -> subprocess.CompletedProcess[str]:
    """`python -m northfinder ARGV` to the end, output captured."""
    return subprocess.run(
        [sys.executable, "-m", "northfinder", *argv],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=subprocess_env(),
        timeout=timeout_s,
    )


def start_cli(*argv: str, cwd: Path) -> subprocess.Popen[str]:
    """`python -m northfinder ARGV` started in the background, output piped."""
    return subprocess.Popen(
        [sys.executable, "-m", "northfinder", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env=subprocess_env(),
    )


def sigint_when(
    proc: subprocess.Popen[str], steps: Sequence[tuple[Callable[[], bool], str]], timeout_s: float
) -> tuple[str, str]:
    """Wait until each condition of `steps` holds in turn (the process still running, all within
    `timeout_s` of wall time), then Ctrl-C it; its (stdout, stderr). Killed if it outlives this."""
    try:
        deadline = time.monotonic() + timeout_s
        for ready, what in steps:
            while not ready():
                assert proc.poll() is None, proc.communicate()
                assert time.monotonic() < deadline, f"{what} not within {timeout_s:g} s"
                time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def only_line(err: str) -> str:
    """stderr is exactly one non-blank line and no traceback: that line."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def northfinder_line(err: str) -> str:
    """The one `northfinder:` line of stderr (a progress bar may have drawn above it), no traceback."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.startswith("northfinder:")]
    assert len(lines) == 1, err
    return lines[0]


def start_sim(*argv: str) -> subprocess.Popen[str]:
    """`python -m firmware_sim ARGV` in its own session (a test's Ctrl-C does not reach it); its
    first stdout line is the endpoints JSON."""
    return subprocess.Popen(
        [sys.executable, "-m", "firmware_sim", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=subprocess_env(),
        start_new_session=True,
    )
