"""`find --simulate --time-scale auto`: firmware-sim's time scale paced to what this host keeps up with.

A time-scaled simulator runs device time on while the host works between a dwell's end and the next
move command (its checks, the events log, the stage dialogue, the links' latency): the position
event's `before_move_s` says how much, in device seconds, measured from the IMU's own sample indices
(the sequencer's settle: the first gyro-z window that saw the table turn). A host keeps up when that
stays near what a real bench shows (well under a second); above KEEP_UP_S, or when a link lost
samples, it does not. After each position the pace doubles the scale while the host keeps up with
room to spare and halves it when it does not, so the run settles at the highest scale this host
keeps up with, under its present load; each change is a `time_scale` event.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

AUTO = "auto"
AUTO_START_SCALE = 40.0
"""The first scale of an auto-paced run (a quiet 2-core host keeps up with 120×)."""
AUTO_MAX_SCALE = 160.0
"""The highest: firmware-sim is started at it, which sizes its buffers (a second of wall time). Above
it the IMU alone is ~6 MB/s through a pty, and on a 2-core host its reader falls behind by tens of
device seconds before `before_move_s` shows it (measured: 200× beside one CPU hog, 320× quiet — the
settle then missed the slew and positions were measured again)."""
AUTO_MIN_SCALE = 1.0
KEEP_UP_S = 1.0
"""`before_move_s` above this (device s) means the host did not keep up (the dwell grid is 1 s)."""
ROOM_S = 0.4
"""`before_move_s` at or below this leaves room for twice the scale."""


def time_scale_arg(text: str) -> float | str:
    """--time-scale's value: a factor, or `auto`."""
    if text.strip().lower() == AUTO:
        return AUTO
    return float(text)


def host_kept_up(event: dict[str, Any], losses_count: bool = True) -> bool | None:
    """Whether one position event shows the host keeping up: False when a link lost samples in the
    dwell (unless `losses_count` is off: faults injected on purpose) or `before_move_s` exceeds
    KEEP_UP_S; None when the event cannot tell (the first position has no dwell before it)."""
    lost = int(event.get("imu", {}).get("lost", 0)) or int(event.get("accel", {}).get("lost", 0))
    if lost and losses_count:
        return False
    lag = event.get("before_move_s")
    if lag is None:
        return None
    return float(lag) <= KEEP_UP_S


def paced_scales(events: Sequence[dict[str, Any]]) -> list[float]:
    """The scales a paced run's `time_scale` events set, in order (empty for a fixed scale)."""
    return [float(e["scale"]) for e in events if e.get("event") == "time_scale"]


def pace_line(events: list[dict[str, Any]]) -> str | None:
    """`time scale auto: 40 → 80 → 160×` for a paced run's summary (None for a fixed scale)."""
    scales = paced_scales(events)
    if not scales:
        return None
    return "time scale auto: " + " → ".join(f"{s:g}" for s in scales) + "×"


class AutoPace:
    """Watches the run's events and sets firmware-sim's time scale (`set_scale`, e.g.
    SimulatorProcess.set_time_scale); `log_event` records each change. `losses_count` off (faults
    injected): lost samples and re-measures are the faults', and the lag alone paces."""

    def __init__(self, set_scale: Callable[[float], None], log_event: Callable[[dict[str, Any]], None],
                 start_scale: float = AUTO_START_SCALE, max_scale: float = AUTO_MAX_SCALE,
                 losses_count: bool = True) -> None:
        self.set_scale, self.log_event = set_scale, log_event
        self.losses_count = losses_count
        self.max_scale = float(max_scale)
        self.scale = min(float(start_scale), self.max_scale)
        self.set_scale(self.scale)
        self.log_event({"event": "time_scale", "scale": self.scale, "why": "start"})

    def on_event(self, event: dict[str, Any]) -> None:
        """A logged event: after a position (or a re-measure) the scale may change."""
        kind = event.get("event")
        if kind == "remeasure" and self.losses_count:
            self._change(self.scale / 2.0, f"position {int(event.get('index', 0)) + 1} measured again")
            return
        if kind != "position":
            return
        kept_up = host_kept_up(event, self.losses_count)
        lag = event.get("before_move_s")
        if kept_up is False:
            self._change(self.scale / 2.0, "the host did not keep up", lag)
        elif kept_up and float(lag) <= ROOM_S:
            self._change(self.scale * 2.0, "the host kept up with room", lag)

    def _change(self, scale: float, why: str, lag: float | None = None) -> None:
        scale = min(max(scale, AUTO_MIN_SCALE), self.max_scale)
        if scale == self.scale:
            return
        self.scale = scale
        self.set_scale(scale)
        self.log_event({"event": "time_scale", "scale": scale, "why": why, "before_move_s": lag})


class PacedEventLog:
    """The run directory as the sequencer sees it (it only appends events), each event also shown to
    the pace once it is logged."""

    def __init__(self, rundir: Any, pace: AutoPace) -> None:
        self.rundir, self.pace = rundir, pace

    def log_event(self, event: dict[str, Any]) -> None:
        self.rundir.log_event(event)
        self.pace.on_event(event)
