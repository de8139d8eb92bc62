"""firmware_sim and northfinder are independent implementations: neither imports the other."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _imported_top_level_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize(
    ("package", "forbidden"),
    # firmware_sim's CANopen node is its own SDO server, written from PROTOCOLS.md §3.1, never the
    # python-canopen stack the driver stands on
    [("firmware_sim", "northfinder"), ("northfinder", "firmware_sim"), ("firmware_sim", "canopen")],
)
def test_no_cross_imports(package, forbidden):
    offenders = [
        str(p.relative_to(ROOT))
        for p in sorted((ROOT / package).rglob("*.py"))
        if forbidden in _imported_top_level_modules(p)
    ]
    assert offenders == [], f"{package} imports {forbidden} in {offenders}"


FORBIDDEN_INTERFACE = "udp_" + "multicast"  # spelled apart so that this file does not match itself


def test_no_multicast_can_interface_anywhere():
    hits = [
        str(p.relative_to(ROOT))
        for folder in ("northfinder", "firmware_sim", "tools")
        for p in (ROOT / folder).rglob("*.py")
        if FORBIDDEN_INTERFACE in p.read_text()
    ]
    assert hits == []
