"""A lab's rotation stage as a northfinder model, written with the lab's own serial code.

The stage here is a Newport SMC100-compatible controller (the one firmware-sim emulates), driven by
these few lines of pyserial rather than northfinder's own SMC100 model: the point is the surface a
lab implements (northfinder.devices.stage.RotaryStage) and the entry point that registers it
(`[project.entry-points."northfinder.models"]` in pyproject.toml). Nothing here is northfinder's
SMC100 code; commands and states are from the SMC100 manual's command set (TS, OR, PA, TP, ST, SL?,
SR?, MM1, VE, TE).
"""

from __future__ import annotations

import time
from typing import Any

import serial

from northfinder.devices.registry import ModelSpec
from northfinder.devices.stage import RotaryStage, StageFault, StageState

READY = {0x32, 0x33, 0x34, 0x35}
DISABLED = {0x3C, 0x3D, 0x3E}


class LabStage(RotaryStage):
    """The lab's stage: one ASCII line out, one line back."""

    def __init__(self, port: str, address: int = 1, log_path: Any = None) -> None:
        self.port = port
        self._addr = str(int(address))
        self._serial = serial.serial_for_url(port, baudrate=57600, timeout=2.0, exclusive=True)
        self._log = open(log_path, "a", encoding="utf-8") if log_path else None  # noqa: SIM115

    def _ask(self, command: str) -> str:
        line = f"{self._addr}{command}\r\n"
        self._serial.write(line.encode("ascii"))
        reply = self._serial.read_until(b"\r\n").decode("ascii", "replace").strip()
        if self._log:
            self._log.write(f"> {line.strip()}\n< {reply}\n")
        if not reply:
            raise StageFault(self.role, self.port, f"no reply to {command!r} — is the lab stage on?")
        return reply[len(self._addr) + 2:]

    def _send(self, command: str) -> None:
        self._serial.write(f"{self._addr}{command}\r\n".encode("ascii"))
        if self._log:
            self._log.write(f"> {self._addr}{command}\n")

    def state(self) -> StageState:
        rest = self._ask("TS")
        errors, code = int(rest[:4], 16), int(rest[4:6], 16)
        stuck = errors or code in DISABLED
        fault = f"controller state 0x{code:02X}, error bits 0x{errors:04X}" if stuck else None
        return StageState(name=f"0x{code:02X}", ready=code in READY and not errors, moving=code == 0x28,
                          homing=code in (0x1E, 0x1F), referenced=not 0x0A <= code <= 0x11, fault=fault)

    def start_home(self) -> None:
        self._send("OR")

    def start_move(self, angle_deg: float) -> None:
        self._send(f"PA{angle_deg:.6f}")

    def angle_deg(self) -> float:
        return float(self._ask("TP"))

    def halt(self) -> StageState:
        self._send("ST")
        for _ in range(200):
            st = self.state()
            if not (st.moving or st.homing):
                return st
            time.sleep(0.05)
        return st

    def limits_deg(self) -> tuple[float, float]:
        return float(self._ask("SL?")), float(self._ask("SR?"))

    def re_enable(self) -> None:
        self._send("MM1")

    def raise_fault(self, state: StageState) -> None:
        exc = StageFault(self.role, self.port, f"the lab stage stopped short: {state.fault or state.name}; "
                         f"last error {self._ask('TE')!r}")
        exc.state_name, exc.reason = state.name, state.fault
        raise exc

    def identity(self) -> dict[str, Any]:
        return {"model": "labstage", "version": self._ask("VE")}

    def close(self) -> None:
        self._serial.close()
        if self._log:
            self._log.close()


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> LabStage:
    return LabStage(section.port, getattr(section, "address", 1), log_path)


SPEC = ModelSpec("turntable", "labstage", _open, None, "a lab's own stage (northfinder's test fixture)")
