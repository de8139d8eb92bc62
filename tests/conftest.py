"""Shared fixtures: the golden byte vectors from ../shared/PROTOCOLS.md."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

GOLDEN_PATH = Path(__file__).parent / "golden" / "vectors.json"


@pytest.fixture(scope="session")
def golden() -> dict:
    """tests/golden/vectors.json, written by tools/make_golden_vectors.py."""
    return json.loads(GOLDEN_PATH.read_text())
