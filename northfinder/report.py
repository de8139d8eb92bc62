"""report.png: each gyro and accelerometer axis against the table angle, with the fitted harmonic,
the residuals, and the tilt. matplotlib is imported lazily (Agg backend, no display needed)."""

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


def write_report(result: dict[str, Any], path: str | Path) -> Path:
    """Draw the run's result (docs/result-schema.md) into a PNG and return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    positions = result["positions"]
    alpha = np.array([p["table_angle_deg"] for p in positions], dtype=float)
    gyro = np.array([p["gyro_dph"] for p in positions], dtype=float).reshape(len(positions), -1)
    accel = np.array([[np.nan if v is None else v for v in p["accel_g"]] for p in positions], dtype=float)
    accel = accel.reshape(len(positions), -1)
    grid = np.linspace(min(alpha.min(), 0.0), max(alpha.max(), 360.0), 361)

    fig = plt.figure(figsize=(13, 11))
    gs = fig.add_gridspec(
        5,
        3,
        height_ratios=[3, 1.3, 3, 1.3, 3],
        left=0.07,
        right=0.98,
        bottom=0.04,
        top=0.94,
        hspace=0.55,
        wspace=0.25,
    )
    rows = [("gyro", gyro, "deg/h", 1.0, 0), ("accel", accel * 1e3, "mg", 1e3, 2)]
    for label, data, unit, _scale, row in rows:
        for k, axis in enumerate("xyz"):
            if k >= data.shape[1]:
                continue
            curve, resid = harmonic_curve(alpha, data[:, k], grid, harmonic=axis != "z")
            ax = fig.add_subplot(gs[row, k])
            ax.plot(alpha, data[:, k], "o", color="C0", label="position mean")
            ax.plot(grid, curve, "-", color="C1", label="R + a·cos α + b·sin α" if axis != "z" else "R")
            ax.ticklabel_format(axis="y", useOffset=False)
            ax.set_title(f"{label} {axis} [{unit}]")
            ax.set_xlabel("table angle α [deg]")
            ax.grid(alpha=0.3)
            if k == 0:
                ax.legend(fontsize=7)
            rax = fig.add_subplot(gs[row + 1, k], sharex=ax)
            rax.axhline(0.0, color="0.5", lw=0.8)
            rax.plot(alpha, resid, "s", color="C3", ms=4)
            rax.set_ylabel(f"residual [{unit}]", fontsize=8)
            rax.grid(alpha=0.3)
            rax.ticklabel_format(axis="y", useOffset=False)

    tilt = result.get("tilt", {})
    pax = fig.add_subplot(gs[4, 0], projection="polar")
    pax.set_theta_zero_location("N")
    pax.set_theta_direction(-1)
    if tilt:
        pax.plot([np.deg2rad(tilt["tilt_azimuth_deg"])] * 2, [0.0, tilt["tilt_deg"]], "-o", color="C2")
    pax.plot(
        [np.deg2rad(result["heading_deg"])] * 2, [0.0, max(tilt.get("tilt_deg", 1.0), 1e-3)], "-", color="C0"
    )
    pax.set_title("tilt (downhill azimuth, deg) and heading", fontsize=9)

    tax = fig.add_subplot(gs[4, 1:])
    tax.axis("off")
    nan = float("nan")
    lines = [
        f"heading ({result['method']}): {result['heading_deg']:.4f}° ± {result['heading_std_deg']:.4f}° (1σ)",
        f"pitch {tilt.get('pitch_deg', nan):+.4f}°   roll {tilt.get('roll_deg', nan):+.4f}°   "
        f"tilt {tilt.get('tilt_deg', nan):.4f}° toward {tilt.get('tilt_azimuth_deg', nan):.2f}°",
        f"latitude {result['latitude_deg']:.4f}°   positions {len(positions)}   "
        f"device time {result['duration_device_s']:.1f} s",
    ]
    for name, m in result.get("methods", {}).items():
        h = m.get("heading_deg")
        lines.append(f"  {name:22s} {'—' if h is None else f'{h:.4f}°'}")
    if "truth" in result:
        lines.append(f"truth {result['truth']['heading_deg']:.4f}°   error {result['error_deg']:+.4f}°")
    if not result.get("complete", True):
        lines.append("INCOMPLETE RUN")
    tax.text(0.0, 1.0, "\n".join(lines), va="top", family="monospace", fontsize=9)
    fig.suptitle("northfinder — turntable north finding")
    out = Path(path)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
