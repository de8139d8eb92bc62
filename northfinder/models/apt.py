"""Thorlabs KDC101 K-Cube + PRM1-Z8 rotation stage over APT binary messages (docs/PROTOCOLS.md §6,
Thorlabs Host-Controller Communications Protocol Issue 28, cited "APT" with its pages) as a
:class:`RotaryStage`; the bytes are `northfinder.codecs.apt`, the start-up dialogue and the role
mapping are docs/second-models.md "Thorlabs APT stage".

The driver is request/response on one SerialTransport (its transcript is the stage's log): every
exchange writes one message and reads the stream through :class:`AptDecoder` until the awaited
reply; unsolicited messages met on the way (MOVE_HOMED, MOVE_COMPLETED, MOVE_STOPPED, status
updates) are kept as the latest status. It stands on no APT library (PROTOCOLS.md §6 "Library").

State comes from the status bits of MOT_REQ_DCSTATUSUPDATE (APT p. 124–127): ready = enabled ∧
homed ∧ not moving ∧ no fault bit; a MOVE_STOPPED with POSITION_ERROR (the servo tripped) is the
role's fault state, with the set bits by their APT names as the reason. Every poll also sends
MOT_ACK_DCSTATUSUPDATE ("server alive", at least once a second over USB, APT p. 129).
"""

from __future__ import annotations

import time
from typing import Any

from northfinder.codecs import apt
from northfinder.devices.registry import ModelSpec
from northfinder.devices.stage import RotaryStage, StageFault, StageState
from northfinder.errors import DeviceError
from northfinder.models._section import value
from northfinder.transport import SerialTransport

DEVICE = "turntable"
BAUDRATE = 115200  # APT §2.1 (p. 29): 115200 baud, 8N1, RTS/CTS
CONTROLLERS = ("KDC101",)
"""HW_GET_INFO model strings this driver drives (the PRM1-Z8's scaling is for the KDC101, APT §8)."""
SOFT_LIMITS_DEG = (-720.0, 720.0)
"""The PRM1-Z8 turns without end; the driver's own limits (two turns each way) bound a plan."""
STOP_TIMEOUT_S = 30.0


