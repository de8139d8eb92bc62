"""report.png: each gyro and accelerometer axis against the table angle (position means with 1σ
error bars), with the fitted harmonic, the residuals, and the tilt.
matplotlib is imported lazily (Agg backend, no display needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def harmonic_curve(
    alpha_deg: np.ndarray, values: np.ndarray, grid_deg: np.ndarray, harmonic: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Fit y = R + a·cos α + b·sin α by least squares (turntable paper eq 6–7, X̂ = (AᵀA)⁻¹AᵀY).

    Returns the curve on `grid_deg` and the residuals at the measured angles. With
    `harmonic=False` only R is fitted: a z axis turns about itself and sees a constant.
    For the plot only; the heading comes from northfinder.estimators.
    """
    a = np.deg2rad(np.asarray(alpha_deg, dtype=float))
    y = np.asarray(values, dtype=float)
    g = np.deg2rad(np.asarray(grid_deg, dtype=float))
    k = 3 if harmonic else 1
    design = np.column_stack([np.ones_like(a), np.cos(a), np.sin(a)])[:, :k]
    grid_design = np.column_stack([np.ones_like(g), np.cos(g), np.sin(g)])[:, :k]
    ok = np.isfinite(y)
    if ok.sum() < k:
        return np.full(g.shape, np.nan), np.full(y.shape, np.nan)
    coef, *_ = np.linalg.lstsq(design[ok], y[ok], rcond=None)
    return grid_design @ coef, y - design @ coef


def mean_std_errors(positions: list[dict[str, Any]]) -> tuple[np.ndarray, np.ndarray]:
    """1σ of each position mean (the error bars): gyro [deg/h] and accelerometer [g], each axis's
    sample spread over the √ of the samples it kept (white noise over the dwell, as the fit)."""
    gyro_se, accel_se = [], []
    for p in positions:
        inv = p.get("invalid_samples") or {}
        kept = [max(int(p["samples"]) - int(inv.get(f"g{a}", 0)), 1) for a in "xyz"]
        g_std = [np.nan if v is None else v for v in p.get("gyro_std_dph") or [np.nan] * 3]
        a_std = [np.nan if v is None else v for v in p.get("accel_std_g") or [np.nan] * 3]
        gyro_se.append(np.asarray(g_std, dtype=float) / np.sqrt(kept[: len(g_std)]))
        accel_se.append(np.asarray(a_std, dtype=float) / np.sqrt(max(int(p["accel_samples"]), 1)))
    return np.array(gyro_se, dtype=float), np.array(accel_se, dtype=float)


