"""Repeatability statistics of a campaign (pure numpy): per method, the deviation of each find's
heading from its reference azimuth — mean, standard deviation, RMS and largest |deviation| in
degrees and arc minutes — and, where the finds reported a σ, its mean against the observed spread.

This is the turntable paper's table 1 (mean, standard deviation, deviation from the true value, in
arc minutes) for every method at once, over finds at one or several reference azimuths.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

ARCMIN_PER_DEG = 60.0
METHODS = ("exact", "coordinate_transform", "vector", "eq11", "uncompensated")
"""The heading methods of result.json's `methods`, in the order the summary shows them."""


def deviation_deg(heading_deg: Any, reference_deg: Any) -> np.ndarray:
    """heading − reference wrapped to [−180, 180) degrees (elementwise)."""
    d = np.asarray(heading_deg, dtype=float) - np.asarray(reference_deg, dtype=float)
    return (d + 180.0) % 360.0 - 180.0


def spread(dev_deg: Sequence[float], sigma_deg: Sequence[float | None] | None = None) -> dict[str, Any]:
    """Statistics of deviations [deg]: n, mean, std (sample, n − 1), RMS, max |dev|, each also in
    arc minutes; with reported σs: their mean, and the observed std over that mean (1 = honest σ).
    Fewer than 2 deviations: std is None."""
    d = np.asarray(dev_deg, dtype=float)
    n = int(d.size)
    out: dict[str, Any] = {"n": n}
    if n == 0:
        return out
    std = float(np.std(d, ddof=1)) if n >= 2 else None
    stats = {
        "mean": float(np.mean(d)),
        "std": std,
        "rms": float(np.sqrt(np.mean(d**2))),
        "max_abs": float(np.max(np.abs(d))),
    }
    for name, v in stats.items():
        out[f"{name}_deg"] = v
        out[f"{name}_arcmin"] = None if v is None else v * ARCMIN_PER_DEG
    sig = [float(s) for s in (sigma_deg or []) if s is not None]
    if sig and len(sig) == n:
        mean_sigma = float(np.mean(sig))
        out["mean_reported_sigma_deg"] = mean_sigma
        out["mean_reported_sigma_arcmin"] = mean_sigma * ARCMIN_PER_DEG
        out["observed_over_reported"] = None if std is None or mean_sigma == 0 else std / mean_sigma
    return out


def method_statistics(runs: Sequence[dict[str, Any]], main_method: str) -> dict[str, dict[str, Any]]:
    """Per method, `spread` of the runs' deviations from their references. Each run has
    `reference_deg`, `methods` {name: heading_deg} and `heading_std_deg` (the σ reported for
    `main_method`, the only method with a σ)."""
    names = [m for m in METHODS if any(m in r["methods"] for r in runs)]
    names += sorted({m for r in runs for m in r["methods"]} - set(names))
    out = {}
    for m in names:
        rows = [r for r in runs if r["methods"].get(m) is not None]
        dev = deviation_deg([r["methods"][m] for r in rows], [r["reference_deg"] for r in rows])
        sig = [r.get("heading_std_deg") for r in rows] if m == main_method else None
        out[m] = spread(dev, sig)
    return out


def step_statistics(runs: Sequence[dict[str, Any]], main_method: str) -> list[dict[str, Any]]:
    """The main method's `spread` at each base heading (step), in step order."""
    out = []
    for step in sorted({int(r["step"]) for r in runs}):
        rows = [r for r in runs if int(r["step"]) == step]
        dev = deviation_deg([r["methods"][main_method] for r in rows], [r["reference_deg"] for r in rows])
        out.append(
            {
                "step": step,
                "reference_deg": float(rows[0]["reference_deg"]),
                **spread(dev, [r.get("heading_std_deg") for r in rows]),
            }
        )
    return out
