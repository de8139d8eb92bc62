"""The rotary-stage role: reference (home), move to an angle, encoder angle, ready / moving / fault
state with the model's own reason text, stop, soft limits, speed.

A model implements the abstract methods; the sequencer polls :meth:`RotaryStage.state` (so that it can
check its stop flag between exchanges) and calls :meth:`RotaryStage.raise_fault` when the state shows
the stage stopped short.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any

from northfinder.errors import DeviceError

ROLE = "turntable"


class StageFault(DeviceError):
    """The stage refused a command or stopped short of its target (stall, following error, disabled).
    `state_name` is the model's state and `reason` its own explanation (an error code's meaning)."""

    state_name: str | None = None
    reason: str | None = None


@dataclass(frozen=True)
class StageState:
    """One reading of the stage's state, in the terms the position plan needs."""

    name: str
    """The model's own name for the state (e.g. SMC100 "READY from MOVING")."""
    ready: bool
    """At rest at its target, able to take the next move."""
    moving: bool
    homing: bool
    referenced: bool
    fault: str | None = None
    """Why the stage cannot move (disabled, error bits), in the model's words; None when it can."""


class RotaryStage(ABC):
    """A rotation stage; a context manager. Angles in degrees."""

    role = ROLE
    port: str | None = None
    model_name: str = ""
    """The registry name of the model (set by registry.open_device)."""

    @abstractmethod
    def state(self) -> StageState: ...

    @abstractmethod
    def start_home(self) -> None:
        """Start the search for the reference (α = 0); returns at once."""

    @abstractmethod
    def start_move(self, angle_deg: float) -> None:
        """Start an absolute move; returns at once (poll `state`)."""

    @abstractmethod
    def angle_deg(self) -> float:
        """The encoder angle."""

    @abstractmethod
    def halt(self) -> StageState:
        """Stop any motion and return the state once stopped — the safe path (Ctrl-C): never a fault."""

    @abstractmethod
    def limits_deg(self) -> tuple[float, float]:
        """The soft limits (negative, positive)."""

    @abstractmethod
    def re_enable(self) -> None:
        """Leave a fault state (after a stall or following error) keeping the reference; StageFault
        if the stage stays unable to move."""

    @abstractmethod
    def raise_fault(self, state: StageState) -> None:
        """Raise the StageFault for a state that stopped short, with the model's reason (it may ask
        the controller for its last error)."""

    @abstractmethod
    def identity(self) -> dict[str, Any]: ...

    @abstractmethod
    def close(self) -> None: ...

    # -- built once on top -------------------------------------------------------------------
    def check_line(self) -> str:
        """`northfinder check`'s line for this device: what answered and what it says it is (a model
        may say more: its state, its data)."""
        ident = ", ".join(f"{k} {v}" for k, v in self.identity().items())
        return f"{self.role} on {self.port}: {ident}"

    def not_referenced_fault(self, state: StageState) -> StageFault:
        """The error for a stage that is not referenced while homing is not allowed."""
        exc = StageFault(ROLE, self.port, "the stage is not referenced and homing is disabled ([turntable] "
                         f"allow_home = false) — home it or set allow_home = true; state {state.name}")
        exc.state_name = state.name
        return exc

    def __enter__(self) -> RotaryStage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
