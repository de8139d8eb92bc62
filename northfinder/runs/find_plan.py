"""`find --target-std DEG` / `--time-budget S`: the run's plan chosen by the plan model.

The same model as `northfinder plan` (northfinder.estimators.plan, docs/estimators.md §11) picks,
among the plans `find` can carry out (stop-and-go, with or without its motion samples), the one
that reaches the target σ soonest or the smallest σ in the budget; its n, dwell and kind replace
[run] positions, dwell_s and plan, and the prediction goes into the start event and the result so
that the run can be held against it.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from northfinder import config as bench
from northfinder.errors import InputError
from northfinder.estimators import plan as model

PLAN_TILT_DEG = 2.0
"""Tilt bound the plan is made for (as `northfinder plan`'s default): the worst case of a bench
levelled to 2°."""


def sensor_for(grade: str | None) -> model.Sensor:
    """The grade's noise, or one line saying what to give."""
    if grade is None:
        raise InputError("--target-std/--time-budget: give --grade NAME for the gyro's noise "
                         f"({', '.join(model.GRADES)})")  # fmt: skip
    if grade not in model.GRADES:
        raise InputError(f"--grade {grade}: use one of {', '.join(model.GRADES)}")
    return model.GRADES[grade]


def stage_for(cfg: bench.BenchConfig) -> model.Stage:
    """The stage the plan is made for: [turntable] speed_deg_s when known, the model's defaults else."""
    speed = float(getattr(cfg.turntable, "speed_deg_s", 0.0) or 0.0)
    return model.Stage(speed_deg_s=speed) if speed > 0 else model.Stage()


def choose_for_run(cfg: bench.BenchConfig, grade: str | None, target_std_deg: float | None,
                   time_budget_s: float | None) -> dict[str, Any]:
    """Set cfg.run's positions, dwell_s and plan from the chosen plan; return the prediction."""
    sensor = sensor_for(grade)
    choice = model.choose_plan(
        sensor, cfg.site.latitude_deg, PLAN_TILT_DEG, stage_for(cfg),
        target_std_deg=target_std_deg, time_budget_s=time_budget_s,
    )  # fmt: skip
    best = choice.best
    cfg.run.positions = int(best.spec.n)
    cfg.run.dwell_s = round(float(best.spec.dwell_s), 3)
    cfg.run.plan = best.spec.kind
    cfg.validate()
    return {
        "kind": best.spec.kind,
        "positions": best.spec.n,
        "dwell_s": cfg.run.dwell_s,
        "grade": grade,
        "target_std_deg": target_std_deg,
        "time_budget_s": time_budget_s,
        "predicted_std_deg": best.sigma_deg,
        "predicted_elapsed_s": best.elapsed_s,
        "limit_deg": best.limit_deg,
        "tilt_bound_deg": PLAN_TILT_DEG,
        "stage": asdict(stage_for(cfg)),
    }
