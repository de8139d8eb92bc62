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

import contextlib
import logging
import signal
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from northfinder.config import RunConfig, position_plan_deg
from northfinder.constants import DPH
from northfinder.errors import ConfigError, DeviceError
from northfinder.rundir import PositionMeans, RunDir, position_means

log = logging.getLogger(__name__)


class _Turntable(Protocol):  # the parts of northfinder.drivers.turntable.Turntable used here
    def status(self) -> Any: ...
    def ensure_referenced(self, allow_home: bool = True) -> Any: ...
    def move_absolute_deg(self, angle_deg: float, wait: bool = True, timeout_s: float = 120.0) -> Any: ...
    def wait_ready(self, timeout_s: float = 120.0, poll_s: float = 0.05) -> Any: ...
    def position_deg(self) -> float: ...
    def stop(self) -> Any: ...
    def soft_limits_deg(self) -> tuple[float, float]: ...


MIN_VISIBLE_MOVE_DEG = 0.5
"""Moves at least this long are expected to show in the gyro z before settling is judged."""


class Interrupted(Exception):
    """The run was stopped by a signal; `positions` holds what was measured before it."""

    def __init__(self, signum: int, positions: list[PositionMeans], stage_state: str | None):
        self.signum = signum
        self.positions = positions
        self.stage_state = stage_state
        super().__init__(f"stopped by {signal.Signals(signum).name} after {len(positions)} positions")


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


@dataclass
class SettleResult:
    """How the settle criterion ended: after how much device time and whether it was met."""

    settle_s: float
    settled: bool
    windows: int


class StopFlag:
    """Signal handlers that only raise a flag (the first time) so that no I/O is torn in half."""

    def __init__(self) -> None:
        self.signum: int | None = None

    def __bool__(self) -> bool:
        return self.signum is not None

    def _handler(self, signum: int, frame: Any) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt  # second signal: stop now
        self.signum = signum

    @contextlib.contextmanager
    def installed(self) -> Iterator[StopFlag]:
        """Install SIGINT and SIGTERM handlers for the duration (main thread only)."""
        old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            for s in old:
                signal.signal(s, self._handler)
            yield self
        finally:
            for s, h in old.items():
                signal.signal(s, h)


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


