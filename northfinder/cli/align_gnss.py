"""`northfinder align --mode gnss`: GNSS-aided alignment of a moving vehicle from any initial heading.

`--config bench.toml` reads the IMU (`[imu]`) and the NMEA receiver (`[gnss]`) of a real vehicle;
`--simulate` starts firmware-sim's vehicle scenario (IMU pty + GNSS pty, the default 300 s drive)
and reports the error against its truth log. The paper's δsin/δcos filter gives the result; the
small-angle filter runs on the same data under `methods.small_angle` (docs/gnss-alignment.md).
Every run leaves a run directory that `northfinder replay` recomputes bit for bit.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

from northfinder import config
from northfinder.cli import _common
from northfinder.cli._align_summary import print_gnss_summary
from northfinder.errors import InputError
from northfinder.rundir import RunDir
from northfinder.runs import base
from northfinder.runs import gnss as gr
from northfinder.runs import gnss_live as live

MIN_DURATION_S = config.GNSS_ALIGN_MIN_DURATION_S
"""5 s still for levelling (GnssAlignConfig.level_s) and some driving after it."""
UNKNOWN_LEVER_ARM_STD_M = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The gnss mode's own flags on the `align` parser."""
    _common.add_flag(
        parser,
        "--heading-error",
        type=float,
        default=None,
        metavar="DEG",
        help="gnss, simulated: the heading prior is the truth heading at the start + DEG (its σ: "
        "--heading-std; default unknown)",
    )
    _common.add_flag(
        parser,
        "--heading-std",
        default=None,
        metavar="DEG|unknown",
        help="gnss: 1σ of the heading prior (--heading DEG, or simulated truth + --heading-error); "
        "'unknown' (default) starts from that heading but lets the first turn decide",
    )
    _common.add_flag(
        parser,
        "--lever-arm",
        default=None,
        metavar="X,Y,Z",
        help="gnss: antenna position in IMU axes [m] (simulated: the truth given to firmware-sim; "
        "hardware: the tape-measured prior, overrides [gnss] lever_arm_m)",
    )
    _common.add_flag(
        parser,
        "--initial-heading",
        type=float,
        default=None,
        metavar="DEG",
        help="gnss, hardware: the same as --heading (kept for older scripts)",
    )
    _common.add_flag(
        parser,
        "--heading",
        type=_common.heading_deg,
        default=None,
        metavar="DEG",
        help="simulated: the true heading; gnss on hardware: the heading prior (σ: --heading-std)",
    )
    _common.add_flag(
        parser, "--latitude", type=float, default=None, metavar="DEG", help="simulated site latitude"
    )
    _common.add_flag(
        parser,
        "--link-latency",
        default=None,
        metavar="MS,JITTER_MS",
        help="gnss, simulated: the IMU and GNSS links deliver MS ± JITTER_MS (device ms) late "
        "(imu=MS:J,gnss=MS:J per link); passed to firmware-sim",
    )


def parse_lever_arm(text: str | None) -> tuple[float, float, float] | None:
    """'0.5,1.5,1.2' → (0.5, 1.5, 1.2); InputError naming the flag otherwise."""
    if text is None:
        return None
    parts = [p.strip() for p in str(text).split(",")]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise InputError(
            f"--lever-arm {text}: give three numbers X,Y,Z in metres (IMU axes x right, y forward, z up)"
        )
    if max(abs(v) for v in values) > 50.0:
        raise InputError(f"--lever-arm {text}: over 50 m from the IMU; give metres, not millimetres")
    return values  # type: ignore[return-value]


LINK_LATENCY_EXAMPLE = "e.g. --link-latency 150,20 or --link-latency imu=0:0,gnss=150:20"


def _latency_pair(text: str, part: str) -> None:
    """One 'MS:JITTER_MS' (or 'MS'): numbers, latency ≥ 0, 0 ≤ jitter ≤ latency; InputError else."""
    try:
        values = [float(v) for v in part.split(":")]
    except ValueError:
        values = []
    if len(values) not in (1, 2) or not all(math.isfinite(v) for v in values):
        raise InputError(f"--link-latency {text}: give MS,JITTER_MS in device ms, {LINK_LATENCY_EXAMPLE}")
    latency, jitter = values[0], values[1] if len(values) == 2 else 0.0
    if latency < 0.0 or not 0.0 <= jitter <= latency:
        raise InputError(
            f"--link-latency {text}: the latency must be >= 0 and the jitter between 0 and the latency "
            f"(device ms), {LINK_LATENCY_EXAMPLE}"
        )


