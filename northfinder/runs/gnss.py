"""`northfinder align --mode gnss`: acquisition, time alignment, result assembly and replay.

What: read a KVH format-A IMU and an NMEA GNSS receiver for a window of device time, keep their
raw bytes in the run directory as they arrive, then align with the paper's δsin/δcos filter
(northfinder.align.gnss_ins.align_gnss) and, on the same data, the small-angle filter
(northfinder.align.small_angle). The filters run once the window is complete (not live): the
progress bar shows device time, fixes and the stream counters.

Why here: the CLI (northfinder/cli/align_gnss.py) and `northfinder replay` share one function,
:func:`compute_gnss_result`, fed from the drivers' arrays live and from the pure decoders
(`decode_imu_stream`, `decode_nmea_log`) in replay — the same bytes give the same arrays, so the
replayed result is bit-identical.

Time alignment (IMU sample index ↔ GNSS time), docs/result-schema-align.md "## gnss":
- `data` (hardware and simulator, docs/gnss-alignment.md §12): the host estimate below refined from
  the data (align.time_offset: IMU heading change against GNSS course, lever arm as a nuisance);
  the simulator reports it against the truth log. When the data cannot tell: `host` / `truth-log`.
- simulator (`truth-log`): firmware-sim's truth log names the absolute sample k0 of the first
  IMU frame delivered to this client, so sample index i starts at device time (k0 + i)/rate; NMEA
  UTC − gnss_start_utc is device time. Exact.
- hardware (`host`): every chunk read from either port is stamped with the host's monotonic clock
  (`imu.rx`, `gnss.rx`: "host_s total_bytes" a line). Each chunk's last complete frame/fix gives
  host ≥ device + offset + latency; the lower envelope (minimum) of host − device time per stream
  estimates each offset, and their difference maps IMU samples to GNSS time. Limits: the GNSS
  sends an epoch's NMEA after computing it (typically 20–100 ms after the epoch, plus ~20 ms on the
  wire at 115200 baud) — this latency is not seen by the host and biases the mapping unless
  `[gnss] latency_s` is given; USB-serial adapters batch bytes (1–16 ms); clock drift between host
  and devices (tens of ppm: < 0.03 ms over 300 s) is ignored.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from northfinder.align.gnss_ins import GnssAlignConfig, GnssAlignResult, GnssSeries, ImuSeries, align_gnss
from northfinder.align.small_angle import align_gnss_small_angle
from northfinder.align.time_offset import NoTimeInformation, estimate_time_offset
from northfinder.config import GnssAlignmentConfig
from northfinder.constants import wrap_deg_180
from northfinder.devices import registry
from northfinder.devices.gnss import GnssFix, LocalEnu, fixes_to_arrays
from northfinder.errors import InputError
from northfinder.report import report_axes, save_report
from northfinder.rundir import CONFIG, IMU_RAW, RunDir, jsonable
from northfinder.runs import base
from northfinder.runs.base import TruthLog, read_truth_log

KIND = "align-gnss"
SCHEMA = "northfinder.align-gnss/1"
GNSS_NMEA = "gnss.nmea"
IMU_RX = "imu.rx"
GNSS_RX = "gnss.rx"
TRUTH_LOG = "truth.jsonl"
OWN_FILES = {CONFIG, IMU_RAW, IMU_RX, GNSS_NMEA, GNSS_RX, TRUTH_LOG}
"""What a run writes before its start event: a failed start that left only these is removed."""
DEFAULT_DURATION_S = GnssAlignmentConfig.duration_s  # [gnss_alignment]'s default (northfinder.config)
VEL_UP_STD_M_S = 100.0
"""NMEA carries no vertical speed (Up is 0 by convention): its σ says "not measured"."""
VEL_UNKNOWN_STD_M_S = 1000.0
"""An epoch whose RMC and VTG were both lost: its velocity row is 0 with this σ (position still used)."""
SMALL_ANGLE_HEADING_STD_DEG = 30.0
"""The small-angle filter needs a heading σ even when the heading is unknown (gnss_ins docs)."""


# ---------------------------------------------------------------------------------------------
# Host receive stamps (written by northfinder.transport.StampedTransport) and the pure alignment
# ---------------------------------------------------------------------------------------------
def read_stamps(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(host_s, total_bytes) of a stamp file; a torn last line is ignored."""
    host, total = [], []
    if path.exists():
        for line in path.read_text(encoding="ascii", errors="replace").splitlines():
            parts = line.split()
            if len(parts) == 2:
                try:
                    h, b = float(parts[0]), int(parts[1])
                except ValueError:
                    continue
                host.append(h)
                total.append(b)
    return np.asarray(host, dtype=float), np.asarray(total, dtype=np.int64)


