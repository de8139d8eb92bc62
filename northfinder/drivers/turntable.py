"""Newport SMC100 rotation stage driver (docs/PROTOCOLS.md §1).

Every line sent and received goes to the transcript (a path or a text file) with a host
timestamp; that logging happens in one place, :class:`northfinder.transport.SerialTransport`.
After every set or move command the driver asks ``TE`` (and ``TS`` when there is an error) and
raises :class:`StageError` naming the controller state and the TE letter. A reply that is not an
SMC100 reply raises :class:`~northfinder.errors.DeviceError` ("… does not answer like an SMC100").

Example::

    from northfinder.drivers.turntable import Turntable

    with Turntable("/dev/ttyUSB0", transcript="stage.log") as stage:
        print(stage.version(), stage.status().state_name)
        stage.ensure_referenced()          # homes (OR) if NOT REFERENCED
        stage.move_absolute_deg(90.0)      # PA90, checks TE, waits for READY
        print(stage.position_deg())        # TP: the encoder, in degrees (= table angle α)
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, TextIO

from northfinder.codecs import smc100
from northfinder.devices.stage import StageFault
from northfinder.errors import DeviceError
from northfinder.transport import SerialTransport

__all__ = ["StageError", "StageStatus", "Turntable"]

DEVICE = "turntable"


class StageError(StageFault):
    """The stage refused a command or is in a state that stops the run.

    `state` (int) and `state_name`, `letter` (TE, '@' none) and `errors` (positioner bits)
    are attributes; the message names the state and the letter.
    """

    def __init__(self, port: str | None, what: str, *, state: int | None = None, letter: str | None = None,
                 errors: int = 0) -> None:
        self.state = state
        self.state_name = smc100.state_name(state) if state is not None else None
        self.letter = letter
        self.reason = f"TE '{letter}' ({smc100.TE_MEANINGS.get(letter, 'unknown')})" if letter else None
        self.errors = errors
        parts = [what]
        if state is not None:
            parts.append(f"state {self.state_name} (0x{state:02X})")
        if letter is not None:
            parts.append(f"TE '{letter}' ({smc100.TE_MEANINGS.get(letter, 'unknown letter')})")
        if errors:
            parts.append("positioner errors: " + ", ".join(smc100.error_names(errors)))
        super().__init__(DEVICE, port, "; ".join(parts))


@dataclass(frozen=True)
class StageStatus:
    """A decoded TS reply."""

    state: int
    errors: int

    @property
    def state_name(self) -> str:
        return smc100.state_name(self.state)

    @property
    def error_names(self) -> list[str]:
        return smc100.error_names(self.errors)

    @property
    def is_ready(self) -> bool:
        return smc100.is_ready(self.state)

    @property
    def is_moving(self) -> bool:
        return smc100.is_moving(self.state)

    @property
    def is_homing(self) -> bool:
        return smc100.is_homing(self.state)

    @property
    def is_referenced(self) -> bool:
        return not smc100.is_not_referenced(self.state)

    @property
    def is_disabled(self) -> bool:
        return smc100.is_disabled(self.state)


class _LineTransport(Protocol):  # what the driver needs from SerialTransport (tests pass their own)
    url: str

    def write(self, data: bytes) -> None: ...
    def read_until(self, terminator: bytes = ..., size: int | None = ...) -> bytes: ...
    def reset_input_buffer(self) -> None: ...
    def note(self, text: str) -> None: ...
    def close(self) -> None: ...


class Turntable:
    """An SMC100 stage on a pyserial URL; a context manager. Angles in degrees."""

    def __init__(
        self,
        port: str,
        *,
        address: int = 1,
        baudrate: int = 57600,
        timeout_s: float = 1.0,
        transcript: str | Path | TextIO | None = None,
        transport: _LineTransport | None = None,
    ) -> None:
        if not 1 <= int(address) <= 31:
            raise DeviceError(DEVICE, port, f"address {address} is out of range — the SMC100 takes 1..31")
        self.port = port
        self.address = int(address)
        self.timeout_s = timeout_s
        self._t = transport if transport is not None else SerialTransport(
            port, device=DEVICE, baudrate=baudrate, timeout_s=timeout_s, transcript=transcript, xonxoff=False
        )

    # -- lines -------------------------------------------------------------------------------
    def _send(self, command: str, value: float | None = None, query: bool = False) -> None:
        self._t.write(smc100.encode_command(self.address, command, value, query))

    def _ask(self, command: str, query: bool = False) -> smc100.Reply:
        """Send a query and return its parsed reply; DeviceError if nothing or garbage comes back."""
        self._t.reset_input_buffer()
        self._send(command, query=query)
        line = self._t.read_until(b"\r\n", 128)
        if not line:
            raise DeviceError(
                DEVICE, self.port,
                f"no answer to {self.address}{command} within {self.timeout_s:g} s — is the stage powered, "
                f"on this port, at address {self.address}?"
            )
        try:
            return smc100.parse_reply(line, expect=command, address=self.address)
        except smc100.ProtocolError:
            raise DeviceError(
                DEVICE, self.port,
                f"the device on {self.port} does not answer like an SMC100 (got {line[:24]!r}) "
                "— is it the right port?"
            ) from None

    def _parse(self, fn, reply: smc100.Reply):
        try:
            return fn(reply)
        except smc100.ProtocolError as exc:
            raise DeviceError(
                DEVICE, self.port, f"the device on {self.port} does not answer like an SMC100 ({exc}) "
                "— is it the right port?"
            ) from None

    def _checked(self, command: str, value: float | None = None, what: str | None = None) -> None:
        """Send a set/move command, then TE; on an error letter read TS and raise StageError."""
        self._send(command, value)
        letter = self.last_error()
        if letter != "@":
            st = self.status()
            text = what or f"{command}{'' if value is None else smc100.format_value(value)} refused"
            raise StageError(self.port, text, state=st.state, letter=letter, errors=st.errors)

    # -- the API -----------------------------------------------------------------------------
    def version(self) -> str:
        """VE: the controller's version text."""
        return self._parse(smc100.parse_ve, self._ask("VE"))

    def status(self) -> StageStatus:
        """TS: controller state and positioner error bits."""
        errors, state = self._parse(smc100.parse_ts, self._ask("TS"))
        return StageStatus(state=state, errors=errors)

    def last_error(self) -> str:
        """TE: the last command's error letter, '@' for none (reading it clears it)."""
        return self._parse(smc100.parse_te, self._ask("TE"))

    def position_deg(self) -> float:
        """TP: the encoder position in degrees."""
        return self._parse(smc100.parse_position, self._ask("TP"))

    def soft_limits_deg(self) -> tuple[float, float]:
        """SL?/SR?: the negative and positive software limits in degrees."""
        lo = self._parse(lambda r: smc100.parse_position(r, "SL"), self._ask("SL", query=True))
        hi = self._parse(lambda r: smc100.parse_position(r, "SR"), self._ask("SR", query=True))
        return lo, hi

    def home(self, timeout_s: float = 120.0, wait: bool = True) -> StageStatus | None:
        """OR (search the reference, α = 0); with `wait`, block until READY."""
        self._checked("OR", what="home (OR) refused")
        return self.wait_ready(timeout_s) if wait else None

    def enable(self) -> StageStatus:
        """MM1: leave DISABLE (after a following error) for READY, clearing the error bits; the
        reference is kept. StageError if the controller refuses or is still not READY."""
        self._checked("MM", 1, what="enable (MM1) refused")
        st = self.status()
        if not st.is_ready or st.errors:
            raise StageError(self.port, "still not READY after MM1 — check the stage (jammed, overloaded?)",
                             state=st.state, errors=st.errors)
        return st

    def ensure_referenced(self, allow_home: bool = True) -> StageStatus:
        """Home if the stage is NOT REFERENCED (StageError if that is not allowed); wait if busy."""
        st = self.status()
        if not st.is_referenced:
            if not allow_home:
                raise StageError(self.port, "the stage is not referenced and homing is not allowed — "
                                 "home it or allow homing", state=st.state, errors=st.errors)
            return self.home()
        if st.is_moving or st.is_homing:
            return self.wait_ready()
        if st.is_disabled or st.errors or not st.is_ready:
            raise StageError(self.port, "the stage cannot move — enable it / clear the error (RS) first",
                             state=st.state, errors=st.errors)
        return st

    def move_absolute_deg(self, angle_deg: float, wait: bool = True,
                          timeout_s: float = 120.0) -> StageStatus | None:
        """PA: move to `angle_deg`; with `wait`, block until READY."""
        self._checked("PA", float(angle_deg), what=f"move to {float(angle_deg):g}° (PA) refused")
        return self.wait_ready(timeout_s) if wait else None

    def move_relative_deg(self, delta_deg: float, wait: bool = True,
                          timeout_s: float = 120.0) -> StageStatus | None:
        """PR: move by `delta_deg`; with `wait`, block until READY."""
        self._checked("PR", float(delta_deg), what=f"move by {float(delta_deg):g}° (PR) refused")
        return self.wait_ready(timeout_s) if wait else None

    def wait_ready(self, timeout_s: float = 120.0, poll_s: float = 0.05) -> StageStatus:
        """Poll TS until READY (at least once); StageError on DISABLE, error bits, NOT REFERENCED
        or when `timeout_s` passes."""
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.status()
            if st.is_ready and not st.errors:
                return st
            if st.errors or st.is_disabled or not st.is_referenced:
                letter = self.last_error()
                raise StageError(self.port, "the stage stopped short of READY", state=st.state,
                                 letter=letter, errors=st.errors)
            if time.monotonic() >= deadline:
                raise StageError(self.port, f"not READY after {timeout_s:g} s — check the stage and the "
                                 "move timeout", state=st.state, errors=st.errors)
            time.sleep(poll_s)

    def stop(self, timeout_s: float = 10.0, poll_s: float = 0.05) -> StageStatus:
        """ST (stop motion), then poll until neither MOVING nor HOMING. Never raises StageError
        for the TE letter: this is the safe path (Ctrl-C)."""
        self._send("ST")
        self.last_error()
        deadline = time.monotonic() + timeout_s
        while True:
            st = self.status()
            if not (st.is_moving or st.is_homing) or time.monotonic() >= deadline:
                return st
            time.sleep(poll_s)

    def close(self) -> None:
        """Close the port (and the transcript if the driver opened it)."""
        self._t.close()

    def __enter__(self) -> Turntable:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Turntable({self.port!r}, address={self.address})"
