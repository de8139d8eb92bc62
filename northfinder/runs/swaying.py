"""`northfinder align --mode swaying`: acquisition, result assembly, report and replay.

What: read an IMU (the inertial-stream role: gyros + accelerometers) on a swaying base for a window
of device time, keep its bytes in the run directory as they arrive (imu.raw), then align with the
inertial-frame cone fit (northfinder.align.swaying) and, on the same samples, the static analytic
coarse alignment (northfinder.align.coarse) for contrast.

Why here: the CLI (northfinder/cli/align_swaying.py) and `northfinder replay` share one function,
:func:`compute_swaying_result`, fed from the driver's arrays live and from the pure decoder of the
model the run recorded (registry.decoder_for) in replay — the same bytes give the same arrays, so the
replayed result is bit-identical.

Truth of a simulated run (docs/simulator.md, "Time alignment of the IMU"): firmware-sim's truth log
names the absolute sample k0 (the model's counter value sequence0) of the first frame it handed to
this client, ending at device time t0_device_s. The first frame decoded (index 0, counter s) is sample
k_first = k0 + ((s − sequence0) mod the counter's period), so the sample with index u ends at
t0_device_s + (k_first − k0 + u)/rate. The truth heading is the logged heading at the end of the
last sample used — the instant the estimator's attitude refers to.
"""

from __future__ import annotations

import contextlib
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from northfinder.align.coarse import coarse_align
from northfinder.align.swaying import (
    METHODS,
    align_swaying_block,
    grade_bias_prior,
    minimum_duration_s,
)
from northfinder.config import ImuConfig, SwayingConfig
from northfinder.constants import DEG, STANDARD_GRAVITY_M_S2, wrap_deg_180
from northfinder.devices import registry
from northfinder.devices.imu import ImuAxes
from northfinder.errors import DeviceError, InputError
from northfinder.report import write_swaying_report as draw_write_swaying_report
from northfinder.rundir import CONFIG, IMU_RAW, RunDir, jsonable
from northfinder.runkinds import Replayed
from northfinder.runs import base
from northfinder.simulate import SimScenario, SimulatorProcess
from northfinder.stopflag import StopFlag

KIND = "align-swaying"
SCHEMA = "northfinder.align-swaying/1"
TRUTH_LOG = "truth.jsonl"
OWN_FILES = {CONFIG, IMU_RAW, TRUTH_LOG}
"""What a run writes before its start event: a failed start that left only these is removed."""
DEFAULT_DURATION_S = SwayingConfig.duration_s  # [swaying]'s defaults (northfinder.config)
DEFAULT_SWAY_PERIOD_S = SwayingConfig.sway_period_s
"""Longest sway period assumed on hardware unless --sway-period says otherwise (ship roll 6–12 s)."""
REFERENCE_SWAY = "roll=10:8,pitch=5:6,yaw=3:10,heave=0.5:7"
"""Issue 5's reference scenario (the swaying-base paper's): roll 10°/8 s, pitch 5°/6 s, yaw 3°/10 s,
heave 0.5 m/7 s."""
SWAY_AXES = ("roll", "pitch", "yaw", "surge", "sway", "heave")
SIM_LEVER_ARM_M = (1.0, 2.0, 1.5)
SIM_LATITUDE_DEG = 40.0
SIM_HEADING_DEG = 37.0
SIM_DEFAULT_TIME_SCALE = 40.0
"""Device time runs 40× the wall clock: 300 s in 7.5 s of reading. Measured on this 2-core host
(2026-11-22, load ≈ 5): the 1000 Hz ship stream read by the Imu driver lost nothing at 50×
(300 s in 8.4 s wall) and at 30×; 40× leaves headroom on a loaded machine."""
GYRO_SATURATION_FRACTION = 0.999


