"""`northfinder align --mode swaying`: true north from a strapdown IMU on a swaying base.

`--config bench.toml` reads the IMU of `[imu]` (and the latitude of `[site]`, or `--latitude`);
`--simulate` starts firmware-sim's ship scenario (the IMU alone on a swaying ship, the reference
sway unless `--sway` says otherwise) and reports the error against its truth log. The inertial-frame
cone fit gives the result; the static coarse alignment on the same samples is under
`methods.coarse` (docs/result-schema-align.md, "## swaying"). Every run leaves a run directory
that `northfinder replay` recomputes bit for bit.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from northfinder import config
from northfinder.align.swaying import METHODS, minimum_duration_s
from northfinder.cli import _common
from northfinder.cli._align_summary import print_swaying_summary
from northfinder.errors import InputError
from northfinder.rundir import RunDir
from northfinder.runs import base
from northfinder.runs import swaying as sr


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The swaying mode's own flags on the `align` parser."""
    _common.add_flag(
        parser,
        "--sway",
        default=None,
        metavar="SPEC",
        help=f'swaying, simulated: "roll=AMP:PERIOD,pitch=AMP:PERIOD,yaw=AMP:PERIOD,heave=AMP_M:PERIOD" '
        f"(deg or m, s; 'none' = still ship; default the reference {sr.REFERENCE_SWAY!r})",
    )
    _common.add_flag(
        parser,
        "--sway-period",
        type=float,
        default=None,
        metavar="S",
        help=f"swaying: the longest sway period [s]; the smoothing window is 4 of them and the window "
        f"must hold 8 (default: from --sway when simulated, else {sr.DEFAULT_SWAY_PERIOD_S:g})",
    )
    _common.add_flag(
        parser,
        "--sway-method",
        dest="method",
        choices=METHODS,
        default=None,
        help="swaying fit (not a turntable heading --method; [swaying] method): cone (constrained fit, "
        "default) | cone-gls (plus a noise-weighted step) | circle "
        "(the paper's free space-circle fit)",
    )
    _common.add_flag(
        parser,
        "--lever-arm",
        default=None,
        metavar="X,Y,Z",
        help="swaying, simulated: the IMU's position from the ship's centre of rotation [m] (default "
        "1,2,1.5); gnss: the antenna's position in IMU axes [m]",
    )
    _common.add_flag(
        parser,
        "--heading",
        type=_common.heading_deg,
        default=None,
        metavar="DEG",
        help="simulated: the true (mean) heading; gnss on hardware: the heading prior (σ: --heading-std)",
    )
    _common.add_flag(
        parser,
        "--latitude",
        type=float,
        default=None,
        metavar="DEG",
        help="site latitude (simulated; on hardware it overrides [site] latitude_deg)",
    )


