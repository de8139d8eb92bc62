"""The shared base of every kind of run: a run context and the guard around opening a device.

A run context holds what every function of a run used to pass around by hand: the configuration,
the run directory, the truth of a simulated run and the outputs (an extra result JSON, whether to
draw report.png), plus the two hooks through which a view watches the run — `progress` (a live
view, entered around the measurement) and `on_event` (every event the run logs). The run never
knows its view: the CLI hands it the hooks and prints the summary itself.
"""

from __future__ import annotations

import contextlib
import gc
import json
import math
import signal
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from northfinder.devices import registry
from northfinder.devices.imu import ImuBlock
from northfinder.errors import DeviceError, InputError, RunAborted
from northfinder.rundir import CONFIG, EVENTS, IMU_RAW, RESULT, RunDir
from northfinder.stopflag import StopFlag

ProgressView = Callable[[int, float], Any]
"""A progress view factory: called with (positions, dwell_s), returns a context manager whose
`__enter__` gives a callable that takes each `northfinder.sequencer.Progress`."""


@dataclass
class RunContext:
    """One run: configuration, run directory, truth, outputs, and the view's hooks."""

    cfg: Any
    rundir: RunDir
    truth: dict[str, float] | None = None
    json_path: str | None = None
    report: bool = True
    progress: ProgressView | None = None
    on_event: Callable[[dict[str, Any]], None] | None = None
    start_extra: dict[str, Any] | None = None
    """Extra fields of the start event (e.g. find's plan prediction)."""
    motion_feed: Any = None
    """find: the per-sample fit fed live (runs.find_motion_feed), None when the result decodes imu.raw."""

    def start(self, config: dict[str, Any]) -> None:
        """Write config.json (the first session only: a resumed run keeps its saved config)."""
        if self.rundir.session == 1:
            self.rundir.write_json(CONFIG, config)

    def event(self, event: dict[str, Any]) -> None:
        """Log one event to events.jsonl and show it to the view's event hook."""
        self.rundir.log_event(event)
        if self.on_event is not None:
            self.on_event(event)

    def view(self, positions: int, dwell_s: float) -> contextlib.AbstractContextManager[Any]:
        """The live progress view (or a silent one if the run has none)."""
        if self.progress is None:
            return contextlib.nullcontext(lambda _p: None)
        return self.progress(positions, dwell_s)

    def finish(self, result: dict[str, Any]) -> None:
        """Save the result: result.json and the extra JSON if asked (write_result), report.png if asked."""
        write_result(self.rundir, result, self.json_path)
        if self.report:
            from northfinder.report import write_report  # matplotlib: only when drawing

            write_report(result, self.rundir.report_path)

    def abort(self, positions_measured: int) -> None:
        """The end event of a run that did not complete."""
        self.event({"event": "end", "complete": False, "positions_measured": positions_measured})


@contextlib.contextmanager
def guard(device: str, port: str, factory: Callable[[], Any]) -> Iterator[Any]:
    """Enter a driver; a low-level OS/serial/CAN failure becomes one DeviceError line naming the port."""
    import can

    try:
        obj = factory()
        entered = obj.__enter__()
    except (OSError, can.CanError) as exc:  # serial.SerialException is an OSError
        raise DeviceError(device, port, f"cannot open it ({exc}); check the port in bench.toml") from None
    try:
        yield entered
    finally:
        obj.__exit__(*sys.exc_info())


def prepare_to_stream(*devices: tuple[str, Any]) -> None:
    """What would stall the interpreter once a device streams, done before the first one opens:
    every (role, bench section)'s model module imported, and the heap collected (so that
    :func:`heap_frozen` freezes little garbage). Either, with the devices streaming, held it for tens
    of ms — at a find's start the collection 64 ms (47 k objects; 165 ms with the report's
    matplotlib), the CAN accelerometer's modules and a GNSS receiver's (pynmeagps) as much — which a
    time-scaled simulator's stream multiplies: at 120× the IMU reader fell 8–20 device s behind, and
    the tilt sensor's start, noted against its newest index, placed that sensor's dwell that late."""
    for role, section in devices:
        registry.spec(role, registry.model_of(section, role))
    gc.collect()


