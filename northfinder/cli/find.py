"""`northfinder find`: measure at n table positions and report true north with its uncertainty.

`--config bench.toml` drives real hardware (or an externally started firmware-sim);
`--simulate` starts firmware-sim as a subprocess, passes the truth and the knobs on, and
reports the error against the truth. Every run leaves a run directory (northfinder.rundir).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import sys
import threading
import time
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from northfinder import config as bench
from northfinder.errors import DeviceError, InputError, RunAborted
from northfinder.history import record_or_warn
from northfinder.rundir import CONFIG, RESULT, PositionMeans, RunDir, compute_result, faults_summary
from northfinder.sequencer import Interrupted, Progress, RunFailed, Sequencer, StopFlag
from northfinder.simulate import SimSettings, SimulatorProcess, bench_config

DEFAULT_TIME_SCALE = 12.0
"""--simulate's default device-time speed-up. python-can's slcan client must keep up with 200·K CAN
frames/s: measured here, K = 15 already fell behind on the shared 2-core host and K = 20 dropped
frames; K = 12 kept up."""
SIM_ACCEL_RATE_HZ = 50.0
"""--simulate runs the CAN accelerometer at 50 Hz (the node's rate is configurable; PROTOCOLS.md's
default is 100 Hz): half the slcan traffic, so a loaded host does not drop frames."""
SIM_DEFAULT_DWELL_S = 20.0
"""--simulate's default dwell per position [device s] (real benches: [run] dwell_s, default 30):
8 × 20 s at K = 12 finishes in under 30 s wall."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "find", help="find true north on a turntable (real bench or --simulate)", description=__doc__
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "--config", metavar="BENCH_TOML", help="bench configuration (real hardware or firmware-sim)"
    )
    src.add_argument(
        "--simulate", action="store_true", help="start firmware-sim as a subprocess and run on it"
    )
    src.add_argument(
        "--resume",
        metavar="RUN_DIR",
        help="finish an interrupted run: re-open its devices from its saved config (a simulated run "
        "starts firmware-sim again), measure the missing positions, write the complete result",
    )
    p.add_argument("--positions", type=int, metavar="N", help="number of table positions (≥ 3)")
    p.add_argument(
        "--dwell",
        type=float,
        metavar="S",
        help=f"dwell per position [device s] (default [run] dwell_s, {SIM_DEFAULT_DWELL_S:g} if --simulate)",
    )
    p.add_argument("--order", choices=bench.ORDERS, help="position order")
    p.add_argument("--method", choices=bench.METHODS, help="heading method reported as the result")
    p.add_argument("--json", metavar="PATH", help="also write the result JSON here")
    p.add_argument("--out", metavar="RUN_DIR", help="run directory (default: runs/find-<UTC time>)")
    p.add_argument("--no-report", action="store_true", help="skip report.png")
    p.add_argument("--unit", metavar="LABEL", help="unit under test, recorded in the results history")
    sim = p.add_argument_group("simulation (with --simulate; passed on to firmware-sim)")
    d = SimSettings()
    sim.add_argument("--heading", type=float, default=d.heading_deg, metavar="DEG", help="true heading")
    sim.add_argument("--pitch", type=float, default=d.pitch_deg, metavar="DEG", help="true pitch")
    sim.add_argument("--roll", type=float, default=d.roll_deg, metavar="DEG", help="true roll")
    sim.add_argument(
        "--latitude",
        type=float,
        default=None,
        metavar="DEG",
        help=f"site latitude (default {d.latitude_deg} simulated; overrides [site] with --config)",
    )
    sim.add_argument("--grade", default=d.grade, help="sensor grade: nav, kvh1760, tactical-mems, consumer")
    sim.add_argument("--seed", type=int, default=d.seed)
    sim.add_argument(
        "--time-scale",
        type=float,
        default=DEFAULT_TIME_SCALE,
        metavar="K",
        help="device time runs K times faster than the wall clock",
    )
    sim.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE", help="firmware-sim fault")
    sim.add_argument("--sim-config", metavar="FILE_TOML", help="firmware-sim's own --config file")
    p.set_defaults(func=run)


