"""`northfinder plan`: before a run, the plan that reaches a target σ soonest (or the best σ in a
time budget) for a gyro, a site and a stage, with its elapsed device time and the alternatives.

The model is northfinder.estimators.plan (docs/estimators.md §11): stop-and-go positions (today),
the same using the samples taken while the table turns (needs a z gyro), and a sweep of whole
revolutions in both directions (needs a z gyro). σ is predicted for white noise, bias drift and
accelerometer noise; the yardstick is the white-noise limit of the ELAPSED time.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import replace

from northfinder.errors import InputError
from northfinder.estimators import plan as model
from northfinder.estimators.heading import DEFAULT_TILT_LIMIT_DEG, MAX_ABS_LATITUDE_DEG

_NUMBERS = {
    "latitude": "--latitude", "target_std": "--target-std", "time_budget": "--time-budget", "arw": "--arw",
    "bias_instability": "--bias-instability", "rrw": "--rrw", "accel_noise": "--accel-noise",
    "tilt": "--tilt-bound", "stage_speed": "--stage-speed", "stage_accel": "--stage-accel",
    "settle": "--settle", "turnaround": "--turnaround",
}  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", help="the plan (kind, n, dwell) for a target σ or a time budget",
                       description=__doc__)  # fmt: skip
    p.add_argument("--grade", metavar="NAME", help=f"sensor preset: {', '.join(model.GRADES)}")
    p.add_argument("--latitude", metavar="DEG", required=True, help="site latitude [deg], north positive")
    goal = p.add_mutually_exclusive_group(required=True)
    goal.add_argument("--target-std", metavar="DEG", help="the heading 1σ to reach [deg]")
    goal.add_argument("--time-budget", metavar="S", help="the elapsed device time available [s]")
    p.add_argument("--arw", metavar="DEG_RT_H", help="gyro angle random walk [°/√h] (overrides the grade)")
    p.add_argument("--bias-instability", metavar="DPH", help="gyro bias instability [°/h] (overrides)")
    p.add_argument("--rrw", metavar="DPH_RT_H", help="gyro rate random walk [°/h/√h] (overrides)")
    p.add_argument("--accel-noise", metavar="UG_RT_HZ", help="accelerometer noise [µg/√Hz] (overrides)")
    p.add_argument("--gyro-axes", default="xyz", metavar="AXES",
                   help="xyz (default), xy or y; without a z gyro only stop-and-go plans")  # fmt: skip
    p.add_argument("--tilt-bound", dest="tilt", default="2", metavar="DEG",
                   help="tilt bound of the table [deg] (default 2)")
    d = model.Stage()
    p.add_argument(
        "--stage-speed", default=str(d.speed_deg_s), metavar="DEG_S", help="stage speed (SMC100 VA)"
    )
    p.add_argument(
        "--stage-accel", default=str(d.accel_deg_s2), metavar="DEG_S2", help="stage acceleration (AC)"
    )
    p.add_argument(
        "--settle", default=str(d.settle_s), metavar="S", help="at rest after a move before a dwell [s]"
    )
    p.add_argument("--turnaround", default=str(d.turnaround_s), metavar="S",
                   help="from a dwell's end to the next move command [s]")  # fmt: skip
    p.add_argument("--no-return", action="store_true", help="the run does not return to its start angle")
    p.set_defaults(func=run)


def _numbers(args: argparse.Namespace) -> dict[str, float | None]:
    """Every numeric flag as a float, or one line naming the flag."""
    out: dict[str, float | None] = {}
    for key, flag in _NUMBERS.items():
        raw = getattr(args, key)
        if raw is None:
            out[key] = None
            continue
        try:
            out[key] = float(raw)
        except ValueError:
            raise InputError(f"{flag} {raw!r}: not a number") from None
        if not math.isfinite(out[key]):
            raise InputError(f"{flag} {raw}: not a finite number")
    return out


def _check(v: dict[str, float | None], args: argparse.Namespace) -> None:
    """One line per user mistake, naming the flag and what to give instead."""
    lat_max, tilt_max = MAX_ABS_LATITUDE_DEG, DEFAULT_TILT_LIMIT_DEG
    rules = [
        ("latitude", abs(v["latitude"]) <= lat_max,
         f"use −{lat_max:g}…{lat_max:g}° (the horizontal Earth rate vanishes at the poles)"),
        ("target_std", v["target_std"] is None or v["target_std"] > 0, "use a σ greater than 0°"),
        ("time_budget", v["time_budget"] is None or v["time_budget"] > 0, "use a time greater than 0 s"),
        ("tilt", 0 <= v["tilt"] < tilt_max, f"use 0…{tilt_max:g}° (level the base)"),
        ("stage_speed", v["stage_speed"] > 0, "use the stage's speed in deg/s (> 0)"),
        ("stage_accel", v["stage_accel"] > 0, "use the stage's acceleration in deg/s² (> 0)"),
        ("settle", v["settle"] >= 0, "use 0 s or more"),
        ("turnaround", v["turnaround"] >= 0, "use 0 s or more"),
        ("arw", v["arw"] is None or v["arw"] > 0, "use an ARW greater than 0 °/√h"),
    ]  # fmt: skip
    for key in ("bias_instability", "rrw", "accel_noise"):
        rules.append((key, v[key] is None or v[key] >= 0, "use 0 or more"))
    for key, ok, what in rules:
        if not ok:
            raise InputError(f"{_NUMBERS[key]} {v[key]:g}: {what}")
    if args.gyro_axes not in model.GYRO_AXES:
        raise InputError(f"--gyro-axes {args.gyro_axes!r}: use one of {', '.join(model.GYRO_AXES)}")


def sensor_from(args: argparse.Namespace, v: dict[str, float | None]) -> model.Sensor:
    """The grade preset with any flag given overriding it; --arw alone is a custom sensor."""
    if args.grade is not None and args.grade not in model.GRADES:
        raise InputError(f"--grade {args.grade!r}: use one of {', '.join(model.GRADES)} or give --arw")
    if args.grade is None and v["arw"] is None:
        raise InputError(f"give --grade ({', '.join(model.GRADES)}) or --arw DEG_RT_H for the gyro")
    base = model.GRADES[args.grade] if args.grade else model.Sensor(arw_deg_rt_h=float(v["arw"]))
    changes = {"gyro_axes": args.gyro_axes}
    for key, field in (("arw", "arw_deg_rt_h"), ("bias_instability", "bias_instability_dph"),
                       ("rrw", "rrw_dph_rt_h"), ("accel_noise", "accel_noise_ug_rt_hz")):  # fmt: skip
        if v[key] is not None:
            changes[field] = v[key]
    return replace(base, **changes)


def run(args: argparse.Namespace) -> int:
    v = _numbers(args)
    _check(v, args)
    sensor = sensor_from(args, v)
    stage = model.Stage(v["stage_speed"], v["stage_accel"], v["settle"], v["turnaround"], not args.no_return)
    choice = model.choose_plan(
        sensor,
        v["latitude"],
        v["tilt"],
        stage,
        target_std_deg=v["target_std"],
        time_budget_s=v["time_budget"],
    )
    _print(choice, sensor, args, v)
    return 0


def _print(choice: model.PlanChoice, sensor: model.Sensor, args: argparse.Namespace, v: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    if not console.is_terminal:
        console = Console(width=max(console.width, 150))
    b = choice.best
    goal = f"σ ≤ {v['target_std']:g}°" if v["target_std"] is not None else f"within {v['time_budget']:g} s"
    console.print(
        f"plan for {goal}: [bold]{b.spec.kind}[/bold], {b.spec.describe()} — predicted σ {b.sigma_deg:.4f}°, "
        f"elapsed {b.elapsed_s:.0f} s device time ({b.elapsed_s / 60:.1f} min), "
        f"{b.ratio:.2f} × the limit of that time"
    )
    console.print(
        f"sensor: ARW {sensor.arw_deg_rt_h:g} °/√h, bias instability {sensor.bias_instability_dph:g} °/h, "
        f"RRW {sensor.rrw_dph_rt_h:g} °/h/√h, accel {sensor.accel_noise_ug_rt_hz:g} µg/√Hz, "
        f"gyro {sensor.gyro_axes}; "
        f"{v['latitude']:g}°, tilt ≤ {v['tilt']:g}°"
    )
    for note in choice.notes:
        console.print(f"note: {note}")
    t = Table(title="alternatives (best of each kind and n; * the chosen plan)")
    for col in ("kind", "schedule", "elapsed [s]", "gyro used [s]", "σ [°]", "white [°]", "drift [°]",
                "limit(elapsed) [°]", "σ/limit"):  # fmt: skip
        t.add_column(col, justify="right" if "[" in col or col == "σ/limit" else "left")
    for p in choice.alternatives:
        mark = "bold" if p is b else None
        cells = (p.elapsed_s, p.used_s, p.sigma_deg, p.white_deg, p.drift_deg, p.limit_deg, p.ratio)
        fmts = (".0f", ".0f", ".4f", ".4f", ".4f", ".4f", ".3f")
        kind = ("* " if p is b else "") + p.spec.kind
        text = [format(c, f) for c, f in zip(cells, fmts, strict=True)]
        t.add_row(kind, p.spec.describe(), *text, style=mark)
    console.print(t)