@contextlib.contextmanager
def heap_frozen() -> Iterator[None]:
    """Run the body with what the process holds so far out of the cyclic collector's reach.

    A full collection walks every object and stops every thread while it does: 50–60 ms once
    matplotlib is imported (the report's preload), which is 6–7 device s at 120× — one gap between
    dwells stretched by that, the stage idle while the IMU ran on unseen. So the heap is frozen
    before the body (gc.freeze: later collections skip it; they walk only what the body makes, a few
    thousand objects), and unfrozen after, so garbage cycles among the frozen objects are collected
    again. Not collected here: the devices stream by now, and a collection is that same stall
    (:func:`prepare_to_stream` does it before they open). Nesting is not supported: the
    inner exit unfreezes."""
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


# ---------------------------------------------------------------------------------------------
# The align runs' plumbing (northfinder.runs.swaying, gnss, gnss_live): the IMU window read in
# device time, start/end events, the result save, the Ctrl-C/SIGTERM ending, replay's event lookup
# and window decode, firmware-sim's truth log. Devices open through `guard` above.
# ---------------------------------------------------------------------------------------------
class WindowView(Protocol):
    """What an align run shows while reading: `show(device seconds read, the mode's counters)`."""

    def show(self, done_s: float, info: str) -> None: ...


WindowProgress = Callable[[float], contextlib.AbstractContextManager[WindowView]]
"""A progress view factory for an align run: called with the window's device seconds, a context
manager giving a WindowView (the CLI hands `northfinder.cli._common.DeviceTimeProgress`)."""


class _SilentView:
    def show(self, done_s: float, info: str) -> None:
        """No view: the run reads without drawing."""


def window_view(progress: WindowProgress | None, duration_s: float) -> contextlib.AbstractContextManager[Any]:
    """The run's progress view, or a silent one if the CLI handed none."""
    return progress(duration_s) if progress is not None else contextlib.nullcontext(_SilentView())


def _wall_utc() -> datetime:
    """The one read of the host's wall clock in the runs layer: labels only (the events' `utc`, the
    default run directory's name), never which samples form a dwell or whether any were lost."""
    return datetime.now(UTC)


def now_utc() -> str:
    """The host UTC time for the events' `utc` (a label, never a decision)."""
    return _wall_utc().isoformat()


def default_out(kind: str) -> Path:
    """runs/<kind>-<UTC time>: the run directory when --out is not given."""
    return Path("runs") / _wall_utc().strftime(f"{kind}-%Y%m%dT%H%M%SZ")


# ---------------------------------------------------------------------------------------------
# IMU blocks
# ---------------------------------------------------------------------------------------------
def select_samples(block: Any, first_index: int, last_index: int) -> Any:
    """The samples of an ImuBlock with first_index ≤ index ≤ last_index (what the live run read)."""
    sel = (block.sample_index >= first_index) & (block.sample_index <= last_index)
    idx = block.sample_index[sel]
    lost = int(idx[-1] - idx[0] + 1 - len(idx)) if len(idx) else 0
    return ImuBlock(
        idx,
        block.gyro_rad_s[sel],
        block.accel_g[sel],
        block.status[sel],
        block.temperature_c[sel],
        lost,
        block.rate_hz,
        tuple(k for k in block.unknown_gaps if first_index < k <= last_index),
    )


