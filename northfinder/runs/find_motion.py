"""The stop-and-go find's motion samples: the per-sample fit over the whole run, from imu.raw.

While the table turns and settles between two dwells the horizontal gyros still see the Earth
rate at the table's current angle; with a z gyro each of those samples is placed at its own angle
(estimators.motion_fit.place_samples, docs/estimators.md §10, eq M1) and the harmonic fit takes
every sample with the table-rate term δ·ω per axis and the stage's wobble (eq M2/M2b, `RUN_TERMS`);
a stretch between dwells that the model does not explain (a knock while the table turned) is left
out (motion_fit.fit_motion_screened). The tilt still comes
from the dwells' accelerometer fit. Live and replay call the same function on the raw log, so a
replayed result equals the live one bit for bit.

Why from the log and not from the drivers' arrays: the sequencer reads the samples between dwells
in pieces (settle windows, margins, what it drops before a move), and the raw log is the one
place that holds them all in order.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from northfinder.constants import DPH
from northfinder.devices import registry
from northfinder.errors import InputError
from northfinder.estimators.heading import HeadingSolution, heading_with_gyro_fit
from northfinder.estimators.motion_fit import RUN_TERMS, fit_motion_screened, place_samples
from northfinder.rundir import IMU_RAW, RunDir


def motion_samples(rd: RunDir, events: Sequence[dict[str, Any]], block: Any = None) -> tuple[Any, str | None]:
    """(alpha_deg, omega_dps, gyro_dph, counts) of a one-session run, or (None, why not).
    `block`: imu.raw already decoded (replay has it), else it is decoded here."""
    starts = [e for e in events if e.get("event") == "start"]
    if len(starts) != 1:
        return None, "a resumed run: its sessions' sample counters do not join"
    positions = [e for e in events if e.get("event") == "position"]
    if len(positions) < 3:
        return None, "fewer than 3 positions"
    imu_cfg = starts[0]["imu"]
    if block is None:
        raw_path = rd.file(IMU_RAW)
        if not raw_path.exists():
            return None, f"no {IMU_RAW}"
        decoder = registry.decoder_for("imu", imu_cfg.get("model"))
        block, _ = decoder.decode_log(raw_path.read_bytes(), imu_cfg)
    gyro = np.asarray(block.gyro_rad_s, dtype=float) / DPH
    if gyro.size == 0 or not np.any(np.isfinite(gyro[:, 2])):
        return None, "no gyro z: the table angle between dwells is unknown"
    # the rests at the positions, and the one after the return when the run pinned it (`returned`)
    returned = [e for e in events if e.get("event") == "returned"]
    rests = positions + returned
    dwells = [(e["imu"]["first_index"], e["imu"]["last_index"], e["table_angle_deg"]) for e in rests]
    rate_hz = float(imu_cfg["rate_hz"])
    alpha, omega, placed, counts = place_samples(block.sample_index, gyro, dwells, rate_hz)
    idx = block.sample_index
    counts["fit_span_device_s"] = float(max(d[1] for d in dwells) - min(d[0] for d in dwells) + 1) / rate_hz
    counts["before_first_dwell_s"] = float(min(d[0] for d in dwells) - idx[0]) / rate_hz
    counts["through_return"] = bool(returned)
    return (alpha, omega, placed, counts), None


def motion_fit_result(rd: RunDir, events: Sequence[dict[str, Any]], sol: HeadingSolution,
                      height_m: float = 0.0, block: Any = None) -> dict[str, Any]:
    """The per-sample fit's heading, 1σ and what it used (`available` False with the reason when
    the run cannot give one). A resumed run: runs.find_sessions."""
    if sum(e.get("event") == "start" for e in events) > 1:
        from northfinder.runs.find_sessions import sessions_motion_fit_result

        return sessions_motion_fit_result(rd, events, sol, height_m)
    placed, why = motion_samples(rd, events, block)
    if placed is None:
        return {"available": False, "reason": why}
    alpha, omega, gyro, counts = placed
    axes = ("x", "y") if np.all(np.isfinite(gyro[:, 0])) else ("y",)
    cols = [0, 1] if axes == ("x", "y") else [1]
    try:
        fit, kept, disturbed = fit_motion_screened(alpha, omega, gyro[:, cols], axes, terms=RUN_TERMS)
    except InputError as exc:
        return {"available": False, "reason": str(exc)}
    rate_hz = float(next(e for e in events if e.get("event") == "start")["imu"]["rate_hz"])
    samples = {**counts, "stretches_disturbed": disturbed,
               "motion": int(np.count_nonzero(kept & (omega != 0))),
               "used_device_s": float(np.count_nonzero(kept)) / rate_hz}
    return gyro_fit_summary(fit, axes, sol, height_m, samples)


def gyro_fit_summary(fit: Any, axes: Sequence[str], sol: HeadingSolution, height_m: float,
                     samples: dict[str, Any], extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """result.json's `motion_fit` of a per-sample gyro fit (one session, several, or fed as the
    samples arrived): the heading from it, its terms and what it used; `extra` goes before the
    residuals (the sessions of a resumed run)."""
    heading, std, methods = heading_with_gyro_fit(sol, fit, height_m=height_m)
    return {
        "available": True,
        "heading_deg": heading,
        "heading_std_deg": std,
        "methods": methods,
        "terms": list(RUN_TERMS),
        "misalignment_dph_per_dps": {ax: float(fit.coef(f"d_{ax}")[0]) for ax in axes},
        "wobble_dph_per_dps": {k: float(fit.coef(k)[0]) for k in ("w_c", "w_s")},
        "samples": samples,
        **(extra or {}),
        "residual_rms_dph": {k: float(v[0]) for k, v in fit.residual_rms.items()},
    }


def report_samples(rd: RunDir, block: Any = None) -> dict[str, Any] | None:
    """The samples the per-sample fit used, for report.png's sample panel (northfinder.report), or
    None when the run has none (plan positions, no gyro z); a resumed run's sessions one after the other."""
    events = rd.events()
    if sum(e.get("event") == "start" for e in events) > 1:
        from northfinder.runs.find_sessions import sessions_report_samples

        return sessions_report_samples(rd, events)
    placed, _ = motion_samples(rd, events, block)
    start = next((e for e in events if e.get("event") == "start"), None)
    if placed is None or start is None:
        return None
    alpha, omega, gyro, _ = placed
    rate_hz = float(start["imu"]["rate_hz"])
    return {"alpha_deg": alpha, "omega_dps": omega, "gyro_dph": gyro, "rate_hz": rate_hz}