def _check_flags(args: argparse.Namespace) -> None:
    if args.positions is not None and args.positions < 3:
        raise InputError(f"--positions {args.positions}: use at least 3 positions")
    if args.dwell is not None and not (math.isfinite(args.dwell) and args.dwell > 0):
        raise InputError(f"--dwell {args.dwell:g}: use a dwell greater than 0 s")
    if args.latitude is not None and not -89.0 <= args.latitude <= 89.0:
        raise InputError(f"--latitude {args.latitude:g}: use −89…89 degrees")
    if args.fault and args.config:
        raise InputError(
            f"--fault {args.fault[0]}: faults are injected by the simulator; use them with --simulate"
        )
    if args.simulate and not (math.isfinite(args.time_scale) and args.time_scale > 0):
        raise InputError(f"--time-scale {args.time_scale:g}: use a factor greater than 0")


def _apply_overrides(cfg: bench.BenchConfig, args: argparse.Namespace) -> bench.BenchConfig:
    if args.positions is not None:
        cfg.run.positions = args.positions
    if args.dwell is not None:
        cfg.run.dwell_s = args.dwell
    if args.order is not None:
        cfg.run.order = args.order
    if args.method is not None:
        cfg.estimator.method = args.method
    if args.latitude is not None:
        cfg.site.latitude_deg = args.latitude
    return cfg.validate()


@contextlib.contextmanager
def open_bench(
    cfg: bench.BenchConfig, rundir: RunDir | None, can_kwargs: dict[str, Any] | None = None
) -> Iterator[tuple[Any, Any, Any]]:
    """Open the turntable, the IMU and the accelerometer with their logs in the run directory.

    `can_kwargs` are extra python-can bus arguments (e.g. `sleep_after_open` for an slcan
    adapter that is a pty and needs no 2 s reset wait); `[accelerometer] bus_options` win.
    """
    from northfinder.drivers.accelerometer import Accelerometer
    from northfinder.drivers.imu import Imu
    from northfinder.drivers.turntable import Turntable

    a = cfg.accelerometer
    with contextlib.ExitStack() as stack:
        tt = stack.enter_context(
            _guard(
                "turntable",
                cfg.turntable.port,
                lambda: Turntable(
                    cfg.turntable.port,
                    address=cfg.turntable.address,
                    baudrate=cfg.turntable.baudrate,
                    timeout_s=5.0,
                    transcript=rundir.transcript_path if rundir else None,
                ),
            )
        )
        tt.status()  # fail fast, naming the port, if something else than an SMC100 answers there
        imu = stack.enter_context(
            _guard(
                "imu",
                cfg.imu.port,
                lambda: Imu(
                    cfg.imu.port,
                    baudrate=cfg.imu.baudrate,
                    timeout_s=5.0,
                    raw_log=rundir.imu_raw_path if rundir else None,
                    link_timeout_s=cfg.imu.link_timeout_s,
                ),
            )
        )
        bus_options = {**(can_kwargs or {}), **a.bus_options}
        acc = stack.enter_context(
            _guard(
                "accelerometer",
                a.channel,
                lambda: Accelerometer(
                    a.interface,
                    a.channel,
                    bitrate=a.bitrate,
                    node_id=a.node_id,
                    rate_hz=a.rate_hz or 100.0,
                    eds_path=bench.accel_eds_path(cfg),
                    log_path=rundir.can_log_path if rundir else None,
                    bus_options=bus_options or None,
                ),
            )
        )
        yield tt, imu, acc


@contextlib.contextmanager
def _guard(device: str, port: str, factory: Any) -> Iterator[Any]:
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


def default_out() -> Path:
    return Path("runs") / datetime.now(UTC).strftime("find-%Y%m%dT%H%M%SZ")


class _ProgressView:
    """rich live progress: position k of n, dwell in device time, live gyro mean and σ."""

    def __init__(self, n: int, dwell_s: float, enabled: bool):
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self.console = Console(stderr=True)
        self.enabled = enabled
        self.progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn("{task.fields[info]}"),
            TimeElapsedColumn(),
            console=self.console,
            transient=False,
            disable=not enabled,
        )
        self.pos_task = self.progress.add_task("positions", total=n, info="referencing the stage")
        self.dwell_task = self.progress.add_task("dwell", total=dwell_s, info="")

    def __call__(self, p: Progress) -> None:
        if p.phase in ("move", "settle", "return", "reference"):
            what = {
                "move": f"moving to {p.target_deg:.1f}°",
                "settle": "settling (gyro-z ringing)",
                "return": "returning to the start",
                "reference": "referencing the stage",
            }[p.phase]
            self.progress.update(
                self.pos_task, info=f"position {max(p.position, 1)} of {p.positions}: {what}"
            )
            if p.phase == "move":
                self.progress.update(self.dwell_task, completed=0.0, info="")
        elif p.phase == "dwell":
            m, s = p.gyro_mean_dph, p.gyro_std_of_mean_dph
            self.progress.update(
                self.pos_task, info=f"position {p.position} of {p.positions} at {p.target_deg:.1f}°"
            )
            self.progress.update(
                self.dwell_task,
                completed=p.dwell_done_s,
                info=f"{p.dwell_done_s:5.1f}/{p.dwell_s:g} s  gyro x {m[0]:+8.3f} y {m[1]:+8.3f} "
                f"z {m[2]:+8.3f} °/h  σ(mean) {s[1]:.3f} °/h",
            )
        elif p.phase == "measured":
            self.progress.update(self.pos_task, completed=p.position)

    def __enter__(self) -> _ProgressView:
        self.progress.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.progress.stop()