def run_info(run_dir: str | Path | None) -> dict[str, Any]:
    """What the title names, read from a find's run directory (config.json, the start event):
    run name, UTC start, unit (its --unit), plan, positions × dwell, grade and seed of a simulated run."""
    import json

    if run_dir is None:
        return {}
    d = Path(run_dir)
    info: dict[str, Any] = {"run": d.name}
    try:
        cfg = json.loads((d / "config.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        cfg = {}
    argv = [str(a) for a in cfg.get("argv") or []]
    if "--unit" in argv[:-1]:
        info["unit"] = argv[argv.index("--unit") + 1]
    run = (cfg.get("bench") or {}).get("run") or {}
    info.update({k: run[k] for k in ("positions", "dwell_s", "plan") if k in run})
    sim = cfg.get("simulate") or {}
    info.update({k: sim[k] for k in ("grade", "seed") if k in sim})
    try:
        for line in (d / "events.jsonl").read_text(encoding="utf-8").splitlines():
            if '"start"' in line:
                ev = json.loads(line)
                if ev.get("event") == "start":
                    info.setdefault("utc", ev.get("utc"))
                    info.setdefault("imu_rate_hz", (ev.get("imu") or {}).get("rate_hz"))
    except (OSError, ValueError):
        pass
    return info


def write_report(result: dict[str, Any], path: str | Path, samples: dict[str, Any] | None = None,
                 run_dir: str | Path | None = None) -> Path:
    """Draw the run's result (docs/result-schema.md) into a PNG and return its path. `samples`
    (alpha_deg, omega_dps, gyro_dph, rate_hz: every sample the per-sample fit used) adds the sample
    panel; `run_dir` (default: the PNG's directory) gives the title's run, time, unit, plan and seed."""
    import matplotlib.pyplot as plt

    out = Path(path)
    fig = draw_report(result, samples=samples, info=run_info(run_dir if run_dir is not None else out.parent))
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def report_title(result: dict[str, Any], info: dict[str, Any]) -> str:
    """Two lines: what was run (run, unit, UTC time, plan, grade, seed) and what it gave (heading ± σ,
    truth and error of a simulated run)."""
    utc = str(info.get("utc") or "")[:19].replace("T", " ")
    plan = result.get("plan") or info.get("plan") or "positions"
    what = [f"run {info['run']}" if info.get("run") else "find",
            f"unit {info['unit']}" if info.get("unit") else "unit not given",
            f"{utc} UTC" if utc else "",
            f"plan {plan}, {result['positions_measured']} × {info['dwell_s']:g} s" if "dwell_s" in info
            else f"plan {plan}",
            f"grade {info['grade']}, seed {info['seed']}" if "grade" in info else "real bench"]
    got = f"heading {result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}° (1σ, {result['method']})"
    if "truth" in result:
        got += f"   truth {result['truth']['heading_deg']:.4f}°   error {result['error_deg']:+.4f}°"
    if not result.get("complete", True):
        got += "   INCOMPLETE RUN"
    return "northfinder find — " + ", ".join(w for w in what if w) + "\n" + got


def draw_report(result: dict[str, Any], samples: dict[str, Any] | None = None,
                info: dict[str, Any] | None = None) -> Any:
    """The report's figure: every gyro sample the fit used against time with the table angle (when
    the run has them); per axis the position means with 1σ error bars, the fitted harmonic and the
    residuals; the heading of each fit with its σ (and the truth); the tilt; the numbers as text."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    info = info or {}
    positions = result["positions"]
    n = len(positions)
    alpha = np.array([p["table_angle_deg"] for p in positions], dtype=float)
    gyro = np.array([p["gyro_dph"] for p in positions], dtype=float).reshape(n, -1)
    accel = np.array([[np.nan if v is None else v for v in p["accel_g"]] for p in positions], dtype=float)
    gyro_se, accel_se = mean_std_errors(positions)
    fig = plt.figure(figsize=(13, 15))
    gs = fig.add_gridspec(4, 3, height_ratios=[2.4, 4.2, 4.2, 3.6], left=0.07, right=0.98,
                          bottom=0.07, top=0.935, hspace=0.42, wspace=0.3)
    _samples_panel(fig.add_subplot(gs[0, :]), samples, result)
    rows = [("gyro", gyro, gyro_se.reshape(n, -1), "deg/h", 1),
            ("accel", accel.reshape(n, -1) * 1e3, accel_se.reshape(n, -1) * 1e3, "mg", 2)]
    for label, data, err, unit, row in rows:
        for k, axis in enumerate("xyz"[: data.shape[1]]):
            pair = gs[row, k].subgridspec(2, 1, height_ratios=[2.6, 1.0], hspace=0.06)
            _axis_panels(fig, pair, 0, 0, f"{label} {axis}", unit, alpha, data[:, k], err[:, k], axis != "z",
                          legend=k == 0)
    _heading_panel(fig.add_subplot(gs[3, 0].subgridspec(1, 2, width_ratios=[0.42, 0.58])[0, 1]), result)
    _polar_panel(fig.add_subplot(gs[3, 1], projection="polar"), result)
    tax = fig.add_subplot(gs[3, 2])
    tax.axis("off")
    tax.text(0.0, 1.0, "\n".join(_text_lines(result)), va="top", family="monospace", fontsize=8)
    fig.suptitle(report_title(result, info), fontsize=11)
    return fig


def _samples_panel(ax: Any, samples: dict[str, Any] | None, result: dict[str, Any]) -> None:
    """Every gyro sample the per-sample fit used (rest and motion) against device time, the table
    angle on the right axis; a run without them (plan positions, a resumed run) says why."""
    ax.set_title("every gyro sample the heading used (rest and motion) and the table angle", fontsize=9)
    ax.set_xlabel("device time from the first dwell [s]")
    ax.set_ylabel("gyro [deg/h]")
    if not samples:
        motion = result.get("motion_fit") or {}
        why = motion.get("reason") or "plan positions: the heading uses the dwell means only (below)"
        ax.text(0.5, 0.5, f"no per-sample fit: {why}", ha="center", va="center", transform=ax.transAxes)
        ax.set_yticks([])
        return
    a = np.asarray(samples["alpha_deg"], dtype=float)
    w = np.asarray(samples["omega_dps"], dtype=float)
    g = np.asarray(samples["gyro_dph"], dtype=float)
    t = np.arange(a.size) / float(samples["rate_hz"])
    rest = w == 0
    step = max(1, a.size // 20000)  # the plot keeps one sample in `step` (the fit used them all)
    for k, axis in enumerate("xy"):
        if not np.any(np.isfinite(g[:, k])):
            continue
        for mask, kind, alpha_pt in ((rest, "rest", 0.5), (~rest, "motion", 0.25)):
            idx = np.flatnonzero(mask)[::step]
            ax.plot(t[idx], g[idx, k], ".", ms=1.0, color=f"C{2 * k + (kind == 'motion')}", alpha=alpha_pt,
                    rasterized=True, label=f"gyro {axis}, {kind} ({np.count_nonzero(mask)} samples)")
    for t_s, session in samples.get("session_starts_s", ()):  # a resumed run: sessions one after another
        ax.axvline(t_s, color="0.3", ls="--", lw=1.0)
        ax.text(t_s, 0.02, f" session {session} (resumed; own gyro bias)", fontsize=7, color="0.3",
                va="bottom", transform=ax.get_xaxis_transform())
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", markerscale=8, ncol=2)
    tw = ax.twinx()
    tw.plot(t, a, "-", color="0.35", lw=0.9, label="table angle α")
    tw.set_ylabel("table angle α [deg]")
    tw.legend(fontsize=7, loc="upper right")


def _heading_panel(ax: Any, result: dict[str, Any]) -> None:
    """The heading of each fit with its 1σ bar: the result, the dwells alone, every method; the truth."""
    rows: list[tuple[str, float, float | None]] = []
    motion, dwell = result.get("motion_fit") or {}, result.get("dwell_fit")
    plan = result.get("plan", "positions")
    rows.append((f"result ({plan})", result["heading_deg"], result["heading_std_deg"]))
    if motion.get("available") and dwell:
        rows.append(("dwell means only", dwell["heading_deg"], dwell["heading_std_deg"]))
    for name, m in result.get("methods", {}).items():
        if m.get("heading_deg") is not None and name != result["method"]:
            rows.append((name, m["heading_deg"], None))
    ref = result["heading_deg"]
    diffs = [(h - ref + 180.0) % 360.0 - 180.0 for _, h, _ in rows]
    truth_d = (result["truth"]["heading_deg"] - ref + 180.0) % 360.0 - 180.0 if "truth" in result else 0.0
    lim = 1.25 * max([4.0 * (std or 0.0) + abs(d) for (_, _, std), d in zip(rows, diffs, strict=True) if std]
                     + [abs(truth_d) + result["heading_std_deg"]])
    for y, ((_, _, std), d) in enumerate(zip(rows, diffs, strict=True)):
        if abs(d) > lim:  # off scale (the uncompensated method): an arrow at the edge and its value
            edge = np.sign(d) * lim * 0.97
            ax.plot([edge], [y], ">" if d > 0 else "<", color="0.4")
            ax.text(edge - np.sign(d) * lim * 0.06, y, f"{d:+.2f}° off scale", fontsize=7, va="center",
                    ha="right" if d > 0 else "left", color="0.3")
            continue
        ax.errorbar([d], [y], xerr=None if std is None else [[std], [std]], fmt="o" if std else "x",
                    color="C0" if std else "0.4", capsize=4)
    ax.set_yticks(range(len(rows)), [r[0] for r in rows], fontsize=8)
    ax.invert_yaxis()
    if "truth" in result:
        ax.axvline(truth_d, color="C2", lw=1.2, label=f"truth {result['truth']['heading_deg']:.3f}°")
        ax.text(truth_d, -0.75, f"truth {result['truth']['heading_deg']:.3f}°", color="C2", fontsize=7,
                ha="center", va="bottom")  # above the first row, clear of every point and note
        ax.set_ylim(len(rows) - 0.5, -1.1)
    ax.axvline(0.0, color="0.7", lw=0.8)
    ax.set_xlabel(f"heading − {ref:.3f}° [deg] (bars: 1σ)", fontsize=8)
    ax.set_title("heading of each fit", fontsize=9)
    ax.grid(alpha=0.3, axis="x")
    ax.set_xlim(-lim, lim)


def _axis_panels(fig: Any, gs: Any, row: int, k: int, title: str, unit: str, alpha: np.ndarray,
                 values: np.ndarray, err: np.ndarray, harmonic: bool, legend: bool = True) -> None:
    """One axis: the position means ± 1σ and the fit above, the residuals below."""
    grid = np.linspace(min(alpha.min(), 0.0), max(alpha.max(), 360.0), 361)
    curve, resid = harmonic_curve(alpha, values, grid, harmonic=harmonic)
    ax = fig.add_subplot(gs[row, k])
    ax.errorbar(alpha, values, yerr=np.where(np.isfinite(err), err, 0.0), fmt="o", color="C0", capsize=3,
                label="position mean ± 1σ")
    ax.plot(grid, curve, "-", color="C1", label="R + a·cos α + b·sin α" if harmonic else "R")
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_title(f"{title} [{unit}]: position means", fontsize=9)
    ax.set_ylabel(f"{title} [{unit}]", fontsize=8)
    ax.tick_params(labelbottom=False)
    ax.grid(alpha=0.3)
    if legend:
        ax.legend(fontsize=7)
    rax = fig.add_subplot(gs[row + 1, k], sharex=ax)
    rax.axhline(0.0, color="0.5", lw=0.8)
    rax.errorbar(alpha, resid, yerr=np.where(np.isfinite(err), err, 0.0), fmt="s", color="C3", ms=4,
                 capsize=2)
    rax.set_ylabel(f"residual\n[{unit}]", fontsize=8)
    rax.set_xlabel("table angle α [deg]", fontsize=8)
    rax.grid(alpha=0.3)
    rax.ticklabel_format(axis="y", useOffset=False)


def _polar_panel(pax: Any, result: dict[str, Any]) -> None:
    """Tilt (radius in degrees, toward the downhill azimuth) and the heading's direction."""
    tilt = result.get("tilt", {})
    pax.set_theta_zero_location("N")
    pax.set_theta_direction(-1)
    r_max = max(float(tilt.get("tilt_deg", 0.0)), 1e-3) * 1.15
    if tilt:
        pax.plot([np.deg2rad(tilt["tilt_azimuth_deg"])] * 2, [0.0, tilt["tilt_deg"]], "-o", color="C2",
                 label=f"tilt {tilt['tilt_deg']:.3f}° toward {tilt['tilt_azimuth_deg']:.1f}°")
    pax.plot([np.deg2rad(result["heading_deg"])] * 2, [0.0, r_max], "-", color="C0",
             label=f"heading {result['heading_deg']:.3f}° (direction only)")
    pax.set_rmax(r_max)
    r_tick = float(tilt.get("tilt_deg", 0.0)) or r_max / 1.15
    pax.set_rticks([float(f"{r_tick / 2:.2g}"), float(f"{r_tick:.3g}")])  # inside the rim: clear of 135°
    pax.set_rlabel_position(157.5)  # the radius labels away from both lines' usual quadrants
    pax.tick_params(axis="y", labelsize=7)
    pax.set_title("tilt and heading (azimuth from north, clockwise)", fontsize=9, pad=10)
    pax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.06), frameon=False,
               title="radius: tilt [deg]", title_fontsize=7)


