"""The measurement sequence on a turntable: reference, then per position move → READY → settle →
dwell → encoder, then return to the start.

Everything that is measured is counted in device samples (CONVENTIONS.md, "Time"): the settle
windows, the dwell and the progress are sample counts over the devices' rates, so a simulator
running K times faster than real time gives the same result. Host wall-clock time is used only
for poll periods and time-outs.

A first SIGINT/SIGTERM only raises a flag; the sequence checks it between device exchanges (never
in the middle of one), stops the stage with `ST`, logs the stage's state, and raises
:class:`Interrupted` with the positions measured so far. A second signal interrupts at once.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from northfinder.config import RunConfig, position_plan_deg
from northfinder.constants import DPH
from northfinder.devices.imu import ImuBlock, InertialStream
from northfinder.devices.stage import RotaryStage, StageFault
from northfinder.devices.tilt import AccelBlock, TiltSensor
from northfinder.errors import ConfigError, DeviceError, NorthfinderError
from northfinder.estimators.dwell import (
    DisturbanceWindows,
    DwellLimits,
    DwellVerdict,
    accel_dwell_verdict,
    combine_verdicts,
    imu_dwell_verdict,
    imu_window,
)
from northfinder.estimators.means import PositionMeans, position_means
from northfinder.estimators.plan import MOTION_KINDS, sweep_targets_deg
from northfinder.stopflag import StopFlag

log = logging.getLogger(__name__)


class _EventLog(Protocol):  # northfinder.rundir.RunDir: the sequencer only appends events to it
    def log_event(self, event: dict[str, Any]) -> None: ...


CAUGHT_UP_WAIT_S = 0.5
"""Host seconds the tilt sensor's start waits for the IMU reader to have read all the IMU sent, so
that the IMU index it notes (a lower bound of the device clock) is not behind by a backlog: the
accelerometer's dwell then ends soon after the IMU's (:meth:`Sequencer._accel_skip_s`). Only a
bound: a reader that never catches up gives its newest index."""
MIN_VISIBLE_MOVE_DEG = 0.5
"""Moves at least this long are expected to show in the gyro z before settling is judged."""
SLOWEST_STAGE_DEG_S = 1.0
"""The stage speed assumed when [turntable] speed_deg_s is not given: bounds of a move are taken
as for the slowest table supported, so a several-minute move at 1 deg/s still works."""


class Interrupted(Exception):
    """The run was stopped by a signal; `positions` holds what was measured before it."""

    def __init__(self, signum: int, positions: list[PositionMeans], stage_state: str | None):
        self.signum = signum
        self.positions = positions
        self.stage_state = stage_state
        super().__init__(f"stopped by {signal.Signals(signum).name} after {len(positions)} positions")


class RunFailed(NorthfinderError):
    """The run cannot go on (a position failed every attempt, the stage failed its retry); the
    positions measured before are in `positions` and are saved by the caller."""

    exit_code = 3

    def __init__(self, message: str, positions: list[PositionMeans]):
        self.positions = positions
        super().__init__(message)


@dataclass
class Progress:
    """One progress report: where the sequence is, and the live gyro statistics of the dwell."""

    position: int
    """1-based index of the position being measured."""
    positions: int
    phase: str
    """'reference', 'move', 'settle', 'dwell', 'measured', 'return'."""
    target_deg: float = float("nan")
    dwell_done_s: float = 0.0
    """Device time collected so far in this position's dwell [s]."""
    dwell_s: float = 0.0
    gyro_mean_dph: list[float] = field(default_factory=list)
    gyro_std_of_mean_dph: list[float] = field(default_factory=list)
    settle_s: float = 0.0
    means: PositionMeans | None = None


class RunningMeans:
    """A dwell's per-axis gyro mean and σ of the mean so far [°/h], for the live progress; samples
    flagged not valid (NaN) are left out."""

    def __init__(self) -> None:
        self.s1, self.s2, self.n_ok = np.zeros(3), np.zeros(3), np.zeros(3)

    def add(self, gyro_dph: np.ndarray) -> tuple[list[float], list[float]]:
        ok = np.isfinite(gyro_dph)
        self.n_ok += ok.sum(axis=0)
        self.s1 += np.where(ok, gyro_dph, 0.0).sum(axis=0)
        self.s2 += (np.where(ok, gyro_dph, 0.0) ** 2).sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.s1 / self.n_ok
            var = np.maximum(self.s2 / self.n_ok - mean**2, 0.0)
        return mean.tolist(), np.sqrt(var / np.maximum(self.n_ok, 1)).tolist()


@dataclass(frozen=True)
class DwellData:
    """One dwell as read: the IMU's blocks, the tilt sensor's block, the IMU's verdict (made while the
    tilt sensor's samples arrived) and the table angle read at rest during it."""

    blocks: list[ImuBlock]
    accel_block: AccelBlock
    imu_verdict: DwellVerdict
    table_angle_deg: float
    accel_expected: int
    """The tilt sensor's dwell as asked (the block may hold fewer when it stopped for the next move)."""
    moved_on: bool = False
    """The next move was commanded as soon as the IMU's dwell was in (:meth:`Sequencer.dwell`)."""