def before_unknown_gap(block: Any, model: str | None = None) -> tuple[Any, dict[str, Any] | None]:
    """The samples before the block's first gap of unknown length, and what was cut (None: none).

    After such a gap (bytes lost on the line: an overrun, a silence) a wrapping device counter tells
    the sample count only modulo its period, so every later sample's device time may be off by a
    whole number of periods (0.5 s for a 128-sample counter at 250 Hz), enough to put an
    alignment's heading tens of degrees off with a small σ. The runs that time-tag samples (the
    align modes) keep the part whose time is known and say so, naming the counter of `model` (the
    model the run recorded) in its own words."""
    inside = [k for k in block.unknown_gaps if k > int(block.sample_index[0])] if len(block) else []
    if not inside:
        return block, None
    at = min(inside)
    rate = float(block.rate_hz)
    cut = select_samples(block, int(block.sample_index[0]), at - 1)
    decoder = registry.decoder_for("imu", model)
    note = {
        "at_index": at,
        "at_s": float(at - block.sample_index[0]) / rate,
        "kept_s": float(cut.sample_index[-1] - cut.sample_index[0] + 1) / rate,
        "dropped_samples": int(len(block) - len(cut)),
        "unknown_gaps": len(inside),
        "why": f"bytes lost on the IMU line (an overrun or a silence): the {decoder.counter_name} counts the "
               f"samples after it only modulo {int(decoder.counter_period)}, so their time is unknown",
    }
    return cut, note


def concat_blocks(blocks: list[Any], rate_hz: float) -> Any:
    """One ImuBlock of the window from the blocks read (gaps stay gaps in sample_index)."""
    return ImuBlock(
        np.concatenate([b.sample_index for b in blocks]),
        np.concatenate([b.gyro_rad_s for b in blocks]),
        np.concatenate([b.accel_g for b in blocks]),
        np.concatenate([b.status for b in blocks]),
        np.concatenate([b.temperature_c for b in blocks]),
        0,
        rate_hz,
        tuple(k for b in blocks for k in b.unknown_gaps),
    )


def read_imu_window(
    imu: Any, duration_s: float, stop: StopFlag, blocks: list[Any], check: Callable[[Any], None] | None = None
) -> Iterator[float]:
    """Read `duration_s` device seconds (samples + lost samples over the rate) into `blocks`,
    1 s of device time per read (few wakeups at a large time scale); yields the device seconds
    read so far after each read, so the caller can poll other ports and draw progress. Ends early
    when `stop` is raised. `check(block)` may refuse a block (it raises) before it is kept."""
    rate = imu.rate_hz
    n_total = int(round(duration_s * rate))
    chunk = max(1, int(rate))
    first = last = None
    while not stop:
        need = n_total if first is None else n_total - (last - first + 1)
        if need <= 0:
            break
        block = imu.read(min(chunk, need), timeout_s=5.0 + chunk / rate)
        if check is not None:
            check(block)
        if first is None:
            first = int(block.sample_index[0])
        if int(block.sample_index[-1]) - first + 1 > n_total:  # a gap overshot the window
            block = select_samples(block, first, first + n_total - 1)
        if len(block):
            blocks.append(block)
            last = int(block.sample_index[-1])
        yield (last - first + 1) / rate if last is not None else 0.0


def imu_start(port: str, imu: Any) -> dict[str, Any]:
    """The start event's `imu`: what the model's decoder must know to replay imu.raw, and the model."""
    return {"port": port, **imu.recorded_settings(), "model": imu.model_name}


def start_event(kind: str, duration_s: float, imu_port: str, imu: Any, **more: Any) -> dict[str, Any]:
    return {
        "event": "start",
        "kind": kind,
        "utc": now_utc(),
        "duration_s": duration_s,
        "imu": imu_start(imu_port, imu),
        **more,
    }


def imu_end(block: Any, stats: dict[str, Any]) -> dict[str, Any]:
    """The end event's `imu`: the window's index range (replay cuts imu.raw by it) and counters."""
    return {
        "first_index": int(block.sample_index[0]),
        "last_index": int(block.sample_index[-1]),
        "samples": len(block),
        "lost_samples": int(block.sample_index[-1] - block.sample_index[0] + 1 - len(block)),
        "stats": stats,
    }