def _text_lines(result: dict[str, Any]) -> list[str]:
    """The numbers: heading ± σ, tilt, latitude, every method, truth and error, completeness."""
    tilt = result.get("tilt", {})
    nan = float("nan")
    lines = [
        f"heading ({result['method']}): {result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}° (1σ)",
        f"pitch {tilt.get('pitch_deg', nan):+.4f}°   roll {tilt.get('roll_deg', nan):+.4f}°",
        f"tilt {tilt.get('tilt_deg', nan):.4f}° toward {tilt.get('tilt_azimuth_deg', nan):.2f}°",
        f"latitude {result['latitude_deg']:.4f}°   positions {len(result['positions'])}",
        f"device time {result['duration_device_s']:.1f} s of dwell",
    ]
    motion, dwell = result.get("motion_fit") or {}, result.get("dwell_fit")
    if motion.get("available") and dwell:
        lines.append(f"plan {result.get('plan')}: every gyro sample ± {result['heading_std_deg']:.4f}°")
        lines.append(f"  dwell means alone {dwell['heading_deg']:.4f}° ± {dwell['heading_std_deg']:.4f}°")
    elif motion:
        lines.append(f"plan positions (dwell means): {str(motion.get('reason', ''))[:40]}")
    lines.append("every method:")
    for name, m in result.get("methods", {}).items():
        h = m.get("heading_deg")
        lines.append(f"  {name:22s} {'—' if h is None else f'{h:.4f}°'}")
    if "truth" in result:
        lines.append(f"truth {result['truth']['heading_deg']:.4f}°   error {result['error_deg']:+.4f}°")
    if not result.get("complete", True):
        lines.append("INCOMPLETE RUN")
    return lines