def parse_link_latency(text: str | None) -> str | None:
    """The firmware-sim `--link-latency` text, checked here so a mistake is one line before the
    simulator starts: 'MS,JITTER_MS' for both links or 'imu=MS:J,gnss=MS:J'."""
    if text is None:
        return None
    text = str(text).strip()
    if "=" in text:
        for item in text.split(","):
            device, _, value = item.partition("=")
            if device.strip().lower() not in ("imu", "gnss"):
                raise InputError(f"--link-latency {text}: name the link imu or gnss, {LINK_LATENCY_EXAMPLE}")
            _latency_pair(text, value)
    else:
        _latency_pair(text, text.replace(",", ":"))
    return text


def _check(args: argparse.Namespace) -> float | None:
    """Every flag mistake one can see before a device is opened; the --duration given, if any."""
    duration = None if args.duration is None else float(args.duration)
    if duration is not None and not (math.isfinite(duration) and duration >= MIN_DURATION_S):
        raise InputError(
            f"--duration {args.duration:g}: use at least {MIN_DURATION_S:g} device seconds "
            "(5 s standing still for levelling, then the drive; default 300)"
        )
    if bool(args.simulate) == bool(args.config):
        raise InputError("give either --config BENCH_TOML (real IMU and GNSS) or --simulate")
    if args.simulate:
        if args.time_scale is not None and not (math.isfinite(args.time_scale) and args.time_scale > 0):
            raise InputError(f"--time-scale {args.time_scale:g}: use a factor greater than 0")
        if args.initial_heading is not None and args.heading_error is not None:
            raise InputError("--initial-heading and --heading-error both given; use one")
    else:
        for flag in ("heading_error", "grade", "seed", "time_scale"):
            if getattr(args, flag, None) is not None:
                raise InputError(
                    f"--{flag.replace('_', '-')} is for --simulate; a real vehicle's truth is unknown"
                )
        if getattr(args, "link_latency", None) is not None:
            raise InputError("--link-latency is for --simulate; a real link's delay is what it is")
        if args.fault:
            raise InputError("--fault is for --simulate")
    if args.heading_error is not None and not math.isfinite(args.heading_error):
        raise InputError(f"--heading-error {args.heading_error}: give degrees")
    _common.check_latitude(args)
    parse_link_latency(getattr(args, "link_latency", None))
    return duration


def parse_heading_std(text: str | None) -> float | None:
    """'--heading-std 5' → 5.0; 'unknown' or absent → None (the filter's uniform prior)."""
    if text is None or str(text).strip().lower() == "unknown":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0.0 < value <= 180.0):
        raise InputError(f"--heading-std {text}: give the prior's 1σ in degrees (0 < σ ≤ 180) or 'unknown'")
    return value


def heading_prior(args: argparse.Namespace) -> tuple[float | None, float | None]:
    """(prior heading on hardware or None, its σ or None) from --heading/--initial-heading/--heading-std.

    Simulated, the prior heading is the truth at the start + --heading-error (gnss_run.compute); its σ
    is --heading-std. A σ without a heading to attach it to is refused."""
    std = parse_heading_std(getattr(args, "heading_std", None))
    heading = None
    if not args.simulate:
        given = [v for v in (getattr(args, "heading", None), args.initial_heading) if v is not None]
        if len(given) == 2:
            raise InputError("--heading and --initial-heading both given; use --heading")
        heading = given[0] if given else None
        if heading is not None and not math.isfinite(heading):
            raise InputError(f"--heading {heading}: give degrees clockwise from true north")
        if std is not None and heading is None:
            raise InputError("--heading-std needs a heading: give --heading DEG (the prior's centre)")
    elif std is not None and args.heading_error is None and args.initial_heading is None:
        raise InputError("--heading-std needs a heading: with --simulate give --heading-error DEG "
                         "(the prior = truth + DEG)")
    return heading, std


def default_out() -> Path:
    return base.default_out(gr.KIND)


