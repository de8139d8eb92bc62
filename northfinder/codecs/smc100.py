"""Newport SMC100 command subset (docs/PROTOCOLS.md §1): bytes ⇄ values, no I/O.

A command is ``<addr><CC>[param][?]\\r\\n``; a reply is ``<addr><CC><text>\\r\\n``. This module
encodes commands, parses replies (TS, TE, TP, SL, SR, VE) and names the controller states,
positioner error bits and TE letters so that a driver can raise errors a user understands.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

__all__ = [
    "ERROR_BITS",
    "TE_MEANINGS",
    "Command",
    "Reply",
    "ProtocolError",
    "encode_command",
    "error_names",
    "format_value",
    "is_disabled",
    "is_homing",
    "is_moving",
    "is_not_referenced",
    "is_ready",
    "parse_command",
    "parse_position",
    "parse_reply",
    "parse_te",
    "parse_ts",
    "parse_ve",
    "state_name",
]

TERMINATOR = b"\r\n"

ERROR_BITS: dict[int, str] = {
    0: "negative end of run",
    1: "positive end of run",
    2: "peak current limit",
    3: "RMS current limit",
    4: "short circuit",
    5: "following error",
    6: "homing timeout",
    7: "wrong stage",
    8: "DC voltage too low",
    9: "80 W output power exceeded",
}

TE_MEANINGS: dict[str, str] = {
    "@": "no error",
    "A": "unknown command",
    "B": "bad address",
    "C": "parameter missing or out of range",
    "D": "not allowed",
    "E": "home already started",
    "G": "displacement out of limits",
    "H": "not allowed in NOT REFERENCED",
    "I": "not allowed in CONFIGURATION",
    "J": "not allowed in DISABLE",
    "K": "not allowed in READY",
    "L": "not allowed in HOMING",
    "M": "not allowed in MOVING",
    "N": "position beyond soft limit",
    "S": "communication timeout",
    "V": "execution error",
}

_READY = {0x32: "READY from HOMING", 0x33: "READY from MOVING", 0x34: "READY from DISABLE",
          0x35: "READY from JOGGING"}
_DISABLE = {0x3C: "DISABLE from READY", 0x3D: "DISABLE from MOVING", 0x3E: "DISABLE from JOGGING"}


def state_name(state: int) -> str:
    """Controller state byte (SS) → its name, e.g. 0x0A → 'NOT REFERENCED after reset'."""
    if 0x0A <= state <= 0x11:
        return "NOT REFERENCED after reset" if state == 0x0A else "NOT REFERENCED"
    if state == 0x14:
        return "CONFIGURATION"
    if state in (0x1E, 0x1F):
        return "HOMING"
    if state == 0x28:
        return "MOVING"
    if state in _READY:
        return _READY[state]
    if state in _DISABLE:
        return _DISABLE[state]
    if state in (0x46, 0x47):
        return "JOGGING"
    return f"UNKNOWN STATE 0x{state:02X}"


def is_ready(state: int) -> bool:
    return state in _READY


def is_moving(state: int) -> bool:
    return state == 0x28


def is_homing(state: int) -> bool:
    return state in (0x1E, 0x1F)


def is_not_referenced(state: int) -> bool:
    return 0x0A <= state <= 0x11


def is_disabled(state: int) -> bool:
    return state in _DISABLE


def error_names(errors: int) -> list[str]:
    """Positioner error bits (EEEE) → the names of the bits that are set, lowest bit first."""
    names = [name for bit, name in ERROR_BITS.items() if errors >> bit & 1]
    names += [f"unknown error bit {bit}" for bit in range(10, 16) if errors >> bit & 1]
    return names


class ProtocolError(ValueError):
    """Bytes that are not a well-formed SMC100 command or reply."""


@dataclass(frozen=True)
class Command:
    address: int
    command: str
    value: float | None
    query: bool


@dataclass(frozen=True)
class Reply:
    address: int
    command: str
    text: str


def format_value(value: float) -> str:
    """Shortest fixed-point text for a parameter: 90.0 → '90', -45.5 → '-45.5' (µ-degree steps)."""
    text = f"{float(value):.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def encode_command(address: int, command: str, value: float | None = None, query: bool = False) -> bytes:
    """`(1, 'PA', 90.0)` → ``b'1PA90\\r\\n'``; `(1, 'TP', query=True)` → ``b'1TP?\\r\\n'``."""
    if not 1 <= address <= 31:
        raise ValueError(f"SMC100 address must be 1..31, got {address}")
    if not re.fullmatch(r"[A-Z]{2}", command):
        raise ValueError(f"SMC100 command must be two upper-case letters, got {command!r}")
    text = f"{address}{command}"
    if value is not None:
        text += format_value(value)
    if query:
        text += "?"
    return text.encode("ascii") + TERMINATOR


_COMMAND_RE = re.compile(rb"(\d{1,2})([A-Z]{2})([-+0-9.eE]*)(\??)\r?\n?")
_NUMBER_RE = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")


def _finite_number(text: str) -> float | None:
    """A plain decimal number (no nan/inf/underscores) that is finite, else None."""
    text = text.strip()
    if not _NUMBER_RE.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None
_REPLY_RE = re.compile(rb"(\d{1,2})([A-Z]{2})([ -~]*?)\r?\n?")


def parse_command(data: bytes) -> Command:
    """``b'1PA90.000\\r\\n'`` → Command(1, 'PA', 90.0, False) (what a device does with a line)."""
    m = _COMMAND_RE.fullmatch(data)
    if m is None:
        raise ProtocolError(f"not an SMC100 command: {data!r}")
    value = None
    if m.group(3):
        value = _finite_number(m.group(3).decode())
        if value is None:
            raise ProtocolError(f"SMC100 command parameter must be a finite number: {data!r}")
    return Command(int(m.group(1)), m.group(2).decode(), value, bool(m.group(4)))


def parse_reply(data: bytes, expect: str | None = None, address: int | None = None) -> Reply:
    """A reply line → Reply(address, command, text); ProtocolError if it is not an SMC100 reply."""
    m = _REPLY_RE.fullmatch(data)
    if m is None:
        raise ProtocolError(f"not an SMC100 reply: {data[:40]!r}")
    reply = Reply(int(m.group(1)), m.group(2).decode(), m.group(3).decode())
    if expect is not None and reply.command != expect:
        raise ProtocolError(f"expected a {expect} reply, got {data[:40]!r}")
    if address is not None and reply.address != address:
        raise ProtocolError(f"expected address {address}, got {data[:40]!r}")
    return reply


def parse_ts(data: bytes | Reply) -> tuple[int, int]:
    """``b'1TS000033\\r\\n'`` → (errors 0x0000, state 0x33)."""
    reply = data if isinstance(data, Reply) else parse_reply(data, "TS")
    if not re.fullmatch(r"[0-9A-Fa-f]{6}", reply.text):
        raise ProtocolError(f"TS reply must carry 6 hex digits, got {reply.text!r}")
    return int(reply.text[:4], 16), int(reply.text[4:], 16)


def parse_te(data: bytes | Reply) -> str:
    """``b'1TEH\\r\\n'`` → 'H' ('@' means no error)."""
    reply = data if isinstance(data, Reply) else parse_reply(data, "TE")
    if len(reply.text) != 1 or not ("@" <= reply.text <= "Z"):
        raise ProtocolError(f"TE reply must carry one letter, got {reply.text!r}")
    return reply.text


def parse_position(data: bytes | Reply, command: str = "TP") -> float:
    """TP / SL / SR reply → degrees: ``b'1TP-12.5\\r\\n'`` → -12.5."""
    reply = data if isinstance(data, Reply) else parse_reply(data, command)
    value = _finite_number(reply.text)
    if value is None:  # nan, inf, '1_0' would pass float() and poison the table angle
        raise ProtocolError(f"{reply.command} reply must carry a finite number, got {reply.text!r}")
    return value


def parse_ve(data: bytes | Reply) -> str:
    """``b'1VE SMC_CC - 2.0.0\\r\\n'`` → 'SMC_CC - 2.0.0'."""
    reply = data if isinstance(data, Reply) else parse_reply(data, "VE")
    return reply.text.strip()