# ---------------------------------------------------------------------------------------------
# Figure helpers the align runs' reports share (northfinder.runs.swaying, northfinder.runs.gnss)
# ---------------------------------------------------------------------------------------------
def report_axes(rows: int, figsize: tuple[float, float], sharex: bool = False) -> tuple[Any, Any]:
    """A figure of `rows` stacked axes on the Agg backend (no display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(rows, 1, figsize=figsize, sharex=sharex)


def save_report(fig: Any, path: str | Path) -> Path:
    """Lay out, write (80 dpi) and close the figure; its path."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def align_title(mode: str, result: dict[str, Any]) -> str:
    """An align report's title: mode, method, heading ± σ, and the truth and error of a simulated run."""
    title = (f"align --mode {mode} ({result.get('method', mode)}): {result['heading_deg']:.3f}° ± "
             f"{result['heading_std_deg']:.3f}° (1σ)")
    if "truth" in result and "error_deg" in result:
        title += f", truth {result['truth']['heading_deg']:.3f}°, error {result['error_deg']:+.3f}°"
    if not result.get("complete", True):
        title += " — INCOMPLETE"
    return title


SWAY_ZOOM_S = 40.0
"""The swaying report shows this much of the body rates sample by sample (the sway's shape); the
whole window as the rates' RMS per SWAY_RMS_WINDOW_S."""
SWAY_RMS_WINDOW_S = 5.0


