"""The turntable find as a run: live measurement, result assembly and replay.

Live (:func:`measure`): open the stage, the IMU and the accelerometer with their logs in the run
directory, configure them, run the position plan (northfinder.sequencer), save the result.
Replay (:func:`replay`): decode the raw logs through the codecs, cut them by the events log and
compute the same per-position means. Live and replay go through the same result function
(:func:`compute_result`), so a replayed result equals the live one bit for bit.

The run does not know its view: the caller hands it a progress view (RunContext.progress) and
prints the summary itself.
"""

from __future__ import annotations

import contextlib
import math
import signal
import sys
import tomllib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from northfinder import config as bench
from northfinder.constants import wrap_deg_180
from northfinder.devices import registry
from northfinder.devices.imu import InertialStream
from northfinder.devices.tilt import TiltSensor
from northfinder.errors import InputError, RunAborted, RunDamaged
from northfinder.estimators.heading import MAX_ABS_LATITUDE_DEG, HeadingSolution
from northfinder.estimators.means import PositionMeans, position_means
from northfinder.estimators.plan import MOTION_KINDS
from northfinder.history import record_or_warn
from northfinder.rundir import CAN_LOG, CONFIG, EVENTS, IMU_RAW, RunDir, session_file
from northfinder.runkinds import Replayed
from northfinder.runs.base import (
    ProgressView,
    RunContext,
    default_out,
    guard,
    heap_frozen,
    now_utc,
    prepare_to_stream,
)
from northfinder.runs.base import discard_unstarted as base_discard_unstarted
from northfinder.runs.find_motion_feed import (
    FedEventLog,
    MotionFeed,
    feed_fit_result,
    replay_feed,
    start_live_feed,
)
from northfinder.runs.find_pace import (
    AUTO,
    AUTO_MAX_SCALE,
    AUTO_START_SCALE,
    KEEP_UP_S,
    AutoPace,
    PacedEventLog,
    paced_scales,
)
from northfinder.sequencer import Interrupted, RunFailed, Sequencer, SequencerLimits
from northfinder.simulate import SimSettings, SimulatorProcess, bench_config
from northfinder.stopflag import StopFlag

SIM_ACCEL_RATE_HZ = 50.0
"""--simulate runs the CAN accelerometer at 50 Hz (the node's rate is configurable; PROTOCOLS.md's
default is 100 Hz): half the slcan traffic, so a loaded host does not drop frames."""
SIM_CONFIG = "firmware_sim.toml"
DEFAULT_TIME_SCALE = 12.0
"""--simulate's default device-time speed-up: one that a 2-core host running the test suite four
finds at a time keeps up with. `--time-scale auto` (runs.find_pace) finds the highest this host
keeps up with now."""
SIM_DEFAULT_DWELL_S = 20.0
"""--simulate's default dwell per position [device s] (real benches: [run] dwell_s, default 30):
8 × 20 s at K = 12 finishes in under 30 s wall."""


@dataclass
class FindRequest:
    """What one find is asked to do: the `northfinder find` flags, as the CLI and a campaign give
    them (None: the bench's own value)."""

    config: str | None = None
    simulate: bool = False
    resume: str | None = None
    positions: int | None = None
    dwell: float | None = None
    order: str | None = None
    method: str | None = None
    json: str | None = None
    out: str | None = None
    no_report: bool = False
    unit: str | None = None
    heading: float = SimSettings.heading_deg
    pitch: float = SimSettings.pitch_deg
    roll: float = SimSettings.roll_deg
    latitude: float | None = None
    grade: str | None = None
    """The gyro's grade: the simulator's (default SimSettings.grade) and the planner's noise."""
    seed: int = SimSettings.seed
    time_scale: float | str = DEFAULT_TIME_SCALE
    """--time-scale: a factor, or "auto" (runs.find_pace)."""
    fault: Sequence[str] = ()
    sim_config: str | None = None
    plan: str | None = None
    target_std: float | None = None
    time_budget: float | None = None
    can: str | None = None
    """--simulate: firmware-sim's CAN node on INTERFACE[:CHANNEL], e.g. socketcan:vcan0."""
    stage: str | None = None
    imu: str | None = None
    tilt: str | None = None
    """--simulate: the simulated devices' models (firmware-sim --stage/--imu/--tilt; None: the defaults)."""


SIM_IMU_GRADES = {"stim": "stim300"}
"""--simulate's grade for an IMU model when --grade is not given (others: SimSettings.grade)."""


def sim_grade(req: FindRequest) -> str:
    """The simulated sensors' grade: --grade, else the simulated IMU model's own, else the default."""
    return req.grade or SIM_IMU_GRADES.get(req.imu or "", SimSettings.grade)