@dataclass
class SettleResult:
    """How the settle criterion ended: after how much device time and whether it was met."""

    settle_s: float
    settled: bool
    windows: int
    after_motion_s: float | None = None
    """Device time from the start of the last gyro-z window still turning to the end of the settle
    (None when no motion was seen): how much of the rest after READY the settle took, at most."""
    onset_index: int | None = None
    """Device index of the first sample of the first gyro-z window that showed the table turning
    (None when no motion was expected or the unit has no gyro z)."""
    end_index: int | None = None
    """Device index of the settle's last sample (None: none read): the dwell starts on the first
    dwell-grid index after it."""

    def as_event(self) -> dict[str, Any]:
        """The settle as the events log records it."""
        event = {"settle_s": self.settle_s, "settled": self.settled, "windows": self.windows,
                 "after_motion_s": self.after_motion_s}
        return event if self.end_index is None else {**event, "end_index": self.end_index}

    @property
    def rest_before_dwell_s(self) -> float:
        """Device time a stream started at READY must drop before the dwell: the settle after the
        motion when it was seen (READY comes after the planned move ends), else the whole settle."""
        return self.settle_s if self.after_motion_s is None else min(self.settle_s, self.after_motion_s)


SLEWING_FRACTION = 0.1
"""A settle window whose mean gyro z is at least this fraction of the fastest window's is part of
the move itself: a stop's ringing averages out over a window, a slew (or its ramps) does not."""


def after_motion_s(window_means_dph: list[float], window_s: float, margin_s: float) -> float | None:
    """Device time from the START of the last window still slewing to the end of the last window
    (plus the margin dropped after the settle); None when no window turned. That window holds some
    of the planned move, so the move ended after it began: a stream started at READY that skips
    this much starts at or after the settle's end (at most two windows later)."""
    means = np.abs(np.asarray(window_means_dph, dtype=float))
    if means.size == 0 or not np.any(means > 0):
        return None
    last_slewing = int(np.nonzero(means >= SLEWING_FRACTION * means.max())[0][-1])
    return (means.size - last_slewing) * window_s + margin_s


def settle_reached(z_windows_dph: list[np.ndarray], ratio: float, rest_dph: float) -> bool:
    """The table's ringing has died out in the gyro-z signal [deg/h].

    Ringing after a stop is a decaying oscillation about the z axis: the spread of gyro z over
    successive equal windows shrinks by a constant factor per window while it rings, and stops
    shrinking once only sensor noise is left. Settled when the last window's spread is no longer
    below `ratio` × the previous one's, the two window means agree within 4σ of their noise, and
    the mean is below `rest_dph` (a window still inside a constant-rate slew — samples that
    arrive late — is steady too, but turning at ~10⁵ deg/h).
    """
    if len(z_windows_dph) < 2:
        return False
    a, b = z_windows_dph[-2], z_windows_dph[-1]
    if abs(float(np.mean(b))) > rest_dph:
        return False
    sa, sb = float(np.std(a)), float(np.std(b))
    if sb < ratio * sa:
        return False
    noise = np.sqrt(sa**2 / a.size + sb**2 / b.size)
    return abs(float(np.mean(b)) - float(np.mean(a))) <= 4.0 * noise + 1e-12


@dataclass(frozen=True)
class SequencerLimits:
    """The sequencer's settings (host time-outs, retries, device-time grids) in one object.

    `poll_s`: the stage's state is polled every poll_s of device time, paced by the IMU's samples
    arriving (host seconds when the stream is silent), so a time-scaled simulator is polled as often
    in device time as a real bench; `read_timeout_s`: host seconds a read may wait beyond the
    samples' own duration; `max_attempts`: measurements of one position before the run stops;
    `dwell`: when a dwell is measured again (estimators.dwell.DwellLimits); `stage_speed_deg_s`
    ([turntable] speed_deg_s, 0 unknown) bounds each move (host timeout) and its settle (device
    time); `stage_settle_s` ([turntable] settle_s) is the rest after READY of a unit without a gyro
    z; `dwell_grid_s`: a dwell starts on a multiple of this many device seconds of IMU samples (so
    it does not depend on host timing);
    `settle_margin_s`: device time dropped after the gyro-z settle criterion is met — it fires once
    the ringing is below one window's noise; the margin lets it decay e^(margin/τ) further (28× for
    the 0.3 s decay of the bench), so the dwell starts with the table at rest."""

    chunk_s: float = 0.5
    poll_s: float = 0.02
    move_timeout_s: float = 120.0
    read_timeout_s: float = 5.0
    max_attempts: int = 3
    dwell: DwellLimits = DwellLimits()
    reconnect_timeout_s: float = 10.0
    stage_speed_deg_s: float = 0.0
    stage_settle_s: float = 5.0
    dwell_grid_s: float = 1.0
    settle_margin_s: float = 1.0

    @classmethod
    def from_options(cls, **options: Any) -> SequencerLimits:
        """Limits from flat keyword options (a test's `seq_kwargs`): DwellLimits' fields go there."""
        dwell_keys = {f for f in DwellLimits.__dataclass_fields__ if f in options}
        dwell = DwellLimits(**{k: options.pop(k) for k in dwell_keys})
        return cls(dwell=dwell, **options)