def write_swaying_report(result: dict[str, Any], resid: dict[str, np.ndarray], path: str | Path) -> Path:
    """report.png of `align --mode swaying` (draw_swaying_report)."""
    return save_report(draw_swaying_report(result, resid), path)


def draw_swaying_report(result: dict[str, Any], resid: dict[str, np.ndarray]) -> Any:
    """The body rates over the first SWAY_ZOOM_S (the sway), their RMS over the whole window, and the
    cone fit's residual per axis of the initial body frame."""
    fig, axes = report_axes(3, (9.5, 10))
    t, w = np.asarray(resid["t_gyro_s"], dtype=float), np.asarray(resid["gyro_dps"], dtype=float)
    ax = axes[0]
    zoom = t <= t[0] + SWAY_ZOOM_S if t.size else np.zeros(0, dtype=bool)
    for j, name in enumerate("xyz"):
        ax.plot(t[zoom], w[zoom, j], lw=0.7, label=f"gyro {name}")
    ax.set_ylabel("body rate [deg/s]")
    ax.set_xlabel("device time since the first sample [s]")
    span = float(t[-1] - t[0]) if t.size else 0.0
    ax.set_title(f"the sway: body rates, first {min(SWAY_ZOOM_S, span):.0f} s of {span:.0f} s", fontsize=9)
    ax.legend(loc="upper right", fontsize=8, ncol=3)
    ax.grid(True, alpha=0.3)
    ax = axes[1]
    if t.size > 1:
        edges = np.arange(t[0], t[-1] + SWAY_RMS_WINDOW_S, SWAY_RMS_WINDOW_S)
        k = np.clip(np.digitize(t, edges) - 1, 0, len(edges) - 1)
        centres = edges + SWAY_RMS_WINDOW_S / 2
        for j, name in enumerate("xyz"):
            counts = np.bincount(k, None, len(edges))
            full = counts >= 0.5 * counts.max()  # a last, partly filled window left out
            rms = np.sqrt(np.bincount(k, w[:, j] ** 2, len(edges))[full] / counts[full])
            ax.plot(centres[full], rms, "-o", ms=2.5, lw=1.0, label=f"gyro {name}")
    ax.set_ylabel(f"body rate RMS per {SWAY_RMS_WINDOW_S:g} s [deg/s]")
    ax.set_xlabel("device time since the first sample [s]")
    ax.set_title("the sway over the whole window", fontsize=9)
    ax.legend(loc="upper right", fontsize=8, ncol=3)
    ax.grid(True, alpha=0.3)
    ax = axes[2]
    r = np.asarray(resid["residual_ug"], dtype=float)
    for j, name in enumerate("xyz"):
        mean = float(np.mean(r[:, j])) if r.size else float("nan")
        ax.plot(resid["t_s"], r[:, j], marker=".",
                label=f"{name} of the initial body frame (mean {mean:+.1f} µg)")
    ax.set_ylabel("cone-fit residual [µg]")
    ax.set_xlabel("window centre, device time [s]")
    ax.set_title("specific force (smoothed) − the fitted Earth-rate cone and lever-arm sway\n"
                 "a constant offset on an axis is the accelerometer's bias (not fitted; in σ as its prior)",
                 fontsize=9)
    ax.legend(loc="center right", fontsize=7)
    ax.grid(True, alpha=0.3)
    fig.suptitle(align_title("swaying", result), fontsize=10)
    return fig


