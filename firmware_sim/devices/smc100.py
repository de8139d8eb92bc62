"""Newport SMC100 rotation-stage controller, the subset of docs/PROTOCOLS.md §1, on a pty.

The codec (bytes ⇄ command/reply) is written here from the protocol sheet. The controller is a
state machine over the physics' table motion: `OR` homes to α = 0, `PA`/`PR` plan a move on
`world.table`; the state goes READY when the *planned* move ends (the table may still ring
a little: that is physics, and the encoder shows it). `TP` reports the encoder, i.e. the
physics' quantized α in degrees. Every command that cannot run leaves its TE letter.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from typing import Any

from firmware_sim import __version__
from firmware_sim.devices.base import Device
from firmware_sim.pty import PtyPort

log = logging.getLogger("firmware_sim.smc100")

# Controller states (SS in TS), docs/PROTOCOLS.md §1
NOT_REFERENCED_FROM_RESET = 0x0A
NOT_REFERENCED_FROM_HOMING = 0x0B
NOT_REFERENCED_FROM_CONFIGURATION = 0x0C
NOT_REFERENCED_FROM_DISABLE = 0x0D
NOT_REFERENCED_FROM_READY = 0x0E
NOT_REFERENCED_FROM_MOVING = 0x0F
CONFIGURATION = 0x14
HOMING = 0x1E
MOVING = 0x28
READY_FROM_HOMING = 0x32
READY_FROM_MOVING = 0x33
READY_FROM_DISABLE = 0x34
DISABLE_FROM_READY = 0x3C
DISABLE_FROM_MOVING = 0x3D

# Positioner error bits (EEEE in TS)
ERR_FOLLOWING = 1 << 5

SOFT_LIMITS_DEG = (-360.0, 360.0)
REST_THRESHOLD_DEG = 1e-6
"""A `move` event's t_rest_s: the table top is within this of its final angle from then on."""
STALL_FRACTION = 0.5
"""Fault stage-stall: the stage jams after this fraction of the move's distance."""


def is_not_referenced(state: int) -> bool:
    return 0x0A <= state <= 0x11


def is_ready(state: int) -> bool:
    return 0x32 <= state <= 0x35


def is_disable(state: int) -> bool:
    return 0x3C <= state <= 0x3E


# ---------------------------------------------------------------------------------------------
# Codec
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SmcCommand:
    """One parsed command line `<addr><CC><param>`."""

    address: int | None
    command: str | None
    param: str
    """Text after the two letters, stripped ('' when none, '?' for an explicit query)."""

    @property
    def query(self) -> bool:
        return self.param == "?"

    @property
    def value(self) -> float | None:
        """The numeric parameter, or None when missing, '?', or not a number."""
        if self.param in ("", "?"):
            return None
        try:
            v = float(self.param)
        except ValueError:
            return None
        return v if math.isfinite(v) else None


_COMMAND_RE = re.compile(r"^(\d*)([A-Za-z]{0,2})(.*)$")


def parse_command(line: bytes | str) -> SmcCommand:
    """`b'1PA90.000\\r\\n'` → SmcCommand(1, 'PA', '90.000'). Never raises: bad parts become None."""
    text = line.decode("ascii", "replace") if isinstance(line, bytes | bytearray) else line
    text = text.strip()
    m = _COMMAND_RE.match(text)
    assert m is not None  # the pattern matches any string
    addr_text, letters, param = m.groups()
    address = int(addr_text) if addr_text else None
    command = letters if len(letters) == 2 and letters.isupper() else None
    return SmcCommand(address, command, param.strip())


def encode_command(address: int, command: str, value: float | str | None = None) -> bytes:
    """The bytes a host sends: `encode_command(1, 'PA', 90)` → b'1PA90\\r\\n'."""
    param = "" if value is None else (value if isinstance(value, str) else format_number(value))
    return f"{address}{command}{param}\r\n".encode("ascii")


def format_number(x: float) -> str:
    """A position on the wire: up to 6 decimals, no trailing zeros (90.0001, -12.5, 360)."""
    text = f"{round(float(x), 6) + 0.0:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def encode_reply(address: int, command: str, payload: str) -> bytes:
    """`encode_reply(1, 'TS', '00000A')` → b'1TS00000A\\r\\n'."""
    return f"{address}{command}{payload}\r\n".encode("ascii")


def encode_status(address: int, errors: int, state: int) -> bytes:
    """TS reply: 4 hex digits of positioner error bits, 2 of controller state."""
    return encode_reply(address, "TS", f"{errors & 0xFFFF:04X}{state & 0xFF:02X}")


def parse_reply(line: bytes | str) -> tuple[int, str, str]:
    """b'1TS00000A\\r\\n' → (1, 'TS', '00000A'); ValueError if it is not a reply line."""
    text = line.decode("ascii") if isinstance(line, bytes | bytearray) else line
    m = re.match(r"^(\d+)([A-Z]{2})(.*)$", text.strip("\r\n"))
    if not m:
        raise ValueError(f"not an SMC100 reply: {text!r}")
    return int(m.group(1)), m.group(2), m.group(3).strip()