def _chunks(raw: bytes, total: np.ndarray) -> list[bytes]:
    ends = np.minimum(total, len(raw))
    starts = np.concatenate([[0], ends[:-1]])
    return [raw[a:b] for a, b in zip(starts.tolist(), ends.tolist(), strict=True)]


def host_offsets(
    imu_raw: bytes,
    imu_stamps,
    nmea_raw: bytes,
    gnss_stamps,
    rate_hz: float,
    utc_ref_s: float,
    time_scale: float = 1.0,
    imu_last_index: int | None = None,
    gnss_last_s: float | None = None,
    imu_model: str | None = None,
    gnss_model: str | None = None,
) -> dict[str, Any]:
    """IMU index 0's start and GNSS time zero on one clock, from host receive stamps (lower envelope).

    A sample with index i ends at off_imu + (i+1)/rate and arrives later; the GGA of an epoch at
    GNSS time u (UTC − utc_ref_s) arrives after off_gnss + u. Host times are scaled by `time_scale`
    (a simulator running K× faster) so the offsets are in device seconds. Returns t0_s =
    off_imu − off_gnss, the start of sample 0 in GNSS time, and the median arrival delays (how
    much the minimum had to choose from). Only the window's samples (≤ imu_last_index) and
    epochs (≤ gnss_last_s) count. The logs are decoded by the recorded models' decoders.
    """
    h_i, b_i = imu_stamps
    h_g, b_g = gnss_stamps
    if len(h_i) == 0 or len(h_g) == 0:
        raise InputError("host time alignment needs the receive stamps imu.rx and gnss.rx; they are empty")
    imu_d = []
    chunks = list(_chunks(imu_raw, b_i))
    for h, index in zip(h_i, registry.decoder_for("imu", imu_model).index_chunks(chunks), strict=True):
        if len(index):
            last = int(index[-1])
            if imu_last_index is not None and last > imu_last_index:
                break
            imu_d.append(h * time_scale - (last + 1) / rate_hz)
    ends, u = registry.decoder_for("gnss", gnss_model).epoch_ends(nmea_raw, utc_ref_s)
    if gnss_last_s is not None:
        keep = u <= gnss_last_s + 1e-6
        ends, u = ends[keep], u[keep]
    # the chunk that completed each GGA: the first whose running byte total reaches its end
    j = np.searchsorted(b_g, ends, side="left")
    ok = j < len(h_g)
    gnss_d = h_g[j[ok]] * time_scale - u[ok]
    if not imu_d or not len(gnss_d):
        raise InputError("host time alignment: no IMU frame or no GNSS epoch in the receive stamps")
    off_i, off_g = float(np.min(imu_d)), float(np.min(gnss_d))
    return {
        "t0_s": off_i - off_g,
        "imu_delay_p50_s": float(np.median(imu_d) - off_i),
        "gnss_delay_p50_s": float(np.median(gnss_d) - off_g),
        "imu_chunks": len(imu_d),
        "gnss_epochs": int(len(gnss_d)),
    }


# ---------------------------------------------------------------------------------------------
# Result assembly: the one function live and replay call
# ---------------------------------------------------------------------------------------------
def gnss_series(fixes: list[GnssFix], utc_ref_s: float, pos_std_m, vel_std_m_s: float) -> GnssSeries:
    """Decoded fixes → the filter's GnssSeries: time since `utc_ref_s`, ENU about the first fix;
    Up velocity (not in NMEA) and lost velocities get a σ that says "not measured"."""
    arr = fixes_to_arrays(fixes)
    vel = arr.vel_enu_m_s.copy()
    vel_std = np.tile([vel_std_m_s, vel_std_m_s, VEL_UP_STD_M_S], (len(arr), 1))
    lost = ~np.isfinite(vel).all(axis=1)
    vel[lost] = 0.0
    vel_std[lost] = VEL_UNKNOWN_STD_M_S
    ref = arr.ref
    return GnssSeries(
        arr.time_s - utc_ref_s,
        arr.pos_enu_m,
        vel,
        np.tile(np.asarray(pos_std_m, float), (len(arr), 1)),
        vel_std,
        (ref.lat0_deg, ref.lon0_deg, ref.h0_m),
    )


