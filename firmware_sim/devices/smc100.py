"""Newport SMC100CC single-axis controller on a pty, as its user manual describes it.

Reference: Newport "SMC100CC & SMC100PP Single-Axis Motion Controller/Driver for DC or Stepper
Motor — User's Manual" V3.0.x, EDH0206En2054 (06/23; the 09/18 edition EDH0206En2051 has the same
command pages), chapter 5 "Remote Mode": §5.1 the state diagram, §5.3 command syntax (`xxAAnn`,
CR LF), §5.5 "Command Set": the command list with the states each command is accepted in (p. 18–19)
and one page per command (p. 20–68) with its Usage row, range, errors and example. Pages below are
the printed page numbers of that edition. docs/PROTOCOLS.md §1 carries the tables (marked as taken
from the manual); docs/conformance/smc100.md is generated from this module by
tools/conformance_smc100.py.

The codec (bytes ⇄ command/reply) is written here from the manual. The controller is a state
machine over the physics' table motion: `OR` homes to α = 0, `PA`/`PR` plan a move on
`world.table`, accepted only in READY (p. 41–42; `PR` adds to the current target); the state goes
READY when the *planned* move ends (the table may still ring a little: that is physics, and the
encoder shows it). `TP` reports the encoder, `TH` the set-point. `ST` (p. 56) and `MM` (p. 37)
without an address, or with address 0, act on every controller. `TS` clears the positioner error
bits it reports (the notes on p. 63). JOGGING is entered only from the keypad (`keypad_jog`); `JM`
enables or disables the keypad (p. 31). This is a CC controller: the commands marked "Not for CC"
(`FR`, `VB`) leave TE `X`. Every command that cannot run leaves its TE letter; set and move
commands never reply (the host reads TE).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass
from typing import Any

from firmware_sim import __version__
from firmware_sim.devices.base import PtyDevice
from firmware_sim.pty import PtyPort

log = logging.getLogger("firmware_sim.smc100")

# Controller states (SS in TS), the manual's TS description; docs/PROTOCOLS.md §1
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
DISABLE_FROM_JOGGING = 0x3E
READY_FROM_JOGGING = 0x35
NOT_REFERENCED_FROM_JOGGING = 0x11
JOGGING_FROM_READY = 0x46
JOGGING_FROM_DISABLE = 0x47

# Positioner error bits (EEEE in TS), the manual's TS description (bits 10–15 not used)
POSITIONER_ERROR_BITS: dict[int, str] = {
    0: "Negative end of run",
    1: "Positive end of run",
    2: "Peak current limit",
    3: "RMS current limit",
    4: "Short circuit detection",
    5: "Following error",
    6: "Homing time out",
    7: "Wrong ESP stage",
    8: "DC voltage too low",
    9: "80 W output power exceeded",
}
ERR_FOLLOWING = 1 << 5

# The TE error codes, the manual's "TE — Get command error" table (every letter it defines).
TE_CODES: dict[str, str] = {
    "@": "No error",
    "A": "Unknown message code or floating point controller address",
    "B": "Controller address not correct",
    "C": "Parameter missing or out of range",
    "D": "Command not allowed",
    "E": "Home sequence already started",
    "F": "ESP stage name unknown",
    "G": "Displacement out of limits",
    "H": "Command not allowed in NOT REFERENCED state",
    "I": "Command not allowed in CONFIGURATION state",
    "J": "Command not allowed in DISABLE state",
    "K": "Command not allowed in READY state",
    "L": "Command not allowed in HOMING state",
    "M": "Command not allowed in MOVING state",
    "N": "Current position out of software limit",
    "S": "Communication Time Out",
    "U": "Error during EEPROM access",
    "V": "Error during command execution",
    "W": "Command not allowed for PP version",
    "X": "Command not allowed for CC version",
}

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
    """`b'1PA90.000\\r\\n'` → SmcCommand(1, 'PA', '90.000'). Never raises: bad parts become None.
    §5.3: upper and lower case are accepted, blanks are ignored anywhere (`2P A1.43 6` = `2PA1.436`)."""
    text = line.decode("ascii", "replace") if isinstance(line, bytes | bytearray) else line
    text = "".join(text.split())
    m = _COMMAND_RE.match(text)
    assert m is not None  # the pattern matches any string
    addr_text, letters, param = m.groups()
    address = int(addr_text) if addr_text else None
    command = letters.upper() if len(letters) == 2 else None
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
# The manual's command list: state groups, parameters
# ---------------------------------------------------------------------------------------------
# State groups of the manual's command list columns.
NR, CF, DI, RD = "NOT REFERENCED", "CONFIGURATION", "DISABLE", "READY"
HO, MV, JG = "HOMING", "MOVING", "JOGGING"
STATE_LETTER = {NR: "H", CF: "I", DI: "J", RD: "K", HO: "L", MV: "M", JG: "D"}
"""The TE letter for 'not allowed in this state' (JOGGING has none of its own: D)."""

STATE_NAMES: dict[int, str] = {
    0x0A: "NOT REFERENCED from reset", 0x0B: "NOT REFERENCED from HOMING",
    0x0C: "NOT REFERENCED from CONFIGURATION", 0x0D: "NOT REFERENCED from DISABLE",
    0x0E: "NOT REFERENCED from READY", 0x0F: "NOT REFERENCED from MOVING",
    0x10: "NOT REFERENCED ESP stage error", 0x11: "NOT REFERENCED from JOGGING",
    0x14: "CONFIGURATION", 0x1E: "HOMING commanded from RS-232-C", 0x1F: "HOMING commanded by Keypad",
    0x28: "MOVING", 0x32: "READY from HOMING", 0x33: "READY from MOVING", 0x34: "READY from DISABLE",
    0x35: "READY from JOGGING", 0x3C: "DISABLE from READY", 0x3D: "DISABLE from MOVING",
    0x3E: "DISABLE from JOGGING", 0x46: "JOGGING from READY", 0x47: "JOGGING from DISABLE",
}
"""Controller states, the manual's TS description."""