class AptStage(RotaryStage):
    """A KDC101 + PRM1-Z8 on a pyserial URL; a context manager."""

    def __init__(self, port: str, *, baudrate: int = BAUDRATE, timeout_s: float = 5.0,
                 transcript: Any = None, speed_deg_s: float = 0.0, accel_deg_s2: float = 0.0,
                 limits_deg: tuple[float, float] = SOFT_LIMITS_DEG, rtscts: bool = True) -> None:
        """`rtscts`: RTS/CTS flow control, as APT §2.1 asks of the FTDI link (harmless on a pty)."""
        self.port = port
        self.timeout_s = float(timeout_s)
        self._limits = (float(limits_deg[0]), float(limits_deg[1]))
        self._t = SerialTransport(port, device=DEVICE, baudrate=baudrate, timeout_s=0.05,
                                  transcript=transcript, rtscts=rtscts)
        self._decoder = apt.AptDecoder()
        self._inbox: list[apt.AptMessage] = []
        self.last_status: apt.MotorStatus | None = None
        self._awaiting: int | None = None
        """MOVE_HOMED or MOVE_COMPLETED owed by the unit for the last home or move (None: none)."""
        try:
            self._t.reset_input_buffer()  # the purge of APT §2.1 (what was dropped is logged)
            self.info = self._identify()
            self.velocity_params = self._velocity(speed_deg_s, accel_deg_s2)
            self._send(apt.set_channel_enable(True))
        except BaseException:
            self._t.close()
            raise

    # -- exchanges ---------------------------------------------------------------------------
    def _send(self, msg: bytes) -> None:
        self._t.write(msg)

    def _await(self, msg_ids: tuple[int, ...], timeout_s: float, what: str) -> apt.AptMessage:
        """Read until a message with one of `msg_ids` (earlier ones kept in order); DeviceError."""
        deadline = time.monotonic() + timeout_s
        while True:
            for k, msg in enumerate(self._inbox):
                self._note(msg)
                if msg.msg_id in msg_ids:
                    del self._inbox[: k + 1]
                    return msg
            self._inbox.clear()
            if time.monotonic() > deadline:
                raise DeviceError(DEVICE, self.port, f"no APT answer to {what} within {timeout_s:g} s "
                                  f"({self._decoder.stats.skipped_bytes} bytes of something else) — is it a "
                                  f"Thorlabs {'/'.join(CONTROLLERS)} on this port, powered, {BAUDRATE} baud?")
            self._inbox.extend(self._decoder.feed(self._t.read_available()))

    def _ask(self, msg: bytes, reply: int, what: str) -> apt.AptMessage:
        self._send(msg)
        return self._await((reply,), self.timeout_s, what)

    def _note(self, msg: apt.AptMessage) -> None:
        """Keep the status an unsolicited or awaited message carries; a motion's end message ends it."""
        if msg.msg_id in (apt.MOT_MOVE_HOMED, apt.MOT_MOVE_COMPLETED, apt.MOT_MOVE_STOPPED):
            self._awaiting = None
        carries_status = (apt.MOT_GET_STATUSUPDATE, apt.MOT_MOVE_COMPLETED, apt.MOT_MOVE_STOPPED)
        if msg.msg_id in carries_status and msg.data:
            self.last_status = apt.parse_status(msg.data)

    def _identify(self) -> apt.HwInfo:
        """HW_REQ_INFO → HW_GET_INFO (APT p. 51–52); a controller this driver does not scale is refused."""
        msg = self._ask(apt.hw_req_info(), apt.HW_GET_INFO, "HW_REQ_INFO")
        info = apt.parse_hw_info(msg.data)
        if info.model not in CONTROLLERS:
            raise DeviceError(DEVICE, self.port, f"{info.describe()} answered: this driver knows the PRM1-Z8 "
                              f"on a {'/'.join(CONTROLLERS)} only (counts per degree, APT §8) — "
                              "use the stage's own model")
        return info

    def _velocity(self, speed_deg_s: float, accel_deg_s2: float) -> tuple[float, float]:
        """MOT_SET_VELPARAMS when the bench gives a speed (APT §8 scaling), then the read-back
        (MOT_REQ_VELPARAMS): (max velocity °/s, acceleration °/s²)."""
        what = "MOT_REQ_VELPARAMS"
        _, _, acc, vel = apt.parse_velocity_params(self._ask(apt.req_velocity_params(), apt.MOT_GET_VELPARAMS,
                                                             what).data)
        if speed_deg_s > 0 or accel_deg_s2 > 0:
            acc = apt.acceleration_from_deg_s2(accel_deg_s2) if accel_deg_s2 > 0 else acc
            vel = apt.velocity_from_deg_s(speed_deg_s) if speed_deg_s > 0 else vel
            self._send(apt.set_velocity_params(acc, vel))
            _, _, acc, vel = apt.parse_velocity_params(
                self._ask(apt.req_velocity_params(), apt.MOT_GET_VELPARAMS, what).data)
        return apt.deg_s_from_velocity(vel), apt.deg_s2_from_acceleration(acc)

    def status(self) -> apt.MotorStatus:
        """MOT_REQ_DCSTATUSUPDATE → the status structure (with the "server alive" acknowledgement)."""
        self._send(apt.ack_status())
        msg = self._ask(apt.req_status(), apt.MOT_GET_STATUSUPDATE, "MOT_REQ_DCSTATUSUPDATE")
        return apt.parse_status(msg.data)

    # -- the role ----------------------------------------------------------------------------
    def state(self) -> StageState:
        """The status bits, and the motion not finished until its MOVE_HOMED / MOVE_COMPLETED came
        (the bits may not show a move yet in the servo cycle that received it)."""
        return state_from_bits(self.status().status_bits, self._awaiting)

    def start_home(self) -> None:
        self._awaiting = apt.MOT_MOVE_HOMED
        self._send(apt.move_home())

    def start_move(self, angle_deg: float) -> None:
        self._awaiting = apt.MOT_MOVE_COMPLETED
        self._send(apt.move_absolute(apt.counts_from_deg(angle_deg)))

    def angle_deg(self) -> float:
        _, counts = apt.parse_position(self._ask(apt.req_position(), apt.MOT_GET_POSCOUNTER,
                                                 "MOT_REQ_POSCOUNTER").data)
        return apt.deg_from_counts(counts)

    def halt(self) -> StageState:
        """MOT_MOVE_STOP (profiled) and wait for MOT_MOVE_STOPPED (APT p. 87–88)."""
        self._send(apt.move_stop(apt.STOP_PROFILED))
        self._await((apt.MOT_MOVE_STOPPED,), STOP_TIMEOUT_S, "MOT_MOVE_STOP")
        return self.state()

    def limits_deg(self) -> tuple[float, float]:
        return self._limits

    def re_enable(self) -> None:
        """MOD_SET_CHANENABLESTATE enable: the servo takes hold again, the reference is kept."""
        self._send(apt.set_channel_enable(True))
        st = self.state()
        if st.fault:
            self.raise_fault(st)

    def raise_fault(self, state: StageState) -> None:
        exc = StageFault(DEVICE, self.port, f"stage stopped short: {state.fault} (status bits: {state.name})")
        exc.state_name, exc.reason = state.name, state.fault
        raise exc

    def identity(self) -> dict[str, Any]:
        return {"model": "apt", "controller": self.info.describe()}

    def check_line(self) -> str:
        st = self.status()
        vel, acc = self.velocity_params
        return (f"turntable on {self.port}: {self.info.describe()} (PRM1-Z8, "
                f"{apt.PRM1Z8_COUNTS_PER_DEG:.4f} counts/°); status {apt.describe_status(st.status_bits)} "
                f"(0x{st.status_bits:08X}); at {apt.deg_from_counts(st.position_counts):.4f}°; "
                f"velocity {vel:.2f} °/s, acceleration {acc:.2f} °/s²")

    def close(self) -> None:
        self._t.close()