# ---------------------------------------------------------------------------------------------
# The sway specification (the same text firmware-sim takes; parsed here, northfinder never imports it)
# ---------------------------------------------------------------------------------------------
def parse_sway(text: str) -> dict[str, list[list[float]]]:
    """'roll=10:8,heave=0.5:7' → {"roll": [[10, 8]], "heave": [[0.5, 7]]}; 'none' → {} (still ship).

    AXIS=AMP:PERIOD_S[:PHASE_DEG], comma-separated; amplitudes in degrees (roll, pitch, yaw) or
    metres (surge, sway, heave). InputError naming the flag and the item otherwise.
    """
    if text.strip().lower() in ("none", "0", "off"):
        return {}
    out: dict[str, list[list[float]]] = {}
    for item in text.split(","):
        axis, sep, value = item.strip().partition("=")
        axis = axis.strip().lower()
        if not sep or axis not in SWAY_AXES:
            raise InputError(
                f"--sway {item.strip()!r}: write AXIS=AMP:PERIOD_S with AXIS one of "
                f'{", ".join(SWAY_AXES)}, e.g. --sway "{REFERENCE_SWAY}"'
            )
        try:
            numbers = [float(v) for v in value.split(":")]
        except ValueError:
            numbers = []
        if not 2 <= len(numbers) <= 3 or not all(math.isfinite(v) for v in numbers) or numbers[1] <= 0:
            unit = "m" if axis in ("surge", "sway", "heave") else "deg"
            raise InputError(
                f"--sway {item.strip()}: give {axis}=AMP:PERIOD_S as numbers (AMP in {unit}, "
                f'PERIOD_S > 0), e.g. --sway "{REFERENCE_SWAY}"'
            )
        out.setdefault(axis, []).append(numbers)
    return out


def format_sway(sway: dict[str, list[list[float]]]) -> str:
    """The inverse of :func:`parse_sway` (what is passed on to firmware-sim)."""
    if not sway:
        return "none"
    return ",".join(
        f"{axis}=" + ":".join(repr(float(v)) for v in term)
        for axis in SWAY_AXES
        for term in sway.get(axis, [])
    )


def longest_period_s(sway: dict[str, list[list[float]]], default_s: float = DEFAULT_SWAY_PERIOD_S) -> float:
    """The longest sway period: it sets the estimator's smoothing window (4 periods)."""
    periods = [term[1] for terms in sway.values() for term in terms]
    return max(periods) if periods else default_s


# ---------------------------------------------------------------------------------------------
# firmware-sim's ship scenario as a subprocess
# ---------------------------------------------------------------------------------------------
@dataclass
class ShipSim(SimScenario):
    """firmware-sim `--scenario ship`: the IMU alone at a lever arm on a swaying ship."""

    scenario: ClassVar[str | None] = "ship"
    FLAGS: ClassVar[tuple[tuple[str, str, str], ...]] = (
        ("sway", "--sway", ""), ("lever_arm_m", "--lever-arm", ""), ("heading_deg", "--heading", "float"),
        ("latitude_deg", "--latitude", "float"), ("grade", "--grade", ""), ("seed", "--seed", "int"),
        ("time_scale", "--time-scale", "float"), ("truth_log", "--truth-log", "opt"),
        ("config", "--config", "opt"),
    )
    RECORDED: ClassVar[tuple[str, ...]] = ("sway", "lever_arm_m", "heading_deg", "latitude_deg", "grade",
                                           "seed", "time_scale", "faults")

    sway: str = REFERENCE_SWAY
    lever_arm_m: tuple[float, float, float] = SIM_LEVER_ARM_M
    heading_deg: float = SIM_HEADING_DEG
    latitude_deg: float = SIM_LATITUDE_DEG
    grade: str = "nav"
    seed: int = 1
    time_scale: float = SIM_DEFAULT_TIME_SCALE
    faults: Sequence[str] = field(default_factory=tuple)
    truth_log: str | None = None
    config: str | None = None
    """A firmware-sim TOML for the keys without a flag (e.g. imu_variant); the flags win."""


