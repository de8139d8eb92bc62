"""tools/vcan_guest.py collects, in the guest, only the test files that mark socketcan tests (the whole
suite's collection took 12 s of the guest's slow Python): every socketcan-marked test this session
collected must be in one of those files, else CI would never run it."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _vcan_guest():
    spec = importlib.util.spec_from_file_location("vcan_guest", REPO / "tools" / "vcan_guest.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_socketcan_test_collected_is_in_a_file_the_guest_runs(request):
    vcan_guest = _vcan_guest()
    files = {f.name for f in vcan_guest.socketcan_test_files()}
    assert "test_socketcan.py" in files
    marked = {item.path.name for item in request.session.items if item.get_closest_marker("socketcan")}
    assert marked <= files, f"socketcan tests the guest would miss: {sorted(marked - files)}"


def test_the_guests_pytest_runs_the_socketcan_tests_of_those_files_and_writes_junit(tmp_path):
    vcan_guest = _vcan_guest()
    junit = tmp_path / "junit.xml"
    command = vcan_guest.pytest_command(junit)
    assert command[:3] == [sys.executable, "-m", "pytest"]
    assert command[command.index("-m", 3) + 1] == "socketcan" and f"--junitxml={junit}" in command
    assert {f"tests/{f.name}" for f in vcan_guest.socketcan_test_files()} <= set(command)