def print_summary(result: dict[str, Any], console: Any = None, run_dir: Path | None = None) -> None:
    """The rich summary table: heading ± σ, tilt, every method, positions, truth and error."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    if console is None:
        console = Console()
        if not console.is_terminal:  # piped or captured: do not squeeze the tables into 80 columns
            console = Console(width=max(console.width, 132))
    t = result["tilt"]
    head = Table(title="northfinder result", show_header=False, box=None)
    head.add_row(
        "heading",
        f"[bold]{result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}°[/] (1σ, {result['method']})",
    )
    head.add_row(
        "tilt",
        f"{t['tilt_deg']:.4f}° toward {t['tilt_azimuth_deg']:.2f}°  "
        f"(pitch {t['pitch_deg']:+.4f}°, roll {t['roll_deg']:+.4f}°)",
    )
    head.add_row("latitude", f"{result['latitude_deg']:.4f}°")
    head.add_row(
        "device time", f"{result['duration_device_s']:.1f} s over {result['positions_measured']} positions"
    )
    if "truth" in result:
        tr = result["truth"]
        head.add_row(
            "truth",
            f"heading {tr['heading_deg']:.4f}°, pitch {tr['pitch_deg']:+.4f}°, roll {tr['roll_deg']:+.4f}°",
        )
        ratio = (
            abs(result["error_deg"]) / result["heading_std_deg"] if result["heading_std_deg"] else math.inf
        )
        head.add_row("error", f"[bold]{result['error_deg']:+.4f}°[/] ({ratio:.2f} σ)")
    if not result.get("complete", True):
        head.add_row(
            "[red]INCOMPLETE[/]",
            f"{result['positions_measured']} of {result['positions_planned']} positions measured",
        )
    console.print(head)
    from northfinder.constants import wrap_deg_180

    methods = Table(title="every method (* = the result)")
    methods.add_column("method")
    methods.add_column(escape("heading [deg]"), justify="right")
    if "truth" in result:
        methods.add_column(escape("error [deg]"), justify="right")
    for name, m in result["methods"].items():
        h = m.get("heading_deg")
        row = [name + (" *" if name == result["method"] else ""), "—" if h is None else f"{h:.4f}"]
        if "truth" in result:
            err = "—" if h is None else f"{float(wrap_deg_180(h - result['truth']['heading_deg'])):+.4f}"
            row.append(err)
        methods.add_row(*row)
    console.print(methods)
    pos = Table(title="positions")
    for col in (
        "#",
        "α [deg]",
        "gyro x [°/h]",
        "gyro y [°/h]",
        "gyro z [°/h]",
        "accel x [mg]",
        "accel y [mg]",
        "accel z [mg]",
        "samples",
        "lost",
        "accel n",
        "accel lost",
    ):
        pos.add_column(escape(col), justify="right")
    for i, p in enumerate(result["positions"], 1):
        g, a = p["gyro_dph"], p["accel_g"]
        pos.add_row(
            str(i),
            f"{p['table_angle_deg']:.3f}",
            *("—" if v is None or v != v else f"{v:+.4f}" for v in g),  # an axis the unit lacks
            *("—" if v is None else f"{v * 1e3:+.3f}" for v in a),
            str(p["samples"]),
            str(p["lost_samples"]),
            str(p["accel_samples"]),
            str(p["accel_lost_samples"]),
        )
    console.print(pos)
    _print_faults(result.get("faults"), console)
    if run_dir is not None:
        console.print(f"run directory: {run_dir}")


def _invalid_lines(imu: dict[str, Any]) -> list[str]:
    """The IMU samples flagged not valid per axis (status bits), if the unit flagged any."""
    counts = imu.get("invalid_samples") or {}
    if not any(counts.values()):
        return []
    each = ", ".join(f"{k} {v}" for k, v in counts.items())
    dwells = ", ".join(f"{k} {v}" for k, v in (imu.get("invalid_in_dwells") or {}).items())
    return [f"IMU samples flagged not valid (left out): {each} in the stream ({dwells} inside kept dwells)"]


def _print_faults(faults: dict[str, Any] | None, console: Any) -> None:
    """What went wrong and what was done: lost samples, re-measured positions, stage errors, EMCY."""
    if not faults:
        return
    from rich.markup import escape

    imu, acc = faults["imu"], faults["accel"]
    lines = [
        f"IMU: {imu['bad_crc']} bad CRC, {imu['resyncs']} resyncs, {imu['sequence_gaps']} gaps, "
        f"{imu['lost_samples']} samples lost in the stream ({imu['lost_in_dwells']} inside kept dwells), "
        f"{imu['reconnects']} reconnects",
        *_invalid_lines(imu),
        f"accelerometer: {acc['lost_samples']} samples lost ({acc['lost_in_dwells']} inside kept dwells), "
        f"{acc['emcy']} EMCY, heartbeats {acc['heartbeats']}",
    ]
    for m in acc["emergencies"]:
        lines.append(f"  EMCY 0x{m['code']:04X} register 0x{m['register']:02X}: {m['meaning']}")
    if acc["heartbeat_lost_positions"]:
        pos = ", ".join(str(k + 1) for k in acc["heartbeat_lost_positions"])
        lines.append(f"  no heartbeat from the node during position(s) {pos}: node watch lost")
    for r in faults["remeasured"]:
        lines.append(
            f"position {r['index'] + 1} measured again (attempt {r['attempt']} rejected): {r['reason']}"
        )
    for e in faults["stage_errors"]:
        lines.append(
            f"stage error on the move to {e['target_deg']:g}° (attempt {e['attempt']}): {e['error']}"
        )
    if faults.get("sessions", 1) > 1:
        lines.append(f"measured in {faults['sessions']} sessions (resumed)")
    console.print("[bold]faults[/]")
    for line in lines:
        console.print(escape(line))


def run(args: argparse.Namespace) -> int:
    _check_flags(args)
    if args.resume:
        return _resume(args)
    settings: SimSettings | None = None
    rundir = RunDir(args.out or default_out())
    if args.simulate:
        sim_config, accel_rate_hz = _sim_config_file(args.sim_config, rundir)
        settings = SimSettings(
            heading_deg=args.heading,
            pitch_deg=args.pitch,
            roll_deg=args.roll,
            latitude_deg=args.latitude if args.latitude is not None else SimSettings.latitude_deg,
            grade=args.grade,
            seed=args.seed,
            time_scale=args.time_scale,
            faults=tuple(args.fault),
            config=str(sim_config),
        )
        cfg = bench.BenchConfig(source="--simulate")
        cfg.site.latitude_deg = settings.latitude_deg
        cfg.accelerometer.rate_hz = accel_rate_hz
        cfg.run.dwell_s = SIM_DEFAULT_DWELL_S
        cfg = _apply_overrides(cfg, args)
    else:
        cfg = _apply_overrides(bench.load(args.config), args)
        bench.require_ports(cfg)
    if not args.no_report:
        # matplotlib takes a second or two to import: do it while the devices are opened and homed.
        threading.Thread(target=_preload_matplotlib, name="preload-matplotlib", daemon=True).start()
    return _measure_and_report(args, cfg, rundir, settings, "measurement and report")


def _measure_and_report(
    args: argparse.Namespace,
    cfg: bench.BenchConfig,
    rundir: RunDir,
    settings: SimSettings | None,
    wall_label: str,
    **measure_kwargs: Any,
) -> int:
    """Start firmware-sim if simulated, measure, draw the report, print the summary (find and
    --resume alike)."""
    t_wall = time.monotonic()
    with contextlib.ExitStack() as stack:
        if settings is not None:
            endpoints = stack.enter_context(SimulatorProcess(settings))
            cfg = bench_config(endpoints, settings.latitude_deg, cfg)
        result = measure(
            cfg,
            rundir,
            settings=settings,
            json_path=args.json,
            report=False,  # drawn below, once the simulator no longer competes for the CPU
            # firmware-sim's slcan adapter is a pty: no USB adapter reset to wait 2 s for.
            can_kwargs={"sleep_after_open": 0.05}
            if settings and cfg.accelerometer.interface == "slcan"
            else None,
            **measure_kwargs,
        )
    record_or_warn(rundir.path, unit=getattr(args, "unit", None))  # the results history (an index)
    if not args.no_report:
        from northfinder.report import write_report

        write_report(result, rundir.report_path)
    print_summary(result, run_dir=rundir.path)
    print(f"wall time {time.monotonic() - t_wall:.1f} s ({wall_label})", file=sys.stderr)
    return 0


def _preload_matplotlib() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401


def _sim_config_file(user_toml: str | None, rundir: RunDir) -> tuple[Path, float]:
    """firmware-sim's --config for this run, kept in the run directory: the user's file (if any)
    with the CAN node's rate set to SIM_ACCEL_RATE_HZ unless the file sets `accel_rate_hz`."""
    import tomllib

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
    rate = float(data.get("accel_rate_hz", SIM_ACCEL_RATE_HZ))
    path = rundir.file("firmware_sim.toml")
    path.write_text(text, encoding="utf-8")
    return path, rate