def _plain_symlog(ax: Any, linthresh: float) -> None:
    """A symmetric-log y axis whose tick labels read as plain degrees (0.1, 1, 10, −10), not 10⁰."""
    import matplotlib.ticker as mticker

    ax.set_yscale("symlog", linthresh=linthresh)
    ax.yaxis.set_major_locator(mticker.SymmetricalLogLocator(base=10, linthresh=linthresh))
    ax.yaxis.set_major_formatter(mticker.FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(mticker.NullFormatter())


def write_gnss_report(result: dict[str, Any], hist: dict[str, Any], path: str | Path) -> Path:
    """report.png of `align --mode gnss` (draw_gnss_report)."""
    return save_report(draw_gnss_report(result, hist), path)


def draw_gnss_report(result: dict[str, Any], hist: dict[str, Any]) -> Any:
    """Heading error (simulated) or heading with ±3σ against time, the IMU position error or the
    heading σ, and the lever arm estimate (dashed: the truth)."""
    fig, axes = report_axes(3, (9.5, 10), sharex=True)
    t = np.asarray(hist["t_s"])
    ax = axes[0]
    sig = np.asarray(hist["heading_std_deg"])
    if "error_deg" in hist:
        ax.plot(t, hist["error_deg"], label=f"{result['method']} error")
        ax.plot(hist["small_t_s"], hist["small_error_deg"], label="small-angle filter error", alpha=0.7)
        ax.fill_between(t, -3 * sig, 3 * sig, color="grey", alpha=0.3, label="±3σ (sin/cos)")
        ax.set_ylabel("heading error [deg] (symmetric log)")
        _plain_symlog(ax, 0.1)
    else:
        ax.plot(t, hist["heading_deg"], label="heading")
        ax.plot(t, np.asarray(hist["heading_deg"]) + 3 * sig, "k:", lw=0.8, label="±3σ")
        ax.plot(t, np.asarray(hist["heading_deg"]) - 3 * sig, "k:", lw=0.8)
        ax.set_ylabel("heading [deg]")
    ax.set_title("heading against time", fontsize=9)
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    ax = axes[1]
    if "position_error_m" in hist:
        ax.plot(t, hist["position_error_m"], label="IMU position error")
        ax.set_ylabel("IMU position error [m]")
    else:
        ax.plot(t, sig, label="heading 1σ")
        ax.set_ylabel("heading 1σ [deg]")
    ax.set_yscale("log")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    ax = axes[2]
    la = np.asarray(hist["lever_arm_m"])
    truth_la = (result.get("truth") or {}).get("lever_arm_m")
    for j, name in enumerate("xyz"):
        (line,) = ax.plot(t, la[:, j], label=f"lever arm {name}")
        if truth_la is not None:
            ax.axhline(truth_la[j], color=line.get_color(), ls="--", lw=0.8)
    ax.set_ylabel("lever arm [m] (dashed: truth)" if truth_la is not None else "lever arm [m]")
    ax.set_xlabel("device time since the first IMU sample [s]")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.suptitle(align_title("gnss", result), fontsize=10)
    return fig
