"""Shared fixtures: the golden byte vectors from ../shared/PROTOCOLS.md; a raw pty pair."""

from __future__ import annotations

import json
import os
import tty
from pathlib import Path

# One BLAS thread per test process: the suite runs 3 xdist workers on 2 cores, where OpenBLAS's own
# threads only compete (test_swaying: 48 s of CPU for 31 s of wall time, 29 s with one thread).
# Set before numpy loads OpenBLAS (it reads these once); subprocesses the tests start inherit them.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import pytest  # noqa: E402

GOLDEN_PATH = Path(__file__).parent / "golden" / "vectors.json"


@pytest.fixture(autouse=True)
def _own_results_history(tmp_path_factory, monkeypatch):
    """Each test its own per-user data directory (platformdirs reads XDG_DATA_HOME), so the runs a
    test makes record into a history of their own, never the user's; subprocesses inherit it."""
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path_factory.mktemp("xdg-data")))
    monkeypatch.delenv("NORTHFINDER_HISTORY_DB", raising=False)


@pytest.fixture(scope="session")
def golden() -> dict:
    """tests/golden/vectors.json, written by tools/make_golden_vectors.py."""
    return json.loads(GOLDEN_PATH.read_text())


@pytest.fixture
def pty_pair():
    """(master fd, slave path) of a fresh pty, both ends raw: a device's wire for a driver under test."""
    master, slave = os.openpty()
    tty.setraw(master)
    tty.setraw(slave)
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


LONGEST_FIRST = (
    "test_campaign.py", "test_e2e_find.py", "test_e2e_units.py", "test_faults.py", "test_plan.py",
    "test_align_gnss.py", "test_gnss_alignment.py", "test_swaying.py", "test_align_swaying.py",
    "test_find_rough_edges.py", "test_sim_real_units.py", "test_canopen_sdo.py", "test_fuzz_decoders.py",
)
"""Test files by their measured time, longest first (`pytest --durations=0` summed per file:
93, 84, 77, 58, 56, 51, 44, 34, 28, 27, 25, 24, 22 s on this 2-core host). pytest-xdist's loadfile
hands out files in collection order, so the long ones start first and the short ones fill the gaps
at the end (longest-processing-time-first); the rest keep their order."""


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: a file stays in order
