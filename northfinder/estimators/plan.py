"""Plan model: the elapsed device time and the predicted heading σ of a turntable plan, and the
planner that picks the plan reaching a target σ soonest (or the best σ in a time budget).

docs/estimators.md §11 (equations P1–P5). Three kinds of plan:

- ``positions``: stop-and-go, the dwell means only (today's find);
- ``positions+motion``: the same schedule, every gyro sample fitted with its own angle
  (motion_fit, eq M2 with the misalignment and the wobble estimated) — needs a z gyro;
- ``sweep``: n rests at equally spaced angles visited in a zig-zag, each move the long way round
  (360° + the step, alternating direction, at the stage's speed), short dwells at rest for the
  tilt and the encoder, every sample fitted (`sweep_targets_deg`) — needs a z gyro.

σ is predicted exactly for the linear-Gaussian model on a time grid: the white part from the
plan's own design (AᵀWA)⁻¹ (P2), the bias drift (Gauss–Markov bias instability and rate random
walk) propagated through the same least-squares operator (P3), the accelerometer's tilt noise
(P4). Pure numpy/scipy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from northfinder.constants import OMEGA_EARTH_RAD_S
from northfinder.errors import InputError
from northfinder.estimators.limits import noise_limit_heading_std_deg
from northfinder.estimators.motion_fit import RUN_TERMS, motion_design

KINDS = ("positions", "positions+motion", "sweep")
MOTION_KINDS = ("positions+motion", "sweep")
"""The kinds that fit every sample (the per-sample fit, motion_fit): they need a z gyro."""
GYRO_AXES = ("xyz", "xy", "y")
EARTH_RATE_DPH = OMEGA_EARTH_RAD_S * 180.0 / math.pi * 3600.0


@dataclass(frozen=True)
class Sensor:
    """What limits the heading: gyro ARW [°/√h], bias instability [°/h] (Gauss–Markov with
    correlation time [s]), rate random walk [°/h/√h], accelerometer noise [µg/√Hz]; gyro_axes
    "xyz" (a z gyro: motion samples usable), "xy" or "y" (stop-and-go only)."""

    arw_deg_rt_h: float
    bias_instability_dph: float = 0.0
    bi_correlation_s: float = 600.0
    rrw_dph_rt_h: float = 0.0
    accel_noise_ug_rt_hz: float = 0.0
    gyro_axes: str = "xyz"

    @property
    def horizontal_axes(self) -> tuple[str, ...]:
        return ("y",) if self.gyro_axes == "y" else ("x", "y")


# Copied BY VALUE from firmware_sim/physics/sensors.py GYRO_PRESETS / ACCEL_PRESETS (northfinder
# never imports firmware_sim): ARW, bias instability, its correlation time, RRW, accel noise.
GRADES: dict[str, Sensor] = {
    "nav": Sensor(0.002, 0.005, 600.0, 0.0005, 10.0),
    "kvh1760": Sensor(0.012, 0.05, 300.0, 0.01, 120.0),
    "tactical-mems": Sensor(0.15, 0.5, 100.0, 0.5, 40.0),
    "consumer": Sensor(1.0, 10.0, 60.0, 10.0, 200.0),
    # Sensonor STIM300, datasheet TS1524 rev.31 Tables 5-3/5-5 (as firmware_sim's stim300 preset):
    # ARW 0.15 °/√h, bias instability 0.3 °/h, accelerometer VRW 0.024 m/s/√h = 40.8 µg/√Hz
    "stim300": Sensor(0.15, 0.3, 100.0, 0.3, 0.024 / 60.0 / 9.80665 * 1e6),
}


@dataclass(frozen=True)
class Stage:
    """The stage and what a stop costs. speed/accel: SMC100 `VA`/`AC` (firmware_sim's defaults
    20 °/s, 80 °/s²); settle_s: from the end of a move until a dwell starts (the gyro-z ringing
    criterion and its margin: 3.0–3.4 s on firmware_sim); turnaround_s: from a dwell's end to the
    next move command (the accelerometer's dwell completing, the encoder read, the dwell's 1 s
    sample grid: 0.5–1.5 s on firmware_sim at 12×); return_to_start: the run ends with the move
    back and its settle — part of the elapsed time (and of a motion plan's fit)."""

    speed_deg_s: float = 20.0
    accel_deg_s2: float = 80.0
    settle_s: float = 3.2
    turnaround_s: float = 1.3
    return_to_start: bool = True


@dataclass(frozen=True)
class PlanSpec:
    """kind, n (positions, or the rests of a sweep), dwell_s at each, order ("sequential" for
    positions, "zigzag" for a sweep: the visiting order of `sweep_targets_deg`)."""

    kind: str
    n: int
    dwell_s: float = 0.0
    order: str = "sequential"

    def describe(self) -> str:
        if self.kind == "sweep":
            return f"{self.n} rests × {self.dwell_s:.1f} s, moves of 1–2 turns, ± alternating"
        return f"{self.n} × {self.dwell_s:.1f} s, {self.order}"


def sweep_targets_deg(n: int, start_deg: float = 0.0) -> list[float]:
    """The stage targets of a sweep [deg, absolute, inside −360…+360]: n equally spaced angles
    a_k = start + k·360/n (taken in [0, 360)), visited lowest, highest, second lowest, second
    highest, …; a low one is reached at a − 360, a high one at a. Every move then goes up from a
    low landing to a higher angle or down from a high landing to a lower one, so each is 360° plus
    the angle between them, in alternating directions: whole turns both ways at the stage's speed,
    the rests at n distinct angles (the tilt and the encoder readings).
    """
    if n < 3:
        raise InputError(f"a sweep needs at least 3 rests, got {n}")
    angles = sorted((start_deg + k * 360.0 / n) % 360.0 for k in range(n))
    order, lo, hi = [], 0, n - 1
    while lo <= hi:
        order.append(angles[lo] - 360.0)
        lo += 1
        if lo <= hi:
            order.append(angles[hi])
            hi -= 1
    return order


@dataclass(frozen=True)
class Schedule:
    """The plan on a uniform grid of dt_s: true table angle [deg] and rate [deg/s], which gyro
    samples the estimator uses, rest samples (encoder readable) and the accelerometer's time."""

    dt_s: float
    alpha_deg: np.ndarray
    omega_dps: np.ndarray
    gyro_used: np.ndarray
    rest: np.ndarray
    accel_s: float

    @property
    def elapsed_s(self) -> float:
        return self.alpha_deg.size * self.dt_s

    @property
    def used_s(self) -> float:
        return float(self.gyro_used.sum()) * self.dt_s


def move_time_s(distance_deg: float, stage: Stage) -> float:
    """Trapezoid (or triangle) move time from rest to rest (eq P1)."""
    d, v, a = abs(distance_deg), stage.speed_deg_s, stage.accel_deg_s2
    return d / v + v / a if d >= v * v / a else 2.0 * math.sqrt(d / a)


def _move(distance_deg: float, vmax: float, accel: float, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Angle offsets and rates of a trapezoid move sampled at dt (mid-sample), rest to rest."""
    d, s = abs(distance_deg), math.copysign(1.0, distance_deg)
    v = vmax if d >= vmax * vmax / accel else math.sqrt(d * accel)
    t_acc, t_tot = v / accel, (d / v + v / accel)
    k = max(1, int(round(t_tot / dt)))
    t = (np.arange(k) + 0.5) * t_tot / k
    rate = np.minimum(np.minimum(accel * t, v), accel * (t_tot - t)).clip(0.0)
    pos = np.where(
        t < t_acc, 0.5 * accel * t**2,
        np.where(t > t_tot - t_acc, d - 0.5 * accel * (t_tot - t) ** 2, 0.5 * v * t_acc + v * (t - t_acc)),
    )  # fmt: skip
    return s * pos, s * rate


class _Builder:
    """Appends rest and move segments to a schedule grid."""

    def __init__(self, dt: float):
        self.dt, self.alpha, self.omega, self.used, self.rest = dt, [], [], [], []
        self.angle = 0.0

    def hold(self, seconds: float, used: bool) -> None:
        k = int(round(seconds / self.dt))
        self.alpha.append(np.full(k, self.angle))
        self.omega.append(np.zeros(k))
        self.used.append(np.full(k, used))
        self.rest.append(np.ones(k, bool))

    def move(self, distance_deg: float, vmax: float, accel: float, used: bool) -> None:
        pos, rate = _move(distance_deg, vmax, accel, self.dt)
        self.alpha.append(self.angle + pos)
        self.omega.append(rate)
        self.used.append(np.full(pos.size, used))
        self.rest.append(np.zeros(pos.size, bool))
        self.angle += distance_deg

    def build(self, accel_s: float) -> Schedule:
        cat = np.concatenate
        return Schedule(self.dt, cat(self.alpha), cat(self.omega), cat(self.used), cat(self.rest), accel_s)


def schedule(spec: PlanSpec, stage: Stage, dt_s: float = 0.1) -> Schedule:
    """The plan's time line (eq P1). positions: [settle, dwell] at each of n equally spaced
    angles, [turnaround, move of 360°/n] between, then the turnaround, the return move and its
    settle; positions+motion: the same, every sample from the first dwell's start to the rest after
    the return used (the run's fit pins the table angle at the dwells and at that rest); sweep: the
    same at the rests of `sweep_targets_deg`, whose moves are 360° plus the step. Every plan starts
    at 0° (the start angle, where the stage stands): a sweep first turns to its first rest at −360°."""
    b = _Builder(dt_s)
    v, a = stage.speed_deg_s, stage.accel_deg_s2
    targets = _targets(spec)
    motion = spec.kind != "positions"
    if targets[0]:
        b.move(targets[0], v, a, False)
    b.hold(stage.settle_s, False)
    for i in range(spec.n):
        if i:
            b.hold(stage.turnaround_s, motion)
            b.move(targets[i] - targets[i - 1], v, a, motion)
            b.hold(stage.settle_s, motion)
        b.hold(spec.dwell_s, True)
    if stage.return_to_start:  # the run pins the rest after the return too (a `returned` event)
        b.hold(stage.turnaround_s, motion)
        b.move(targets[0] - targets[-1], v, a, motion)
        b.hold(stage.settle_s, motion)
    return b.build(spec.n * spec.dwell_s)


def _targets(spec: PlanSpec) -> list[float]:
    """The stage targets of a plan: 360°/n steps (positions), the zig-zag of a sweep."""
    if spec.kind == "sweep":
        return sweep_targets_deg(spec.n)
    return [k * 360.0 / spec.n for k in range(spec.n)]


def _backward_ar1(p: np.ndarray, phi: float) -> np.ndarray:
    """g_j = p_j + φ·g_{j+1} along the last axis (g past the end = 0), in numpy: within blocks short
    enough that φ^len ≥ e^−200, g_j = φ^−j·Σ_{k≥j} φ^k·p_k by a reversed cumulative sum; the block
    after carries in as φ^(end−j)·g_end. (scipy.signal.lfilter does the same but costs 1.7 s to import.)"""
    n = p.shape[-1]
    out = np.empty_like(p, dtype=float)
    decay = -math.log(phi) if phi > 0.0 else math.inf
    block = n if decay == 0.0 else max(1, min(n, int(200.0 / decay)))
    carry = np.zeros(p.shape[:-1])
    end = n
    while end > 0:
        start = max(0, end - block)
        k = np.arange(end - start)
        w = phi**k
        tail = np.cumsum((p[..., start:end] * w)[..., ::-1], axis=-1)[..., ::-1]
        out[..., start:end] = tail / w + phi ** (end - start - k) * carry[..., None]
        carry = out[..., start]
        end = start
    return out


def _drift_cov(p_axis: np.ndarray, dt: float, sensor: Sensor) -> np.ndarray:
    """Covariance of the LS error from bias drift on one axis (eq P3): e = Σ_k P_k d_k.

    Rate random walk (q = RRW/60 °/h/√s): Cov = q²·Σ_j dt·G_jG_jᵀ, G_j = Σ_{k≥j} P_k.
    Gauss–Markov (σ = B, φ = e^{−dt/τ}): g_j = P_j + φ·g_{j+1}, Cov = σ²[g_0g_0ᵀ + (1−φ²)Σ_{j≥1} g_jg_jᵀ].
    """
    cov = np.zeros((p_axis.shape[0],) * 2)
    if sensor.rrw_dph_rt_h > 0.0:
        g = np.cumsum(p_axis[:, ::-1], axis=1)[:, ::-1]
        cov += (sensor.rrw_dph_rt_h / 60.0) ** 2 * dt * (g @ g.T)
    if sensor.bias_instability_dph > 0.0:
        phi = math.exp(-dt / sensor.bi_correlation_s)
        g = _backward_ar1(p_axis, phi)
        cov += sensor.bias_instability_dph**2 * (
            np.outer(g[:, 0], g[:, 0]) + (1 - phi**2) * (g[:, 1:] @ g[:, 1:].T)
        )
    return cov


def rate_covariance_dph2(sch: Schedule, kind: str, sensor: Sensor) -> np.ndarray:
    """2×2 covariance of the fitted (v_x, v_y) [(°/h)²]: white (eq P2) + drift (eq P3).

    White: each grid sample of length dt has σ² = N²/dt with N = ARW·60 [°/h·√s], so
    Cov = (AᵀWA)⁻¹, W = dt/N². positions fits the dwell samples without motion terms (= the
    dwell means weighted by their length); the motion kinds fit every sample with δ (eq M2).
    """
    axes = sensor.horizontal_axes
    terms = () if kind == "positions" else RUN_TERMS
    used = np.flatnonzero(sch.gyro_used)
    a_mat, _ = motion_design(sch.alpha_deg[used], sch.omega_dps[used], axes, terms)
    n_dph = sensor.arw_deg_rt_h * 60.0
    w = sch.dt_s / n_dph**2
    normal_inv = np.linalg.inv(w * (a_mat.T @ a_mat))
    cov = normal_inv.copy()
    m, p = used.size, normal_inv.shape[0]
    pmat = w * normal_inv @ a_mat.T
    for j in range(len(axes)):
        full = np.zeros((p, sch.alpha_deg.size))
        full[:, used] = pmat[:, j * m : (j + 1) * m]
        cov += _drift_cov(full, sch.dt_s, sensor)
    return cov[:2, :2]


@dataclass(frozen=True)
class Prediction:
    """A plan's elapsed device time and predicted heading σ (and its parts) [s, deg]."""

    spec: PlanSpec
    elapsed_s: float
    used_s: float
    sigma_deg: float
    white_deg: float
    drift_deg: float
    accel_deg: float
    limit_deg: float

    @property
    def ratio(self) -> float:
        """σ over the white-noise limit of the ELAPSED time (the issue's yardstick)."""
        return self.sigma_deg / self.limit_deg


def _grid_dt(spec: PlanSpec, stage: Stage) -> float:
    """A grid fine enough for the moves, at most ~6000 samples for long plans."""
    rough = spec.n * (spec.dwell_s + stage.settle_s + stage.turnaround_s) + 400.0
    if spec.kind == "sweep":
        rough += spec.n * 540.0 / stage.speed_deg_s
    return max(0.05, rough / 6000.0)


def predict(spec: PlanSpec, sensor: Sensor, latitude_deg: float, tilt_deg: float, stage: Stage) -> Prediction:
    """Predicted σψ of a plan (eq P2–P5) and its elapsed time.

    σψ = √(tr Cov/2)·k/ω_N with k = 1/cos ε (the tilt bound ε with the worst azimuth, §5), plus
    the accelerometer: σ_u = ρ·√(2/T_acc)/√2 per horizontal component, δψ = tan L·δu (P4).
    """
    sch = schedule(spec, stage, _grid_dt(spec, stage))
    omega_n_dph = EARTH_RATE_DPH * math.cos(math.radians(latitude_deg))
    k = 1.0 / math.cos(math.radians(tilt_deg))
    white_only = replace(sensor, bias_instability_dph=0.0, rrw_dph_rt_h=0.0)
    cov_w = rate_covariance_dph2(sch, spec.kind, white_only)
    cov = rate_covariance_dph2(sch, spec.kind, sensor)
    to_deg = math.degrees(k / omega_n_dph)
    white = math.sqrt(np.trace(cov_w) / 2.0) * to_deg
    total_gyro = math.sqrt(np.trace(cov) / 2.0) * to_deg
    sigma_u = sensor.accel_noise_ug_rt_hz * 1e-6 * math.sqrt(1.0 / max(sch.accel_s, 1e-9))
    accel = math.degrees(abs(math.tan(math.radians(latitude_deg))) * sigma_u)
    limit = float(
        noise_limit_heading_std_deg(
            sensor.arw_deg_rt_h, sch.elapsed_s, latitude_deg, tilt_deg, 90.0, len(sensor.horizontal_axes)
        )
    )
    return Prediction(
        spec, sch.elapsed_s, sch.used_s, math.hypot(total_gyro, accel), white,
        math.sqrt(max(total_gyro**2 - white**2, 0.0)), accel, limit,
    )  # fmt: skip


def positions_dwell_for(elapsed_s: float, n: int, stage: Stage) -> float:
    """The dwell [s] whose n-position plan lasts elapsed_s (eq P1 solved for the dwell); ≤ 0 when
    the moves and settles alone take longer."""
    return _dwell_for(elapsed_s, [k * 360.0 / n for k in range(n)], stage)


def sweep_dwell_for(elapsed_s: float, n: int, stage: Stage) -> float:
    """The dwell [s] at each of a sweep's n rests whose plan lasts elapsed_s (≤ 0: the moves alone
    take longer)."""
    return _dwell_for(elapsed_s, sweep_targets_deg(n), stage)


def _dwell_for(elapsed_s: float, targets: list[float], stage: Stage) -> float:
    n = len(targets)
    fixed = move_time_s(targets[0], stage) + n * stage.settle_s + (n - 1) * stage.turnaround_s
    fixed += sum(move_time_s(b - a, stage) for a, b in zip(targets[:-1], targets[1:], strict=True))
    if stage.return_to_start:
        fixed += stage.turnaround_s + move_time_s(targets[-1] - targets[0], stage) + stage.settle_s
    return (elapsed_s - fixed) / n


POSITION_COUNTS = (4, 6, 8, 12, 16)
SWEEP_RESTS = (3, 4, 6, 8, 12, 16)
TIE = 0.02
"""Relative margin within which plans count as equally fast (or equally good)."""


@dataclass(frozen=True)
class PlanChoice:
    """The chosen plan, every alternative considered (best per kind and n), and why some kinds
    were left out."""

    best: Prediction
    alternatives: list[Prediction]
    notes: list[str]


def _spec_for(kind: str, n: int, elapsed_s: float, stage: Stage) -> PlanSpec | None:
    if kind == "sweep":
        d = sweep_dwell_for(elapsed_s, n, stage)
        return PlanSpec(kind, n, dwell_s=d, order="zigzag") if d >= 0.5 else None
    d = positions_dwell_for(elapsed_s, n, stage)
    return PlanSpec(kind, n, dwell_s=d) if d >= 0.5 else None


def _for_target(kind, n, target, sensor, lat, tilt, stage, max_s) -> Prediction | None:
    """The shortest elapsed time of (kind, n) whose σ ≤ target: bisection on the elapsed time,
    bracketed first by σ ∝ 1/√(time used) from one prediction (a few steps instead of ~15)."""
    spec = _spec_for(kind, n, max_s, stage)
    if spec is None or predict(spec, sensor, lat, tilt, stage).sigma_deg > target:
        return None

    def meets(t: float) -> bool:
        s = _spec_for(kind, n, t, stage)
        return s is not None and predict(s, sensor, lat, tilt, stage).sigma_deg <= target

    lo, hi = 1.0, max_s
    probe = min(max_s, 300.0)
    spec = _spec_for(kind, n, probe, stage)
    if spec is not None:
        p = predict(spec, sensor, lat, tilt, stage)
        fixed = max(p.elapsed_s - p.used_s, 0.0)
        guess = fixed + p.used_s * (p.sigma_deg / target) ** 2
        for factor in (0.9, 1.1):  # widen until the bracket holds (drift makes σ fall slower)
            t = min(max(guess * factor, lo), hi)
            if factor < 1.0 and not meets(t):
                lo = t
            elif factor > 1.0 and meets(t):
                hi = t
    while hi - lo >= 0.5:
        mid = 0.5 * (lo + hi)
        if meets(mid):
            hi = mid
        else:
            lo = mid
    return predict(_spec_for(kind, n, hi, stage), sensor, lat, tilt, stage)


def choose_plan(
    sensor: Sensor,
    latitude_deg: float,
    tilt_deg: float,
    stage: Stage,
    *,
    target_std_deg: float | None = None,
    time_budget_s: float | None = None,
    max_time_s: float = 6.0 * 3600.0,
) -> PlanChoice:
    """The plan that reaches target_std_deg soonest, or the smallest σ within time_budget_s (eq P5).

    Kinds with motion samples need a z gyro (gyro_axes "xyz"); without one they are left out
    and `notes` says why. Raises InputError when no plan reaches the target within max_time_s.
    """
    if (target_std_deg is None) == (time_budget_s is None):
        raise InputError("give either a target σ or a time budget (not both)")
    kinds = list(KINDS)
    notes = []
    if sensor.gyro_axes != "xyz":
        kinds = ["positions"]
        notes.append(
            "stop-and-go only: without a z gyro the table angle is known only at rest (the encoder is "
            "read when the stage stops), so samples taken while it turns cannot be placed"
        )
    counts = {"sweep": SWEEP_RESTS}
    alts: list[Prediction] = []
    for kind in kinds:
        for n in counts.get(kind, POSITION_COUNTS):
            if target_std_deg is not None:
                p = _for_target(kind, n, target_std_deg, sensor, latitude_deg, tilt_deg, stage, max_time_s)
            else:
                spec = _spec_for(kind, n, time_budget_s, stage)
                p = None if spec is None else predict(spec, sensor, latitude_deg, tilt_deg, stage)
            if p is not None:
                alts.append(p)
    if not alts:
        if target_std_deg is not None:
            raise InputError(f"no plan reaches σ {target_std_deg:g}° within {max_time_s / 3600:g} h; "
                             "relax the target or use a better gyro")  # fmt: skip
        raise InputError(f"no plan fits in {time_budget_s:g} s (the moves and settles alone take longer); "
                         "give a longer time budget")  # fmt: skip
    if target_std_deg is not None:

        def score(p: Prediction) -> float:
            return p.elapsed_s
    else:

        def score(p: Prediction) -> float:
            return p.sigma_deg

    alts.sort(key=lambda p: (score(p), p.sigma_deg))
    # near-ties (within TIE of the best): the fewest stops or revolutions is the simpler run
    near = [p for p in alts if score(p) <= (1.0 + TIE) * score(alts[0])]
    return PlanChoice(min(near, key=lambda p: (p.spec.n, score(p))), alts, notes)