# ---------------------------------------------------------------------------------------------
# Controller
# ---------------------------------------------------------------------------------------------
class Smc100(Device):
    """The controller on its own pty, driving `world.table`.

    `stall_move` (fault stage-stall=N): the N-th PA/PR since start jams half-way (the table
    physics stops it short), then the following-error bit is set and the state is DISABLE
    (from MOVING), as on a real stage that jams. `MM1` (or `RS` and `OR`) recovers.
    """

    name = "turntable"

    def __init__(self, world: Any, *, address: int = 1, stall_move: int | None = None,
                 soft_limits_deg: tuple[float, float] = SOFT_LIMITS_DEG, port: PtyPort | None = None,
                 on_event: Any = None) -> None:
        self.world = world
        self.table = world.table
        self.address = int(address)
        self.stall_move = stall_move
        self.default_limits_deg = (float(soft_limits_deg[0]), float(soft_limits_deg[1]))
        self.port = port if port is not None else PtyPort("turntable")
        self.on_event = on_event
        """Called as on_event("move", t, fields) for every planned motion (truth log)."""
        self._rx = bytearray()
        self.moves = 0
        self._reset_state()

    def _reset_state(self) -> None:
        self.state = NOT_REFERENCED_FROM_RESET
        self.errors = 0
        self.last_error = "@"
        self.limits_deg = list(self.default_limits_deg)
        self.target_deg: float | None = None
        self._end_s: float | None = None  # planned end of the current homing/move/stop
        self._stalling = False

    # -- Device surface ---------------------------------------------------------------------
    def fileno(self) -> int | None:
        return self.port.watch_fileno()

    def endpoint(self) -> str:
        return self.port.path

    def close(self) -> None:
        self.port.close()

    def on_readable(self, t_device_s: float) -> None:
        self._rx += self.port.read()
        while True:
            cut = min((i for i in (self._rx.find(b"\r"), self._rx.find(b"\n")) if i >= 0), default=-1)
            if cut < 0:
                if len(self._rx) > 4096:  # garbage without line ends: forget it
                    self._rx.clear()
                return
            line = bytes(self._rx[:cut])
            del self._rx[: cut + 1]
            if line.strip():
                self.advance(t_device_s)
                self.handle_line(line, t_device_s)

    def advance(self, t_device_s: float) -> None:
        if self._end_s is None or t_device_s < self._end_s:
            return
        self._end_s = None
        if self.state == HOMING:
            self.state = READY_FROM_HOMING
            self.target_deg = 0.0
        elif self.state == MOVING:
            if self._stalling:
                self._stalling = False
                self.errors |= ERR_FOLLOWING
                self.state = DISABLE_FROM_MOVING
                self.target_deg = self._encoder_deg(t_device_s)
                log.info("stage stalled (move %d): following error, DISABLE", self.moves)
            else:
                self.state = READY_FROM_MOVING

    # -- commands -----------------------------------------------------------------------------
    def handle_line(self, line: bytes, t: float) -> None:
        """Act on one command line at device time t; replies go to the port."""
        cmd = parse_command(line)
        if cmd.address is None or not 1 <= cmd.address <= 31:
            self._error("B")
            return
        if cmd.address != self.address:
            return  # another controller on the RS-485 chain
        if cmd.command is None:
            self._error("A")
            return
        handler = getattr(self, f"_cmd_{cmd.command.lower()}", None)
        if handler is None:
            self._error("A")
            return
        handler(cmd, t)

    def _reply(self, command: str, payload: str) -> None:
        self.port.write(encode_reply(self.address, command, payload))

    def _error(self, letter: str) -> None:
        self.last_error = letter

    def _state_letter(self) -> str | None:
        """TE letter for 'not allowed in this state', or None when the state allows motion."""
        s = self.state
        if is_not_referenced(s):
            return "H"
        if s == CONFIGURATION:
            return "I"
        if is_disable(s):
            return "J"
        if s == HOMING:
            return "L"
        if s == MOVING:
            return "M"
        return None

    def _cmd_te(self, cmd: SmcCommand, t: float) -> None:
        self._reply("TE", self.last_error)
        self.last_error = "@"

    def _cmd_ts(self, cmd: SmcCommand, t: float) -> None:
        self.port.write(encode_status(self.address, self.errors, self.state))

    def _cmd_tp(self, cmd: SmcCommand, t: float) -> None:
        self._reply("TP", format_number(self._encoder_deg(t)))

    def _cmd_ve(self, cmd: SmcCommand, t: float) -> None:
        self._reply("VE", f" SMC100CC firmware_sim {__version__}")

    def _cmd_rs(self, cmd: SmcCommand, t: float) -> None:
        if self._end_s is not None:
            self.table.stop(t)
        self._reset_state()

    def _cmd_or(self, cmd: SmcCommand, t: float) -> None:
        s = self.state
        if s == HOMING:
            self._error("E")
        elif not is_not_referenced(s):
            self._error(self._state_letter() or "K")
        else:
            self.state = HOMING
            self.errors = 0
            start_deg = self._motor_deg(t)
            self._end_s = float(self.table.home(t))
            self._move_event("home", t, start_deg)

    def _cmd_pa(self, cmd: SmcCommand, t: float) -> None:
        self._move(cmd, t, relative=False)

    def _cmd_pr(self, cmd: SmcCommand, t: float) -> None:
        self._move(cmd, t, relative=True)

    def _move(self, cmd: SmcCommand, t: float, *, relative: bool) -> None:
        if cmd.query:
            if relative or self.target_deg is None:
                self._error("D")
            else:
                self._reply("PA", format_number(self.target_deg))
            return
        value = cmd.value
        if value is None:
            self._error("C")
            return
        letter = self._state_letter()
        if letter is not None:
            self._error(letter)
            return
        base = self.target_deg if self.target_deg is not None else self._encoder_deg(t)
        target = base + value if relative else value
        lo, hi = self.limits_deg
        if not lo <= target <= hi:
            self._error("N")
            return
        self.moves += 1
        self.state = MOVING
        self.target_deg = target
        self._stalling = self.stall_move is not None and self.moves == self.stall_move
        stall = STALL_FRACTION if self._stalling else None
        start_deg = self._motor_deg(t)
        self._end_s = float(self.table.command_move(t, math.radians(target), stall_fraction=stall))
        self._move_event("stall" if self._stalling else "move", t, start_deg)

    def _cmd_st(self, cmd: SmcCommand, t: float) -> None:
        if self.state == MOVING:
            self._stalling = False
            start_deg = self._motor_deg(t)
            self._end_s = float(self.table.stop(t))
            self.target_deg = math.degrees(self.table.target_rad)
            self._move_event("stop", t, start_deg)
        elif self.state == HOMING:
            self._end_s = None
            start_deg = self._motor_deg(t)
            self.table.stop(t)
            self._move_event("stop", t, start_deg)
            self.state = NOT_REFERENCED_FROM_HOMING

    def _limit(self, cmd: SmcCommand, t: float, index: int) -> None:
        name = "SL" if index == 0 else "SR"
        if cmd.query or cmd.param == "":
            self._reply(name, format_number(self.limits_deg[index]))
            return
        value = cmd.value
        if value is None or (index == 0 and value > 0.0) or (index == 1 and value < 0.0):
            self._error("C")
            return
        if self.state in (MOVING, HOMING):
            self._error(self._state_letter() or "D")
            return
        self.limits_deg[index] = value

    def _cmd_sl(self, cmd: SmcCommand, t: float) -> None:
        self._limit(cmd, t, 0)

    def _cmd_sr(self, cmd: SmcCommand, t: float) -> None:
        self._limit(cmd, t, 1)

    def _cmd_pw(self, cmd: SmcCommand, t: float) -> None:
        """PW1 enters CONFIGURATION (from NOT REFERENCED only), PW0 leaves it."""
        if cmd.query or cmd.param == "":
            self._reply("PW", "1" if self.state == CONFIGURATION else "0")
            return
        if cmd.value == 1.0:
            if is_not_referenced(self.state):
                self.state = CONFIGURATION
            elif self.state != CONFIGURATION:
                self._error(self._state_letter() or "K")
        elif cmd.value == 0.0:
            if self.state == CONFIGURATION:
                self.state = NOT_REFERENCED_FROM_CONFIGURATION
        else:
            self._error("C")

    def _cmd_mm(self, cmd: SmcCommand, t: float) -> None:
        """MM0 enters DISABLE from READY, MM1 leaves DISABLE to READY (clears the error bits)."""
        if cmd.query or cmd.param == "":
            self._reply("MM", f"{self.state:02X}")
            return
        if cmd.value == 0.0:
            if is_ready(self.state):
                self.state = DISABLE_FROM_READY
            elif not is_disable(self.state):
                self._error(self._state_letter() or "D")
        elif cmd.value == 1.0:
            if is_disable(self.state):
                self.state = READY_FROM_DISABLE
                self.errors = 0
                self.target_deg = self._encoder_deg(t)
            elif not is_ready(self.state):
                self._error(self._state_letter() or "D")
        else:
            self._error("C")

    # -- physics ---------------------------------------------------------------------------
    def _motor_deg(self, t: float) -> float:
        return math.degrees(float(self.table.motor_kinematics(t)[0]))

    def _move_event(self, kind: str, t: float, from_deg: float) -> None:
        """The plan just made, for the truth log: when the motion starts and ends (the state goes
        READY then), when the top is at rest (ringing under REST_THRESHOLD_DEG), from and to where.
        A later move or stop replaces the plan from its own t_start_s on."""
        if self.on_event is None:
            return
        self.on_event("move", t, {
            "kind": kind, "t_start_s": float(t), "t_end_s": float(self.table.move_end_s),
            "t_rest_s": float(self.table.rest_s(math.radians(REST_THRESHOLD_DEG))),
            "from_deg": from_deg, "to_deg": self._motor_deg(float(self.table.move_end_s)),
            "rest_threshold_deg": REST_THRESHOLD_DEG,
        })

    def _encoder_deg(self, t: float) -> float:
        return math.degrees(float(self.table.encoder_rad(t)))
