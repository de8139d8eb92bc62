"""The plan model and planner (docs/estimators.md §11): its time accounting against issue 13's run,
its σ against a Monte Carlo of per-sample data (tolerance from the Monte Carlo's own sampling
error), the planner's choice, and `northfinder plan`'s output and one-line mistakes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from northfinder.cli import main
from northfinder.errors import InputError
from northfinder.estimators import plan as P
from northfinder.estimators.motion_fit import RUN_TERMS
from tests.helpers import load_tool, only_line, run_cli

TOOL = load_tool("plan_vs_limit")
LAT, TILT, HEADING, ELAPSED = 40.0, 2.0, 37.0, 240.0
STAGE = P.Stage()


def _spec(kind: str) -> P.PlanSpec:
    if kind == "sweep":
        return P.PlanSpec(kind, 4, P.sweep_dwell_for(ELAPSED, 4, STAGE), "zigzag")
    return P.PlanSpec(kind, 8, P.positions_dwell_for(ELAPSED, 8, STAGE))


def _monte_carlo_sigma(spec: P.PlanSpec, sensor: P.Sensor, trials: int, seed: int, rate_hz: float = 50.0):
    sch = P.schedule(spec, STAGE, 1.0 / rate_hz)
    rng = np.random.default_rng(seed)
    err = TOOL.MotionErrors()
    out = []
    for start in range(0, trials, 50):
        k = min(50, trials - start)
        gyro, accel = TOOL.simulate_samples(rng, k, sch, sensor, err, HEADING, LAT, TILT, 90.0)
        if spec.kind == "positions":
            h = TOOL.headings_positions(sch, gyro, accel, sensor, LAT)
        else:
            h = TOOL.headings_motion(sch, gyro, accel, sensor, LAT, RUN_TERMS)
        out.append(h - HEADING)
    e = (np.concatenate(out) + 180.0) % 360.0 - 180.0
    return float(np.std(e, ddof=1))


def test_time_model_accounts_for_every_second_of_the_find():
    """8 × 20 s positions: between two dwells a turnaround, a 45° move and a settle (7.0 s with
    firmware_sim's stage: `find --simulate` spans 209 s from its first dwell's start to its last
    dwell's end); the elapsed time adds the first settle and the return (turnaround, 315° back,
    settle), which a motion plan fits too. The white part of the prediction is √(elapsed/dwell) ×
    the limit of the elapsed time."""
    spec = P.PlanSpec("positions", 8, 20.0)
    p = P.predict(spec, P.GRADES["nav"], LAT, 0.0, STAGE)
    fine = P.schedule(spec, STAGE, 0.01)
    between_s = STAGE.turnaround_s + P.move_time_s(45.0, STAGE) + STAGE.settle_s
    back_s = STAGE.turnaround_s + P.move_time_s(315.0, STAGE) + STAGE.settle_s
    assert fine.elapsed_s == pytest.approx(STAGE.settle_s + 160.0 + 7 * between_s + back_s, abs=0.05)
    assert p.elapsed_s == pytest.approx(fine.elapsed_s, rel=0.01)
    assert p.used_s == pytest.approx(160.0, abs=0.5)
    assert p.white_deg / p.limit_deg == pytest.approx(math.sqrt(p.elapsed_s / p.used_s), rel=0.01)
    assert P.move_time_s(45.0, STAGE) == pytest.approx(2.5)  # 45/20 + 20/80
    motion = P.schedule(P.PlanSpec("positions+motion", 8, 20.0), STAGE, 0.01)
    assert motion.used_s == pytest.approx(fine.elapsed_s - STAGE.settle_s, abs=0.1)  # but the first settle


def test_the_solvers_give_plans_of_the_asked_length():
    for kind in P.KINDS:
        sch = P.schedule(_spec(kind), STAGE, 0.01)
        assert sch.elapsed_s == pytest.approx(ELAPSED, abs=0.2), kind
    # a sweep's moves alone can outlast the time: 8 rests (8 moves of 405–675°) do not fit in 200 s
    assert P.sweep_dwell_for(200.0, 8, STAGE) < 0.0


def test_sweep_targets_turn_whole_revolutions_both_ways_to_distinct_rests():
    for n in (3, 4, 5, 8):
        t = np.array(P.sweep_targets_deg(n))
        moves = np.diff(t)
        assert np.all(np.abs(moves) > 360.0) and np.all(np.sign(moves[1:]) == -np.sign(moves[:-1]))
        assert moves[0] > 0 and t.min() >= -360.0 and t.max() <= 360.0
        assert sorted(np.round(t % 360.0, 9)) == [k * 360.0 / n for k in range(n)]
    assert P.sweep_targets_deg(4) == [-360.0, 270.0, -270.0, 180.0]
    with pytest.raises(InputError, match="at least 3"):
        P.sweep_targets_deg(2)


@pytest.mark.parametrize("kind", P.KINDS)
def test_prediction_matches_monte_carlo(kind):
    """Nav grade with δ, scale factors, bias instability and RRW: the Monte Carlo σ over 300 trials
    is within 3 sampling standard errors (1/√(2(M−1)) relative) of the prediction."""
    trials = 300
    pred = P.predict(_spec(kind), P.GRADES["nav"], LAT, TILT, STAGE).sigma_deg
    mc = _monte_carlo_sigma(_spec(kind), P.GRADES["nav"], trials, seed=11)
    assert abs(mc / pred - 1.0) < 3.0 / math.sqrt(2 * (trials - 1)), (mc, pred)


@pytest.mark.parametrize("kind", ["positions", "sweep"])
def test_drift_prediction_matches_monte_carlo(kind):
    """A drifting gyro (bias instability 0.03 °/h over 100 s, RRW 0.15 °/h/√h): the drift part is as
    large as the white one, so a wrong drift propagation (eq P3) would miss by far more than the
    tolerance."""
    sensor = P.Sensor(0.002, 0.03, 100.0, 0.15, 10.0)
    pred = P.predict(_spec(kind), sensor, LAT, TILT, STAGE)
    assert pred.drift_deg > 0.4 * pred.white_deg
    trials = 300
    mc = _monte_carlo_sigma(_spec(kind), sensor, trials, seed=12)
    assert abs(mc / pred.sigma_deg - 1.0) < 3.0 / math.sqrt(2 * (trials - 1)), (mc, pred.sigma_deg)


def test_planner_reaches_the_target_soonest_near_the_limit():
    choice = P.choose_plan(P.GRADES["nav"], LAT, TILT, STAGE, target_std_deg=0.05)
    best = choice.best
    assert best.sigma_deg <= 0.05
    assert best.spec.kind in ("positions+motion", "sweep")
    assert best.ratio < 1.05
    stop_and_go = min(p.elapsed_s for p in choice.alternatives if p.spec.kind == "positions")
    assert best.elapsed_s < 0.8 * stop_and_go
    assert all(p.sigma_deg <= 0.05 for p in choice.alternatives)
    # a long target still has motion plans among its alternatives, and the best is near the limit
    long = P.choose_plan(P.GRADES["nav"], LAT, TILT, STAGE, target_std_deg=0.02)
    assert {"sweep", "positions+motion"} <= {p.spec.kind for p in long.alternatives}
    assert long.best.ratio < 1.05 and long.best.sigma_deg <= 0.02


def test_without_a_z_gyro_only_stop_and_go():
    sensor = P.Sensor(0.002, gyro_axes="y")
    choice = P.choose_plan(sensor, LAT, TILT, STAGE, time_budget_s=240.0)
    assert {p.spec.kind for p in choice.alternatives} == {"positions"}
    assert "z gyro" in choice.notes[0]
    with pytest.raises(InputError, match="either a target"):
        P.choose_plan(sensor, LAT, TILT, STAGE)


def test_cli_prints_the_plan_and_its_time(tmp_path):
    r = run_cli("plan", "--grade", "nav", "--latitude", "40", "--target-std", "0.05", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    head = r.stdout.splitlines()[0]
    assert head.startswith("plan for σ ≤ 0.05°:") and "elapsed" in head and "predicted σ" in head
    assert "alternatives" in r.stdout
    r = run_cli("plan", "--grade", "nav", "--latitude", "40", "--time-budget", "240", "--gyro-axes", "y",
                cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "stop-and-go only: without a z gyro" in r.stdout
    assert "sweep" not in r.stdout and "positions+motion" not in r.stdout


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["--grade", "nav", "--latitude", "95", "--target-std", "0.05"], "--latitude 95"),
        (["--grade", "nav", "--latitude", "40", "--target-std", "-1"], "--target-std -1"),
        (["--grade", "gold", "--latitude", "40", "--target-std", "0.05"], "--grade 'gold'"),
        (["--latitude", "40", "--target-std", "0.05"], "give --grade"),
        (["--arw", "abc", "--latitude", "40", "--target-std", "0.05"], "--arw 'abc': not a number"),
        (["--grade", "nav", "--latitude", "40", "--time-budget", "60", "--gyro-axes", "q"],
         "--gyro-axes 'q'"),
        (["--grade", "nav", "--latitude", "40", "--time-budget", "60", "--stage-speed", "0"],
         "--stage-speed 0"),
        (["--grade", "nav", "--latitude", "40", "--time-budget", "5"], "no plan fits in 5 s"),
        (["--grade", "consumer", "--latitude", "40", "--target-std", "0.0001"], "no plan reaches σ 0.0001°"),
    ],
)
def test_cli_mistakes_are_one_line(argv, says, capsys):
    assert main(["plan", *argv]) == 2
    err = capsys.readouterr().err
    line = only_line(err)
    assert line.startswith("northfinder: error: ") and says in line, line