def check_request(req: FindRequest) -> None:
    """The flags' own ranges, before anything is opened or written (messages name the flag)."""
    if req.positions is not None and req.positions < 3:
        raise InputError(f"--positions {req.positions}: use at least 3 positions")
    if req.dwell is not None and not (math.isfinite(req.dwell) and req.dwell > 0):
        raise InputError(f"--dwell {req.dwell:g}: use a dwell greater than 0 s")
    lim = MAX_ABS_LATITUDE_DEG
    if req.latitude is not None and not (math.isfinite(req.latitude) and -lim <= req.latitude <= lim):
        raise InputError(f"--latitude {req.latitude:g}: use −{lim:g}…{lim:g} degrees (north positive; within "
                         f"{90 - lim:g}° of a pole the heading is undefined)")
    models = [f"--{k} {v}" for k, v in (("stage", req.stage), ("imu", req.imu), ("tilt", req.tilt)) if v]
    if models and not req.simulate:
        raise InputError(f"{models[0]}: the simulated device's model; with --config the bench.toml's "
                         "`model =` of its section names it")
    if req.fault and req.config:
        msg = f"--fault {req.fault[0]}: faults are injected by the simulator; use them with --simulate"
        raise InputError(msg)
    if req.time_scale == AUTO:
        if req.resume:
            raise InputError("--time-scale auto: for a new --simulate run; --resume takes a factor")
    elif req.simulate and not (math.isfinite(req.time_scale) and req.time_scale > 0):
        raise InputError(f"--time-scale {req.time_scale:g}: use a factor greater than 0 (or auto)")
    for flag, value in (("--target-std", req.target_std), ("--time-budget", req.time_budget)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise InputError(f"{flag} {value:g}: use a value greater than 0")
    if req.target_std is not None or req.time_budget is not None:
        if req.target_std is not None and req.time_budget is not None:
            raise InputError("--target-std and --time-budget: give one of them, not both")
        if req.positions is not None or req.dwell is not None or req.plan is not None:
            raise InputError("--target-std/--time-budget choose --positions, --dwell and --plan; "
                             "give either the goal or the plan")  # fmt: skip


def _apply_overrides(cfg: bench.BenchConfig, req: FindRequest,
                     latitude_deg: float | None) -> bench.BenchConfig:
    """The flags override the bench's fields (`latitude_deg`: the site's, if given); then one
    validation."""
    if req.positions is not None:
        cfg.run.positions = req.positions
    if req.dwell is not None:
        cfg.run.dwell_s = req.dwell
    if req.order is not None:
        cfg.run.order = req.order
    if req.method is not None:
        cfg.estimator.method = req.method
    if req.plan is not None:
        cfg.run.plan = req.plan
    if latitude_deg is not None:
        cfg.site.latitude_deg = latitude_deg
    return cfg.validate()


def prepare_new(req: FindRequest) -> tuple[bench.BenchConfig, RunDir, SimSettings | None, dict | None]:
    """The bench, the run directory, the simulator's settings and the plan's prediction (with
    --target-std/--time-budget) of a new find. The directory is made only once the configuration is
    known to be good: a bad config leaves nothing behind."""
    if req.simulate:
        sim_text, accel_rate_hz = sim_config_text(req.sim_config)
        cfg = bench.BenchConfig(source="--simulate")
        cfg.accelerometer.rate_hz = accel_rate_hz
        cfg.run.dwell_s = SIM_DEFAULT_DWELL_S
        cfg.turntable.model = req.stage or cfg.turntable.model
        cfg.imu.model = req.imu or cfg.imu.model
        cfg.accelerometer.model = req.tilt or cfg.accelerometer.model
        latitude_deg = req.latitude if req.latitude is not None else SimSettings.latitude_deg
        cfg = _apply_overrides(cfg, req, latitude_deg)
    else:
        cfg = _apply_overrides(bench.load(req.config), req, req.latitude)
        bench.require_ports(cfg)
    prediction = None
    if req.target_std is not None or req.time_budget is not None:
        from northfinder.runs.find_plan import choose_for_run

        grade = sim_grade(req) if req.simulate else req.grade
        prediction = choose_for_run(cfg, grade, req.target_std, req.time_budget)
    out = req.out or default_out("find")
    rundir = RunDir.new_run(out, f", or continue that one with `northfinder find --resume {out}`")
    settings = None
    if req.simulate:
        settings = SimSettings(
            heading_deg=req.heading,
            pitch_deg=req.pitch,
            roll_deg=req.roll,
            latitude_deg=cfg.site.latitude_deg,
            grade=sim_grade(req),
            seed=req.seed,
            time_scale=AUTO_MAX_SCALE if req.time_scale == AUTO else float(req.time_scale),
            paced=req.time_scale == AUTO,
            faults=tuple(req.fault),
            config=str(write_sim_config(rundir, sim_text)),
            can=req.can,
            stage_model=cfg.turntable.model,
            imu_model=cfg.imu.model,
            tilt_model=cfg.accelerometer.model,
        )
    return cfg, rundir, settings, prediction


def run_find(req: FindRequest, progress: ProgressView | None = None) -> tuple[dict[str, Any], RunDir, str]:
    """One find as `northfinder find` makes it (new or --resume): the result, its run directory and
    what the wall time covered ("measurement and report", "resumed session k")."""
    check_request(req)
    kwargs: dict[str, Any] = {}
    prediction = None
    if req.resume:
        r = prepare_resume(req.resume, req.time_scale, req.fault)
        cfg, rundir, settings = r.cfg, r.rundir, r.settings
        kwargs = {"previous": r.previous, "skip": r.skip}
        label = f"resumed session {rundir.session}"
    else:
        cfg, rundir, settings, prediction = prepare_new(req)
        label = "measurement and report"
    result = measure_and_report(cfg, rundir, settings, json_path=req.json, report=not req.no_report,
                                unit=req.unit, progress=progress, prediction=prediction, **kwargs)
    return result, rundir, label


@contextlib.contextmanager
def open_bench(
    cfg: bench.BenchConfig, rundir: RunDir | None, can_kwargs: dict[str, Any] | None = None
) -> Iterator[tuple[Any, Any, Any]]:
    """Open the turntable, the IMU and the accelerometer with their logs in the run directory.

    `can_kwargs` are extra python-can bus arguments (e.g. `sleep_after_open` for an slcan
    adapter that is a pty and needs no 2 s reset wait); `[accelerometer] bus_options` win.
    """
    a, t = cfg.accelerometer, cfg.turntable
    prepare_to_stream(("turntable", t), ("imu", cfg.imu), ("accelerometer", a))
    with contextlib.ExitStack() as stack:
        tt = stack.enter_context(guard("turntable", t.port, lambda: registry.open_device(
            "turntable", t, rundir.transcript_path if rundir else None)))
        tt.state()  # fail fast, naming the port, if something else than the model answers there
        imu = stack.enter_context(guard("imu", cfg.imu.port, lambda: registry.open_device(
            "imu", cfg.imu, rundir.imu_raw_path if rundir else None)))
        acc = stack.enter_context(guard("accelerometer", a.channel, lambda: registry.open_device(
            "accelerometer", a, rundir.can_log_path if rundir else None, can_kwargs=can_kwargs or {},
            eds_path=bench.accel_eds_path(cfg))))
        yield tt, imu, acc


def sim_config_text(user_toml: str | None) -> tuple[str, float]:
    """firmware-sim's --config text for this run and the CAN node's rate: the user's file (if any)
    with the rate set to SIM_ACCEL_RATE_HZ unless the file sets `accel_rate_hz`. Read (and checked)
    before the run directory exists, so a bad file leaves nothing behind."""
    text = ""
    data: dict[str, Any] = {}
    if user_toml:
        try:
            text = Path(user_toml).read_text(encoding="utf-8")
            data = tomllib.loads(text)
        except FileNotFoundError:
            raise InputError(f"--sim-config {user_toml}: no such file") from None
        except tomllib.TOMLDecodeError as exc:
            raise InputError(f"--sim-config {user_toml}: TOML syntax error: {exc}") from None
    if "accel_rate_hz" not in data:
        # top-level keys go before any [table] header
        text = f"accel_rate_hz = {SIM_ACCEL_RATE_HZ!r}  # northfinder find --simulate\n" + text
    return text, float(data.get("accel_rate_hz", SIM_ACCEL_RATE_HZ))


def write_sim_config(rundir: RunDir, text: str) -> Path:
    """Keep firmware-sim's --config in the run directory (resume starts the simulator from it)."""
    path = rundir.file(SIM_CONFIG)
    path.write_text(text, encoding="utf-8")
    return path


def _sim_info(settings: SimSettings | None) -> dict[str, Any] | None:
    """What config.json and the start event record of a simulated run (truth and knobs)."""
    if settings is None:
        return None
    return {**settings.truth(), "grade": settings.grade, "seed": settings.seed,
            "time_scale": AUTO if settings.paced else settings.time_scale, "faults": list(settings.faults),
            "models": {"stage": settings.stage_model, "imu": settings.imu_model,
                       "tilt": settings.tilt_model},
            **({"can": settings.can} if settings.can else {})}


def _configure(cfg: bench.BenchConfig, imu: InertialStream, acc: TiltSensor,
               rundir: RunDir) -> dict[str, Any]:
    """Read the IMU's settings back (the decoder must know them), set the rate if the config asks
    another; configure the tilt sensor (each step an event); what the start event records of it."""
    imu.configure_for_run(cfg.imu.rate_hz)
    return acc.configure_for_run(cfg.accelerometer, rundir.log_event)


MOTION_FIT_FED = "fed"
"""The start event's `motion_fit`: the per-sample fit was fed as the samples arrived
(runs.find_motion_feed); runs without it were fitted in one batch (runs.find_motion)."""


def _start_event(ctx: RunContext, imu: InertialStream, acc_info: dict[str, Any],
                 sim_info: dict[str, Any] | None,
                 stage_identity: dict[str, Any] | None = None) -> dict[str, Any]:
    """The session's start event: what replay needs to decode its logs, and the plan."""
    cfg = ctx.cfg
    return {
        "event": "start",
        "session": ctx.rundir.session,
        "simulate": sim_info,
        "utc": now_utc(),
        "latitude_deg": cfg.site.latitude_deg,
        "height_m": cfg.site.height_m,
        "method": cfg.estimator.method,
        "positions_planned": cfg.run.positions,
        "dwell_s": cfg.run.dwell_s,
        "plan": cfg.run.plan,
        "motion_fit": MOTION_FIT_FED,
        "turntable": {"model": registry.model_of(cfg.turntable, "turntable"),
                      "identity": stage_identity or {}},
        "imu": {"port": cfg.imu.port, **imu.recorded_settings(), "identity": imu.identity(),
                "model": registry.model_of(cfg.imu, "imu")},
        "accelerometer": {**acc_info, "model": registry.model_of(cfg.accelerometer, "accelerometer")},
        "truth": ctx.truth,
        **(ctx.start_extra or {}),
    }


def _sequence(ctx: RunContext, devices: tuple[Any, Any, Any], stop: StopFlag, previous: list[PositionMeans],
              skip: set[int] | None, seq_kwargs: dict[str, Any] | None,
              pace: AutoPace | None = None) -> list[PositionMeans]:
    """Run the position plan with the view's progress (and a caller's `on_progress` after it)."""
    tt, imu, acc = devices
    cfg = ctx.cfg
    seq_kwargs = dict(seq_kwargs or {})
    extra = seq_kwargs.pop("on_progress", None)
    with ctx.view(cfg.run.positions, cfg.run.dwell_s) as view:

        def on_progress(p: Any) -> None:
            view(p)
            if extra is not None:
                extra(p)

        limits = SequencerLimits.from_options(stage_speed_deg_s=cfg.turntable.speed_deg_s,
                                              stage_settle_s=cfg.turntable.settle_s, **seq_kwargs)
        events = FedEventLog(ctx.rundir, ctx.motion_feed) if ctx.motion_feed is not None else ctx.rundir
        if pace is not None:
            events = PacedEventLog(events, pace)
        seq = Sequencer(tt, imu, acc, cfg.run, limits, allow_home=cfg.turntable.allow_home, rundir=events,
                        on_progress=on_progress, stop_flag=stop, skip=skip or set())
        try:
            with heap_frozen():  # no full collection stalls the reaction to a dwell's end
                return previous + seq.run()
        except Interrupted as intr:
            intr.positions = previous + intr.positions
            aborted(ctx, intr)
        except RunFailed as fail:
            failed(ctx, fail, previous + fail.positions)
    raise AssertionError("unreachable")  # aborted/failed always raise


def measure(
    cfg: bench.BenchConfig,
    rundir: RunDir,
    *,
    settings: SimSettings | None = None,
    json_path: str | None = None,
    report: bool = True,
    progress: Any = None,
    can_kwargs: dict[str, Any] | None = None,
    previous: list[PositionMeans] | None = None,
    skip: set[int] | None = None,
    seq_kwargs: dict[str, Any] | None = None,
    prediction: dict[str, Any] | None = None,
    pace_scale: Callable[[float], None] | None = None,
) -> dict[str, Any]:
    """One north find on the bench `cfg` describes: open the devices, run the sequence, save the
    run directory, return the result. A signal stops it: RunAborted (exit 130, 143 for SIGTERM)
    after the stage is stopped and what was measured is saved; a fault the run cannot get past
    (RunFailed) also saves first. `progress`: a progress view factory (RunContext.progress), None
    for none. `previous`/`skip`: a resumed run's positions already measured (and their plan
    indices); `rundir.session` > 1 then. `seq_kwargs` go to the Sequencer (an `on_progress` there
    is called after the progress view). `pace_scale`: sets a paced simulator's time scale
    (--time-scale auto, runs.find_pace)."""
    ctx = RunContext(cfg, rundir, settings.truth() if settings else None, json_path, report, progress,
                     start_extra={"plan_prediction": prediction} if prediction else None)
    sim_info = _sim_info(settings)
    ctx.start({"bench": cfg.to_dict(), "simulate": sim_info, "argv": sys.argv, "plan_prediction": prediction})
    stop = StopFlag()
    with stop.installed(), open_bench(cfg, rundir, can_kwargs) as (tt, imu, acc):
        acc_info = _configure(cfg, imu, acc, rundir)
        ctx.event(_start_event(ctx, imu, acc_info, sim_info, tt.identity()))
        # the per-sample fit fed from the stream as it arrives (memory flat in run length); a resumed
        # session's fit joins sessions from the logs (find_motion)
        one_session_fit = rundir.session == 1 and cfg.run.plan in MOTION_KINDS
        ctx.motion_feed = start_live_feed(imu) if one_session_fit else None
        pace = None
        if pace_scale is not None:  # injected faults lose samples on purpose: paced by the lag alone
            pace = AutoPace(pace_scale, rundir.log_event, losses_count=not (settings and settings.faults))
        positions = _sequence(ctx, (tt, imu, acc), stop, list(previous or []), skip, seq_kwargs, pace)
    result = _result(ctx, positions, complete=True)
    ctx.finish(result)
    return result


def _result(ctx: RunContext, positions: Sequence[PositionMeans], complete: bool) -> dict[str, Any]:
    cfg = ctx.cfg
    events = ctx.rundir.events()
    return compute_result(positions, cfg.site.latitude_deg, cfg.estimator.method, height_m=cfg.site.height_m,
                          truth=ctx.truth, complete=complete, positions_planned=cfg.run.positions,
                          faults=faults_summary(events), plan=cfg.run.plan, devices=devices_summary(events),
                          motion=_live_motion(ctx, events),
                          prediction=(ctx.start_extra or {}).get("plan_prediction"))


def _live_motion(ctx: RunContext, events: Sequence[dict[str, Any]]):
    """The live run's per-sample fit: from the IMU's tap; a one-session run on a model that cannot
    tap its stream takes it as its replay will, from the decoded imu.raw through the same feed (so
    the two are bit-identical); a resumed run from the logs (find_motion)."""
    height_m = ctx.cfg.site.height_m
    if ctx.motion_feed is not None or ctx.rundir.session != 1:
        return _motion(ctx.rundir, events, height_m, feed=ctx.motion_feed)

    def from_log(sol: Any) -> Any:
        start = next(e for e in events if e.get("event") == "start")
        block, _ = _decode_session(ctx.rundir, 1, start)
        rate_hz = float(start["imu"]["rate_hz"])
        return _motion(ctx.rundir, events, height_m, block, replay_rate_hz=rate_hz)(sol)

    return from_log


def _motion(rd: RunDir, events: Sequence[dict[str, Any]], height_m: float, block: Any = None,
            feed: MotionFeed | None = None, replay_rate_hz: float | None = None):
    """The per-sample fit for compute_result. A one-session run's comes from a MotionFeed
    (runs.find_motion_feed): live `feed` fed from the IMU's tap, in replay (`replay_rate_hz` given)
    one fed from the decoded `block` — the same numbers. Otherwise (a resumed run, a model that
    cannot tap) from this run's raw log (find_motion; replay hands over the block it has decoded)."""
    from northfinder.runs.find_motion import motion_fit_result

    if feed is not None:
        return lambda sol: feed_fit_result(feed, events, sol, height_m)
    if replay_rate_hz is not None and block is not None:
        return lambda sol: feed_fit_result(replay_feed(block, events, replay_rate_hz), events, sol, height_m)
    return lambda sol: motion_fit_result(rd, events, sol, height_m, block)


def save_partial(ctx: RunContext, positions: list[PositionMeans]) -> None:
    """End event (incomplete) and, with 3 positions or more, the partial result."""
    ctx.abort(len(positions))
    if len(positions) >= 3:
        ctx.finish(_result(ctx, positions, complete=False))


def pace_note(events: Sequence[dict[str, Any]]) -> str | None:
    """One line when a simulated run went faster than this host keeps up with, None otherwise.

    firmware-sim drops what its client leaves unread for a second of wall time, so at a time scale
    above 1 with no fault injected, samples lost on a link (IMU bytes, CAN frames) mean the host fell
    behind — not the bench. And device time runs on while the host works between a dwell's end and
    the next move: a `before_move_s` above find_pace.KEEP_UP_S says that gap between dwells was
    stretched by the host — at every move when the median is (--time-scale auto paces itself by
    the same measure, move by move)."""
    start = next((e for e in events if e.get("event") == "start"), None)
    sim = (start or {}).get("simulate") or {}
    scales = paced_scales(events)
    scale = scales[-1] if scales else float(sim.get("time_scale") or 1.0)
    if scale <= 1.0 or sim.get("faults"):
        return None
    flag = f"--time-scale {scale:g}" + (" (auto)" if scales else "")
    stats = [e for e in events if e.get("event") == "stats"]
    imu = sum(int(e.get("imu", {}).get("lost_samples", 0)) for e in stats)
    crc = sum(int(e.get("imu", {}).get("bad_crc", 0)) for e in stats)
    acc = sum(int(e.get("accel", {}).get("lost_samples", 0)) for e in stats)
    if imu or crc or acc:
        return (f"at {flag} this host did not keep up: the IMU link lost {imu:,} samples "
                f"({crc:,} bad CRCs), the accelerometer {acc:,} (firmware-sim drops what is left unread "
                "for 1 s of wall time); run at a lower --time-scale")
    lags = [float(e["before_move_s"]) for e in events
            if e.get("event") == "position" and e.get("before_move_s") is not None]
    behind = [x for x in lags if x > KEEP_UP_S]
    if not behind:
        return None
    lag = float(np.median(lags))
    if lag > KEEP_UP_S:
        what, gaps = f"did not keep up: device time ran on {lag:.1f} s (median)", "the gaps"
    else:
        what = (f"fell behind at {len(behind)} of {len(lags)} moves: device time ran on up to "
                f"{max(behind):.1f} s")
        gaps = "those gaps"
    return (f"at {flag} this host {what} between a dwell's end and the next move, against ≤ {KEEP_UP_S:g} s "
            f"when it keeps up; {gaps} between dwells were stretched by that (nothing lost) — run at a lower "
            "--time-scale, or auto")


def failed(ctx: RunContext, fail: RunFailed, positions: list[PositionMeans]) -> None:
    """A fault the run could not get past: save what was measured, then one line saying so (and
    when a simulated run outran this host, that too)."""
    save_partial(ctx, positions)
    rd = ctx.rundir.path
    note = pace_note(ctx.rundir.events())
    raise RunFailed(
        f"{fail}; {note + '; ' if note else ''}"
        f"{len(positions)} of {ctx.cfg.run.positions} positions measured and saved in {rd} "
        f"(northfinder replay {rd}; finish it with northfinder find --resume {rd})",
        positions,
    )


def aborted(ctx: RunContext, intr: Interrupted) -> None:
    """Stopped by a signal: save what was measured, then RunAborted (130, or 143 for SIGTERM)."""
    k, n, rd = len(intr.positions), ctx.cfg.run.positions, ctx.rundir.path
    save_partial(ctx, intr.positions)
    err = RunAborted(
        f"run stopped by {signal.Signals(intr.signum).name} after {k} of {n} positions; stage "
        f"{intr.stage_state}; the data is saved in {rd} (northfinder replay {rd}; "
        f"finish it with northfinder find --resume {rd})"
    )
    if intr.signum == signal.SIGTERM:
        err.exit_code = 143
    raise err


@dataclass
class Resumed:
    """What `find --resume` continues: the saved bench, the new session's run directory, the
    simulator's settings (a simulated run), and the positions already measured."""

    cfg: bench.BenchConfig
    rundir: RunDir
    settings: SimSettings | None
    previous: list[PositionMeans]
    skip: set[int]


def prepare_resume(run_dir: str | Path, time_scale: float, faults: Sequence[str] = ()) -> Resumed:
    """A new session in the same run directory (its own raw logs), on the devices of the saved
    config; it measures the plan indices that have no position event yet."""
    rundir = RunDir(run_dir, create=False)
    saved = rundir.read_json(CONFIG)
    events = rundir.events()
    if any(e.get("event") == "end" and e.get("complete") for e in events):
        raise InputError(f"--resume {rundir.path}: the run is already complete (northfinder replay it)")
    starts = [e for e in events if e.get("event") == "start"]
    if not starts:
        raise InputError(f"--resume {rundir.path}: the run never started (no start event); run it anew")
    done = {int(e["index"]) for e in events if e.get("event") == "position"}
    previous = replay(rundir.path).positions
    rundir = RunDir(rundir.path, create=False, session=len(starts) + 1)
    cfg = bench.from_dict(saved["bench"], source=str(rundir.file(CONFIG)))
    sim = saved.get("simulate")
    settings = None
    sim_toml = rundir.file(SIM_CONFIG)
    if sim:
        settings = SimSettings(
            heading_deg=sim["heading_deg"],
            pitch_deg=sim["pitch_deg"],
            roll_deg=sim["roll_deg"],
            latitude_deg=sim["latitude_deg"],
            grade=sim["grade"],
            # a new power-on of the simulated bench: fresh sensor noise, the same truth
            seed=int(sim["seed"]) + rundir.session - 1,
            time_scale=float(time_scale),
            faults=tuple(faults) if faults else tuple(sim.get("faults", ())),
            config=str(sim_toml) if sim_toml.exists() else None,
            can=sim.get("can"),
            **{f"{role}_model": name for role, name in sim.get("models", {}).items()},
        )
    else:
        bench.require_ports(cfg)
    return Resumed(cfg, rundir, settings, previous, done)


def measure_and_report(
    cfg: bench.BenchConfig,
    rundir: RunDir,
    settings: SimSettings | None,
    *,
    json_path: str | None = None,
    report: bool = True,
    unit: str | None = None,
    **measure_kwargs: Any,
) -> dict[str, Any]:
    """Start firmware-sim if simulated, measure, record the run in the results history, draw the
    report (find and --resume alike); the result. Printing is the caller's. A start that fails
    before the run began leaves no directory behind (:func:`discard_unstarted`)."""
    try:
        with contextlib.ExitStack() as stack:
            if settings is not None:
                sim = SimulatorProcess(settings)
                endpoints = stack.enter_context(sim)
                cfg = bench_config(endpoints, settings.latitude_deg, cfg)
                if settings.paced:  # started at the highest scale (its buffers); paced from the start
                    sim.set_time_scale(AUTO_START_SCALE)
                    measure_kwargs["pace_scale"] = sim.set_time_scale
            # firmware-sim's slcan adapter is a pty: no USB adapter reset to wait 2 s for.
            slcan_pty = settings is not None and cfg.accelerometer.interface == "slcan"
            result = measure(cfg, rundir, settings=settings, json_path=json_path,
                             report=False,  # drawn below, once the simulator no longer competes for the CPU
                             can_kwargs={"sleep_after_open": 0.05} if slcan_pty else None, **measure_kwargs)
    except BaseException:
        discard_unstarted(rundir)
        raise
    record_or_warn(rundir.path, unit=unit)  # the results history (an index of run directories)
    if report:
        from northfinder.report import write_report
        from northfinder.runs.find_motion import report_samples

        samples = report_samples(rundir) if (result.get("motion_fit") or {}).get("available") else None
        write_report(result, rundir.report_path, samples=samples)
    return result


_OWN_FILES = {CONFIG, SIM_CONFIG, IMU_RAW, CAN_LOG, "turntable.log"}


def discard_unstarted(rundir: RunDir) -> bool:
    """A find's run directory with no event yet is removed (runs.base.discard_unstarted); one with
    events but no start event is kept: replay and --resume say it never began."""
    return base_discard_unstarted(rundir, _OWN_FILES)


# -- result assembly (live and replay) ------------------------------------------------------
def _solve(positions: Sequence[PositionMeans], latitude_deg: float, method: str, height_m: float = 0.0):
    from northfinder.estimators.heading import solve_heading

    alpha = np.array([p.table_angle_deg for p in positions])
    gyro = np.array([p.gyro_dph for p in positions], dtype=float)
    accel = np.array([p.accel_g for p in positions])
    # Standard error of each position's mean from its own spread (white noise over the dwell),
    # over the samples each axis kept (those flagged not valid are left out).
    kept = [[p.samples - p.invalid_samples.get(f"g{a}", 0) for a in "xyz"] for p in positions]
    n_gyro = np.maximum(np.array(kept, dtype=float), 1.0)
    n_accel = np.array([max(p.accel_samples, 1) for p in positions], dtype=float)[:, None]
    gyro_se = np.array([p.gyro_std_dph for p in positions], dtype=float) / np.sqrt(n_gyro)
    accel_se = np.array([p.accel_std_g for p in positions]) / np.sqrt(n_accel)
    gyro, gyro_se = _gyro_axes_for_fit(gyro, gyro_se)
    return solve_heading(
        alpha,
        gyro,
        accel,
        latitude_deg,
        method=method,
        gyro_std_dph=gyro_se,
        accel_std_g=accel_se,
        height_m=height_m,
    )


def _gyro_axes_for_fit(gyro_dph: np.ndarray, gyro_se_dph: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gyro axes the unit has (finite at every position), shaped as solve_heading takes them:
    (n,) for a single gyro on y (the seed paper's), (n, 2) for x and y, (n, 3) for x y z."""
    has = np.all(np.isfinite(gyro_dph), axis=0)
    if has[0] and has[1]:
        cols = [0, 1, 2] if has[2] else [0, 1]
        return gyro_dph[:, cols], gyro_se_dph[:, cols]
    if has[1]:
        return gyro_dph[:, 1], gyro_se_dph[:, 1]
    axes = "".join(a for a, h in zip("xyz", has, strict=True) if h) or "none"
    raise InputError(f"the IMU's gyro axes ({axes}) cannot find north: it needs gyro y, or x and y")


def compute_result(
    positions: Sequence[PositionMeans],
    latitude_deg: float,
    method: str = "exact",
    *,
    height_m: float = 0.0,
    truth: dict[str, float] | None = None,
    complete: bool = True,
    positions_planned: int | None = None,
    faults: dict[str, Any] | None = None,
    plan: str = "positions",
    motion: Callable[[HeadingSolution], dict[str, Any]] | None = None,
    prediction: dict[str, Any] | None = None,
    devices: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The result dict (docs/result-schema.md) from per-position means: every method's heading,
    the tilt, the per-position data, the error against the truth for a simulated run, and what
    went wrong on the way (`faults`, from :func:`faults_summary` of the events log).

    plan "positions+motion" or "sweep" with `motion` (the dwells' solution → find_motion.motion_fit_result):
    the heading and its 1σ come from the per-sample fit when it is available; the dwells' own
    heading stays in `dwell_fit` (and is the result, with the reason, when it is not)."""
    if len(positions) < 3:
        raise InputError(f"only {len(positions)} positions measured; a heading needs at least 3")
    sol = _solve(positions, latitude_deg, method, height_m)
    heading_deg, heading_std_deg, headings = sol.heading_deg, sol.heading_std_deg, sol.methods
    motion_info = motion(sol) if (plan in MOTION_KINDS and motion is not None) else None
    if motion_info is not None and motion_info["available"]:
        heading_deg, heading_std_deg = motion_info["heading_deg"], motion_info["heading_std_deg"]
        headings = motion_info["methods"]
    result: dict[str, Any] = {
        "schema": "northfinder.result/1",
        "complete": bool(complete),
        "positions_planned": int(positions_planned if positions_planned is not None else len(positions)),
        "positions_measured": len(positions),
        "method": method,
        "plan": plan,
        "heading_deg": float(heading_deg),
        "heading_std_deg": float(heading_std_deg),
        "methods": {name: {"heading_deg": float(h)} for name, h in headings.items()},
        "dwell_fit": {"heading_deg": float(sol.heading_deg), "heading_std_deg": float(sol.heading_std_deg)},
        "tilt": {
            "pitch_deg": float(sol.pitch_deg),
            "roll_deg": float(sol.roll_deg),
            "tilt_deg": float(sol.tilt_deg),
            "tilt_azimuth_deg": float(sol.tilt_azimuth_deg),
        },
        "latitude_deg": float(latitude_deg),
        "height_m": float(height_m),
        "duration_device_s": float(sum(p.duration_device_s for p in positions)),
        "fit": {
            "gyro_residual_rms_dph": sol.gyro_residual_rms_dph,
            "accel_residual_rms_g": sol.accel_residual_rms_g,
            "accel_magnitude_g": float(sol.accel_magnitude_g),
            "noise": sol.gyro_fit.noise,
        },
        "positions": [asdict(p) for p in positions],
    }
    if motion_info is not None:
        result["motion_fit"] = motion_info
    if prediction is not None:
        result["plan_prediction"] = prediction
    if devices:
        result["devices"] = devices
    if faults is not None:
        result["faults"] = faults
    if truth is not None:
        keys = ("heading_deg", "pitch_deg", "roll_deg", "latitude_deg")
        result["truth"] = {k: float(truth[k]) for k in keys}
        result["error_deg"] = float(wrap_deg_180(result["heading_deg"] - truth["heading_deg"]))
    return result


_IMU_COUNTERS = ("frames", "bad_crc", "resyncs", "sequence_gaps", "lost_samples", "skipped_bytes")
_ACCEL_COUNTERS = ("pairs", "unpaired", "counter_gaps", "lost_samples", "emcy", "heartbeats", "malformed",
                   "kernel_drops")


def _imu_faults(stats: list[dict[str, Any]], kept: list[dict[str, Any]]) -> dict[str, Any]:
    """The IMU's stream counters summed over sessions, reconnects, stalls, the kept dwells' lost
    samples and the samples flagged not valid per axis the unit has."""
    imu: dict[str, Any] = {k: int(sum(int(e.get("imu", {}).get(k, 0)) for e in stats)) for k in _IMU_COUNTERS}
    imu["reconnects"] = int(sum(int(e.get("imu_reconnects", 0)) for e in stats))
    imu["stalls"] = int(sum(int(e.get("imu_stalls", 0)) for e in stats))
    imu["lost_in_dwells"] = int(sum(int(e["imu"]["lost"]) for e in kept))
    gyro_axes = next((str(e["imu_axes"]) for e in stats if "imu_axes" in e), "xyz")
    accel_axes = next((str(e["imu_accel_axes"]) for e in stats if "imu_accel_axes" in e), "xyz")
    imu["gyro_axes"], imu["accel_axes"] = gyro_axes, accel_axes
    names = [f"g{a}" for a in gyro_axes] + [f"a{a}" for a in accel_axes]
    imu["invalid_samples"] = {  # per axis the unit has: frames flagged not valid in the stream
        k: int(sum(int(e.get("imu", {}).get(f"invalid_{k}", 0)) for e in stats)) for k in names
    }
    imu["invalid_in_dwells"] = {  # per gyro axis: flagged samples left out of the kept dwells
        k: int(sum(int(e["imu"].get("invalid", {}).get(k, 0)) for e in kept)) for k in names if k[0] == "g"
    }
    return imu


def _accel_faults(events: Sequence[dict[str, Any]], stats: list[dict[str, Any]],
                  kept: list[dict[str, Any]]) -> dict[str, Any]:
    """The node's counters, emergencies, the kept dwells' lost samples, and the positions whose
    dwell saw no heartbeat (device time ≥ 2.5 heartbeat periods of 1 s)."""
    accel: dict[str, Any] = {
        k: int(sum(int(e.get("accel", {}).get(k, 0)) for e in stats)) for k in _ACCEL_COUNTERS
    }
    accel["lost_in_dwells"] = int(sum(int(e["accel"]["lost"]) for e in kept))
    accel["emergencies"] = [m for e in stats for m in e.get("emergencies", [])]
    silent: list[int] = []
    rate_hz = 0.0
    for e in events:
        if e.get("event") == "start":
            rate_hz = float(e.get("accelerometer", {}).get("rate_hz") or 0.0)
        elif e.get("event") == "position" and rate_hz > 0 and e["accel"].get("heartbeats") == 0:
            if (e["accel"]["samples"] + e["accel"]["lost"]) / rate_hz >= 2.5:
                silent.append(int(e["index"]))
    accel["heartbeat_lost_positions"] = silent
    return accel


def faults_summary(events: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """What went wrong during a run and what was done about it, from its events log alone (the live
    run and replay both call this, so the result's `faults` replays exactly):

    - `remeasured`: every position measured again, with the attempt and the reason;
    - `stage_errors`: stage errors on moves (stall / following error) and the retry;
    - `imu`: the decoder's stream counters summed over sessions (bad CRC, resyncs, gaps, lost
      samples), the reconnects, and the samples lost inside the kept dwells;
    - `accel`: the node's counters, its emergencies, the kept dwells' lost samples, and the
      positions whose dwell saw no heartbeat (device time ≥ 2.5 heartbeat periods of 1 s);
    - `sessions`: how many times the run was started (1 + resumes).
    """
    stats = [e for e in events if e.get("event") == "stats"]
    kept = [e for e in events if e.get("event") == "position"]
    imu = _imu_faults(stats, kept)
    accel = _accel_faults(events, stats, kept)
    return {
        "sessions": max(1, sum(e.get("event") == "start" for e in events)),
        "remeasured": [
            {"index": int(e["index"]), "attempt": int(e["attempt"]), "reason": str(e["reason"])}
            for e in events
            if e.get("event") == "remeasure"
        ],
        "stage_errors": [
            {
                "target_deg": e.get("target_deg"),
                "attempt": int(e.get("attempt", 1)),
                "error": str(e.get("error")),
            }
            for e in events
            if e.get("event") == "stage_error"
        ],
        "imu": imu,
        "accel": accel,
    }


# -- replay --------------------------------------------------------------------------------------
@dataclass
class ReplayOutcome:
    """What replay found: the recomputed result (None if fewer than 3 positions) and the state."""

    result: dict[str, Any] | None
    complete: bool
    positions_measured: int
    positions_planned: int
    positions: list[PositionMeans] = field(default_factory=list)


def _decode_session(rd: RunDir, session: int, start: dict[str, Any]) -> tuple[Any, Any]:
    """One session's IMU samples and accelerometer samples, decoded from its own raw logs by the
    decoders of the models the run recorded (registry.decoder_for)."""
    imu_cfg = start["imu"]
    raw_path = rd.file(session_file(IMU_RAW, session))
    raw = raw_path.read_bytes() if raw_path.exists() else b""
    block, _ = registry.decoder_for("imu", imu_cfg.get("model")).decode_log(raw, imu_cfg)
    acc_cfg = start["accelerometer"]
    accel_block = registry.decoder_for("accelerometer", acc_cfg.get("model")).decode_log(
        rd.file(session_file(CAN_LOG, session)), acc_cfg)
    return block, accel_block


def devices_summary(events: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Each role's model (and the identity its device reported) from the run's first start event."""
    starts = [e for e in events if e.get("event") == "start"]
    if not starts:
        return {}
    out = {}
    for role in registry.ROLES:
        entry = starts[0].get(role)
        if isinstance(entry, dict):
            out[role] = {"model": registry.model_of(entry, role), "identity": entry.get("identity", {})}
    return out


def _check_covered(rd: RunDir, session: int, ev: dict[str, Any], block: Any, k: int) -> None:
    """A raw log cut short (a copy interrupted, a disk full) ends inside a kept dwell: say so, in
    samples, instead of letting an empty selection reach the estimator as NaN."""
    i0, i1 = int(ev["imu"]["first_index"]), int(ev["imu"]["last_index"])
    expected = i1 - i0 + 1 - int(ev["imu"]["lost"])
    have = int(np.count_nonzero((block.sample_index >= i0) & (block.sample_index <= i1)))
    if have < expected and (len(block.sample_index) == 0 or int(block.sample_index[-1]) < i1):
        name = session_file(IMU_RAW, session)
        raise RunDamaged(f"{rd.path}: {name} ends inside position {k} ({have} of {expected} samples); "
                         "the raw log is cut short, restore it from a full copy")


def _position_from_logs(ev: dict[str, Any], block: Any, accel_block: Any, rate_hz: float) -> PositionMeans:
    """One position event's means from the session's decoded samples (the live run's function)."""
    i0, i1 = ev["imu"]["first_index"], ev["imu"]["last_index"]
    sel = (block.sample_index >= i0) & (block.sample_index <= i1)
    if accel_block is not None:
        c0, c1 = ev["accel"]["first_counter"], ev["accel"]["last_counter"]
        accel = accel_block.accel_g[(accel_block.counter >= c0) & (accel_block.counter <= c1)]
    else:
        accel = np.empty((0, 3))
    return position_means(ev["table_angle_deg"], block.gyro_rad_s[sel], accel, ev["imu"]["lost"],
                          ev["accel"]["lost"], rate_hz, ev["imu"].get("gyro_axes", "xyz"))


def replay(path: str | Path, method: str | None = None) -> ReplayOutcome:
    """Recompute the result of a run from its raw logs alone.

    Decodes imu.raw and can.asc through the codecs, cuts them by the sample ranges in
    events.jsonl, and feeds the same per-position means and estimator as the live run.
    """
    rd = RunDir(path, create=False)
    events = rd.events()
    starts = [e for e in events if e.get("event") == "start"]
    if not starts:
        raise InputError(f"{rd.path}: {EVENTS} has no start event; the run never began")
    positions: list[PositionMeans] = []
    session = 0
    block = accel_block = None
    rate_hz = float(starts[0]["imu"]["rate_hz"])
    for ev in events:
        if ev.get("event") == "start":
            session += 1
            rate_hz = float(ev["imu"]["rate_hz"])
            block, accel_block = _decode_session(rd, session, ev)
        elif ev.get("event") == "position" and block is not None:
            _check_covered(rd, session, ev, block, len(positions) + 1)
            positions.append(_position_from_logs(ev, block, accel_block, rate_hz))
    start = starts[0]
    # a run recorded since the fed fit replays through the same feed; an older one (its live result
    # from the batch fit, equal to 1e-12) through the batch fit, so that it too replays bit for bit
    fed = session == 1 and start.get("motion_fit") == MOTION_FIT_FED
    complete = any(e.get("event") == "end" and e.get("complete") for e in events)
    planned = int(start.get("positions_planned", sum(e.get("event") == "position" for e in events)))
    result = None
    if len(positions) >= 3:
        result = compute_result(
            positions,
            start["latitude_deg"],
            method or start.get("method", "exact"),
            height_m=start.get("height_m", 0.0),
            truth=start.get("truth"),
            complete=complete,
            positions_planned=planned,
            faults=faults_summary(events),
            devices=devices_summary(events),
            plan=start.get("plan", "positions"),
            motion=_motion(rd, events, start.get("height_m", 0.0), block if session == 1 else None,
                           replay_rate_hz=rate_hz if fed else None),
            prediction=start.get("plan_prediction"),
        )
    return ReplayOutcome(result, complete, len(positions), planned, positions)


def replayed(path: str | Path, method: str | None = None) -> Replayed:
    """:func:`replay` as the find's replay in the run-kind registry (northfinder.runkinds)."""
    out = replay(path, method)
    return Replayed(out.result, out.complete, out.positions_measured, out.positions_planned,
                    [asdict(p) for p in out.positions])
