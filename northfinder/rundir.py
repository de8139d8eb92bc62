"""The run directory: raw logs flushed position by position, the events log, result.json, replay.

Layout (file names are fixed so that `northfinder replay RUN_DIR` finds them)::

    config.json      the configuration used (bench tables, and the simulator's truth if simulated)
    imu.raw          the IMU's bytes exactly as they arrived (written by the Imu driver)
    can.asc          every CAN frame, python-can ASCII log (written by the Accelerometer driver)
    turntable.log    the stage's command transcript (written by the Turntable driver)
    events.jsonl     one JSON object a line: start, one per position (sample ranges), end/abort
    result.json      the result (docs/result-schema.md)
    report.png       the plots (northfinder.report)

The live run and replay compute the per-position means through the same function
(:func:`position_means`) from the same decoded arrays, so replay reproduces the live numbers
bit for bit.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from northfinder.constants import DPH, wrap_deg_180
from northfinder.errors import InputError

IMU_RAW = "imu.raw"
CAN_LOG = "can.asc"
TRANSCRIPT = "turntable.log"
EVENTS = "events.jsonl"
CONFIG = "config.json"
RESULT = "result.json"
REPORT = "report.png"


@dataclass
class PositionMeans:
    """What one table position contributes to the fit: means, spreads and sample counts."""

    table_angle_deg: float
    gyro_dph: list[float]
    gyro_std_dph: list[float]
    """Sample standard deviation of each gyro axis over the dwell [deg/h]."""
    accel_g: list[float]
    accel_std_g: list[float]
    samples: int
    lost_samples: int
    accel_samples: int
    accel_lost_samples: int
    duration_device_s: float


def _column_mean_std(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Contiguous per-axis rows: numpy's pairwise summation then runs in one fixed order whatever
    # the caller's memory layout, which is what makes live and replay means bit-identical.
    rows = np.ascontiguousarray(np.asarray(values, dtype=np.float64).T)
    if rows.shape[1] == 0:
        nan = np.full(rows.shape[0], np.nan)
        return nan, nan
    mean = rows.mean(axis=1)
    std = rows.std(axis=1, ddof=1) if rows.shape[1] > 1 else np.zeros(rows.shape[0])
    return mean, std


def position_means(
    table_angle_deg: float,
    gyro_rad_s: np.ndarray,
    accel_g: np.ndarray,
    imu_lost: int,
    accel_lost: int,
    imu_rate_hz: float,
) -> PositionMeans:
    """Per-position means of the gyro [deg/h] and the accelerometer [g] from decoded samples.

    The one function both the live run and replay call. Duration is device time: samples
    (received and lost) over the IMU rate.
    """
    g_mean, g_std = _column_mean_std(gyro_rad_s)
    a_mean, a_std = _column_mean_std(accel_g)
    n_imu = int(np.asarray(gyro_rad_s).shape[0])
    return PositionMeans(
        table_angle_deg=float(table_angle_deg),
        gyro_dph=(g_mean / DPH).tolist(),
        gyro_std_dph=(g_std / DPH).tolist(),
        accel_g=a_mean.tolist(),
        accel_std_g=a_std.tolist(),
        samples=n_imu,
        lost_samples=int(imu_lost),
        accel_samples=int(np.asarray(accel_g).shape[0]),
        accel_lost_samples=int(accel_lost),
        duration_device_s=(n_imu + int(imu_lost)) / float(imu_rate_hz),
    )


def _solve(positions: Sequence[PositionMeans], latitude_deg: float, method: str, height_m: float = 0.0):
    from northfinder.estimators.heading import solve_heading

    alpha = np.array([p.table_angle_deg for p in positions])
    gyro = np.array([p.gyro_dph for p in positions])
    accel = np.array([p.accel_g for p in positions])
    # Standard error of each position's mean from its own spread (white noise over the dwell).
    n_gyro = np.array([max(p.samples, 1) for p in positions], dtype=float)[:, None]
    n_accel = np.array([max(p.accel_samples, 1) for p in positions], dtype=float)[:, None]
    gyro_se = np.array([p.gyro_std_dph for p in positions]) / np.sqrt(n_gyro)
    accel_se = np.array([p.accel_std_g for p in positions]) / np.sqrt(n_accel)
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


def compute_result(
    positions: Sequence[PositionMeans],
    latitude_deg: float,
    method: str = "exact",
    *,
    height_m: float = 0.0,
    truth: dict[str, float] | None = None,
    complete: bool = True,
    positions_planned: int | None = None,
) -> dict[str, Any]:
    """The result dict (docs/result-schema.md) from per-position means: every method's heading,
    the tilt, the per-position data, and the error against the truth for a simulated run."""
    if len(positions) < 3:
        raise InputError(f"only {len(positions)} positions measured; a heading needs at least 3")
    sol = _solve(positions, latitude_deg, method, height_m)
    result: dict[str, Any] = {
        "schema": "northfinder.result/1",
        "complete": bool(complete),
        "positions_planned": int(positions_planned if positions_planned is not None else len(positions)),
        "positions_measured": len(positions),
        "method": method,
        "heading_deg": float(sol.heading_deg),
        "heading_std_deg": float(sol.heading_std_deg),
        "methods": {name: {"heading_deg": float(h)} for name, h in sol.methods.items()},
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
    if truth is not None:
        keys = ("heading_deg", "pitch_deg", "roll_deg", "latitude_deg")
        result["truth"] = {k: float(truth[k]) for k in keys}
        result["error_deg"] = float(wrap_deg_180(result["heading_deg"] - truth["heading_deg"]))
    return result


class RunDir:
    """A run directory being written (or read back). Each write is flushed and fsynced."""

    def __init__(self, path: str | Path, *, create: bool = True):
        self.path = Path(path)
        if create:
            try:
                self.path.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                msg = f"--out {self.path}: cannot create the run directory ({exc.strerror})"
                raise InputError(msg) from None
        elif not self.path.is_dir():
            raise InputError(f"{self.path}: no such run directory")

    # -- paths -------------------------------------------------------------------------------
    def file(self, name: str) -> Path:
        return self.path / name

    @property
    def imu_raw_path(self) -> Path:
        return self.file(IMU_RAW)

    @property
    def can_log_path(self) -> Path:
        return self.file(CAN_LOG)

    @property
    def transcript_path(self) -> Path:
        return self.file(TRANSCRIPT)

    @property
    def report_path(self) -> Path:
        return self.file(REPORT)

    # -- writing -----------------------------------------------------------------------------
    def write_json(self, name: str, data: dict[str, Any]) -> Path:
        """Write a JSON file atomically (temp file + rename) so a reader never sees half of it."""
        target = self.file(name)
        tmp = target.with_suffix(target.suffix + ".tmp")
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(jsonable(data), fh, indent=2, allow_nan=False)
            fh.write("\n")
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
        return target

    def log_event(self, event: dict[str, Any]) -> None:
        """Append one event line to events.jsonl and push it to disk."""
        with open(self.file(EVENTS), "a", encoding="utf-8") as fh:
            fh.write(json.dumps(jsonable(event), allow_nan=False) + "\n")
            fh.flush()
            os.fsync(fh.fileno())

    # -- reading -----------------------------------------------------------------------------
    def read_json(self, name: str) -> dict[str, Any]:
        try:
            return json.loads(self.file(name).read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"{self.path}: {name} is missing; not a northfinder run directory?") from None

    def events(self) -> list[dict[str, Any]]:
        """Every event; a torn last line (power cut mid-write) is ignored."""
        try:
            lines = self.file(EVENTS).read_text(encoding="utf-8").splitlines()
        except FileNotFoundError:
            raise InputError(f"{self.path}: {EVENTS} is missing; not a northfinder run directory?") from None
        out = []
        for line in lines:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
        return out


def jsonable(obj: Any) -> Any:
    """numpy scalars/arrays → Python; NaN/inf → None (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


@dataclass
class ReplayOutcome:
    """What replay found: the recomputed result (None if fewer than 3 positions) and the state."""

    result: dict[str, Any] | None
    complete: bool
    positions_measured: int
    positions_planned: int
    positions: list[PositionMeans] = field(default_factory=list)


def replay(path: str | Path, method: str | None = None) -> ReplayOutcome:
    """Recompute the result of a run from its raw logs alone.

    Decodes imu.raw and can.asc with the drivers' pure decoders, cuts them by the sample ranges in
    events.jsonl, and feeds the same per-position means and estimator as the live run.
    """
    from northfinder.drivers.accelerometer import decode_can_log
    from northfinder.drivers.imu import decode_imu_stream

    rd = RunDir(path, create=False)
    events = rd.events()
    start = next((e for e in events if e.get("event") == "start"), None)
    if start is None:
        raise InputError(f"{rd.path}: {EVENTS} has no start event; the run never began")
    pos_events = [e for e in events if e.get("event") == "position"]
    complete = any(e.get("event") == "end" and e.get("complete") for e in events)
    imu_cfg = start["imu"]
    raw = rd.imu_raw_path.read_bytes() if rd.imu_raw_path.exists() else b""
    block, _ = decode_imu_stream(raw, imu_cfg["rate_hz"], imu_cfg["rot_format"], imu_cfg["rot_units"])
    if rd.can_log_path.exists():
        accel_block, _ = decode_can_log(rd.can_log_path, node_id=start["accelerometer"]["node_id"])
    else:
        accel_block = None
    positions: list[PositionMeans] = []
    for ev in pos_events:
        i0, i1 = ev["imu"]["first_index"], ev["imu"]["last_index"]
        sel = (block.sample_index >= i0) & (block.sample_index <= i1)
        if accel_block is not None:
            c0, c1 = ev["accel"]["first_counter"], ev["accel"]["last_counter"]
            asel = (accel_block.counter >= c0) & (accel_block.counter <= c1)
            accel = accel_block.accel_g[asel]
        else:
            accel = np.empty((0, 3))
        positions.append(
            position_means(
                ev["table_angle_deg"],
                block.gyro_rad_s[sel],
                accel,
                ev["imu"]["lost"],
                ev["accel"]["lost"],
                imu_cfg["rate_hz"],
            )
        )
    planned = int(start.get("positions_planned", len(pos_events)))
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
        )
    return ReplayOutcome(result, complete, len(positions), planned, positions)
