"""A run directory as a history row: every column derived from the run's own files
(result.json, config.json, events.jsonl, campaign.json), so any copy re-indexes to the same row.

The row's key is the run's id: `history.json` in the run directory keeps it once the run was
recorded (with where its row went); a run never recorded gets the id a UUID5 of host and path
gives, so indexing it twice gives one row.
"""

from __future__ import annotations

import json
import math
import os
import socket
import uuid
from collections.abc import Callable, Iterable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from northfinder import runkinds

ENV_UNIT = "NORTHFINDER_UNIT"
"""Environment variable giving the unit label when a run's command line had no `--unit`."""
CAMPAIGN_JSON = runkinds.CAMPAIGN_JSON
CAMPAIGN_STATE = "campaign-state.json"
RECORD_JSON = "history.json"
"""In a run directory: the run's id and where its history row went (docs/result-schema.md)."""


# ---------------------------------------------------------------------------------------------
# A run directory as a row
# ---------------------------------------------------------------------------------------------
def _read(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _start_event(run_dir: Path) -> dict[str, Any]:
    try:
        with open(run_dir / "events.jsonl", encoding="utf-8") as fh:
            for line in fh:
                try:
                    e = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if e.get("event") == "start":
                    return e
    except FileNotFoundError:
        pass
    return {}


def unit_from_argv(argv: Iterable[str] | None) -> str | None:
    """The value of `--unit X` / `--unit=X` in a saved command line."""
    args = list(argv or [])
    for k, a in enumerate(args):
        if a == "--unit" and k + 1 < len(args):
            return args[k + 1]
        if a.startswith("--unit="):
            return a.split("=", 1)[1]
    return None


def _faults(result: dict[str, Any]) -> dict[str, int]:
    """The non-zero fault counters of a find (re-measured positions, stage errors, lost samples,
    EMCY, resumed sessions) or an align (lost IMU samples)."""
    f = result.get("faults") or {}
    out: dict[str, int] = {}
    if f:
        imu, acc = f.get("imu", {}), f.get("accel", {})
        out = {
            "remeasured": len(f.get("remeasured", [])),
            "stage_errors": len(f.get("stage_errors", [])),
            "imu_lost": int(imu.get("lost_samples", 0)),
            "imu_bad_crc": int(imu.get("bad_crc", 0)),
            "accel_lost": int(acc.get("lost_samples", 0)),
            "emcy": int(acc.get("emcy", 0)),
            "sessions_resumed": int(f.get("sessions", 1)) - 1,
        }
    elif isinstance(result.get("imu"), dict):
        out = {"imu_lost": int(result["imu"].get("lost_samples", 0))}
    return {k: v for k, v in out.items() if v}


def _tilt_deg(result: dict[str, Any]) -> float | None:
    t = result.get("tilt")
    if isinstance(t, dict) and t.get("tilt_deg") is not None:
        return float(t["tilt_deg"])
    p, r = result.get("pitch_deg"), result.get("roll_deg")
    if p is None or r is None:
        return None
    c = max(-1.0, min(1.0, math.cos(math.radians(p)) * math.cos(math.radians(r))))
    return math.degrees(math.acos(c))


def _utc(start: dict[str, Any], fallback: Path) -> str:
    """The run's start time (UTC ISO) from its start event, else the file's modification time."""
    if start.get("utc"):
        d = datetime.fromisoformat(str(start["utc"]))
        return (d.replace(tzinfo=UTC) if d.tzinfo is None else d.astimezone(UTC)).isoformat()
    return datetime.fromtimestamp(fallback.stat().st_mtime, UTC).isoformat()


def row_from_run(run_dir: str | Path, unit: str | None = None) -> dict[str, Any] | None:
    """The history row of a completed run directory; None if it holds no complete result. The row
    is its kind's (northfinder.runkinds: find_row, align_row, campaign_row)."""
    d = Path(run_dir).resolve()
    return runkinds.kind_of(d).history_row(d, unit)


def find_row(run_dir: Path, unit: str | None = None) -> dict[str, Any] | None:
    """A find's row: a run row with its positions and dwell."""
    return _run_row(run_dir, unit, "find", _find_columns)


def _find_columns(result: dict[str, Any], config: dict[str, Any], start: dict[str, Any]) -> dict[str, Any]:
    """A find's own columns: positions measured and the dwell (the bench's [run], else the start event)."""
    run_cfg = (config.get("bench") or {}).get("run", {})
    return {"positions": result.get("positions_measured"),
            "dwell_s": run_cfg.get("dwell_s", start.get("dwell_s"))}


def align_row(run_dir: Path, unit: str | None = None) -> dict[str, Any] | None:
    """An alignment's row (swaying or GNSS): a run row without positions or dwell."""
    return _run_row(run_dir, unit, None, lambda *_: {"positions": None, "dwell_s": None})


def _run_row(
    d: Path, unit: str | None, kind_default: str | None, columns: Callable[..., dict[str, Any]]
) -> dict[str, Any] | None:
    """The row of a run directory holding one result.json; `columns(result, config, start event)`
    gives the kind's own columns (positions, dwell)."""
    result = _read(d / "result.json")
    if not result or not result.get("complete", False):
        return None
    config = _read(d / "config.json") or {}
    start = _start_event(d)
    parent = d.parent
    in_campaign = (parent / CAMPAIGN_JSON).exists() or (parent / CAMPAIGN_STATE).exists()
    return {
        **identity(d),
        "time_utc": _utc(start, d / "result.json"),
        "kind": str(result.get("kind") or config.get("kind") or kind_default or "find"),
        "unit": unit
        or unit_from_argv(config.get("argv"))
        or _campaign_unit(parent)
        or os.environ.get(ENV_UNIT, ""),
        "latitude_deg": result.get("latitude_deg"),
        **columns(result, config, start),
        "duration_s": result.get("duration_device_s"),
        "method": result.get("method"),
        "heading_deg": result.get("heading_deg"),
        "sigma_deg": result.get("heading_std_deg"),
        "error_deg": result.get("error_deg"),
        "tilt_deg": _tilt_deg(result),
        "faults": json.dumps(_faults(result), sort_keys=True),
        "campaign": str(parent) if in_campaign else None,
        "simulated": int(bool(config.get("simulate") or result.get("truth"))),
    }


def _campaign_unit(parent: Path) -> str | None:
    """The unit of the campaign a find belongs to (a resumed campaign's command line has none)."""
    c = _read(parent / CAMPAIGN_JSON)
    return (c or {}).get("unit") or None


def campaign_row(d: Path, unit: str | None = None) -> dict[str, Any] | None:
    """A finished campaign's row: the main method's mean deviation, observed σ and mean tilt."""
    c = _read(d / CAMPAIGN_JSON)
    if not c or not c.get("complete"):
        return None
    stats = c.get("statistics", {}).get(c.get("method", "exact"), {})
    plan = c.get("plan", {})
    return {
        **identity(d),
        "time_utc": str(c.get("started_utc")),
        "kind": "campaign",
        "unit": unit or c.get("unit") or os.environ.get(ENV_UNIT, ""),
        "latitude_deg": c.get("latitude_deg"),
        "positions": plan.get("positions"),
        "dwell_s": plan.get("dwell_s"),
        "duration_s": None,
        "method": c.get("method"),
        "heading_deg": None,
        "sigma_deg": stats.get("std_deg"),
        "error_deg": stats.get("mean_deg"),
        "tilt_deg": c.get("mean_tilt_deg"),
        "faults": json.dumps({"failed_finds": len(c["failed"])} if c.get("failed") else {}),
        "campaign": None,
        "simulated": int(bool(c.get("simulate"))),
    }


def run_id(run_dir: Path) -> str:
    """The run's id: the one its history.json keeps, else UUID5(host:path) — the same on every
    re-index of this directory on this host, distinct between benches."""
    kept = (_read(run_dir / RECORD_JSON) or {}).get("run_id")
    if kept:
        return str(kept)
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"northfinder-run://{socket.gethostname()}{run_dir}"))


def identity(run_dir: Path) -> dict[str, str]:
    """The key columns: run_id, the host that made the run (or indexed it), the directory."""
    kept = _read(run_dir / RECORD_JSON) or {}
    host = str(kept.get("host") or socket.gethostname())
    return {"run_id": run_id(run_dir), "host": host, "run_dir": str(run_dir)}


def write_record(run_dir: Path, row: dict[str, Any], where: dict[str, Any]) -> None:
    """history.json: the run's id and where its row went (`db`, `state` recorded|pending, `outbox`)."""
    record = {
        "run_id": row["run_id"],
        "host": row["host"],
        **where,
        "utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }
    tmp = run_dir / (RECORD_JSON + ".tmp")
    tmp.write_text(json.dumps(record, indent=1) + "\n", encoding="utf-8")
    os.replace(tmp, run_dir / RECORD_JSON)