WORKING = frozenset({CF, DI, RD})
"""Where a working motion parameter may be set (CONFIGURATION stores it, PW0 saves it): the
manual's Usage row for AC, JR, VA, SL, SR (p. 20, 32, 64, 54, 55)."""
LOOP = frozenset({CF, DI})
"""The control-loop parameters FD, FE, FF, KD, KI, KP, KV: CONFIGURATION and DISABLE (p. 24–26, 33–36)."""
CONFIG_ONLY = frozenset({CF})


@dataclass(frozen=True)
class Param:
    """One parameter of the command list with a set and a query form."""

    title: str
    default: float | int | str
    low: float = 0.0
    high: float = 1e12
    set_in: frozenset[str] = CONFIG_ONLY
    kind: str = "float"  # float, int, str


PARAMS: dict[str, Param] = {
    "AC": Param("Set/Get acceleration", 80.0, 1e-6, 1e12, WORKING),
    "BA": Param("Set/Get backlash compensation", 0.0),
    "BH": Param("Set/Get hysteresis compensation", 0.0),
    "DV": Param("Set/Get driver voltage", 48.0, 12.0, 48.0),
    "FD": Param("Set/Get low pass filter for Kd", 1000.0, 1e-6, 2000.0, LOOP),
    "FE": Param("Set/Get following error limit", 0.5, 1e-6, 1e12, LOOP),
    "FF": Param("Set/Get friction compensation", 0.0, 0.0, 1e12, LOOP),
    "HT": Param("Set/Get HOME search type", 1, 0, 4, kind="int"),
    "ID": Param("Set/Get stage identifier", "URS100BCC", kind="str"),
    "JM": Param("Enable/disable keypad", 1, 0, 1, WORKING, kind="int"),
    "JR": Param("Set/Get jerk time", 0.05, 0.001, 1e12, WORKING),
    "KD": Param("Set/Get derivative gain", 0.0, 0.0, 1e12, LOOP),
    "KI": Param("Set/Get integral gain", 10.0, 0.0, 1e12, LOOP),
    "KP": Param("Set/Get proportional gain", 100.0, 0.0, 1e12, LOOP),
    "KV": Param("Set/Get velocity feed forward", 0.0, 0.0, 1e12, LOOP),
    "OH": Param("Set/Get HOME search velocity", 20.0, 1e-6, 1e12),
    "OT": Param("Set/Get HOME search time-out", 100.0, 1.0, 1e3),
    "SA": Param("Set/Get controller's RS-485 address", 1, 2, 31, kind="int"),
    "SC": Param("Set/Get control loop state", 1, 0, 1, CONFIG_ONLY, kind="int"),
    "SU": Param("Set/Get encoder increment value", 1e-4, 1e-6, 1e12),
    "VA": Param("Set/Get velocity", 20.0, 1e-6, 1e12, WORKING),
    "ZX": Param("Set/Get SmartStage configuration", 2, 1, 3, CONFIG_ONLY, kind="int"),
}
"""Stored parameters, allowed states from each command's Usage row in the manual. A value set in
CONFIGURATION is saved by PW0 (the controller's memory); one set in another allowed state is a
working value that RS forgets."""