def measure(
    cfg: bench.BenchConfig,
    rundir: RunDir,
    *,
    settings: SimSettings | None = None,
    json_path: str | None = None,
    report: bool = True,
    progress: bool = True,
    can_kwargs: dict[str, Any] | None = None,
    previous: list[PositionMeans] | None = None,
    skip: set[int] | None = None,
    seq_kwargs: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One north find on the bench `cfg` describes: open the devices, run the sequence, save the
    run directory, return the result. A signal stops it: RunAborted (exit 130, 143 for SIGTERM)
    after the stage is stopped and what was measured is saved; a fault the run cannot get past
    (RunFailed) also saves first. `previous`/`skip`: a resumed run's positions already measured
    (and their plan indices); `rundir.session` > 1 then. `seq_kwargs` go to the Sequencer (an
    `on_progress` there is called after the progress view)."""
    truth = settings.truth() if settings else None
    previous = list(previous or [])
    sim_info = None
    if settings is not None:
        sim_info = {
            **settings.truth(),
            "grade": settings.grade,
            "seed": settings.seed,
            "time_scale": settings.time_scale,
            "faults": list(settings.faults),
        }
    if rundir.session == 1:
        rundir.write_json(CONFIG, {"bench": cfg.to_dict(), "simulate": sim_info, "argv": sys.argv})
    stop = StopFlag()
    with stop.installed(), open_bench(cfg, rundir, can_kwargs) as (tt, imu, acc):
        imu.configure()  # read the IMU's rate and gyro format back: the decoder must know them
        if float(cfg.imu.rate_hz) != imu.rate_hz:
            imu.configure(rate_hz=cfg.imu.rate_hz)
        acc.wait_heartbeat()
        a = cfg.accelerometer  # SDO: identity, mapping, rate, heartbeat time (each step an event)
        acc_info = acc.configure(rate_hz=a.rate_hz or None, heartbeat_ms=a.heartbeat_ms,
                                 rate_object=a.rate_object, log=rundir.log_event)
        rundir.log_event(
            {
                "event": "start",
                "session": rundir.session,
                "simulate": sim_info,
                "utc": datetime.now(UTC).isoformat(),
                "latitude_deg": cfg.site.latitude_deg,
                "height_m": cfg.site.height_m,
                "method": cfg.estimator.method,
                "positions_planned": cfg.run.positions,
                "dwell_s": cfg.run.dwell_s,
                "imu": {
                    "port": cfg.imu.port,
                    "rate_hz": imu.rate_hz,
                    "rot_format": imu.rot_format,
                    "rot_units": imu.rot_units,
                },
                "accelerometer": {
                    "interface": cfg.accelerometer.interface,
                    "channel": cfg.accelerometer.channel,
                    "node_id": cfg.accelerometer.node_id,
                    "rate_hz": acc.rate_hz,
                    "identity": acc_info["identity"],
                    "layout": acc.layout.to_dict(),
                },
                "truth": truth,
            }
        )
        view = _ProgressView(cfg.run.positions, cfg.run.dwell_s, enabled=progress)
        seq_kwargs = dict(seq_kwargs or {})
        extra = seq_kwargs.pop("on_progress", None)

        def on_progress(p: Progress) -> None:
            view(p)
            if extra is not None:
                extra(p)

        seq = Sequencer(
            tt,
            imu,
            acc,
            cfg.run,
            allow_home=cfg.turntable.allow_home,
            rundir=rundir,
            on_progress=on_progress,
            stop_flag=stop,
            accel_rate_hz=acc.rate_hz,
            skip=skip or set(),
            stage_speed_deg_s=cfg.turntable.speed_deg_s,
            stage_settle_s=cfg.turntable.settle_s,
            **seq_kwargs,
        )
        try:
            with view:
                positions = previous + seq.run()
        except Interrupted as intr:
            intr.positions = previous + intr.positions
            _aborted(intr, cfg, rundir, truth, json_path, report)
        except RunFailed as fail:
            _failed(fail, previous + fail.positions, cfg, rundir, truth, json_path, report)
    result = compute_result(
        positions,
        cfg.site.latitude_deg,
        cfg.estimator.method,
        height_m=cfg.site.height_m,
        truth=truth,
        positions_planned=cfg.run.positions,
        faults=faults_summary(rundir.events()),
    )
    _save(result, rundir, json_path, report)
    return result


def _save(result: dict[str, Any], rundir: RunDir, json_path: str | None, report: bool) -> None:
    rundir.write_json(RESULT, result)
    if json_path:
        RunDir(Path(json_path).parent).write_json(Path(json_path).name, result)
    if report:
        from northfinder.report import write_report

        write_report(result, rundir.report_path)


def _save_partial(
    positions: list[PositionMeans],
    cfg: bench.BenchConfig,
    rundir: RunDir,
    truth: dict[str, float] | None,
    json_path: str | None,
    report: bool,
) -> None:
    """End event (incomplete) and, with 3 positions or more, the partial result."""
    k = len(positions)
    rundir.log_event({"event": "end", "complete": False, "positions_measured": k})
    if k >= 3:
        result = compute_result(
            positions,
            cfg.site.latitude_deg,
            cfg.estimator.method,
            height_m=cfg.site.height_m,
            truth=truth,
            complete=False,
            positions_planned=cfg.run.positions,
            faults=faults_summary(rundir.events()),
        )
        _save(result, rundir, json_path, report)


def _failed(
    fail: RunFailed,
    positions: list[PositionMeans],
    cfg: bench.BenchConfig,
    rundir: RunDir,
    truth: dict[str, float] | None,
    json_path: str | None,
    report: bool,
) -> None:
    """A fault the run could not get past: save what was measured, then one line saying so."""
    _save_partial(positions, cfg, rundir, truth, json_path, report)
    raise RunFailed(
        f"{fail}; {len(positions)} of {cfg.run.positions} positions measured and saved in {rundir.path} "
        f"(northfinder replay {rundir.path}; finish it with northfinder find --resume {rundir.path})",
        positions,
    )


def _resume(args: argparse.Namespace) -> int:
    """`find --resume RUN_DIR`: a new session in the same run directory (its own raw logs), on the
    devices of the saved config; measures the plan indices that have no position event yet."""
    from northfinder.rundir import replay

    rundir = RunDir(args.resume, create=False)
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
    sim_toml = rundir.file("firmware_sim.toml")
    if sim:
        settings = SimSettings(
            heading_deg=sim["heading_deg"],
            pitch_deg=sim["pitch_deg"],
            roll_deg=sim["roll_deg"],
            latitude_deg=sim["latitude_deg"],
            grade=sim["grade"],
            # a new power-on of the simulated bench: fresh sensor noise, the same truth
            seed=int(sim["seed"]) + rundir.session - 1,
            time_scale=float(args.time_scale),
            faults=tuple(args.fault) if args.fault else tuple(sim.get("faults", ())),
            config=str(sim_toml) if sim_toml.exists() else None,
        )
    else:
        bench.require_ports(cfg)
    return _measure_and_report(
        args, cfg, rundir, settings, f"resumed session {rundir.session}", previous=previous, skip=done
    )


def _aborted(
    intr: Interrupted,
    cfg: bench.BenchConfig,
    rundir: RunDir,
    truth: dict[str, float] | None,
    json_path: str | None,
    report: bool,
) -> None:
    k, n = len(intr.positions), cfg.run.positions
    _save_partial(intr.positions, cfg, rundir, truth, json_path, report)
    err = RunAborted(
        f"run stopped by {signal.Signals(intr.signum).name} after {k} of {n} positions; stage "
        f"{intr.stage_state}; the data is saved in {rundir.path} (northfinder replay {rundir.path}; "
        f"finish it with northfinder find --resume {rundir.path})"
    )
    if intr.signum == signal.SIGTERM:
        err.exit_code = 143
    raise err
