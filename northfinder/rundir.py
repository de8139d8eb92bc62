"""The run directory: raw logs flushed position by position, the events log, result.json, replay.

Layout (file names are fixed so that `northfinder replay RUN_DIR` finds them)::

    config.json      the configuration used (bench tables, and the simulator's truth if simulated)
    imu.raw          the IMU's bytes exactly as they arrived (written by the Imu driver)
    can.asc          every CAN frame, python-can ASCII log (written by the Accelerometer driver)
    turntable.log    the stage's command transcript (written by the Turntable driver)
    events.jsonl     one JSON object a line: start, one per position (sample ranges), end/abort
    result.json      the result (docs/result-schema.md)
    report.png       the plots (northfinder.report)

A run resumed with `northfinder find --resume RUN_DIR` is a second *session*: its devices are
new streams (the IMU's sample counter and the CAN counter start again), so it writes its own
`imu-2.raw`, `can-2.asc`, `turntable-2.log` (session k: `-k`), and its `start` event says which;
replay decodes each session's logs for the position events that follow its start event.

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
    invalid_samples: dict[str, int] = field(default_factory=dict)
    """IMU gyro samples flagged not valid (status bit cleared) and left out, per gyro axis the unit
    has ("gx", "gy", "gz"); an axis the unit lacks has a NaN mean (None in JSON)."""


def _column_mean_std(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # Contiguous per-axis rows: numpy's pairwise summation then runs in one fixed order whatever
    # the caller's memory layout, which is what makes live and replay means bit-identical.
    # NaN marks a sample flagged not valid: each axis is averaged over its own valid samples.
    rows = np.ascontiguousarray(np.asarray(values, dtype=np.float64).T)
    mean = np.full(rows.shape[0], np.nan)
    std = np.full(rows.shape[0], np.nan)
    for k, row in enumerate(rows):
        ok = row[~np.isnan(row)]
        if ok.size:
            mean[k] = ok.mean()
            std[k] = ok.std(ddof=1) if ok.size > 1 else 0.0
    return mean, std


def position_means(
    table_angle_deg: float,
    gyro_rad_s: np.ndarray,
    accel_g: np.ndarray,
    imu_lost: int,
    accel_lost: int,
    imu_rate_hz: float,
    gyro_axes: str = "xyz",
) -> PositionMeans:
    """Per-position means of the gyro [deg/h] and the accelerometer [g] from decoded samples.

    The one function both the live run and replay call. Duration is device time: samples
    (received and lost) over the IMU rate. Gyro samples flagged not valid are NaN and left out;
    they are counted per axis of `gyro_axes` (the axes the unit has, e.g. "y").
    """
    g_mean, g_std = _column_mean_std(gyro_rad_s)
    nan_count = np.isnan(np.asarray(gyro_rad_s, dtype=np.float64)).sum(axis=0)
    invalid = {f"g{a}": int(nan_count["xyz".index(a)]) for a in gyro_axes}
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
        invalid_samples=invalid,
    )


def _solve(positions: Sequence[PositionMeans], latitude_deg: float, method: str, height_m: float = 0.0):
    from northfinder.estimators.heading import solve_heading

    alpha = np.array([p.table_angle_deg for p in positions])
    gyro = np.array([p.gyro_dph for p in positions], dtype=float)
    accel = np.array([p.accel_g for p in positions])
    # Standard error of each position's mean from its own spread (white noise over the dwell),
    # over the samples each axis kept (those flagged not valid are left out).
    kept = [[p.samples - p.invalid_samples.get(f"g{a}", 0) for a in "xyz"] for p in positions]
    n_gyro = np.maximum(np.array(kept, dtype=float), 1.0)
    n_accel = np.array([max(p.accel_samples, 1) for p in positions], dtype=float)[:, None]
    gyro_se = np.array([p.gyro_std_dph for p in positions], dtype=float) / np.sqrt(n_gyro)
    accel_se = np.array([p.accel_std_g for p in positions]) / np.sqrt(n_accel)
    gyro, gyro_se = _gyro_axes_for_fit(gyro, gyro_se)
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


def _gyro_axes_for_fit(gyro_dph: np.ndarray, gyro_se_dph: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The gyro axes the unit has (finite at every position), shaped as solve_heading takes them:
    (n,) for a single gyro on y (the seed paper's), (n, 2) for x and y, (n, 3) for x y z."""
    has = np.all(np.isfinite(gyro_dph), axis=0)
    if has[0] and has[1]:
        cols = [0, 1, 2] if has[2] else [0, 1]
        return gyro_dph[:, cols], gyro_se_dph[:, cols]
    if has[1]:
        return gyro_dph[:, 1], gyro_se_dph[:, 1]
    axes = "".join(a for a, h in zip("xyz", has, strict=True) if h) or "none"
    raise InputError(f"the IMU's gyro axes ({axes}) cannot find north: it needs gyro y, or x and y")