class ShipSimProcess(SimulatorProcess):
    """SimulatorProcess for the ship scenario: endpoints {"imu": PTY}."""

    required_endpoints = ("imu",)
    scenario_name = "ship"


# ---------------------------------------------------------------------------------------------
# Acquisition
# ---------------------------------------------------------------------------------------------
@dataclass
class Window:
    """What one acquisition read: the window's IMU samples and the run's start/end events."""

    block: Any
    start: dict[str, Any]
    end: dict[str, Any]
    stop: StopFlag


def check_stream(block: Any, port: str, gyro_range_dps: float | None) -> None:
    """Refuse early what the alignment cannot use: accelerometers the IMU flags not valid (the
    block's per-axis validity, ImuBlock.valid, whatever the model's status words), or all zero, and
    gyros at the end of their range (the model's `gyro_range_dps`; None: not known, not checked)."""
    axes = ImuAxes.from_valid(block.valid) if len(block) else None
    accel = block.accel_g[np.isfinite(block.accel_g)]
    if axes is not None and (axes.accel != "xyz" or not np.any(accel)):
        raise DeviceError(
            "imu",
            port,
            f"reports no valid accelerometers ({axes.describe()} in its samples' validity): the swaying "
            "alignment needs an IMU with three gyros and three accelerometers",
        )
    gyro = np.abs(block.gyro_rad_s[np.isfinite(block.gyro_rad_s)])
    peak = float(np.max(gyro)) / DEG if len(gyro) else 0.0
    if gyro_range_dps is not None and peak >= GYRO_SATURATION_FRACTION * gyro_range_dps:
        raise InputError(
            f"gyro reached {peak:.1f} °/s, the ±{gyro_range_dps:g} °/s range of the IMU on "
            f"{port}: the sway saturates the gyro — align in calmer sea or with a wider-range IMU"
        )


def acquire(
    rd: RunDir,
    *,
    imu: ImuConfig,
    duration_s: float,
    settings: dict[str, Any],
    configure_imu: bool = False,
    progress: base.WindowProgress | None = None,
    config_extra: dict[str, Any] | None = None,
) -> Window:
    """Read `duration_s` device seconds (samples + lost samples over the rate) from the IMU of the
    `[imu]` section `imu` (its model, port, rate …); raw bytes go to imu.raw as they arrive, the
    window's index range to events.jsonl. A signal ends the reading early (`Window.stop` says
    which). `settings`: what the estimator needs (latitude, method, sway period, simulate) — stored
    in the start event so replay finds it."""
    rd.write_json(CONFIG, {"kind": KIND, "argv": sys.argv, **settings, **(config_extra or {})})
    stop = StopFlag()
    blocks: list[Any] = []
    port = imu.port
    with stop.installed():
        with base.guard(
            "imu", port, lambda: registry.open_device("imu", imu, rd.imu_raw_path, rate_hz=float(imu.rate_hz))
        ) as device:
            if configure_imu:
                device.configure_for_run(None)  # read rate and gyro format back: the decoder must know them
            start = base.start_event(KIND, duration_s, port, device, **settings)
            rd.log_event(start)
            with base.window_view(progress, duration_s) as view:
                gyro_range = device.gyro_range_dps
                for done_s in base.read_imu_window(
                    device, duration_s, stop, blocks, check=lambda b: check_stream(b, port, gyro_range)
                ):
                    st = device.stats
                    view.show(
                        done_s,
                        f"{done_s:6.1f}/{duration_s:g} s  lost {st.lost_samples}  bad CRC {st.bad_crc}  "
                        f"resyncs {st.resyncs}",
                    )
            rate = device.rate_hz
            stats = device.stats.as_dict()
    # port closed: imu.raw is complete on disk
    complete = not stop
    if not blocks:
        rd.log_event({"event": "end", "complete": False, "imu": {"samples": 0}})
        raise base.abort_or(stop, rd, "no IMU samples were read")
    block = base.concat_blocks(blocks, rate)
    end = {"event": "end", "complete": complete, "utc": base.now_utc(), "imu": base.imu_end(block, stats)}
    rd.log_event(end)
    return Window(block, start, end, stop)