QI_LIMITS: dict[str, tuple[str, float, float, float]] = {
    "L": ("peak current limit, A", 1.5, 0.05, 3.0),
    "R": ("rms current limit, A", 0.5, 0.05, 1.5),
    "T": ("rms current averaging time, s", 1.0, 0.01, 100.0),
}
"""QI's three sub-parameters (p. 45): `xxQILnn`, `xxQIRnn`, `xxQITnn` and their `?` forms, set in
CONFIGURATION only; QIR must not exceed QIL; QIT > 0.01 s."""

PP_ONLY = {"FR": "Set/Get stepper motor configuration", "VB": "Set/Get base velocity"}
"""Commands the manual's command list marks "Not for CC" (p. 18): this CC controller answers TE X.
(DV, FD, FE, FF, KD, KI, KP, KV, SC, SU are marked "Not for PP": a CC controller has them.)"""

COMMANDS: dict[str, str] = {
    **{code: p.title for code, p in PARAMS.items()},
    **PP_ONLY,
    "JD": "Leave JOGGING state", "MM": "Enter/Leave DISABLE state",
    "OR": "Execute HOME search", "PA": "Move absolute", "PR": "Move relative",
    "PT": "Get motion time for a relative move", "PW": "Enter/Leave CONFIGURATION state",
    "QI": "Set/Get motor's current limits",
    "RA": "Get analog input value", "RB": "Get TTL input value", "RS": "Reset controller",
    "SB": "Set/Get TTL output value", "SE": "Configure/Execute simultaneous started move",
    "SL": "Set/Get negative software limit", "SR": "Set/Get positive software limit",
    "ST": "Stop motion", "TB": "Get command error string", "TE": "Get command error",
    "TH": "Get set-point position", "TP": "Get current position",
    "TS": "Get positioner error and controller state", "VE": "Get controller revision information",
    "ZT": "Get all axis parameters",
}
"""Every two-letter command of the manual's command list, with the manual's title."""

ZT_ORDER = ("AC", "BA", "BH", "DV", "FD", "FE", "FF", "HT", "JM", "JR", "KD", "KI", "KP", "KV", "OH", "OT",
            "QIL", "QIR", "QIT", "SA", "SC", "SL", "SR", "SU", "VA", "ZX")
"""What ZT dumps (p. 67), one `<addr><CC><value>` line each. The manual's example shows the first
and last lines, `1PW1` both (both editions, 2018 and 2023), floats with six decimals
(`1AC320.000000`, `1BA0.000000`, `1VA80.000000`), integers bare (`1ZX3`), in alphabetical
order; which parameters sit between `BA` and `VA` it elides (`…`): this list is firmware-sim's."""
CONFIG_EXCEPT_JOGGING = frozenset({NR, CF, DI, RD, HO, MV})
"""RS, TE and ZT: every state but JOGGING (their Usage rows, p. 48, 59, 67)."""


