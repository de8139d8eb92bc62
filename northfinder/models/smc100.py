"""Newport SMC100 rotation stage (docs/PROTOCOLS.md §1) as a :class:`RotaryStage`: the driver
`northfinder.drivers.turntable.Turntable`, the bytes `northfinder.codecs.smc100`."""

from __future__ import annotations

from typing import Any

from northfinder.devices.registry import ModelSpec
from northfinder.devices.stage import RotaryStage, StageState
from northfinder.drivers.turntable import StageStatus, Turntable
from northfinder.models._section import value


def _fault(st: StageStatus) -> str | None:
    if st.is_disabled or st.errors:
        errors = ["positioner errors: " + ", ".join(st.error_names)] if st.errors else []
        return "; ".join([f"state {st.state_name}", *errors])
    return None


class Smc100Stage(Turntable, RotaryStage):
    """The SMC100 in the rotary-stage role (StageError is a StageFault: the TE letter is its reason)."""

    def state(self) -> StageState:
        st = self.status()
        return StageState(name=st.state_name, ready=st.is_ready and not st.errors, moving=st.is_moving,
                          homing=st.is_homing, referenced=st.is_referenced, fault=_fault(st))

    def start_home(self) -> None:
        self.home(wait=False)

    def start_move(self, angle_deg: float) -> None:
        self.move_absolute_deg(angle_deg, wait=False)

    def angle_deg(self) -> float:
        return self.position_deg()

    def halt(self) -> StageState:
        st = self.stop()
        return StageState(name=st.state_name, ready=st.is_ready and not st.errors, moving=st.is_moving,
                          homing=st.is_homing, referenced=st.is_referenced, fault=_fault(st))

    def limits_deg(self) -> tuple[float, float]:
        return self.soft_limits_deg()

    def re_enable(self) -> None:
        self.enable()

    def raise_fault(self, state: StageState) -> None:
        self.wait_ready(timeout_s=0.0)  # raises StageError naming the state and the TE letter

    def identity(self) -> dict[str, Any]:
        return {"model": "smc100", "version": self.version()}

    def check_line(self) -> str:
        st = self.status()
        errors = ", ".join(st.error_names) if st.errors else "no errors"
        return (f"turntable on {self.port}: {self.version()}; state {st.state_name} (0x{st.state:02X}), "
                f"{errors}")


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> Smc100Stage:
    return Smc100Stage(value(section, "port", ""), address=value(section, "address", 1),
                       baudrate=value(section, "baudrate", 57600), timeout_s=options.get("timeout_s", 5.0),
                       transcript=log_path)


SPEC = ModelSpec("turntable", "smc100", _open, None, "Newport SMC100 (ASCII over RS-232)")