class Sequencer:
    """Runs the position plan on a rotary stage, an inertial stream and a tilt sensor (roles, opened)."""

    def __init__(
        self,
        turntable: RotaryStage,
        imu: InertialStream,
        accelerometer: TiltSensor,
        run: RunConfig,
        limits: SequencerLimits = SequencerLimits(),
        *,
        allow_home: bool = True,
        rundir: _EventLog | None = None,
        on_progress: Callable[[Progress], None] | None = None,
        stop_flag: StopFlag | None = None,
        skip: set[int] | frozenset[int] = frozenset(),
    ):
        """`skip`: plan indices already measured (--resume)."""
        self.turntable = turntable
        self.imu = imu
        self.accel = accelerometer
        self.run_cfg = run
        self.limits = limits
        self.allow_home = allow_home
        self.rundir = rundir
        self.on_progress = on_progress or (lambda p: None)
        self.stop_flag = stop_flag if stop_flag is not None else StopFlag()
        self.accel_rate_hz = float(accelerometer.rate_hz)
        self.skip = frozenset(int(k) for k in skip)
        self._move_deg = 0.0
        self._homing_travel_deg = 0.0
        """How far homing turned the table before the first position: its motion may still be in the
        IMU bytes a USB link holds back, so the first settle waits to see it (|Δα|, deg)."""
        self.positions: list[PositionMeans] = []
        self._plan: list[float] = []
        self._rest_angle_deg: float | None = None
        """The table angle read during the last dwell (None once a move is commanded)."""
        self._last_dwell_end: int | None = None
        """Device index of the last kept dwell's last IMU sample."""
        self._last_imu_index: int | None = None
        """Device index of the last IMU sample read."""
        self._accel_started_at: int | None = None
        """The IMU's newest sample index just before the tilt sensor's last start command."""
        self._commanded: tuple[float, float] | None = None
        """(target, travel) of a move commanded before its position's attempt began."""

    # -- helpers -----------------------------------------------------------------------------
    def _event(self, event: dict[str, Any]) -> None:
        if self.rundir is not None:
            self.rundir.log_event(event)

    def _check_stop(self) -> None:
        if self.stop_flag:
            state = None
            moving = None
            try:
                st = self.turntable.halt()
                state = st.name
                moving = bool(st.moving or st.homing)
            except Exception as exc:  # noqa: BLE001 - report, then still save and exit
                log.warning("could not stop the stage cleanly: %s", exc)
                state = f"unknown ({exc})"
            assert self.stop_flag.signum is not None
            self._event(
                {
                    "event": "abort",
                    "signal": signal.Signals(self.stop_flag.signum).name,
                    "positions_measured": len(self.positions),
                    "stage_state": state,
                    "stage_moving": moving,
                }
            )
            raise Interrupted(self.stop_flag.signum, list(self.positions), state)

    def plan_deg(self) -> list[float]:
        """The commanded angles, each shifted by whole turns into the stage's soft limits; for a
        sweep the long-way targets of estimators.plan.sweep_targets_deg, which need −360…+360."""
        lo, hi = self.turntable.limits_deg()
        if self.run_cfg.plan == "sweep":
            targets = sweep_targets_deg(self.run_cfg.positions, self.run_cfg.start_deg)
            if min(targets) < lo - 1e-9 or max(targets) > hi + 1e-9:
                raise ConfigError(
                    f"[run] plan = sweep: its moves need the stage's soft limits to span "
                    f"{min(targets):g}…{max(targets):g}°, the stage has {lo:g}…{hi:g}° — widen them "
                    "(SL/SR) or use plan = positions+motion"
                )
            return targets
        plan = []
        for a in position_plan_deg(self.run_cfg.positions, self.run_cfg.start_deg, self.run_cfg.order):
            shifted = a
            while shifted > hi:
                shifted -= 360.0
            while shifted < lo:
                shifted += 360.0
            if not lo <= shifted <= hi:
                raise ConfigError(
                    f"[run] start_deg: position {a:.3f}° cannot be planned inside the stage's "
                    f"soft limits {lo:.3f}…{hi:.3f}°; change start_deg or the limits"
                )
            plan.append(shifted)
        return plan

    def _move_duration_s(self, move_deg: float) -> float:
        """An upper bound of a move's duration [s] from its length and the stage's speed (the slowest
        supported when unknown), with its acceleration ramps (at most a second at 1 deg/s)."""
        speed = self.limits.stage_speed_deg_s if self.limits.stage_speed_deg_s > 0 else SLOWEST_STAGE_DEG_S
        return abs(move_deg) / speed + 2.0

    def _poll_ready(self, what: str, move_deg: float = 0.0) -> None:
        """Poll the stage's state until READY (checking the stop flag); StageFault naming the state and
        the model's reason. The host time-out is move_timeout_s, or twice the move's bound when that
        is longer."""
        timeout_s = max(self.limits.move_timeout_s, 2.0 * self._move_duration_s(move_deg))
        deadline = time.monotonic() + timeout_s
        while True:
            self._check_stop()
            st = self.turntable.state()
            if st.ready:
                return
            if st.fault or not (st.referenced or st.homing):
                self.turntable.raise_fault(st)
                return
            if time.monotonic() > deadline:
                raise DeviceError(
                    "turntable",
                    self.turntable.port,
                    f"not READY {timeout_s:g} s after {what} "
                    f"(state {st.name}) — check the stage's speed and load",
                )
            self.imu.wait_device_s(self.limits.poll_s, self.limits.poll_s)

    def _move_once(self, target_deg: float) -> None:
        """Command the move and wait for READY. The IMU samples from before the command are dropped
        first, as for every move (the settle after it looks for this move's slew: after a stage fault
        the rest since the faulted move is the host's fault handling, and on a loaded host a settle
        once ended in it and the retried move fell into the dwell)."""
        self.imu.discard_pending()
        self.turntable.start_move(target_deg)
        self._poll_ready(f"the move to {target_deg:g}°", self._move_deg)

    def _stage_error(self, target_deg: float, attempt: int, exc: StageFault) -> None:
        self._event({"event": "stage_error", "target_deg": target_deg, "attempt": attempt, "error": str(exc),
                     "state": exc.state_name, "reason": exc.reason})

    def _move(self, target_deg: float, commanded: bool = False) -> None:
        """Move (`commanded`: the move command was sent already) and wait for READY. A stage fault
        (following error / stall → disabled) is logged, the stage re-enabled and the move tried once
        more; a second failure stops the stage and the run (RunFailed, the data so far kept)."""
        try:
            if commanded:
                self._poll_ready(f"the move to {target_deg:g}°", self._move_deg)
            else:
                self._move_once(target_deg)
            return
        except StageFault as exc:
            self._stage_error(target_deg, 1, exc)
            log.warning("%s; re-enabling and trying the move once more", exc)
            first = exc
        try:
            self.turntable.re_enable()
            self._move_once(target_deg)
        except StageFault as exc:
            self._stage_error(target_deg, 2, exc)
            state = self._safe_stop()
            raise RunFailed(
                f"turntable on {self.turntable.port or '?'}: the move to {target_deg:g}° failed "
                f"twice ({first}; then {exc}); stage stopped ({state})",
                list(self.positions),
            ) from None

    def _safe_stop(self) -> str:
        try:
            return str(self.turntable.halt().name)
        except Exception as exc:  # noqa: BLE001 - the run is stopping anyway; say so
            return f"unknown ({exc})"

    def _reference(self) -> None:
        """Home the stage if it is not referenced (stop-flag aware), or a clear StageFault when
        homing is not allowed; wait if it is busy."""
        st = self.turntable.state()
        if st.referenced and not st.homing:
            if st.moving:
                self._poll_ready("the stage's own move")
            elif not st.ready:
                self.turntable.raise_fault(st)
            return
        if not st.homing:
            if not self.allow_home:
                raise self.turntable.not_referenced_fault(st)
            self._event({"event": "home", "state": st.name})
            before_deg = self._encoder_or_none()
            self.imu.discard_pending()  # what is left is from before the home command
            self.turntable.start_home()
            self._poll_ready("homing")
            after_deg = self._encoder_or_none()
            # unknown start: assume a visible travel (the first settle then waits for motion in gyro z)
            known = before_deg is not None and after_deg is not None
            self._homing_travel_deg = abs(after_deg - before_deg) if known else 360.0
            return
        self._poll_ready("homing")

    def _encoder_or_none(self) -> float | None:
        try:
            return float(self.turntable.angle_deg())
        except (DeviceError, ValueError):
            return None

    def _read_imu(self, n: int) -> ImuBlock:
        block = self.imu.read_samples(n, self.limits.read_timeout_s)
        self._last_imu_index = int(block.sample_index[-1])
        return block

    def _has_gyro_z(self) -> bool:
        return self.imu.has_gyro_z()

    def _gyro_axes(self) -> str:
        return self.imu.axes.gyro

    def _align_to_grid(self, n_grid: int) -> None:
        """Read (and drop) samples until the next one's device index is a multiple of `n_grid`, so
        that windows and dwells lie on a fixed sample grid whatever the host's timing; none when it
        is already (a model that cannot tell its next index: one read to learn it)."""
        nxt = self.imu.next_index(self.limits.read_timeout_s)
        if nxt is None:
            nxt = int(self._read_imu(1).sample_index[-1]) + 1
        k = (-nxt) % n_grid
        if k:
            self._read_imu(k)

    def settle(self, expect_motion: bool = True, move_deg: float | None = None) -> SettleResult:
        """:meth:`_settle`, and the IMU index it ended at (the dwell starts on the grid after it)."""
        result = self._settle(expect_motion, move_deg)
        result.end_index = self._last_imu_index
        return result

    def _settle(self, expect_motion: bool, move_deg: float | None) -> SettleResult:
        """Wait (in device time) until the table is at rest after a move; called after READY.

        With a gyro z: windows on a fixed sample grid from the move command on, first until the
        slew shows (|mean| above settle_rest_dph), then until the ringing has died out
        (:func:`settle_reached`), at most the move's own bound (length over the stage's speed) plus
        settle_max_s after the slew showed. Without one (a single-axis or x-y unit): the stage's
        READY, then [turntable] settle_s of samples (those before READY were dropped)."""
        cfg = self.run_cfg
        rate = float(self.imu.rate_hz)
        n_win = max(2, int(round(cfg.settle_window_s * rate)))
        if not self._has_gyro_z():
            self.imu.discard_pending()  # READY has been seen: what arrived so far may be older
            n_settle = int(round(self.limits.stage_settle_s * rate))
            if n_settle:
                self._read_imu(n_settle)
            return SettleResult(n_settle / rate, True, 0)
        move_s = self._move_duration_s(self._move_deg if move_deg is None else move_deg)
        max_windows = max(1, int(np.ceil((cfg.settle_max_s + move_s) * rate / n_win)))
        min_windows = int(np.ceil(cfg.settle_min_s * rate / n_win))
        ready_index = self.imu.caught_up_index(CAUGHT_UP_WAIT_S)  # the move is behind it (READY)
        if not expect_motion and ready_index is not None and self._last_imu_index is not None:
            if ready_index > self._last_imu_index:  # a backlog from before the command: no settle
                self._read_imu(ready_index - self._last_imu_index)
        self._align_to_grid(n_win)
        means_dph: list[float] = []
        onset: int | None = None
        if expect_motion:
            onset, slew_dph = self._find_slew(n_win, move_s, ready_index)
            means_dph.append(slew_dph)
        windows: list[np.ndarray] = []
        for k in range(1, max_windows + 1):
            self._check_stop()
            z = np.asarray(self._read_imu(n_win).gyro_rad_s)[:, 2] / DPH
            windows.append(z[np.isfinite(z)])
            means_dph.append(float(np.mean(windows[-1])) if windows[-1].size else 0.0)
            if k >= min_windows and settle_reached(windows[-2:], cfg.settle_ratio, cfg.settle_rest_dph):
                margin_s = self._settle_margin(rate)
                rest_s = after_motion_s(means_dph, n_win / rate, margin_s) if expect_motion else None
                return SettleResult(k * n_win / rate + margin_s, True, k, rest_s, onset)
        rest_s = after_motion_s(means_dph, n_win / rate, 0.0) if expect_motion else None
        return SettleResult(max_windows * n_win / rate, False, max_windows, rest_s, onset)

    def _find_slew(self, n_win: int, move_s: float, ready_index: int | None) -> tuple[int, float]:
        """Read windows until the gyro z shows the table turning: (first index of that window, its
        mean [°/h]). Given up after twice the move's bound — counted from the window past
        `ready_index` (the IMU index when the reader had read all sent after READY) when the reader
        was behind: the slew lies before READY, whatever backlog came first."""
        rate = float(self.imu.rate_hz)
        n_max = int(np.ceil(2.0 * move_s * rate / n_win))
        k, first = 0, None
        while True:
            self._check_stop()
            block = self._read_imu(n_win)
            first = int(block.sample_index[0]) if first is None else first
            z = np.asarray(block.gyro_rad_s)[:, 2] / DPH
            if abs(float(np.nanmean(z))) > self.run_cfg.settle_rest_dph:
                return int(block.sample_index[0]), float(np.nanmean(z))
            k += 1
            if k >= n_max and (ready_index is None or int(block.sample_index[-1]) > ready_index):
                last = int(block.sample_index[-1])
                lost = last - first + 1 - k * n_win
                why = (f"the IMU stream lost {lost} of its samples meanwhile: the slew may be among them"
                       if lost else "is the IMU on the table, its z along the table axis?")
                raise DeviceError("imu", self.imu.port,
                                  f"the gyro z axis showed no table motion during the move — {why}")

    def _settle_margin(self, rate: float) -> float:
        """Drop settle_margin_s of samples after the settle criterion; returns that time [s]."""
        n = int(round(self.limits.settle_margin_s * rate))
        if n:
            self._read_imu(n)
        return n / rate

    def _read_accel(self, n: int, until_stopped: bool = False) -> AccelBlock:
        if until_stopped:
            return self.accel.read_until_stopped(n, self._event)
        return self.accel.read_samples(n, self.limits.read_timeout_s)

    def _may_move_on(self, n_wanted: int, n_dwell: int) -> bool:
        """Whether the next move may be commanded before the tilt sensor's dwell is all here: the
        sensor proves its stops, and what it has yet to send of the `n_wanted` samples since its
        start — all it could lose to the stop — is within the dwell's allowed shortfall
        (1 − accel_min_fraction of `n_dwell`): a sensor or link that lags more is waited for."""
        if not self.accel.stop_reported:
            return False
        allowed = (1.0 - self.limits.dwell.accel_min_fraction) * n_dwell
        return n_wanted - self.accel.pending_samples() <= allowed

    def _skip_accel(self, n: int, until_stopped: bool) -> None:
        """Drop the tilt sensor's next `n` samples of device time: counted by its sample counter, so
        that the frames lost among them do not push its dwell later."""
        last: int | None = None
        while n > 0:
            block = self._read_accel(n, until_stopped)
            if not len(block):
                return
            counter = np.asarray(block.counter)
            n -= int(counter[-1]) - (int(counter[0]) - 1 if last is None else last)
            last = int(counter[-1])

    def dwell(self, index: int, target_deg: float, settle_s: float = 0.0,
              after: int | None = None) -> DwellData:
        """Collect dwell_s·rate IMU samples right after settling (in chunks, reporting live
        statistics), then dwell_s·rate accelerometer samples: those after its NMT start at READY,
        less the first settle_s·rate of them (:meth:`_accel_skip_s`: up to the settle's end).

        The two dwells need not coincide: both lie inside the same rest (the accelerometer was
        started at or after READY and skips at least to the end of the IMU's settle; it is stopped
        before the next move is commanded, and only what it sent before its stop is read), so a CAN
        link that lags, or loses frames, shifts nothing.

        What the host does between the IMU's last dwell sample and the next move command lets device
        time run on unseen. So the table angle is read during the dwell, and the move to plan
        position `after` is commanded as soon as the IMU's dwell is in when :meth:`_may_move_on`
        (the tilt sensor proves its stops and is at most its allowed shortfall behind): the checks,
        and the tilt sensor's last samples, come while the table turns, its dwell being what it sent
        before its stop. A dwell found bad is then measured again after a move back."""
        cfg = self.run_cfg
        rate = float(self.imu.rate_hz)
        n_total = max(2, int(round(cfg.dwell_s * rate)))
        n_chunk = max(1, int(round(self.limits.chunk_s * rate)))
        n_grid = int(round(self.limits.dwell_grid_s * rate))
        if n_grid > 1:
            self._align_to_grid(n_grid)
        blocks = []
        windows = DisturbanceWindows(imu_window(rate, self.limits.dwell))
        running = RunningMeans()
        skip = int(np.ceil(settle_s * self.accel_rate_hz))
        n_accel = max(2, int(round(cfg.dwell_s * self.accel_rate_hz)))
        got, moved_on = 0, False
        while got < n_total:
            self._check_stop()
            block = self._read_imu(min(n_chunk, n_total - got))
            got += len(block.sample_index)
            if self._rest_angle_deg is None:
                self._rest_angle_deg = float(self.turntable.angle_deg())  # at rest: any time in the dwell
            if got >= n_total:  # the IMU's dwell is in: the move first, its bookkeeping after
                angle_deg = self._rest_angle_deg
                moved_on = after is not None and self._may_move_on(skip + n_accel, n_accel)
                if moved_on:
                    self._command_move(after, self._plan[after])
            blocks.append(block)
            g = np.asarray(block.gyro_rad_s) / DPH
            windows.add(np.hstack([g, np.asarray(block.accel_g)]))
            mean, std_of_mean = running.add(g)
            if not moved_on:  # (after the move command the view says "move")
                self.on_progress(Progress(index + 1, len(self._plan), "dwell", target_deg,
                                          dwell_done_s=got / rate, dwell_s=cfg.dwell_s, gyro_mean_dph=mean,
                                          gyro_std_of_mean_dph=std_of_mean))
        self._check_stop()
        imu_verdict = self._imu_verdict(blocks, windows)  # while the tilt sensor's dwell arrives
        self._skip_accel(skip, until_stopped=moved_on)
        return DwellData(blocks, self._read_accel(n_accel, until_stopped=moved_on), imu_verdict, angle_deg,
                         n_accel, moved_on)

    # -- the sequence ------------------------------------------------------------------------
    def run(self) -> list[PositionMeans]:
        """Measure every position of the plan (but those in `skip`) and return their means."""
        try:
            return self._run()
        finally:
            self.log_stats()

    def _run(self) -> list[PositionMeans]:
        self.on_progress(Progress(0, self.run_cfg.positions, "reference"))
        self._check_stop()
        self._reference()
        self._check_stop()
        if self.run_cfg.plan == "sweep" and not self._has_gyro_z():
            raise ConfigError(
                f"[run] plan = sweep needs a gyro z to place the samples taken while the table turns; "
                f"the IMU has gyro {self._gyro_axes()} only — use plan = positions"
            )
        self._plan = self.plan_deg()
        n = len(self._plan)
        todo = [i for i in range(n) if i not in self.skip]
        for i, after in zip(todo, todo[1:] + [None], strict=True):
            self._measure_position(i, self._plan[i], after)
        self.accel.pause()
        if self.run_cfg.return_to_start:
            self.on_progress(Progress(n, n, "return", self._plan[0]))
            self._return_to_start()
        self._event({"event": "end", "complete": True, "positions_measured": len(self.positions)})
        return list(self.positions)

    def _return_to_start(self) -> None:
        """The move back to the first position. A plan that fits every sample (MOTION_KINDS) with a
        gyro z then settles and reads the encoder at rest once more (a `returned` event with the IMU
        indices of a short rest): the return's samples are then pinned at both ends and join the fit,
        so the time the return takes is not lost to it."""
        target = self._plan[0]
        pin = self.run_cfg.plan in MOTION_KINDS and self._has_gyro_z()
        here = float(self.turntable.angle_deg()) if pin else target
        self._move(target)
        if not pin:
            return
        travel_deg = abs(target - here)
        try:
            settle = self.settle(expect_motion=travel_deg >= MIN_VISIBLE_MOVE_DEG, move_deg=travel_deg)
            rest = self._read_imu(max(2, int(round(self.run_cfg.settle_window_s * float(self.imu.rate_hz)))))
        except DeviceError as exc:  # every position is measured: the fit then ends at the last dwell
            self._event({"event": "return_unpinned", "error": str(exc)})
            log.warning("no rest measured after the return (%s): the fit ends at the last dwell", exc)
            return
        idx = np.asarray(rest.sample_index)
        self._event({
            "event": "returned", "commanded_deg": target,
            "table_angle_deg": float(self.turntable.angle_deg()),
            "settle": settle.as_event(),
            "imu": {"first_index": int(idx[0]), "last_index": int(idx[-1]), "samples": int(idx.size)},
        })

    def _measure_position(self, i: int, target: float, after: int | None = None) -> PositionMeans:
        """Move, settle and dwell; measure again (up to max_attempts) when the IMU or the
        accelerometer timed out or vanished, lost too much, or the dwell shows a disturbance. A kept
        dwell commands the move to plan position `after` before it is recorded: the host's
        bookkeeping then runs while the table turns, not while a time-scaled simulator's device time
        runs on."""
        n = len(self._plan)
        reasons: list[str] = []
        for attempt in range(1, self.limits.max_attempts + 1):
            try:
                settle, data, counts = self._attempt(i, target, after)
            except StageFault:
                raise  # _move already retried once
            except DeviceError as exc:
                if exc.device not in ("imu", "accelerometer"):
                    raise
                reason = f"{exc.device} read failed: {exc}"
                if exc.device == "imu" and self._reconnect_imu(i, exc):
                    reason = f"imu link lost and reconnected: {exc}"
            else:
                problems = combine_verdicts(data.imu_verdict,
                                            self._accel_verdict(data.accel_block, data.accel_expected))
                if not problems:
                    self._check_stop()
                    try:
                        if after is not None and not data.moved_on:
                            self._command_move(after, self._plan[after])
                    finally:  # recorded even if the next move could not be commanded
                        self._flush_logs()
                        extra = {"attempt": attempt, "heartbeats": counts[0], "emcy": counts[1],
                                 "early_move": data.moved_on}
                        means = self._record(i, target, data.table_angle_deg, settle, data.blocks,
                                             data.accel_block, extra)
                    self.on_progress(Progress(i + 1, n, "measured", target, dwell_done_s=self.run_cfg.dwell_s,
                                              dwell_s=self.run_cfg.dwell_s, gyro_mean_dph=means.gyro_dph,
                                              settle_s=settle.settle_s, means=means))
                    return means
                reason = "; ".join(problems)
            reasons.append(reason)
            log.warning("position %d attempt %d: %s", i + 1, attempt, reason)
            self._event({"event": "remeasure", "index": i, "attempt": attempt, "reason": reason})
            self._check_stop()
        self._flush_logs()
        self._finish_move_on(target)  # the table at rest when the run ends
        raise RunFailed(
            f"position {i + 1} of {n} ({target:g}°) failed {self.limits.max_attempts} times — "
            f"last: {reasons[-1]}",
            list(self.positions),
        )

    def _command_move(self, i: int, target: float) -> float:
        """The first half of a move to plan position i: the view told, the tilt sensor paused, the
        IMU's older samples dropped, the move commanded; returns the travel the settle expects to
        see [deg]."""
        self.on_progress(Progress(i + 1, len(self._plan), "move", target, 0.0, self.run_cfg.dwell_s))
        here = self._rest_angle_deg if self._rest_angle_deg is not None else float(self.turntable.angle_deg())
        self._rest_angle_deg = None
        self._move_deg = target - here
        # homing's motion, not yet seen in the IMU data, counts as part of the first move;
        # the data since the home command are kept for that (discarded before it)
        travel_deg = abs(self._move_deg) + self._homing_travel_deg
        self.accel.pause()  # quiet during the move; started again after the settle
        if not self._homing_travel_deg:
            self.imu.discard_pending()  # what is left is from before the move command
        self.turntable.start_move(target)
        self._commanded = (target, travel_deg)
        return travel_deg

    def _attempt(self, i: int, target: float, after: int | None = None
                 ) -> tuple[SettleResult, DwellData, tuple[int, int]]:
        """One measurement of a position: move (the tilt sensor paused; commanded already when the
        last position's dwell was kept), settle, dwell (commanding the move to `after` when it may);
        the tilt sensor's status and fault reports during the dwell."""
        n = len(self._plan)
        self._finish_move_on(target)
        commanded = self._commanded is not None and self._commanded[0] == target
        travel_deg = self._commanded[1] if commanded else self._command_move(i, target)
        self._commanded = None
        self._move(target, commanded=True)
        self.on_progress(Progress(i + 1, n, "settle", target, 0.0, self.run_cfg.dwell_s))
        # at READY: its first samples are skipped until the settle's end
        self._accel_started_at = None
        self.accel.resume(self._check_stop, self._event, before_start=self._note_accel_start)
        settle = self.settle(expect_motion=travel_deg >= MIN_VISIBLE_MOVE_DEG, move_deg=travel_deg)
        self._homing_travel_deg = 0.0
        hb0, emcy0 = self.accel.counts()
        data = self.dwell(i, target, self._accel_skip_s(settle), after)
        hb1, emcy1 = self.accel.counts()
        return settle, data, (hb1 - hb0, emcy1 - emcy0)

    def _finish_move_on(self, target: float) -> None:
        """When a move to another position than `target` was commanded already (the next one, by a
        dwell then measured again: :meth:`dwell`): let it end (READY), so that the move back to
        `target` starts from a table at rest."""
        if self._commanded is None or self._commanded[0] == target:
            return
        other, _ = self._commanded
        self._commanded = None
        self._move(other, commanded=True)
        self._rest_angle_deg = None

    def _note_accel_start(self) -> None:
        self._accel_started_at = self.imu.caught_up_index(CAUGHT_UP_WAIT_S)

    def _accel_skip_s(self, settle: SettleResult) -> float:
        """Device seconds of the tilt sensor's samples to drop after its start, so that its dwell
        begins where the settle ended. On the IMU's clock: the newest IMU sample just before the
        start command is at or behind the device time the command took effect (the IMU link lags,
        never leads), so settle end − that index is the rest still to skip, or more — however late
        the host sent the start. A model that cannot say its newest index: the start is taken to be
        at READY and the settle after the motion is skipped (SettleResult.rest_before_dwell_s)."""
        started, ended = self._accel_started_at, self._last_imu_index
        if started is None or ended is None:
            return settle.rest_before_dwell_s
        return max(0.0, (ended + 1 - started) / float(self.imu.rate_hz))

    def _reconnect_imu(self, i: int, exc: DeviceError) -> bool:
        """After a failed IMU read: re-open its link if it vanished (InertialStream.recover) and log how
        it went; False when the link was there (the read just timed out)."""
        try:
            outcome = self.imu.recover(self.limits.reconnect_timeout_s)
        except DeviceError as again:
            self._event({"event": "imu_reconnect", "index": i, "ok": False, "error": str(again)})
            raise RunFailed(f"{again} (after: {exc})", list(self.positions)) from None
        if outcome is None:
            return False
        self._event({"event": "imu_reconnect", "index": i, "ok": True, **outcome, "error": str(exc)})
        return True

    def _imu_verdict(self, blocks: list[ImuBlock], windows: DisturbanceWindows) -> DwellVerdict:
        """The IMU's share of why a dwell must be measured again (estimators.dwell)."""
        return imu_dwell_verdict(blocks, imu_rate_hz=float(self.imu.rate_hz), gyro_axes=self._gyro_axes(),
                                 stalls=self.imu.stall_indices, limits=self.limits.dwell, windows=windows)

    def _accel_verdict(self, accel_block: AccelBlock, expected: int | None = None) -> DwellVerdict:
        """The tilt sensor's share of why a dwell must be measured again (estimators.dwell)."""
        return accel_dwell_verdict(accel_block, accel_rate_hz=self.accel_rate_hz, limits=self.limits.dwell,
                                   expected=expected)

    def log_stats(self) -> None:
        """The devices' counters for this session (bad CRC, resyncs, lost, EMCY…) to the events log."""
        try:
            counters = {**self.imu.counters(), **self.accel.counters()}
        except Exception as exc:  # noqa: BLE001 - counters are a report, never a reason to fail
            log.warning("could not read the drivers' counters: %s", exc)
            return
        self._event({"event": "stats", **counters})

    def _flush_logs(self) -> None:
        """Push the raw logs to disk after each position (the IMU and stage transports flush every
        write; the tilt sensor's log may buffer)."""
        self.accel.flush_log()

    def _record(
        self,
        i: int,
        target: float,
        angle_deg: float,
        settle: SettleResult,
        blocks: list[ImuBlock],
        accel_block: AccelBlock,
        extra: dict[str, Any] | None = None,
    ) -> PositionMeans:
        idx = np.concatenate([np.asarray(b.sample_index) for b in blocks])
        gyro = np.concatenate([np.asarray(b.gyro_rad_s) for b in blocks], axis=0)
        counter = np.asarray(accel_block.counter)
        imu_lost = int(idx[-1] - idx[0] + 1 - idx.size)
        accel_lost = int(accel_block.lost_samples)
        axes = self._gyro_axes()
        means = position_means(
            angle_deg, gyro, np.asarray(accel_block.accel_g), imu_lost, accel_lost, float(self.imu.rate_hz),
            axes,
        )
        self.positions.append(means)
        before_move_s = None
        if settle.onset_index is not None and self._last_dwell_end is not None:
            before_move_s = (settle.onset_index - self._last_dwell_end) / float(self.imu.rate_hz)
        self._last_dwell_end = int(idx[-1])
        self._event(
            {
                "event": "position",
                "index": i,
                "commanded_deg": target,
                "table_angle_deg": angle_deg,
                "settle": settle.as_event(),
                "imu": {
                    "first_index": int(idx[0]),
                    "last_index": int(idx[-1]),
                    "samples": int(idx.size),
                    "lost": imu_lost,
                    "gyro_axes": axes,
                    "invalid": means.invalid_samples,
                },
                "accel": {
                    "first_counter": int(counter[0]),
                    "last_counter": int(counter[-1]),
                    "samples": int(counter.size),
                    "lost": accel_lost,
                    "heartbeats": int((extra or {}).get("heartbeats", 0)),
                    "emcy": int((extra or {}).get("emcy", 0)),
                },
                "attempt": int((extra or {}).get("attempt", 1)),
                "before_move_s": before_move_s,
                "early_move": bool((extra or {}).get("early_move", False)),
                "gyro_dph": means.gyro_dph,
                "accel_g": means.accel_g,
            }
        )
        return means