STILL_SPEED_M_S = 0.5
"""GNSS speed above which the vehicle is taken to be moving: 10× the 0.05 m/s velocity noise."""


def check_still_start(fixes: list[GnssFix], t_s: np.ndarray, t_start_s: float, level_s: float) -> None:
    """The filter levels the IMU on the window's first `level_s` (gnss_ins.coarse_level): the
    vehicle must stand still then. InputError saying so if a fix in that span shows it moving."""
    sel = np.nonzero((t_s >= t_start_s) & (t_s <= t_start_s + level_s))[0]
    speeds = [fixes[i].speed_m_s for i in sel if fixes[i].speed_m_s is not None]
    if speeds and max(speeds) > STILL_SPEED_M_S:
        raise InputError(
            f"the vehicle moved during the first {level_s:g} s of the window (GNSS speed up to "
            f"{max(speeds):.1f} m/s): the alignment levels the IMU on a still start — start the run "
            "standing still"
        )


def _method_dict(res: GnssAlignResult, truth_heading_deg: float | None) -> dict[str, Any]:
    out = {
        "heading_deg": res.heading_deg,
        "heading_std_deg": res.heading_std_deg,
        "converged_after_s": res.converged_after_s,
        "lever_arm_m": res.lever_arm_m.tolist(),
    }
    if truth_heading_deg is not None:
        out["error_deg"] = float(wrap_deg_180(res.heading_deg - truth_heading_deg))
    return out


def _restart_dict(res: GnssAlignResult, t_start_imu: float) -> dict[str, Any] | None:
    """The unknown-heading restart (GnssAlignResult.restart) with its time from the first IMU sample."""
    if res.restart is None:
        return None
    return {**res.restart, "t_s": res.restart["t_s"] - t_start_imu}


def _time_below(t: np.ndarray, err: np.ndarray, thr: float) -> float | None:
    """First time after which |err| stays below thr to the end (None: not reached)."""
    bad = np.nonzero(np.abs(err) >= thr)[0]
    if len(t) == 0 or (len(bad) and bad[-1] == len(err) - 1):
        return None
    return float(t[bad[-1] + 1] if len(bad) else t[0])


def _initial_heading(flt: dict[str, Any], truth_start_deg: float | None) -> float:
    """The filters' start heading ψ0: --heading (a prior), the simulator's truth at the start +
    --heading-error, else 0° (unknown: the sin/cos filter's uniform prior ignores it)."""
    initial = flt.get("initial_heading_deg")
    if flt.get("heading_error_deg") is not None:
        if truth_start_deg is None:
            raise InputError(
                "--heading-error needs the simulator's truth log (the truth heading at the start)"
            )
        initial = (truth_start_deg + float(flt["heading_error_deg"])) % 360.0
    return float(initial if initial is not None else 0.0)


def imu_grade(start: dict[str, Any]) -> str | None:
    """The IMU grade when known: the simulator's (`simulate.grade`) or the run's `filter.imu_grade`;
    None on hardware without it (the filter then keeps its conservative default noise)."""
    return (start.get("simulate") or {}).get("grade") or start["filter"].get("imu_grade") or None


def _both_filters(
    imu: ImuSeries, gnss: GnssSeries, psi0: float, flt: dict[str, Any], grade: str | None = None
) -> tuple[GnssAlignResult, GnssAlignResult]:
    """The sin/cos heading filter (the result) and the small-angle filter, on the same data; the IMU
    noise of `grade` when it is known (GnssAlignConfig.for_imu_grade)."""
    heading_std = flt.get("heading_std_deg")
    cfg = GnssAlignConfig.for_imu_grade(
        grade,
        heading_std_deg=heading_std,
        lever_arm_b_m=tuple(flt["lever_arm_prior_m"]),
        lever_arm_std_m=float(flt["lever_arm_std_m"]),
    )
    main = align_gnss(imu, gnss, psi0, cfg)
    small_cfg = GnssAlignConfig(
        **{**cfg.__dict__, "heading_std_deg": heading_std or SMALL_ANGLE_HEADING_STD_DEG}
    )
    return main, align_gnss_small_angle(imu, gnss, psi0, small_cfg)