def state_from_bits(bits: int, awaiting: int | None = None) -> StageState:
    """The role's state from APT status bits (p. 125–127) and the end message still owed."""
    enabled, homed = bool(bits & apt.SB_ENABLED), bool(bits & apt.SB_HOMED)
    homing = bool(bits & apt.SB_HOMING) or awaiting == apt.MOT_MOVE_HOMED
    moving = bool(bits & apt.MOVING_BITS) or awaiting is not None
    fault = apt.describe_status(bits & apt.FAULT_BITS) if bits & apt.FAULT_BITS else None
    if fault is None and not enabled:
        fault = "channel disabled"
    owed = f"; awaiting {_END_NAMES[awaiting]}" if awaiting in _END_NAMES else ""
    name = apt.describe_status(bits) + owed
    return StageState(name=name, ready=enabled and homed and not moving and fault is None,
                      moving=moving, homing=homing, referenced=homed, fault=fault)


_END_NAMES = {apt.MOT_MOVE_HOMED: "MOVE_HOMED", apt.MOT_MOVE_COMPLETED: "MOVE_COMPLETED"}


def _open(section: Any, log_path: Any, options: dict[str, Any]) -> AptStage:
    return AptStage(value(section, "port", ""), baudrate=BAUDRATE,
                    timeout_s=options.get("timeout_s", 5.0), transcript=log_path,
                    speed_deg_s=float(value(section, "speed_deg_s", 0.0) or 0.0))


SPEC = ModelSpec("turntable", "apt", _open, None, "Thorlabs KDC101 + PRM1-Z8 (APT binary protocol)")