# ---------------------------------------------------------------------------------------------
# The simulator's truth log (docs/simulator.md)
# ---------------------------------------------------------------------------------------------
def first_counter(raw: bytes, model: str | None) -> tuple[int, int]:
    """The model's own counter of the first sample of a raw IMU log, and the counter's period."""
    decoder = registry.decoder_for("imu", model)
    return decoder.first_counter(raw), int(decoder.counter_period)


def truth_at_end(rd: RunDir, start: dict[str, Any], first_index: int, last_index: int) -> dict[str, Any]:
    """The ship's attitude at the end of the window's last sample (and at its start), from the truth
    log; the device time comes from the imu_connect anchor and the first frame's sequence number."""
    truth = base.read_truth_log(rd.file(TRUTH_LOG))
    rate = float(start["imu"]["rate_hz"])
    c = truth.connect
    if c is None:
        raise InputError(
            f"{rd.path}: the truth log has no imu_connect event; cannot place the samples in time"
        )
    if truth.grid_events:
        raise base.grid_moved(rd)
    if float(c["rate_hz"]) != rate:
        raise InputError(
            f"{rd.path}: the truth log's IMU rate {c['rate_hz']:g} Hz is not the run's {rate:g} Hz"
        )
    s0, period = first_counter(rd.file(IMU_RAW).read_bytes(), start["imu"].get("model"))
    k_first = int(c["k0"]) + (s0 - int(c["sequence0"])) % period
    t_of_end = lambda u: float(c["t0_device_s"]) + (k_first - int(c["k0"]) + u) / rate  # noqa: E731
    t_end = t_of_end(last_index)
    t_start = t_of_end(first_index - 1)
    if t_end > truth.t_s[-1] + 1.0 / float(truth.header.get("truth_rate_hz", 50.0)):
        raise InputError(
            f"{rd.path}: the truth log ends at {truth.t_s[-1]:.3f} s, before the window's end "
            f"at {t_end:.3f} s of device time"
        )
    return {
        "heading_deg": float(truth.heading_at(t_end)),
        "pitch_deg": float(truth.at(t_end, "pitch_deg")),
        "roll_deg": float(truth.at(t_end, "roll_deg")),
        "heading_at_start_deg": float(truth.heading_at(t_start)),
        "t_device_s": t_end,
        "t_start_device_s": t_start,
        "time_alignment": {
            "method": "truth-log",
            "k0": int(c["k0"]),
            "sequence0": int(c["sequence0"]),
            "first_sequence": s0,
            "k_first": k_first,
        },
        "sway": truth.header.get("sway"),
        "lever_arm_m": (truth.header.get("imu") or {}).get("lever_arm_b_m"),
    }