def _add_truth(
    result: dict[str, Any],
    hist: dict[str, Any],
    truth: TruthLog,
    main: GnssAlignResult,
    small: GnssAlignResult,
    gnss_origin: Any,
    t_start_imu: float,
    truth_start: float | None,
) -> None:
    """A simulated run: the truth at the last update, each filter's error and its time below 1° and
    0.5° (from the first IMU sample), the position and lever-arm errors."""
    h = main.history
    t_last = float(h.t_s[-1])
    truth_end = float(truth.heading_at(t_last))
    result["truth"] = {
        "heading_deg": truth_end,
        "heading_at_start_deg": truth_start,
        "pitch_deg": float(truth.at(t_last, "pitch_deg")),
        "roll_deg": float(truth.at(t_last, "roll_deg")),
        "lever_arm_m": truth.lever_arm_m,
        "t_device_s": t_last,
    }
    result["error_deg"] = float(wrap_deg_180(main.heading_deg - truth_end))
    result["methods"][main.method]["error_deg"] = result["error_deg"]
    result["methods"]["small_angle"]["error_deg"] = float(wrap_deg_180(small.heading_deg - truth_end))
    err = np.asarray(wrap_deg_180(h.heading_deg - truth.heading_at(h.t_s)), dtype=float)
    s_err = np.asarray(
        wrap_deg_180(small.history.heading_deg - truth.heading_at(small.history.t_s)), dtype=float
    )
    hist["error_deg"], hist["small_error_deg"] = err, s_err
    for name, t_arr, e in ((main.method, h.t_s, err), ("small_angle", small.history.t_s, s_err)):
        m = result["methods"][name]
        for thr, key in ((1.0, "time_below_1deg_s"), (0.5, "time_below_0p5deg_s")):
            tb = _time_below(t_arr, e, thr)
            m[key] = None if tb is None else tb - t_start_imu
    if truth.origin is not None and np.isfinite(truth.pos_enu_m).all():
        _add_position_error(result, hist, truth, h, gnss_origin, t_start_imu, main.method)
    if truth.lever_arm_m is not None:
        result["lever_arm_error_m"] = float(
            np.linalg.norm(main.lever_arm_m - np.asarray(truth.lever_arm_m))
        )


def _add_position_error(
    result: dict[str, Any],
    hist: dict[str, Any],
    truth: TruthLog,
    h: Any,
    gnss_origin: Any,
    t_start_imu: float,
    method: str,
) -> None:
    """The IMU position error against the truth (in the run's GNSS origin), at the end and at worst
    once the heading error stayed below 1°."""
    site = LocalEnu(*truth.origin)
    lat, lon, hh = site.from_enu(truth.at(h.t_s, "pos_enu_m"))
    true_enu = LocalEnu(*gnss_origin).to_enu(lat, lon, hh).reshape(-1, 3)
    perr = h.pos_enu_m - true_enu
    hist["position_error_m"] = np.linalg.norm(perr, axis=1)
    result["position_error_m"] = float(hist["position_error_m"][-1])
    result["position_error_horizontal_m"] = float(np.hypot(perr[-1, 0], perr[-1, 1]))
    t_1deg = result["methods"][method]["time_below_1deg_s"]
    if t_1deg is not None:  # converged in truth: |heading error| < 1° from then on
        after = h.t_s - t_start_imu >= t_1deg - 1e-9
        result["position_error_max_after_convergence_m"] = float(
            hist["position_error_m"][after].max()
        )