def abort_or(stop: StopFlag, rd: RunDir, what: str) -> Exception:
    """InputError(what) for a run that was not stopped; RunAborted (130, 143 for SIGTERM) naming
    the signal and the run directory to replay otherwise."""
    if not stop:
        return InputError(what)
    err = RunAborted(
        f"run stopped by {signal.Signals(stop.signum).name}; {what}; the data is saved in "
        f"{rd.path} (northfinder replay {rd.path})"
    )
    if stop.signum == signal.SIGTERM:
        err.exit_code = 143
    return err


def write_result(rd: RunDir, result: dict[str, Any], json_path: str | None) -> None:
    """result.json in the run directory, and a copy at --json PATH if given: the one writer of a
    run's result (every kind of run saves through it)."""
    rd.write_json(RESULT, result)
    if json_path:
        RunDir(Path(json_path).parent).write_json(Path(json_path).name, result)


def finish_window(
    rd: RunDir,
    stop: StopFlag,
    compute: Callable[[bool], tuple[dict[str, Any], Any]],
    save: Callable[[dict[str, Any], Any], None],
) -> dict[str, Any]:
    """Align on the window (`compute(complete)`, the function replay uses) and `save` the result.
    A window cut short by a signal is aligned if it can be, then RunAborted (exit 130/143)."""
    complete = not stop
    try:
        result, extra = compute(complete)
    except InputError as exc:
        if complete:
            raise
        raise abort_or(stop, rd, str(exc)) from None
    save(result, extra)
    if not complete:
        raise abort_or(stop, rd, f"the result of the {result['duration_device_s']:.1f} s read is saved")
    return result


# ---------------------------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------------------------
def run_events(rd: RunDir, kind: str, mode: str) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """The run's start event (InputError if it is not a run of `kind`) and its end event (None if
    the run was killed before it saved its window)."""
    events = rd.events()
    start = next((e for e in events if e.get("event") == "start"), None)
    if start is None or start.get("kind") != kind:
        raise InputError(
            f"{rd.path}: not an `align --mode {mode}` run ({EVENTS} has no start event of kind {kind})"
        )
    end = next((e for e in events if e.get("event") == "end"), None)
    return start, end


def imu_window_from_raw(rd: RunDir, start: dict[str, Any], end: dict[str, Any]) -> Any:
    """The window's IMU samples decoded from imu.raw alone (the pure decoder: bit-identical)."""
    imu_cfg = start["imu"]
    raw = rd.file(IMU_RAW).read_bytes() if rd.file(IMU_RAW).exists() else b""
    block, _ = registry.decoder_for("imu", imu_cfg.get("model")).decode_log(raw, imu_cfg)
    return select_samples(block, int(end["imu"]["first_index"]), int(end["imu"]["last_index"]))


# ---------------------------------------------------------------------------------------------
# The simulator's truth log (JSON lines, docs/simulator.md)
# ---------------------------------------------------------------------------------------------
@dataclass
class TruthLog:
    """What northfinder needs from firmware-sim's truth log: the header, this client's
    `imu_connect` anchor (absolute sample k0, sequence0, t0_device_s, rate_hz), and truth against
    device time (heading unwrapped)."""

    header: dict[str, Any]
    connect: dict[str, Any] | None
    grid_events: int
    """imu_grid events after the connect (a rate change or configuration mode moved the k ↔ time map)."""
    t_s: np.ndarray
    heading_deg: np.ndarray  # unwrapped
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    pos_enu_m: np.ndarray  # of the IMU, about `origin`

    @property
    def imu_k0(self) -> int | None:
        """Absolute sample number k (1, 2, … since power-on) of the first frame this client received."""
        return int(self.connect["k0"]) if self.connect is not None else None

    @property
    def imu_rate_hz(self) -> float | None:
        rate = (self.header.get("imu") or {}).get("rate_hz")
        return float(rate) if rate is not None else None

    @property
    def imu_t0_s(self) -> float | None:
        """Device time at which the first received sample's interval starts: sample k covers
        [(k − 1)/rate, k/rate] (docs/simulator.md)."""
        if self.imu_k0 is None or not self.imu_rate_hz:
            return None
        return (self.imu_k0 - 1) / self.imu_rate_hz

    @property
    def lever_arm_m(self) -> list[float] | None:
        """The GNSS antenna's lever arm (vehicle scenario)."""
        la = (self.header.get("gnss") or {}).get("lever_arm_b_m")
        return [float(v) for v in la] if la is not None else None

    @property
    def origin(self) -> tuple[float, float, float] | None:
        o = self.header.get("enu_origin")
        return (float(o["latitude_deg"]), float(o["longitude_deg"]), float(o["height_m"])) if o else None

    def at(self, t_s: float | np.ndarray, what: str) -> np.ndarray:
        """Linear interpolation of a truth column at device time(s)."""
        col = getattr(self, what)
        t = np.asarray(t_s, dtype=float)
        if col.ndim == 1:
            return np.interp(t, self.t_s, col)
        return np.stack([np.interp(t, self.t_s, col[:, j]) for j in range(col.shape[1])], axis=-1)

    def heading_at(self, t_s: float | np.ndarray) -> np.ndarray:
        return np.mod(self.at(t_s, "heading_deg"), 360.0)


