"""No CAN interface that can leave the machine. (That firmware_sim and northfinder never import each
other, nor firmware_sim the canopen library, is an import-linter contract: tests/test_layers.py.)"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


FORBIDDEN_INTERFACE = "udp_" + "multicast"  # spelled apart so that this file does not match itself


def test_no_multicast_can_interface_anywhere():
    hits = [
        str(p.relative_to(ROOT))
        for folder in ("northfinder", "firmware_sim", "tools")
        for p in (ROOT / folder).rglob("*.py")
        if FORBIDDEN_INTERFACE in p.read_text()
    ]
    assert hits == []