def compute_result(
    positions: Sequence[PositionMeans],
    latitude_deg: float,
    method: str = "exact",
    *,
    height_m: float = 0.0,
    truth: dict[str, float] | None = None,
    complete: bool = True,
    positions_planned: int | None = None,
    faults: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The result dict (docs/result-schema.md) from per-position means: every method's heading,
    the tilt, the per-position data, the error against the truth for a simulated run, and what
    went wrong on the way (`faults`, from :func:`faults_summary` of the events log)."""
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
    if faults is not None:
        result["faults"] = faults
    if truth is not None:
        keys = ("heading_deg", "pitch_deg", "roll_deg", "latitude_deg")
        result["truth"] = {k: float(truth[k]) for k in keys}
        result["error_deg"] = float(wrap_deg_180(result["heading_deg"] - truth["heading_deg"]))
    return result


def session_file(name: str, session: int) -> str:
    """`imu.raw` for session 1, `imu-2.raw` for session 2 (a resumed run), …"""
    if int(session) <= 1:
        return name
    stem, dot, suffix = name.partition(".")
    return f"{stem}-{int(session)}{dot}{suffix}"


class RunDir:
    """A run directory being written (or read back). Each write is flushed and fsynced.

    `session` (1, or k for the k-th `--resume`) picks the raw log names (session_file)."""

    def __init__(self, path: str | Path, *, create: bool = True, session: int = 1):
        self.path = Path(path)
        self.session = int(session)
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
        return self.file(session_file(IMU_RAW, self.session))

    @property
    def can_log_path(self) -> Path:
        return self.file(session_file(CAN_LOG, self.session))

    @property
    def transcript_path(self) -> Path:
        return self.file(session_file(TRANSCRIPT, self.session))

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


_IMU_COUNTERS = ("frames", "bad_crc", "resyncs", "sequence_gaps", "lost_samples", "skipped_bytes")
_ACCEL_COUNTERS = ("pairs", "unpaired", "counter_gaps", "lost_samples", "emcy", "heartbeats", "malformed")


def faults_summary(events: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """What went wrong during a run and what was done about it, from its events log alone (the live
    run and replay both call this, so the result's `faults` replays exactly):

    - `remeasured`: every position measured again, with the attempt and the reason;
    - `stage_errors`: stage errors on moves (stall / following error) and the retry;
    - `imu`: the decoder's stream counters summed over sessions (bad CRC, resyncs, gaps, lost
      samples), the reconnects, and the samples lost inside the kept dwells;
    - `accel`: the node's counters, its emergencies, the kept dwells' lost samples, and the
      positions whose dwell saw no heartbeat (device time ≥ 2.5 heartbeat periods of 1 s);
    - `sessions`: how many times the run was started (1 + resumes).
    """
    stats = [e for e in events if e.get("event") == "stats"]
    kept = [e for e in events if e.get("event") == "position"]
    imu = {k: int(sum(int(e.get("imu", {}).get(k, 0)) for e in stats)) for k in _IMU_COUNTERS}
    imu["reconnects"] = int(sum(int(e.get("imu_reconnects", 0)) for e in stats))
    imu["stalls"] = int(sum(int(e.get("imu_stalls", 0)) for e in stats))
    imu["lost_in_dwells"] = int(sum(int(e["imu"]["lost"]) for e in kept))
    gyro_axes = next((str(e["imu_axes"]) for e in stats if "imu_axes" in e), "xyz")
    accel_axes = next((str(e["imu_accel_axes"]) for e in stats if "imu_accel_axes" in e), "xyz")
    imu["gyro_axes"], imu["accel_axes"] = gyro_axes, accel_axes
    names = [f"g{a}" for a in gyro_axes] + [f"a{a}" for a in accel_axes]
    imu["invalid_samples"] = {  # per axis the unit has: frames flagged not valid in the stream
        k: int(sum(int(e.get("imu", {}).get(f"invalid_{k}", 0)) for e in stats)) for k in names
    }
    imu["invalid_in_dwells"] = {  # per gyro axis: flagged samples left out of the kept dwells
        k: int(sum(int(e["imu"].get("invalid", {}).get(k, 0)) for e in kept)) for k in names if k[0] == "g"
    }
    accel: dict[str, Any] = {
        k: int(sum(int(e.get("accel", {}).get(k, 0)) for e in stats)) for k in _ACCEL_COUNTERS
    }
    accel["lost_in_dwells"] = int(sum(int(e["accel"]["lost"]) for e in kept))
    accel["emergencies"] = [m for e in stats for m in e.get("emergencies", [])]
    silent: list[int] = []
    rate_hz = 0.0
    for e in events:
        if e.get("event") == "start":
            rate_hz = float(e.get("accelerometer", {}).get("rate_hz") or 0.0)
        elif e.get("event") == "position" and rate_hz > 0 and e["accel"].get("heartbeats") == 0:
            if (e["accel"]["samples"] + e["accel"]["lost"]) / rate_hz >= 2.5:
                silent.append(int(e["index"]))
    accel["heartbeat_lost_positions"] = silent
    return {
        "sessions": max(1, sum(e.get("event") == "start" for e in events)),
        "remeasured": [
            {"index": int(e["index"]), "attempt": int(e["attempt"]), "reason": str(e["reason"])}
            for e in events
            if e.get("event") == "remeasure"
        ],
        "stage_errors": [
            {
                "target_deg": e.get("target_deg"),
                "attempt": int(e.get("attempt", 1)),
                "error": str(e.get("error")),
            }
            for e in events
            if e.get("event") == "stage_error"
        ],
        "imu": imu,
        "accel": accel,
    }


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


def _decode_session(rd: RunDir, session: int, start: dict[str, Any]) -> tuple[Any, Any]:
    """One session's IMU samples and accelerometer samples, decoded from its own raw logs."""
    from northfinder.drivers.accelerometer import decode_can_log
    from northfinder.drivers.imu import decode_imu_stream

    imu_cfg = start["imu"]
    raw_path = rd.file(session_file(IMU_RAW, session))
    raw = raw_path.read_bytes() if raw_path.exists() else b""
    block, _ = decode_imu_stream(raw, imu_cfg["rate_hz"], imu_cfg["rot_format"], imu_cfg["rot_units"])
    can_path = rd.file(session_file(CAN_LOG, session))
    accel_block = None
    if can_path.exists():
        accel_block, _ = decode_can_log(can_path, node_id=start["accelerometer"]["node_id"],
                                        layout=start["accelerometer"].get("layout"))
    return block, accel_block


def replay(path: str | Path, method: str | None = None) -> ReplayOutcome:
    """Recompute the result of a run from its raw logs alone.

    Decodes imu.raw and can.asc with the drivers' pure decoders, cuts them by the sample ranges in
    events.jsonl, and feeds the same per-position means and estimator as the live run.
    """
    rd = RunDir(path, create=False)
    events = rd.events()
    starts = [e for e in events if e.get("event") == "start"]
    if not starts:
        raise InputError(f"{rd.path}: {EVENTS} has no start event; the run never began")
    start = starts[0]
    pos_events = [e for e in events if e.get("event") == "position"]
    complete = any(e.get("event") == "end" and e.get("complete") for e in events)
    positions: list[PositionMeans] = []
    session = 0
    block = accel_block = None
    imu_cfg = start["imu"]
    for ev in events:
        if ev.get("event") == "start":
            session += 1
            imu_cfg = ev["imu"]
            block, accel_block = _decode_session(rd, session, ev)
            continue
        if ev.get("event") != "position" or block is None:
            continue
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
                ev["imu"].get("gyro_axes", "xyz"),
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
            faults=faults_summary(events),
        )
    return ReplayOutcome(result, complete, len(positions), planned, positions)