class Sequencer:
    """Runs the position plan on a turntable, an IMU and an accelerometer (drivers, opened)."""

    def __init__(
        self,
        turntable: _Turntable,
        imu: Any,
        accelerometer: Any,
        run: RunConfig,
        *,
        allow_home: bool = True,
        rundir: RunDir | None = None,
        on_progress: Callable[[Progress], None] | None = None,
        stop_flag: StopFlag | None = None,
        accel_rate_hz: float = 100.0,
        chunk_s: float = 0.5,
        poll_s: float = 0.02,
        move_timeout_s: float = 120.0,
    ):
        self.turntable = turntable
        self.imu = imu
        self.accel = accelerometer
        self.run_cfg = run
        self.allow_home = allow_home
        self.rundir = rundir
        self.on_progress = on_progress or (lambda p: None)
        self.stop_flag = stop_flag if stop_flag is not None else StopFlag()
        self.accel_rate_hz = float(accel_rate_hz)
        self.chunk_s = chunk_s
        self.poll_s = poll_s
        self.move_timeout_s = move_timeout_s
        self.positions: list[PositionMeans] = []
        self._plan: list[float] = []

    # -- helpers -----------------------------------------------------------------------------
    def _event(self, event: dict[str, Any]) -> None:
        if self.rundir is not None:
            self.rundir.log_event(event)

    def _check_stop(self) -> None:
        if self.stop_flag:
            state = None
            moving = None
            try:
                st = self.turntable.stop()
                state = st.state_name
                moving = bool(st.is_moving or st.is_homing)
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
        """The commanded angles, each shifted by whole turns into the stage's soft limits."""
        lo, hi = self.turntable.soft_limits_deg()
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

    def _move(self, target_deg: float) -> None:
        self.turntable.move_absolute_deg(target_deg, wait=False)
        deadline = time.monotonic() + self.move_timeout_s
        while True:
            self._check_stop()
            st = self.turntable.status()
            if st.is_ready and not st.errors:
                return
            if st.is_disabled or st.errors or not st.is_referenced:
                self.turntable.wait_ready(timeout_s=0.0)  # raises StageError naming the state and letter
                return
            if time.monotonic() > deadline:
                raise DeviceError(
                    "turntable",
                    getattr(self.turntable, "port", None),
                    f"not READY {self.move_timeout_s:g} s after the move to {target_deg:g}° "
                    f"(state {st.state_name}) — check the stage's speed and load",
                )
            time.sleep(self.poll_s)

    def _read_imu(self, n: int) -> Any:
        return self.imu.read(n, timeout_s=max(5.0, 2.0 * n / self.imu.rate_hz + 5.0))

    def settle(self, expect_motion: bool = True) -> SettleResult:
        """Read gyro-z windows (device time) from the move command on: first until the slew shows
        (|mean| above settle_rest_dph; samples that arrive late still show the table at rest
        before the move), then until the ringing has died out, at most settle_max_s after that."""
        cfg = self.run_cfg
        rate = float(self.imu.rate_hz)
        n_win = max(2, int(round(cfg.settle_window_s * rate)))
        max_windows = max(1, int(np.ceil(cfg.settle_max_s * rate / n_win)))
        min_windows = int(np.ceil(cfg.settle_min_s * rate / n_win))
        if expect_motion:
            for _ in range(int(np.ceil(self.move_timeout_s * rate / n_win))):
                self._check_stop()
                z = np.asarray(self._read_imu(n_win).gyro_rad_s)[:, 2] / DPH
                if abs(float(np.mean(z))) > cfg.settle_rest_dph:
                    break
            else:
                raise DeviceError(
                    "imu",
                    getattr(self.imu, "port", None),
                    "the gyro z axis showed no table motion during the move — is the IMU on the table, "
                    "its z along the table axis?",
                )
        windows: list[np.ndarray] = []
        for k in range(1, max_windows + 1):
            self._check_stop()
            windows.append(np.asarray(self._read_imu(n_win).gyro_rad_s)[:, 2] / DPH)
            if k >= min_windows and settle_reached(windows[-2:], cfg.settle_ratio, cfg.settle_rest_dph):
                return SettleResult(k * n_win / rate, True, k)
        return SettleResult(max_windows * n_win / rate, False, max_windows)

    def _start_accelerometer(self, quiet_s: float = 0.1, timeout_s: float = 10.0) -> None:
        """NMT start, once the CAN link has delivered everything sent before the last NMT stop.

        The node was stopped before the move, so once nothing more arrives (host time: this only
        drains a link that lags) every sample that follows was taken after the start.
        """
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.accel.discard_pending() == 0:
                time.sleep(quiet_s)
                if self.accel.discard_pending() == 0:
                    break
            else:
                time.sleep(0.02)
        self.accel.start_node()

    def _read_accel(self, n: int) -> Any:
        return self.accel.read(n, timeout_s=max(5.0, 2.0 * n / self.accel_rate_hz + 5.0))

    def dwell(self, index: int, target_deg: float, settle_s: float = 0.0) -> tuple[list[Any], Any]:
        """Collect dwell_s·rate IMU samples right after settling (in chunks, reporting live
        statistics), then dwell_s·rate accelerometer samples: those after its NMT start at READY,
        less the first settle_s·rate of them.

        The two dwells need not coincide: both lie inside the same rest (the accelerometer was
        started at or after READY in device time, READY + settle_s is at or after the settle the
        IMU showed, and the next move is commanded only after both dwells have arrived), so a CAN
        link that lags, or loses frames, shifts nothing."""
        cfg = self.run_cfg
        rate = float(self.imu.rate_hz)
        n_total = max(2, int(round(cfg.dwell_s * rate)))
        n_chunk = max(1, int(round(self.chunk_s * rate)))
        blocks = []
        got = 0
        s1 = np.zeros(3)
        s2 = np.zeros(3)
        while got < n_total:
            self._check_stop()
            block = self._read_imu(min(n_chunk, n_total - got))
            blocks.append(block)
            g = np.asarray(block.gyro_rad_s) / DPH
            got += g.shape[0]
            s1 += g.sum(axis=0)
            s2 += (g**2).sum(axis=0)
            mean = s1 / got
            var = np.maximum(s2 / got - mean**2, 0.0)
            self.on_progress(
                Progress(
                    index + 1,
                    len(self._plan),
                    "dwell",
                    target_deg,
                    dwell_done_s=got / rate,
                    dwell_s=cfg.dwell_s,
                    gyro_mean_dph=mean.tolist(),
                    gyro_std_of_mean_dph=np.sqrt(var / got).tolist(),
                )
            )
        self._check_stop()
        skip = int(np.ceil(settle_s * self.accel_rate_hz))
        if skip > 0:
            self._read_accel(skip)
        n_accel = max(2, int(round(cfg.dwell_s * self.accel_rate_hz)))
        return blocks, self._read_accel(n_accel)

    # -- the sequence ------------------------------------------------------------------------
    def run(self) -> list[PositionMeans]:
        """Measure every position of the plan and return the per-position means."""
        self.on_progress(Progress(0, self.run_cfg.positions, "reference"))
        self.turntable.ensure_referenced(allow_home=self.allow_home)
        self._check_stop()
        self._plan = self.plan_deg()
        n = len(self._plan)
        for i, target in enumerate(self._plan):
            self.on_progress(Progress(i + 1, n, "move", target, 0.0, self.run_cfg.dwell_s))
            here = float(self.turntable.position_deg())
            self.accel.stop_node()  # quiet during the move; started again after the settle
            self.imu.discard_pending()  # what is left is from before the move command
            self._move(target)
            self.on_progress(Progress(i + 1, n, "settle", target, 0.0, self.run_cfg.dwell_s))
            self._start_accelerometer()  # at READY: its first samples are skipped by the settle time
            settle = self.settle(expect_motion=abs(target - here) >= MIN_VISIBLE_MOVE_DEG)
            blocks, accel_block = self.dwell(i, target, settle.settle_s)
            self._check_stop()
            angle_deg = float(self.turntable.position_deg())
            self._flush_logs()
            means = self._record(i, target, angle_deg, settle, blocks, accel_block)
            self.on_progress(
                Progress(
                    i + 1,
                    n,
                    "measured",
                    target,
                    dwell_done_s=self.run_cfg.dwell_s,
                    dwell_s=self.run_cfg.dwell_s,
                    gyro_mean_dph=means.gyro_dph,
                    settle_s=settle.settle_s,
                    means=means,
                )
            )
        self.accel.stop_node()
        if self.run_cfg.return_to_start:
            self.on_progress(Progress(n, n, "return", self._plan[0]))
            self._move(self._plan[0])
        self._event({"event": "end", "complete": True, "positions_measured": len(self.positions)})
        return list(self.positions)

    def _flush_logs(self) -> None:
        """Push the raw logs to disk after each position (the IMU and stage transports flush every
        write; the CAN log is a python-can writer that buffers)."""
        flush = getattr(self.accel, "flush_log", None)
        if callable(flush):
            flush()
            return
        # Until the Accelerometer driver has flush_log(): its can.Logger's file, under its lock
        # (the notifier thread writes to it).
        lock = getattr(self.accel, "_lock", None) or contextlib.nullcontext()
        with lock:
            handle = getattr(getattr(self.accel, "_logger", None), "file", None)
            if handle is not None and not handle.closed:
                handle.flush()

    def _record(
        self,
        i: int,
        target: float,
        angle_deg: float,
        settle: SettleResult,
        blocks: list[Any],
        accel_block: Any,
    ) -> PositionMeans:
        idx = np.concatenate([np.asarray(b.sample_index) for b in blocks])
        gyro = np.concatenate([np.asarray(b.gyro_rad_s) for b in blocks], axis=0)
        counter = np.asarray(accel_block.counter)
        imu_lost = int(idx[-1] - idx[0] + 1 - idx.size)
        accel_lost = int(accel_block.lost_samples)
        means = position_means(
            angle_deg, gyro, np.asarray(accel_block.accel_g), imu_lost, accel_lost, float(self.imu.rate_hz)
        )
        self.positions.append(means)
        self._event(
            {
                "event": "position",
                "index": i,
                "commanded_deg": target,
                "table_angle_deg": angle_deg,
                "settle": {"settle_s": settle.settle_s, "settled": settle.settled, "windows": settle.windows},
                "imu": {
                    "first_index": int(idx[0]),
                    "last_index": int(idx[-1]),
                    "samples": int(idx.size),
                    "lost": imu_lost,
                },
                "accel": {
                    "first_counter": int(counter[0]),
                    "last_counter": int(counter[-1]),
                    "samples": int(counter.size),
                    "lost": accel_lost,
                },
                "gyro_dph": means.gyro_dph,
                "accel_g": means.accel_g,
            }
        )
        return means