def state_group(state: int) -> str:
    """The command-list column a controller state belongs to."""
    if is_not_referenced(state):
        return NR
    if state == CONFIGURATION:
        return CF
    if state in (0x1E, 0x1F):
        return HO
    if state == MOVING:
        return MV
    if is_ready(state):
        return RD
    if is_disable(state):
        return DI
    return JG


def motion_time_s(distance: float, velocity: float, acceleration: float) -> float:
    """PT: a trapezoidal move's duration (triangular when it never reaches `velocity`)."""
    d = abs(float(distance))
    if d * acceleration >= velocity * velocity:
        return d / velocity + velocity / acceleration
    return 2.0 * math.sqrt(d / acceleration)


# ---------------------------------------------------------------------------------------------
# Controller
# ---------------------------------------------------------------------------------------------
class Smc100(PtyDevice):
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
        self.saved: dict[str, Any] = {code: p.default for code, p in PARAMS.items()}
        self.saved.update({f"QI{sub}": spec[1] for sub, spec in QI_LIMITS.items()})
        """The controller's memory (what PW0 saved); the table's own figures for AC, VA, OH, SU."""
        self.saved.update(AC=math.degrees(self.table.accel_rad_s2), VA=math.degrees(self.table.speed_rad_s),
                          OH=math.degrees(self.table.home_speed_rad_s), SA=self.address)
        if self.table.encoder_step_rad > 0:
            self.saved["SU"] = math.degrees(self.table.encoder_step_rad)
        self._table_rad = {"AC": self.table.accel_rad_s2, "VA": self.table.speed_rad_s,
                           "OH": self.table.home_speed_rad_s}
        self._table_deg = {code: self.saved[code] for code in self._table_rad}
        self._reset_state()

    def _reset_state(self) -> None:
        self.state = NOT_REFERENCED_FROM_RESET
        self.errors = 0
        self.last_error = "@"
        self.limits_deg = list(self.default_limits_deg)
        self.target_deg: float | None = None
        self._end_s: float | None = None  # planned end of the current homing/move/stop
        self._stalling = False
        self.params: dict[str, Any] = dict(self.saved)
        self.ttl_out = 0
        self.se_target_deg: float | None = None
        self._pending: dict[str, Any] = {}
        self._apply_motion_params()

    def _apply_motion_params(self) -> None:
        """AC, VA, OH drive the table's planner (the table's own figures, bit for bit, until changed)."""
        rad = {code: (self._table_rad[code] if self.params[code] == self._table_deg[code]
                      else math.radians(float(self.params[code]))) for code in self._table_rad}
        self.table.accel_rad_s2, self.table.speed_rad_s, self.table.home_speed_rad_s = (
            rad["AC"], rad["VA"], rad["OH"])

    # -- Device surface ---------------------------------------------------------------------
    def on_input(self, data: bytes, t_device_s: float) -> None:
        self._rx += data
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
        if cmd.address in (None, 0) and cmd.command in ("ST", "MM"):
            # ST (p. 56) and MM (p. 37) without an address or with address 0: every controller
            handler = self._cmd_st if cmd.command == "ST" else self._cmd_mm
            handler(cmd, t)
            return
        if cmd.address is None:
            if cmd.command == "SE" and cmd.param == "":  # bare SE (p. 52): start the SE moves
                self._execute_simultaneous(t)
            else:
                self._error("B")
            return
        if not 1 <= cmd.address <= 31:
            self._error("B")
            return
        if cmd.address != self.address:
            return  # another controller on the RS-485 chain
        if cmd.command is None:
            self._error("A")
            return
        if cmd.command in PP_ONLY:
            self._error("X")
            return
        if cmd.command in PARAMS:
            self._param(cmd.command, cmd, t)
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

    def _refused_here(self, allowed: frozenset[str] | set[str]) -> bool:
        """Leave the state's TE letter and say True when the present state is not `allowed`."""
        group = state_group(self.state)
        if group in allowed:
            return False
        self._error(STATE_LETTER[group])
        return True

    def _param(self, code: str, cmd: SmcCommand, t: float) -> None:
        """A stored parameter: `?` (or nothing) answers it, a value sets it where allowed."""
        spec = PARAMS[code]
        if cmd.query or cmd.param == "":
            # ZX? answers the stage reference (p. 68: `1ZX?` → `1ZXURS100CC`), not ZX's value
            self._reply(code, self._format_param("ID" if code == "ZX" else code))
            return
        if self._refused_here(spec.set_in):
            return
        if spec.kind == "str":
            value: Any = cmd.param
            if not 1 <= len(value) <= 31 or not value.isprintable():
                self._error("C")
                return
        else:
            number = cmd.value
            if number is None or not spec.low <= number <= spec.high or (
                    spec.kind == "int" and number != int(number)):
                self._error("C")
                return
            value = int(number) if spec.kind == "int" else float(number)
        self.params[code] = value
        if self.state == CONFIGURATION:
            self._pending[code] = value
        if code in ("AC", "VA", "OH"):
            self._apply_motion_params()

    def _format_param(self, code: str) -> str:
        value = self.params[code]
        return value if isinstance(value, str) else format_number(value)

    def _cmd_te(self, cmd: SmcCommand, t: float) -> None:
        if self._refused_here(CONFIG_EXCEPT_JOGGING):
            return
        self._reply("TE", self.last_error)
        self.last_error = "@"

    def _cmd_qi(self, cmd: SmcCommand, t: float) -> None:
        """QIL/QIR/QIT (p. 45): peak and rms current limits, rms averaging time; CONFIGURATION only."""
        sub, param = cmd.param[:1].upper(), cmd.param[1:].strip()
        if sub not in QI_LIMITS:
            self._error("C")
            return
        key = f"QI{sub}"
        if param in ("", "?"):
            self._reply(key, format_number(self.params[key]))
            return
        if self._refused_here(CONFIG_ONLY):
            return
        try:
            value = float(param)
        except ValueError:
            value = math.nan
        _, _, low, high = QI_LIMITS[sub]
        ok = low <= value <= high if sub != "T" else low < value <= high
        if sub == "R" and not value <= float(self.params["QIL"]):
            ok = False
        if sub == "L" and not value >= float(self.params["QIR"]):
            ok = False
        if not ok:
            self._error("C")
            return
        self.params[key] = value
        self._pending[key] = value

    def _cmd_tb(self, cmd: SmcCommand, t: float) -> None:
        """TB<letter> → that code's text; TB alone → the last error's (and clears it, as TE)."""
        letter = cmd.param if cmd.param not in ("", "?") else self.last_error
        if letter not in TE_CODES:
            self._error("C")
            return
        self._reply("TB", f"{letter} {TE_CODES[letter]}")
        if cmd.param in ("", "?"):
            self.last_error = "@"

    def _cmd_ts(self, cmd: SmcCommand, t: float) -> None:
        """TS (p. 62–63): the notes say TS reads the positioner error buffer and clears it."""
        self.port.write(encode_status(self.address, self.errors, self.state))
        self.errors = 0

    def _cmd_tp(self, cmd: SmcCommand, t: float) -> None:
        self._reply("TP", format_number(self._encoder_deg(t)))

    def _cmd_th(self, cmd: SmcCommand, t: float) -> None:
        self._reply("TH", format_number(math.degrees(float(self.table.planned_kinematics(t)[0]))))

    def _cmd_ve(self, cmd: SmcCommand, t: float) -> None:
        self._reply("VE", f" SMC100CC firmware_sim {__version__}")

    def _cmd_ra(self, cmd: SmcCommand, t: float) -> None:
        self._reply("RA", "0")  # nothing wired to the analog input: 0 V

    def _cmd_rb(self, cmd: SmcCommand, t: float) -> None:
        self._reply("RB", "0")  # no TTL input driven

    def _cmd_sb(self, cmd: SmcCommand, t: float) -> None:
        if cmd.query or cmd.param == "":
            self._reply("SB", str(self.ttl_out))
            return
        if self._refused_here({DI, RD, HO, MV, JG}):  # SB's Usage row (p. 50)
            return
        value = cmd.value
        if value is None or value != int(value) or not 0 <= value <= 15:
            self._error("C")
            return
        self.ttl_out = int(value)

    def _cmd_zt(self, cmd: SmcCommand, t: float) -> None:
        """The multi-line parameter dump as the manual's example prints it (p. 67): `1PW1`, one
        line per parameter (floats with six decimals), `1PW1` again."""
        if self._refused_here(CONFIG_EXCEPT_JOGGING):
            return
        lines = [encode_reply(self.address, "PW", "1")]
        for code in ZT_ORDER:
            if code == "SL":
                value: Any = self.limits_deg[0]
            elif code == "SR":
                value = self.limits_deg[1]
            else:
                value = self.params[code]
            text = value if isinstance(value, str | int) else f"{float(value):.6f}"
            lines.append(encode_reply(self.address, code, str(text)))
        lines.append(encode_reply(self.address, "PW", "1"))
        self.port.write(b"".join(lines))

    def _cmd_pt(self, cmd: SmcCommand, t: float) -> None:
        if self._refused_here({DI, RD, HO, MV}):  # PT's Usage row (p. 43)
            return
        value = cmd.value
        if value is None or not 1e-6 < value < 1e12:  # PT's range (p. 43): > 1e-6 and < 1e12
            self._error("C")
            return
        seconds = motion_time_s(value, float(self.params["VA"]), float(self.params["AC"]))
        self._reply("PT", format_number(seconds))

    def _cmd_rs(self, cmd: SmcCommand, t: float) -> None:
        if self._refused_here(CONFIG_EXCEPT_JOGGING):
            return
        if cmd.param == "##":  # RS##: the address back to 1 (not in the user manual: public drivers')
            self.saved["SA"] = 1
            self.address = 1
        if self._end_s is not None:
            self.table.stop(t)
        self._reset_state()

    def _cmd_or(self, cmd: SmcCommand, t: float) -> None:
        s = self.state
        if s == HOMING:
            self._error("E")
        elif not self._refused_here({NR}):
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
        """PA/PR (p. 41–42): "only accepted in READY state"; PR adds to the current target."""
        # PA? and PR? both return the target position (p. 41, 42)
        value = self._ready_value(cmd, cmd.query, "PR" if relative else "PA", self.target_deg)
        if value is None:
            return
        base = self.target_deg if self.target_deg is not None else self._encoder_deg(t)
        target = base + value if relative else value
        self._start_move(target, t)

    def _ready_value(self, cmd: SmcCommand, query: bool, code: str,
                     current_deg: float | None) -> float | None:
        """The number a READY-only target command (PA, PR, SE) sets, or None once it is answered: a
        query replies `current_deg` (error D while there is none), no number is error C, and another
        state refuses it with that state's error."""
        if query:
            if current_deg is None:
                self._error("D")
            else:
                self._reply(code, format_number(current_deg))
            return None
        if cmd.value is None:
            self._error("C")
            return None
        if self._refused_here({RD}):
            return None
        return cmd.value

    def _start_move(self, target: float, t: float) -> None:
        lo, hi = self.limits_deg
        if not lo <= self._encoder_deg(t) <= hi:
            self._error("N")
            return
        if not lo <= target <= hi:
            self._error("G")
            return
        self.moves += 1
        self.state = MOVING
        self.target_deg = target
        self._stalling = self.stall_move is not None and self.moves == self.stall_move
        stall = STALL_FRACTION if self._stalling else None
        start_deg = self._motor_deg(t)
        self._end_s = float(self.table.command_move(t, math.radians(target), stall_fraction=stall))
        self._move_event("stall" if self._stalling else "move", t, start_deg)

    def _cmd_se(self, cmd: SmcCommand, t: float) -> None:
        """xxSEnn configures the target of a simultaneous start; a bare SE starts them all."""
        value = self._ready_value(cmd, cmd.query or cmd.param == "", "SE", self.se_target_deg)
        if value is None:
            return
        lo, hi = self.limits_deg
        if not lo <= value <= hi:
            self._error("G")
            return
        self.se_target_deg = value

    def _execute_simultaneous(self, t: float) -> None:
        if self.se_target_deg is None or state_group(self.state) != RD:
            return
        target, self.se_target_deg = self.se_target_deg, None
        self._start_move(target, t)

    def _cmd_st(self, cmd: SmcCommand, t: float) -> None:
        """ST (p. 56): DISABLE, READY (nothing to stop) and motion; H, I elsewhere, D in JOGGING."""
        if self._refused_here({DI, RD, HO, MV}):
            return
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
        if self._refused_here(WORKING):
            return
        if self.state != CONFIGURATION and self.target_deg is not None and (
                (index == 0 and value > self.target_deg) or (index == 1 and value < self.target_deg)):
            self._error("C")  # p. 54-55: SL ≤ set-point ≤ SR as a working value
            return
        self.limits_deg[index] = value

    def _cmd_sl(self, cmd: SmcCommand, t: float) -> None:
        self._limit(cmd, t, 0)

    def _cmd_sr(self, cmd: SmcCommand, t: float) -> None:
        self._limit(cmd, t, 1)

    def _cmd_pw(self, cmd: SmcCommand, t: float) -> None:
        """PW1 enters CONFIGURATION from NOT REFERENCED, PW0 saves and leaves it (p. 44: allowed in
        those two states; J K L M elsewhere). PW1 in CONFIGURATION, PW0 in NOT REFERENCED: nothing to do."""
        if cmd.query or cmd.param == "":
            self._reply("PW", "1" if self.state == CONFIGURATION else "0")
            return
        if cmd.value not in (0.0, 1.0):
            self._error("C")
            return
        if self._refused_here({NR, CF}):
            return
        if cmd.value == 1.0 and self.state != CONFIGURATION:
            self.state = CONFIGURATION
            self._pending = {}
        elif cmd.value == 0.0 and self.state == CONFIGURATION:
            self.saved.update(self._pending)
            if "SA" in self._pending:
                self.address = int(self._pending["SA"])
            self.state = NOT_REFERENCED_FROM_CONFIGURATION

    def _cmd_mm(self, cmd: SmcCommand, t: float) -> None:
        """MM0 enters DISABLE from READY, MM1 leaves DISABLE to READY (clears the error bits)."""
        if cmd.query or cmd.param == "":
            self._reply("MM", f"{self.state:02X}")
            return
        if self._refused_here({DI, RD}):  # MM's Usage row (p. 37)
            return
        if cmd.value == 0.0:
            if is_ready(self.state):
                self.state = DISABLE_FROM_READY
        elif cmd.value == 1.0:
            if is_disable(self.state):
                self.state = READY_FROM_DISABLE
                self.errors = 0
                self.target_deg = self._encoder_deg(t)
        else:
            self._error("C")

    def keypad_jog(self) -> None:
        """A jog button pressed on the keypad (the only way into JOGGING: no command enters it;
        JD leaves it, p. 30). Allowed from READY or DISABLE while the keypad is enabled (JM1)."""
        if int(self.params["JM"]) == 1 and (is_ready(self.state) or is_disable(self.state)):
            self.state = JOGGING_FROM_READY if is_ready(self.state) else JOGGING_FROM_DISABLE

    def _cmd_jd(self, cmd: SmcCommand, t: float) -> None:
        if not self._refused_here({JG}):
            self.state = READY_FROM_JOGGING

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
