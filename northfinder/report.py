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


def write_report(result: dict[str, Any], path: str | Path) -> Path:
    """Draw the run's result (docs/result-schema.md) into a PNG and return its path."""
    import matplotlib.pyplot as plt

    fig = draw_report(result)
    out = Path(path)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def draw_report(result: dict[str, Any]) -> Any:
    """The report's figure: per axis the position means with 1σ error bars, the fitted harmonic
    and the residuals; the tilt and heading on a polar plot; the numbers as text."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    positions = result["positions"]
    n = len(positions)
    alpha = np.array([p["table_angle_deg"] for p in positions], dtype=float)
    gyro = np.array([p["gyro_dph"] for p in positions], dtype=float).reshape(n, -1)
    accel = np.array([[np.nan if v is None else v for v in p["accel_g"]] for p in positions], dtype=float)
    gyro_se, accel_se = mean_std_errors(positions)
    fig = plt.figure(figsize=(13, 12.5))
    gs = fig.add_gridspec(5, 3, height_ratios=[3, 1.3, 3, 1.3, 3.4], left=0.08, right=0.98, bottom=0.04,
                          top=0.94, hspace=0.75, wspace=0.32)
    rows = [("gyro", gyro, gyro_se.reshape(n, -1), "deg/h", 0),
            ("accel", accel.reshape(n, -1) * 1e3, accel_se.reshape(n, -1) * 1e3, "mg", 2)]
    for label, data, err, unit, row in rows:
        for k, axis in enumerate("xyz"[: data.shape[1]]):
            _axis_panels(fig, gs, row, k, f"{label} {axis}", unit, alpha, data[:, k], err[:, k], axis != "z")
    _polar_panel(fig.add_subplot(gs[4, 0], projection="polar"), result)
    tax = fig.add_subplot(gs[4, 1:])
    tax.axis("off")
    tax.text(0.22, 1.0, "\n".join(_text_lines(result)), va="top", family="monospace", fontsize=9)
    fig.suptitle("northfinder — turntable north finding")
    return fig


def _axis_panels(fig: Any, gs: Any, row: int, k: int, title: str, unit: str, alpha: np.ndarray,
                 values: np.ndarray, err: np.ndarray, harmonic: bool) -> None:
    """One axis: the position means ± 1σ and the fit above, the residuals below."""
    grid = np.linspace(min(alpha.min(), 0.0), max(alpha.max(), 360.0), 361)
    curve, resid = harmonic_curve(alpha, values, grid, harmonic=harmonic)
    ax = fig.add_subplot(gs[row, k])
    ax.errorbar(alpha, values, yerr=np.where(np.isfinite(err), err, 0.0), fmt="o", color="C0", capsize=3,
                label="position mean ± 1σ")
    ax.plot(grid, curve, "-", color="C1", label="R + a·cos α + b·sin α" if harmonic else "R")
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_title(f"{title} [{unit}]")
    ax.set_xlabel("table angle α [deg]")
    ax.grid(alpha=0.3)
    if k == 0:
        ax.legend(fontsize=7)
    rax = fig.add_subplot(gs[row + 1, k], sharex=ax)
    rax.axhline(0.0, color="0.5", lw=0.8)
    rax.errorbar(alpha, resid, yerr=np.where(np.isfinite(err), err, 0.0), fmt="s", color="C3", ms=4,
                 capsize=2)
    rax.set_ylabel(f"residual\n[{unit}]", fontsize=8)
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
    pax.set_title("tilt and heading (azimuth from north, clockwise)", fontsize=9, pad=14)
    pax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.08, 0.35), frameon=False,
               title="radius: tilt [deg]", title_fontsize=7, alignment="left")


def _text_lines(result: dict[str, Any]) -> list[str]:
    """The numbers: heading ± σ, tilt, latitude, every method, truth and error, completeness."""
    tilt = result.get("tilt", {})
    nan = float("nan")
    lines = [
        f"heading ({result['method']}): {result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}° (1σ)",
        f"pitch {tilt.get('pitch_deg', nan):+.4f}°   roll {tilt.get('roll_deg', nan):+.4f}°   "
        f"tilt {tilt.get('tilt_deg', nan):.4f}° toward {tilt.get('tilt_azimuth_deg', nan):.2f}°",
        f"latitude {result['latitude_deg']:.4f}°   positions {len(result['positions'])}   "
        f"device time {result['duration_device_s']:.1f} s",
    ]
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
