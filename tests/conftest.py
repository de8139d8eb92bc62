"""Shared fixtures: the golden byte vectors from ../shared/PROTOCOLS.md; a raw pty pair."""

from __future__ import annotations

import json
import os
import tty
from pathlib import Path

import pytest

GOLDEN_PATH = Path(__file__).parent / "golden" / "vectors.json"


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