# ---------------------------------------------------------------------------------------------
# Result assembly: the one function live and replay call
# ---------------------------------------------------------------------------------------------
def compute_swaying_result(
    block: Any,
    start: dict[str, Any],
    end: dict[str, Any],
    truth: dict[str, Any] | None,
    *,
    complete: bool = True,
) -> tuple[dict[str, Any], Any]:
    """The estimator (start["method"]) and the static coarse alignment on the window's samples →
    (result dict, the SwayingSolution for the report)."""
    if len(block) == 0:
        raise InputError("no IMU samples were read; nothing to align")
    rate = float(start["imu"]["rate_hz"])
    lat = float(start["latitude_deg"])
    grade = (start.get("simulate") or {}).get("grade") or start.get("imu_grade")
    prior = grade_bias_prior(grade)
    sol = align_swaying_block(
        block,
        lat,
        rate_hz=rate,
        method=start["method"],
        max_sway_period_s=float(start["max_sway_period_s"]),
        height_m=float(start.get("height_m", 0.0)),
        **prior,
    )
    main = {
        "heading_deg": sol.heading_deg,
        "heading_std_deg": sol.heading_std_deg,
        "pitch_deg": sol.pitch_deg,
        "roll_deg": sol.roll_deg,
        "pitch_std_deg": sol.pitch_std_deg,
        "roll_std_deg": sol.roll_std_deg,
    }
    result: dict[str, Any] = {
        "schema": SCHEMA,
        "kind": KIND,
        "complete": bool(complete),
        "method": sol.method,
        **main,
        "duration_device_s": sol.duration_device_s,
        "latitude_deg": lat,
        "max_sway_period_s": float(start["max_sway_period_s"]),
        "minimum_duration_s": minimum_duration_s(float(start["max_sway_period_s"])),
        "methods": {
            sol.method: dict(main),
            "coarse": _coarse_method(block, rate, lat),
        },
        "sigma_covers": sigma_covers(prior),
        "diagnostics": sol.diagnostics,
        "imu": {**end["imu"], "rate_hz": rate},
    }
    if truth is not None:
        result["truth"] = {k: v for k, v in truth.items() if k != "time_alignment"}
        result["time_alignment"] = truth["time_alignment"]
        result["error_deg"] = float(wrap_deg_180(sol.heading_deg - truth["heading_deg"]))
        for m in result["methods"].values():
            m["error_deg"] = float(wrap_deg_180(m["heading_deg"] - truth["heading_deg"]))
    return json.loads(json.dumps(jsonable(result), allow_nan=False)), sol


def _coarse_method(block: Any, rate_hz: float, latitude_deg: float) -> dict[str, Any]:
    """The contrast method on the same samples: the static analytic coarse alignment (window means),
    with a σ only when the base was still."""
    coarse = coarse_align(block.gyro_rad_s, block.accel_g, rate_hz, latitude_deg)
    still = bool(coarse.diagnostics["base_still"])
    return {
        "heading_deg": coarse.heading_deg,
        "heading_std_deg": coarse.heading_std_deg if still else None,
        "pitch_deg": coarse.pitch_deg,
        "roll_deg": coarse.roll_deg,
        "note": "static analytic coarse alignment (window means); σ: the still-base noise limit"
        if still
        else "static analytic coarse alignment (window means); no σ: the base moves, the "
        "window-mean rate carries the sway, not the Earth rate",
        **coarse.diagnostics,
    }


def sigma_covers(prior: dict[str, float]) -> dict[str, Any]:
    """What the reported 1σ includes and what it does not (the summary prints both)."""
    covers = ["white gyro and accelerometer noise (measured)",
              "the IMU's lever arm from the sway centre: estimated with the heading and its sway removed",
              "sway leakage and other errors left in the cone fit's residual (measured)"]
    omits = ["scale-factor and misalignment errors that mimic the Earth-rate cone"]
    if prior:
        covers.append(f"gyro bias floor of the grade ({prior['gyro_bias_dph']:g} °/h, "
                      f"accelerometer {prior['accel_bias_ug']:g} µg, 1σ)")
        covers.append(f"the bias the sway rectifies through the grade's gyro scale-factor asymmetry "
                      f"({prior['gyro_sf_asymmetry_ppm']:g} ppm, 1σ)")
    else:
        omits.append("the gyro bias floor εE/(Ωe·cos L) and the sway-rectified scale-factor asymmetry: "
                     "the IMU grade is not known")
    return {"covers": covers, "omits": omits}