def _simulated_window(args: argparse.Namespace, rd: RunDir, duration: float, prior_std: float | None) -> Any:
    """firmware-sim's vehicle as a subprocess, read for `duration` device seconds; the simulator has
    stopped (its truth log is complete) before the filters take the CPU."""
    lever = parse_lever_arm(args.lever_arm)
    sim = live.VehicleSim(
        lever_arm_m=lever or live.SIM_LEVER_ARM_M,
        grade=args.grade or "kvh1760",
        seed=1 if args.seed is None else args.seed,
        time_scale=args.time_scale or live.SIM_DEFAULT_TIME_SCALE,
        latitude_deg=getattr(args, "latitude", None),
        heading_deg=getattr(args, "heading", None),
        faults=tuple(args.fault),
        truth_log=str((rd.path / gr.TRUTH_LOG).resolve()),
        link_latency=parse_link_latency(getattr(args, "link_latency", None)),
    )
    settings = {
        "initial_heading_deg": args.initial_heading,
        "heading_std_deg": prior_std,
        "heading_error_deg": args.heading_error,
        "lever_arm_prior_m": [0.0, 0.0, 0.0],  # the filter is not told the simulator's lever arm
        "lever_arm_std_m": UNKNOWN_LEVER_ARM_STD_M,
        "pos_std_m": [0.5, 0.5, 1.0],
        "vel_std_m_s": 0.05,
    }
    with live.VehicleSimProcess(sim) as endpoints:
        rate_hz = float(endpoints.get("imu_rate_hz", sim.imu_rate_hz))
        imu = config.ImuConfig(port=str(endpoints["imu"]), rate_hz=rate_hz,  # type: ignore[arg-type]
                               rot_format=str(endpoints.get("imu_rot_format", "DELTA")), rot_units="RAD")
        return live.acquire(
            rd,
            imu=imu,
            gnss=config.GnssConfig(port=str(endpoints["gnss"])),
            duration_s=duration,
            progress=_common.DeviceTimeProgress,
            filter_settings=settings,
            simulate=sim.to_dict(),
            gnss_start_utc=str(endpoints.get("gnss_start_utc")),
            time_scale=sim.time_scale,
            config_extra={"endpoints": endpoints},
        )


def _bench_window(
    args: argparse.Namespace,
    bench: config.BenchConfig,
    rd: RunDir,
    duration: float,
    prior_heading: float | None,
    prior_std: float | None,
) -> Any:
    """The IMU and GNSS receiver of the bench file ([imu], [gnss]: northfinder.config, one validation)."""
    lever = parse_lever_arm(args.lever_arm)
    config.require_align(bench, "gnss")
    g = bench.gnss
    prior = lever or g.lever_arm_m
    settings = {
        "initial_heading_deg": prior_heading,
        "heading_std_deg": prior_std,
        "heading_error_deg": None,
        "lever_arm_prior_m": list(prior) if prior is not None else [0.0, 0.0, 0.0],
        "lever_arm_std_m": g.lever_arm_std_m if prior is not None else UNKNOWN_LEVER_ARM_STD_M,
        "pos_std_m": list(g.pos_std_m),
        "vel_std_m_s": g.vel_std_m_s,
        "imu_grade": bench.imu.grade or None,  # the filter's IMU noise (runs/gnss.imu_grade)
    }
    return live.acquire(
        rd,
        imu=bench.imu,
        gnss=g,
        duration_s=duration,
        progress=_common.DeviceTimeProgress,
        filter_settings=settings,
        configure_imu=True,
        config_extra={"bench": {"imu": asdict(bench.imu), "gnss": asdict(g), "source": bench.source}},
    )


def run(args: argparse.Namespace) -> int:
    duration = _check(args)
    prior_heading, prior_std = heading_prior(args)
    parse_lever_arm(args.lever_arm)
    bench = config.load(args.config) if args.config else None  # flags override its [gnss_alignment]
    if duration is None:
        duration = (bench.gnss_alignment if bench is not None else config.GnssAlignmentConfig()).duration_s
    rd = RunDir.new_run(args.out or default_out())
    t_wall = time.monotonic()
    with base.removed_if_unstarted(rd, gr.OWN_FILES):  # a failed start leaves no empty directory
        if args.simulate:
            window = _simulated_window(args, rd, duration, prior_std)
        else:
            window = _bench_window(args, bench, rd, duration, prior_heading, prior_std)
    return _common.finish_and_print(args, rd, window, live.finish, print_gnss_summary, t_wall,
                                    "both filters and the report")