def parse_lever_arm(text: str | None) -> tuple[float, float, float] | None:
    """'1,2,1.5' → (1.0, 2.0, 1.5); InputError naming the flag otherwise."""
    if text is None:
        return None
    try:
        values = tuple(float(p) for p in str(text).split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise InputError(
            f"--lever-arm {text}: give three numbers X,Y,Z in metres (IMU axes x right, "
            "y forward, z up), e.g. --lever-arm 1,2,1.5"
        )
    return values  # type: ignore[return-value]


def _check(
    args: argparse.Namespace,
) -> tuple[float, dict[str, list[list[float]]], float, config.BenchConfig | None]:
    """Every mistake one can see before a device is opened: (duration, sway, longest period, the
    bench file if any). Flags override the bench file's [swaying]; without one, its defaults."""
    if bool(args.simulate) == bool(args.config):
        raise InputError("give either --config BENCH_TOML (a real IMU) or --simulate")
    if not args.simulate:
        for flag in ("sway", "heading", "grade", "seed", "time_scale", "lever_arm"):
            if getattr(args, flag, None) is not None:
                hint = (
                    "; on a real ship give --sway-period for the longest sway period"
                    if flag == "sway"
                    else ""
                )
                raise InputError(f"--{flag.replace('_', '-')} is for --simulate (the simulated ship){hint}")
        if args.fault:
            raise InputError("--fault is for --simulate")
    bench = config.load(args.config) if args.config else None
    section = bench.swaying if bench is not None else config.SwayingConfig()
    sway = sr.parse_sway(args.sway if args.sway is not None else sr.REFERENCE_SWAY) if args.simulate else {}
    parse_lever_arm(args.lever_arm)
    period = args.sway_period
    if period is None:
        period = sr.longest_period_s(sway, section.sway_period_s)
    p_max = config.MAX_SWAY_PERIOD_S
    if not (math.isfinite(period) and 0.0 < period <= p_max):
        raise InputError(f"--sway-period {period:g}: give the longest sway period in seconds (0 … {p_max:g})")
    duration = section.duration_s if args.duration is None else float(args.duration)
    need = minimum_duration_s(period)
    if not math.isfinite(duration) or duration < need:
        where = f"{bench.source}: [swaying] duration_s =" if args.duration is None and bench else "--duration"
        raise InputError(
            f"{where} {duration:g}: too short for the swaying alignment, which needs at least "
            f"{need:.0f} device seconds (two smoothing windows of 4 × the {period:g} s longest "
            "sway period); 300 s gives ~0.05° with a navigation-grade IMU"
        )
    _common.check_latitude(args)
    if (
        args.simulate
        and args.time_scale is not None
        and not (math.isfinite(args.time_scale) and args.time_scale > 0)
    ):
        raise InputError(f"--time-scale {args.time_scale:g}: use a factor greater than 0")
    return duration, sway, float(period), bench


def default_out() -> Path:
    return base.default_out(sr.KIND)


def _simulated_window(
    args: argparse.Namespace, rd: RunDir, duration: float, sway: dict[str, Any], settings: dict[str, Any]
) -> Any:
    """firmware-sim's swaying ship as a subprocess, read for `duration` device seconds; the simulator
    has stopped (its truth log is complete) before the estimator takes the CPU."""
    sim = sr.ShipSim(
        sway=sr.format_sway(sway),
        lever_arm_m=parse_lever_arm(args.lever_arm) or sr.SIM_LEVER_ARM_M,
        heading_deg=sr.SIM_HEADING_DEG if args.heading is None else float(args.heading),
        latitude_deg=sr.SIM_LATITUDE_DEG if args.latitude is None else float(args.latitude),
        grade=args.grade or "nav",
        seed=1 if args.seed is None else int(args.seed),
        time_scale=args.time_scale or sr.SIM_DEFAULT_TIME_SCALE,
        faults=tuple(args.fault),
        truth_log=str((rd.path / sr.TRUTH_LOG).resolve()),
    )
    settings.update(latitude_deg=sim.latitude_deg, height_m=0.0, simulate=sim.to_dict())
    with sr.ShipSimProcess(sim) as endpoints:  # type: ignore[arg-type]
        return sr.acquire(
            rd,
            imu=config.ImuConfig(port=str(endpoints["imu"]), rate_hz=1000),
            duration_s=duration,
            progress=_common.DeviceTimeProgress,
            settings=settings,
            config_extra={"endpoints": endpoints},
        )


def _bench_window(
    args: argparse.Namespace, bench: config.BenchConfig, rd: RunDir, duration: float, settings: dict[str, Any]
) -> Any:
    """The IMU of the bench file ([imu], [site]: northfinder.config, one validation; --latitude wins)."""
    latitude = config.require_align(bench, "swaying", args.latitude)
    imu = bench.imu
    settings.update(latitude_deg=latitude, height_m=bench.site.height_m, simulate=None)
    return sr.acquire(
        rd,
        imu=imu,
        duration_s=duration,
        progress=_common.DeviceTimeProgress,
        settings=settings,
        configure_imu=True,
        config_extra={"bench": {"imu": asdict(imu), "site": asdict(bench.site), "source": bench.source}},
    )


def run(args: argparse.Namespace) -> int:
    duration, sway, period, bench = _check(args)
    rd = RunDir.new_run(args.out or default_out())
    t_wall = time.monotonic()
    # matplotlib takes a second or two to import: do it while the simulator or the IMU port starts
    _common.preload_matplotlib()
    method = args.method or (bench.swaying if bench is not None else config.SwayingConfig()).method
    settings: dict[str, Any] = {"method": method, "max_sway_period_s": period}
    with base.removed_if_unstarted(rd, sr.OWN_FILES):  # a failed start leaves no empty directory
        if args.simulate:
            window = _simulated_window(args, rd, duration, sway, settings)
        else:
            window = _bench_window(args, bench, rd, duration, settings)
    return _common.finish_and_print(args, rd, window, sr.finish, print_swaying_summary, t_wall,
                                    "estimator and report")