def result_from_run(
    rd: RunDir, block: Any, start: dict[str, Any], end: dict[str, Any], complete: bool
) -> tuple[dict[str, Any], Any]:
    """The result of a run from its window's samples (live: the driver's arrays; replay: decoded)."""
    block, cut = base.before_unknown_gap(block, start["imu"].get("model"))
    truth = None
    if start.get("simulate"):
        last = int(end["imu"]["last_index"]) if cut is None else int(block.sample_index[-1])
        truth = truth_at_end(rd, start, int(end["imu"]["first_index"]), last)
    result, sol = compute_swaying_result(block, start, end, truth, complete=complete)
    if cut is not None:
        result["imu_unknown_gap"] = cut
    return result, sol


def replay_swaying_run(run_dir: str | Path) -> tuple[dict[str, Any], bool]:
    """Recompute an `align --mode swaying` run's result from imu.raw and the events alone.

    Returns (result, complete); bit-identical to the live result.json for the same run.
    """
    rd = RunDir(run_dir, create=False)
    start, end = base.run_events(rd, KIND, "swaying")
    if end is None or not end["imu"].get("samples"):
        raise InputError(
            f"{rd.path}: the run has no window of samples (killed before it saved one); nothing to recompute"
        )
    block = base.imu_window_from_raw(rd, start, end)
    complete = bool(end.get("complete"))
    result, _ = result_from_run(rd, block, start, end, complete)
    return result, complete


def replayed(run_dir: str | Path, method: str | None = None) -> Replayed:
    """:func:`replay_swaying_run` as this kind's replay in the run-kind registry (no method to choose)."""
    result, complete = replay_swaying_run(run_dir)
    return Replayed(result, complete)


# ---------------------------------------------------------------------------------------------
# The report: the cone fit's own residuals (the estimator gives no heading history)
# ---------------------------------------------------------------------------------------------
def cone_residuals(block: Any, sol: Any) -> dict[str, np.ndarray]:
    """The estimator's own residuals for the report: each smoothing window's specific force in i_b0
    less the fitted model (the Earth-rate cone and the lever arm's sway, docs/swaying.md eq. 4a)
    [µg], at the window centres, and the gyro trace. Drawn only: not in the result. ValueError when
    the method has no residual model (the circle fit)."""
    if len(sol.window_residual_m_s2) == 0:
        raise ValueError("no residual model for this method")
    rate = float(block.rate_hz)
    step = max(1, int(rate // 20))
    return {
        "t_s": np.asarray(sol.window_t_s),
        "residual_ug": np.asarray(sol.window_residual_m_s2) / STANDARD_GRAVITY_M_S2 * 1e6,
        "gyro_dps": block.gyro_rad_s[::step] / DEG,
        "t_gyro_s": (block.sample_index[::step] - block.sample_index[0]) / rate,
    }


def write_swaying_report(result: dict[str, Any], resid: dict[str, Any], path: str | Path) -> Path:
    """report.png, drawn by the report layer (northfinder.report.write_swaying_report)."""
    return draw_write_swaying_report(result, resid, path)


def finish(rd: RunDir, w: Window, *, json_path: str | None = None, report: bool = True) -> dict[str, Any]:
    """Align on the window (the function replay uses), save result.json (+ --json) and report.png.
    A window cut short by a signal is aligned if it is long enough, then RunAborted (exit 130/143)."""

    def save(result: dict[str, Any], sol: Any) -> None:
        base.write_result(rd, result, json_path)
        if report:
            with contextlib.suppress(ValueError):  # a window too short for one residual point: no plot
                write_swaying_report(
                    result, cone_residuals(w.block, sol), rd.report_path
                )

    return base.finish_window(
        rd, w.stop, lambda complete: result_from_run(rd, w.block, w.start, w.end, complete), save
    )


__all__ = [
    "KIND",
    "METHODS",
    "ShipSim",
    "ShipSimProcess",
    "acquire",
    "compute_swaying_result",
    "finish",
    "parse_sway",
    "replay_swaying_run",
    "replayed",
    "result_from_run",
    "write_swaying_report",
]
