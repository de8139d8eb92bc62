"""A resumed find's motion samples: the per-sample fit over its sessions (docs/estimators.md §10,
"Sessions").

`find --resume` opens a new session in the same run directory, with its own raw logs (imu-2.raw, …).
The sessions' IMU sample counters do not join: the counter restarts with each session (a new
firmware-sim process in simulation, a new power-on or a gap of host time on a bench) and nothing
device-side gives the offset — the KVH's sequence counter is 7 bits, it wraps every 128 samples.
So no sample index is invented across sessions: each session's samples are placed between its own
dwells (eq M1, as runs.find_motion does for one session) and the fit shares the Earth rate, the
misalignment and the wobble across sessions with a gyro bias per session
(estimators.motion_sessions). Live and replay call the same functions on the raw logs.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from northfinder.constants import DPH
from northfinder.devices import registry
from northfinder.errors import InputError
from northfinder.estimators.heading import HeadingSolution
from northfinder.estimators.motion_fit import RUN_TERMS, place_samples
from northfinder.estimators.motion_sessions import fit_motion_sessions
from northfinder.rundir import IMU_RAW, RunDir, session_file
from northfinder.runs.find_motion import gyro_fit_summary

SESSIONS_JOIN = (
    "none: each session's samples are placed between its own dwells and fitted with its own gyro bias "
    "(the Earth rate, misalignment and wobble shared); the IMU's sample counter restarts with each "
    "session and nothing device-side gives the offset between two sessions (the KVH's sequence "
    "counter is 7 bits, the gap between sessions is host time)"
)
"""What result.json says of how a resumed run's sessions were joined (docs/estimators.md §10)."""


def _session_events(events: Sequence[dict[str, Any]]) -> list[tuple[dict[str, Any], list[dict[str, Any]]]]:
    """(start event, the rests it measured: positions and the `returned` rest) of each session."""
    out: list[tuple[dict[str, Any], list[dict[str, Any]]]] = []
    for e in events:
        if e.get("event") == "start":
            out.append((e, []))
        elif e.get("event") in ("position", "returned") and out:
            out[-1][1].append(e)
    return out


def session_motion_samples(rd: RunDir, events: Sequence[dict[str, Any]]) -> tuple[list[tuple], str | None]:
    """Each session's placed samples (alpha_deg, omega_dps, gyro_dph, counts + "session") as
    motion_samples gives them for a one-session run — the samples between two dwells of the same
    session only — or ([], why not). A session with fewer than two rests adds nothing (its own
    bias absorbs a single angle) and is counted in `sessions_unused`."""
    parts: list[tuple] = []
    why = "no session with two dwells and a gyro z"
    for k, (start, rests) in enumerate(_session_events(events), 1):
        if len(rests) < 2:
            continue
        raw_path = rd.file(session_file(IMU_RAW, k))
        if not raw_path.exists():
            why = f"no {raw_path.name}"
            continue
        imu_cfg = start["imu"]
        decoder = registry.decoder_for("imu", imu_cfg.get("model"))
        block, _ = decoder.decode_log(raw_path.read_bytes(), imu_cfg)
        gyro = np.asarray(block.gyro_rad_s, dtype=float) / DPH
        if gyro.size == 0 or not np.any(np.isfinite(gyro[:, 2])):
            why = "no gyro z: the table angle between dwells is unknown"
            continue
        dwells = [(e["imu"]["first_index"], e["imu"]["last_index"], e["table_angle_deg"]) for e in rests]
        rate_hz = float(imu_cfg["rate_hz"])
        alpha, omega, placed, counts = place_samples(block.sample_index, gyro, dwells, rate_hz)
        counts["session"] = k
        counts["dwells"] = len(rests)
        span = max(d[1] for d in dwells) - min(d[0] for d in dwells) + 1
        counts["fit_span_device_s"] = float(span) / rate_hz
        counts["through_return"] = any(e.get("event") == "returned" for e in rests)
        parts.append((alpha, omega, placed, counts))
    return parts, (None if parts else why)


def sessions_motion_fit_result(rd: RunDir, events: Sequence[dict[str, Any]], sol: HeadingSolution,
                               height_m: float = 0.0) -> dict[str, Any]:
    """motion_fit_result of a resumed run: every session's placed samples in one fit with a gyro
    bias per session (estimators.motion_fit.fit_motion_sessions); `sessions` lists what each gave
    and `join` says how the sessions were joined (SESSIONS_JOIN)."""
    parts, why = session_motion_samples(rd, events)
    if not parts:
        return {"available": False, "reason": f"a resumed run: {why}"}
    alpha, omega, gyro = (np.concatenate([p[k] for p in parts]) for k in range(3))
    session = np.concatenate([np.full(p[0].size, p[3]["session"]) for p in parts])
    axes = ("x", "y") if np.all(np.isfinite(gyro[:, 0])) else ("y",)
    cols = [0, 1] if axes == ("x", "y") else [1]
    try:
        fit, kept, disturbed = fit_motion_sessions(alpha, omega, gyro[:, cols], session, axes,
                                                   terms=RUN_TERMS)
    except InputError as exc:
        return {"available": False, "reason": f"a resumed run: {exc}"}
    rate_hz = float(next(e for e in events if e.get("event") == "start")["imu"]["rate_hz"])
    n_sessions = sum(e.get("event") == "start" for e in events)
    sessions = [{"session": int(p[3]["session"]), "dwells": int(p[3]["dwells"]), "rest": int(p[3]["rest"]),
                 "motion": int(p[3]["motion"]), "stretches_dropped": int(p[3]["stretches_dropped"]),
                 "bias_dph": {ax: float(fit.coef(f"R_{ax}@{p[3]['session']}")[0]) for ax in axes}}
                for p in parts]
    counts = {k: int(sum(p[3][k] for p in parts)) for k in ("rest", "motion", "stretches_dropped")}
    samples = {**counts, "stretches_disturbed": disturbed,
               "fit_span_device_s": float(sum(p[3]["fit_span_device_s"] for p in parts)),
               "through_return": any(p[3]["through_return"] for p in parts),
               "motion": int(np.count_nonzero(kept & (omega != 0))),
               "used_device_s": float(np.count_nonzero(kept)) / rate_hz,
               "sessions_unused": n_sessions - len(parts)}
    return gyro_fit_summary(fit, axes, sol, height_m, samples, {"sessions": sessions, "join": SESSIONS_JOIN})


def sessions_report_samples(rd: RunDir, events: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """report.png's samples (runs.find_motion.report_samples) of a resumed run: every session's
    placed samples one after the other, and where each later session starts on that axis
    (`session_starts_s`: the samples' own count, not the host time between the sessions)."""
    parts, _ = session_motion_samples(rd, events)
    start = next((e for e in events if e.get("event") == "start"), None)
    if not parts or start is None:
        return None
    rate_hz = float(start["imu"]["rate_hz"])
    sizes = np.cumsum([p[0].size for p in parts])
    starts = [(int(n) / rate_hz, int(p[3]["session"])) for n, p in zip(sizes[:-1], parts[1:], strict=True)]
    return {"alpha_deg": np.concatenate([p[0] for p in parts]),
            "omega_dps": np.concatenate([p[1] for p in parts]),
            "gyro_dph": np.concatenate([p[2] for p in parts]), "rate_hz": rate_hz, "session_starts_s": starts}
