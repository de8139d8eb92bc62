"""`northfinder align --mode swaying`: acquisition, result assembly, report and replay.

What: read a KVH format-A IMU (gyros + accelerometers) on a swaying base for a window of device
time, keep its bytes in the run directory as they arrive (imu.raw), then align with the
inertial-frame cone fit (northfinder.align.swaying) and, on the same samples, the static analytic
coarse alignment (northfinder.align.coarse) for contrast.

Why here: the CLI (northfinder/cli/align_swaying.py) and `northfinder replay` share one function,
:func:`compute_swaying_result`, fed from the driver's arrays live and from the pure decoder
(`decode_imu_stream`) in replay — the same bytes give the same arrays, so the replayed result is
bit-identical.

Truth of a simulated run (docs/simulator.md, "Time alignment of the IMU"): firmware-sim's truth log
names the absolute sample k0 (sequence number sequence0) of the first frame it handed to this
client, ending at device time t0_device_s. The first frame decoded (index 0, sequence s) is sample
k_first = k0 + ((s − sequence0) mod 128), so the sample with index u ends at
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
from typing import Any

import numpy as np

from northfinder.align.coarse import coarse_align
from northfinder.align.swaying import (
    KVH_GYRO_RANGE_DPS,
    METHODS,
    align_swaying_block,
    grade_bias_prior,
    minimum_duration_s,
)
from northfinder.config import SwayingConfig
from northfinder.constants import DEG, STANDARD_GRAVITY_M_S2, wrap_deg_180
from northfinder.devices import registry
from northfinder.errors import DeviceError, InputError
from northfinder.report import report_axes, save_report
from northfinder.rundir import CONFIG, IMU_RAW, RunDir, jsonable
from northfinder.runs import base
from northfinder.simulate import SimulatorProcess, firmware_sim_argv
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
class ShipSim:
    """firmware-sim `--scenario ship`: the IMU alone at a lever arm on a swaying ship."""

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

    def argv(self) -> list[str]:
        return firmware_sim_argv(
            {
                "--scenario": "ship",
                "--sway": self.sway,
                "--lever-arm": self.lever_arm_m,
                "--heading": float(self.heading_deg),
                "--latitude": float(self.latitude_deg),
                "--grade": self.grade,
                "--seed": int(self.seed),
                "--time-scale": float(self.time_scale),
                "--truth-log": self.truth_log or None,
                "--config": self.config or None,
            },
            self.faults,
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "scenario": "ship",
            "sway": self.sway,
            "lever_arm_m": list(self.lever_arm_m),
            "heading_deg": self.heading_deg,
            "latitude_deg": self.latitude_deg,
            "grade": self.grade,
            "seed": self.seed,
            "time_scale": self.time_scale,
            "faults": list(self.faults),
        }


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


def check_stream(block: Any, port: str) -> None:
    """Refuse early what the alignment cannot use: no valid accelerometers (KVH status bits 4–6,
    docs/PROTOCOLS.md §2, or all-zero fields) and gyros at the end of their range."""
    status = np.asarray(block.status, dtype=np.int64)
    if len(status) and (np.mean(((status >> 4) & 0b111) == 0b111) < 0.5 or not np.any(block.accel_g)):
        raise DeviceError(
            "imu",
            port,
            "reports no valid accelerometers (status bits 4–6 clear): the swaying "
            "alignment needs a 3-axis gyro + accelerometer IMU (KVH 1750/1760/1775)",
        )
    peak = float(np.max(np.abs(block.gyro_rad_s))) / DEG if len(status) else 0.0
    if peak >= GYRO_SATURATION_FRACTION * KVH_GYRO_RANGE_DPS:
        raise InputError(
            f"gyro reached {peak:.1f} °/s, the ±{KVH_GYRO_RANGE_DPS:g} °/s range of the IMU on "
            f"{port}: the sway saturates the gyro — align in calmer sea or with a wider-range IMU"
        )


def acquire(
    rd: RunDir,
    *,
    imu_port: str,
    rate_hz: float,
    duration_s: float,
    settings: dict[str, Any],
    baudrate: int = 921600,
    imu_model: str = "",
    configure_imu: bool = False,
    progress: base.WindowProgress | None = None,
    config_extra: dict[str, Any] | None = None,
) -> Window:
    """Read `duration_s` device seconds (samples + lost samples over the rate) from the IMU; raw bytes
    go to imu.raw as they arrive, the window's index range to events.jsonl. A signal ends the
    reading early (`Window.stop` says which). `settings`: what the estimator needs (latitude,
    method, sway period, simulate) — stored in the start event so replay finds it."""
    rd.write_json(CONFIG, {"kind": KIND, "argv": sys.argv, **settings, **(config_extra or {})})
    stop = StopFlag()
    blocks: list[Any] = []
    with stop.installed():
        with base.guard(
            "imu",
            imu_port,
            lambda: registry.open_device("imu", {"model": imu_model, "port": imu_port, "baudrate": baudrate},
                                         rd.imu_raw_path, rate_hz=rate_hz),
        ) as imu:
            if configure_imu:
                imu.configure_for_run(None)  # read rate and gyro format back: the decoder must know them
            start = base.start_event(KIND, duration_s, imu_port, imu, **settings)
            rd.log_event(start)
            with base.window_view(progress, duration_s) as view:
                for done_s in base.read_imu_window(
                    imu, duration_s, stop, blocks, check=lambda b: check_stream(b, imu_port)
                ):
                    st = imu.stats
                    view.show(
                        done_s,
                        f"{done_s:6.1f}/{duration_s:g} s  lost {st.lost_samples}  bad CRC {st.bad_crc}  "
                        f"resyncs {st.resyncs}",
                    )
            rate = imu.rate_hz
            stats = imu.stats.as_dict()
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
    coarse = coarse_align(block.gyro_rad_s, block.accel_g, rate, lat)
    still = bool(coarse.diagnostics["base_still"])
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
            "coarse": {
                "heading_deg": coarse.heading_deg,
                "heading_std_deg": coarse.heading_std_deg if still else None,
                "pitch_deg": coarse.pitch_deg,
                "roll_deg": coarse.roll_deg,
                "note": "static analytic coarse alignment (window means); σ: the still-base noise limit"
                if still
                else "static analytic coarse alignment (window means); no σ: the base moves, the "
                "window-mean rate carries the sway, not the Earth rate",
                **coarse.diagnostics,
            },
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
    block, cut = base.before_unknown_gap(block)
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


def write_swaying_report(result: dict[str, Any], resid: dict[str, np.ndarray], path: str | Path) -> Path:
    """report.png: the body rates (the sway), the cone-fit residuals, the result and its truth."""
    fig, axes = report_axes(2, (9, 7))
    ax = axes[0]
    for j, name in enumerate("xyz"):
        ax.plot(resid["t_gyro_s"], resid["gyro_dps"][:, j], lw=0.6, label=f"gyro {name}")
    ax.set_ylabel("body rate [deg/s]")
    ax.set_xlabel("device time since the first sample [s]")
    title = (
        f"align --mode swaying ({result['method']}): {result['heading_deg']:.3f}° ± "
        f"{result['heading_std_deg']:.3f}° (1σ)"
    )
    if "truth" in result:
        title += f", truth {result['truth']['heading_deg']:.3f}°, error {result['error_deg']:+.3f}°"
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    ax = axes[1]
    for j, name in enumerate(("x", "y", "z")):
        ax.plot(resid["t_s"], resid["residual_ug"][:, j], marker=".", label=f"i_b0 {name}")
    ax.set_ylabel("cone-fit residual [µg]")
    ax.set_xlabel("window centre, device time [s]")
    ax.set_title(
        "smoothed specific force in i_b0 − the fitted Earth-rate cone and lever-arm sway (the fit's windows)",
        fontsize=9,
    )
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    return save_report(fig, path)


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
    "result_from_run",
    "write_swaying_report",
]