def compute_gnss_result(
    imu_block: Any,
    fixes: list[GnssFix],
    start: dict[str, Any],
    end: dict[str, Any],
    truth: TruthLog | None,
    t0_index0_s: float,
    alignment: dict[str, Any],
    *,
    complete: bool = True,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Both filters on the window's samples and fixes → (result dict, time histories for the report).

    `t0_index0_s`: start of IMU sample index 0 in GNSS time (time_alignment). `start`/`end` are the
    run's events (filter settings, stream counters).
    """
    flt = start["filter"]
    rate = float(start["imu"]["rate_hz"])
    if len(imu_block) == 0:
        raise InputError("no IMU samples were read; nothing to align")
    if len(fixes) < 2:
        raise InputError(
            f"only {len(fixes)} GNSS fixes were read; check the receiver has a fix (antenna, sky view)"
        )
    idx = imu_block.sample_index
    imu = ImuSeries(rate, imu_block.gyro_rad_s, imu_block.accel_g, idx, t0_index0_s + float(idx[0]) / rate)
    gnss = gnss_series(fixes, float(end["utc_ref_s"]), flt["pos_std_m"], flt["vel_std_m_s"])
    t_start_imu = imu.t0_s
    t_end_imu = t0_index0_s + (float(idx[-1]) + 1.0) / rate
    check_still_start(fixes, gnss.t_s, t_start_imu, GnssAlignConfig.level_s)
    truth_start = float(truth.heading_at(t_start_imu)) if truth is not None else None
    psi0 = _initial_heading(flt, truth_start)
    heading_std = flt.get("heading_std_deg")
    main, small = _both_filters(imu, gnss, psi0, flt, imu_grade(start))
    h = main.history
    t_last = float(h.t_s[-1])
    result: dict[str, Any] = {
        "schema": SCHEMA,
        "kind": KIND,
        "complete": bool(complete),
        "method": main.method,
        "heading_deg": main.heading_deg,
        "heading_std_deg": main.heading_std_deg,
        "pitch_deg": main.pitch_deg,
        "roll_deg": main.roll_deg,
        "lever_arm_m": main.lever_arm_m.tolist(),
        "lever_arm_std_m": main.lever_arm_std_m.tolist(),
        "gyro_bias_dph": main.gyro_bias_dph.tolist(),
        "accel_bias_ug": main.accel_bias_ug.tolist(),
        "converged_after_s": main.converged_after_s,
        "duration_device_s": (float(idx[-1]) - float(idx[0]) + 1.0) / rate,
        "filter_start_s": main.start_s - t_start_imu,
        "filter_end_s": t_last - t_start_imu,
        "initial_heading_deg": psi0,
        "initial_heading_std_deg": heading_std,
        "restart": _restart_dict(main, t_start_imu),
        "lever_arm_prior_m": list(flt["lever_arm_prior_m"]),
        "lever_arm_prior_std_m": float(flt["lever_arm_std_m"]),
        "imu_noise": dict(main.extra),
        "position": dict(
            zip(
                ("lat_deg", "lon_deg", "height_m"),
                (float(v) for v in LocalEnu(*gnss.origin).from_enu(main.pos_enu_m)),
                strict=True,
            )
        ),
        "time_alignment": alignment,
        "imu": {**end["imu"], "rate_hz": rate, "window_s": [t_start_imu, t_end_imu]},
        "gnss": {**end["gnss"], "updates": len(h.t_s), "origin": list(gnss.origin)},
        "methods": {main.method: _method_dict(main, None), "small_angle": _method_dict(small, None)},
    }
    hist: dict[str, Any] = {
        "t_s": h.t_s - t_start_imu,
        "heading_deg": h.heading_deg,
        "heading_std_deg": h.heading_std_deg,
        "lever_arm_m": h.lever_arm_m,
        "small_t_s": small.history.t_s - t_start_imu,
        "small_heading_deg": small.history.heading_deg,
    }
    if truth is not None:
        _add_truth(result, hist, truth, main, small, gnss.origin, t_start_imu, truth_start)
    return result, hist


# ---------------------------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------------------------
def window_from_logs(rd: RunDir, start: dict[str, Any], end: dict[str, Any]) -> tuple[Any, list[GnssFix]]:
    """The IMU samples and the fixes of the window, decoded from imu.raw and gnss.nmea alone."""
    block = base.imu_window_from_raw(rd, start, end)
    nmea = rd.file(GNSS_NMEA).read_bytes() if rd.file(GNSS_NMEA).exists() else b""
    fixes, _ = registry.decoder_for("gnss", start.get("gnss", {}).get("model")).decode_log(nmea)
    return block, fixes[: int(end["gnss"]["fixes"])]


def _host_estimate(
    rd: RunDir, start: dict[str, Any], end: dict[str, Any], gnss_last_s: float | None
) -> dict[str, Any] | None:
    """host_offsets on the run's logs and stamps (None: no stamps, or nothing in them)."""
    try:
        return host_offsets(
            rd.file(IMU_RAW).read_bytes(),
            read_stamps(rd.file(IMU_RX)),
            rd.file(GNSS_NMEA).read_bytes(),
            read_stamps(rd.file(GNSS_RX)),
            float(start["imu"]["rate_hz"]),
            float(end["utc_ref_s"]),
            float(start.get("time_scale", 1.0)),
            int(end["imu"]["last_index"]),
            gnss_last_s,
            imu_model=start["imu"].get("model"),
            gnss_model=start.get("gnss", {}).get("model"),
        )
    except (InputError, FileNotFoundError):
        return None


def data_estimate(
    imu_block: Any, fixes: list[GnssFix], rate_hz: float, utc_ref_s: float, t0_coarse_s: float
) -> tuple[float | None, dict[str, Any]]:
    """Refine a coarse start of IMU index 0 from the data (align.time_offset: IMU heading change
    against GNSS course): (t0 or None, the estimate's fields or {"unavailable": why})."""
    if imu_block is None or len(imu_block) == 0 or len(fixes) < 2:
        return None, {"unavailable": "no IMU samples or fewer than 2 GNSS fixes"}
    arr = fixes_to_arrays(fixes)
    first = float(imu_block.sample_index[0]) / rate_hz
    try:
        est = estimate_time_offset(
            imu_block.gyro_rad_s, imu_block.accel_g, imu_block.sample_index, rate_hz,
            arr.time_s - utc_ref_s, arr.vel_enu_m_s, float(arr.lat_deg[0]), t0_coarse_s + first,
        )
    except NoTimeInformation as exc:
        return None, {"unavailable": str(exc)}
    return est.t0_s - first, {**est.as_dict(), "t0_s": est.t0_s - first}


def time_alignment(
    rd: RunDir,
    start: dict[str, Any],
    end: dict[str, Any],
    truth: TruthLog | None,
    gnss_last_s: float | None,
    imu_block: Any = None,
    fixes: list[GnssFix] | None = None,
) -> tuple[float, dict]:
    """Start of IMU sample index 0 in GNSS time (docs/gnss-alignment.md "Time alignment").

    `data` (hardware and simulator): the host-stamp estimate (+ [gnss] latency_s) refined from the
    data by align.time_offset. If the data cannot tell, hardware falls back to `host` and the
    simulator to `truth-log`, with the reason. On the simulator the truth log's k0 is the reference
    every estimate is reported against (`data_minus_truth_s`, `host_minus_truth_s`)."""
    rate = float(start["imu"]["rate_hz"])
    host = _host_estimate(rd, start, end, gnss_last_s)
    latency = float(start.get("gnss_latency_s", 0.0))
    t_data, data = (None, {"unavailable": "no host receive stamps to start from"})
    if host is not None:
        t_data, data = data_estimate(imu_block, fixes or [], rate, float(end["utc_ref_s"]),
                                     host["t0_s"] + latency)
    info: dict[str, Any] = {"data": data}
    if host is not None:
        info["host_estimate"] = {**host, "gnss_latency_s": latency}
    if truth is not None and truth.imu_t0_s is not None:
        if truth.grid_events:
            raise base.grid_moved(rd)
        if truth.imu_rate_hz != rate:
            raise InputError(
                f"{rd.path}: the truth log's IMU rate {truth.imu_rate_hz:g} Hz is not the run's {rate:g} Hz"
            )
        t_truth = truth.imu_t0_s
        info["truth"] = {"imu_k0": truth.imu_k0, "t0_s": t_truth}
        if host is not None:
            info["host_minus_truth_s"] = host["t0_s"] + latency - t_truth
        if t_data is not None:
            info["data_minus_truth_s"] = t_data - t_truth
            return t_data, {"method": "data", "t0_s": t_data, **info}
        return t_truth, {"method": "truth-log", "t0_s": t_truth, **info}
    if host is None:
        raise InputError(f"{rd.path}: no way to align IMU and GNSS time (no truth log k0, no receive stamps)")
    if t_data is not None:
        return t_data, {"method": "data", "t0_s": t_data, **info}
    t0 = host["t0_s"] + latency
    return t0, {"method": "host", "t0_s": t0, "gnss_latency_s": latency, **host, **info}


def load_truth(rd: RunDir, start: dict[str, Any]) -> TruthLog | None:
    if not start.get("simulate"):
        return None
    return read_truth_log(rd.file(TRUTH_LOG))


def result_from_run(
    rd: RunDir,
    imu_block: Any,
    fixes: list[GnssFix],
    start: dict[str, Any],
    end: dict[str, Any],
    complete: bool,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The result of a run from its window's data (live: the drivers' arrays; replay: decoded logs)."""
    truth = load_truth(rd, start)
    imu_block, cut = base.before_unknown_gap(imu_block)
    last = fixes[-1].time_s - float(end["utc_ref_s"]) if fixes else None
    t0, info = time_alignment(rd, start, end, truth, last, imu_block, fixes)
    result, hist = compute_gnss_result(imu_block, fixes, start, end, truth, t0, info, complete=complete)
    if cut is not None:
        result["imu_unknown_gap"] = cut
    return result, hist


def replay_gnss_run(run_dir: str | Path) -> tuple[dict[str, Any], bool]:
    """Recompute an `align --mode gnss` run's result from imu.raw, gnss.nmea and the events alone.

    Returns (result, complete); bit-identical to the live result.json for the same run.
    """
    rd = RunDir(run_dir, create=False)
    start, end = base.run_events(rd, KIND, "gnss")
    if end is None:
        raise InputError(
            f"{rd.path}: the run has no end event (it was killed before saving its window); "
            "nothing to recompute"
        )
    complete = bool(end.get("complete"))
    block, fixes = window_from_logs(rd, start, end)
    result, _ = result_from_run(rd, block, fixes, start, end, complete)
    return json.loads(json.dumps(jsonable(result))), complete


# ---------------------------------------------------------------------------------------------
# The report
# ---------------------------------------------------------------------------------------------
def write_gnss_report(result: dict[str, Any], hist: dict[str, Any], path: str | Path) -> Path:
    """report.png: heading error (or heading) and σ against time, position error, lever arm."""
    fig, axes = report_axes(3, (9, 10), sharex=True)
    t = np.asarray(hist["t_s"])
    ax = axes[0]
    sig = np.asarray(hist["heading_std_deg"])
    if "error_deg" in hist:
        ax.plot(t, hist["error_deg"], label=f"{result['method']} error")
        ax.plot(hist["small_t_s"], hist["small_error_deg"], label="small-angle error", alpha=0.7)
        ax.fill_between(t, -3 * sig, 3 * sig, color="grey", alpha=0.3, label="±3σ (sin/cos)")
        ax.set_ylabel("heading error [deg]")
        ax.set_yscale("symlog", linthresh=1.0)
    else:
        ax.plot(t, hist["heading_deg"], label="heading")
        ax.plot(t, np.asarray(hist["heading_deg"]) + 3 * sig, "k:", lw=0.8, label="±3σ")
        ax.plot(t, np.asarray(hist["heading_deg"]) - 3 * sig, "k:", lw=0.8)
        ax.set_ylabel("heading [deg]")
    ax.set_title(f"align --mode gnss: {result['heading_deg']:.3f}° ± {result['heading_std_deg']:.3f}° (1σ)")
    ax.legend(loc="upper right")
    ax.grid(True, alpha=0.3)
    ax = axes[1]
    if "position_error_m" in hist:
        ax.plot(t, hist["position_error_m"])
        ax.set_ylabel("IMU position error [m]")
        ax.set_yscale("log")
    else:
        ax.plot(t, sig)
        ax.set_ylabel("heading 1σ [deg]")
        ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax = axes[2]
    la = np.asarray(hist["lever_arm_m"])
    truth_la = (result.get("truth") or {}).get("lever_arm_m")
    for j, name in enumerate("xyz"):
        (line,) = ax.plot(t, la[:, j], label=f"lever arm {name}")
        if truth_la is not None:
            ax.axhline(truth_la[j], color=line.get_color(), ls="--", lw=0.8)
    ax.set_ylabel("lever arm [m] (dashed: truth)")
    ax.set_xlabel("device time since the first IMU sample [s]")
    ax.legend(loc="upper right")
    ax.grid(True, alpha=0.3)
    return save_report(fig, path)


def save_result(
    rd: RunDir, result: dict[str, Any], hist: dict[str, Any], json_path: str | None, report: bool = True
) -> None:
    base.write_result(rd, result, json_path)
    if report:
        write_gnss_report(result, hist, rd.report_path)


__all__ = [
    "CONFIG",
    "GNSS_NMEA",
    "KIND",
    "compute_gnss_result",
    "replay_gnss_run",
    "result_from_run",
    "time_alignment",
]