def read_truth_log(path: Path) -> TruthLog:
    """Parse firmware-sim's truth log (JSON lines: a header, `truth` rows, `event`s); a torn last
    line is ignored. InputError naming the file if it is missing or has no truth rows."""
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise InputError(f"{path}: the simulator's truth log is missing") from None
    header: dict[str, Any] = {}
    connect = None
    grid = 0
    rows: list[tuple] = []
    for line in lines:
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        kind = rec.get("type") if isinstance(rec, dict) else None
        if kind == "truth":
            pos = rec.get("imu_pos_enu_m", [math.nan] * 3)
            rows.append((rec["t_device_s"], rec["heading_deg"], rec["pitch_deg"], rec["roll_deg"], pos))
        elif kind == "header" and not header:
            header = rec
        elif kind == "event" and rec.get("event") == "imu_connect" and connect is None:
            connect = rec
        elif kind == "event" and rec.get("event") == "imu_grid" and connect is not None:
            grid += 1
    if not rows:
        raise InputError(f"{path}: the truth log has no truth rows")
    rows.sort(key=lambda r: r[0])
    return TruthLog(
        header=header,
        connect=connect,
        grid_events=grid,
        t_s=np.array([r[0] for r in rows], dtype=float),
        heading_deg=np.rad2deg(np.unwrap(np.deg2rad([r[1] for r in rows]))),
        pitch_deg=np.array([r[2] for r in rows], dtype=float),
        roll_deg=np.array([r[3] for r in rows], dtype=float),
        pos_enu_m=np.array([r[4] for r in rows], dtype=float).reshape(-1, 3),
    )


def grid_moved(rd: RunDir) -> InputError:
    return InputError(
        f"{rd.path}: the simulated IMU's sample grid moved after this client connected "
        "(imu_grid event in the truth log); its samples no longer map to device time"
    )


def discard_unstarted(rd: RunDir, own_files: set[str]) -> bool:
    """Remove a run directory this run created whose run never logged an event (bad port, the
    simulator did not start, Ctrl-C before the devices answered): config.json and empty or partial
    raw logs (`own_files`, the kind's own) are nothing replay or --resume could use. A directory
    holding anything else, or events, is kept (replay and --resume then say what it holds)."""
    path = rd.path
    if not getattr(rd, "created", False) or rd.session != 1 or rd.file(EVENTS).exists() or not path.is_dir():
        return False
    entries = list(path.iterdir())
    if any(e.name not in own_files or e.is_dir() for e in entries):
        return False
    for e in entries:
        e.unlink()
    path.rmdir()
    return True


@contextlib.contextmanager
def removed_if_unstarted(rd: RunDir, own_files: set[str]) -> Iterator[RunDir]:
    """Around an align run's start: a failure before its start event leaves no empty directory."""
    try:
        yield rd
    except BaseException:
        discard_unstarted(rd, own_files)
        raise
