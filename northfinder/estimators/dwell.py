"""Whether a dwell is good enough to keep: gaps and lost samples (device counters), samples flagged not
valid, and disturbances (a window mean far off the dwell's level). Pure: the sequencer hands in the
dwell's samples and acts on the answer (measure the position again).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.ma  # noqa: F401 - np.median imports it on its first call (~7 ms, the GIL held): not mid-run

from northfinder.constants import DPH

DISTURBANCE_Z = 7.0
"""A window mean this many of its own white-noise σ from the dwell's median is a disturbance:
P(|z| > 7) ≈ 3e-12 per window, so a clean dwell of thousands of windows never trips it."""
ACCEL_QUANTUM_G = 1e-6
"""The accelerometer's step (1 µg): its per-sample σ is at least step/√12."""


@dataclass(frozen=True)
class DwellLimits:
    """When a dwell is measured again: an IMU gap longer than `imu_max_gap_s` (device time), more
    than `max_lost_fraction` of the IMU samples lost (or flagged not valid on a gyro axis), more than
    `accel_max_lost_fraction` of the accelerometer's lost, fewer than `accel_min_fraction` of its
    dwell read before it stopped for the next move, or a disturbance in windows of
    `disturbance_window_s` (twice that for the accelerometer)."""

    imu_max_gap_s: float = 0.1
    max_lost_fraction: float = 0.05
    accel_max_lost_fraction: float = 0.2
    disturbance_window_s: float = 0.1
    accel_min_fraction: float = 0.9
    """A tilt sensor stopped for the next move before this fraction of its dwell had come: again."""


def disturbance_z(samples: np.ndarray, window: int, floor: float = 0.0) -> tuple[float, int]:
    """Largest |window mean − median of the window means| in units of the white-noise σ of a window
    mean, over every column; returns (z, window index).

    A robust step/bump test (not from the papers: a plain outlier test on block means). At rest a
    dwell's samples are white noise about a constant, so block means of `window` samples scatter
    with σ/√window, where the per-sample σ is estimated from first differences (std(Δx)/√2 for
    white noise), robustly by the median over blocks so that a bump inflates nothing. `floor` is
    the smallest per-sample σ (a quantized channel's step/√12).
    """
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    n_win = x.shape[0] // int(window)
    if n_win < 3:
        return 0.0, -1
    blocks = x[: n_win * window].reshape(n_win, window, x.shape[1])
    return _window_z(blocks.mean(axis=1), np.std(np.diff(blocks, axis=1), axis=1), window, floor)


def _window_z(means: np.ndarray, diff_std: np.ndarray, window: int, floor: float) -> tuple[float, int]:
    """From the windows' means and first-difference stds [n_win, k]: the largest |mean − median of
    the means| in σ of a window mean (σ per sample = median diff std / √2, at least `floor`), and
    its window."""
    sigma = np.maximum(np.median(diff_std, axis=0) / np.sqrt(2.0), floor)  # [k]
    z = np.abs(means - np.median(means, axis=0)) / (np.maximum(sigma, 1e-300) / np.sqrt(window))
    j = int(np.argmax(z.max(axis=1)))
    return float(z[j].max()), j


def disturbance_valid(samples: np.ndarray, window: int) -> tuple[float, int]:
    """:func:`disturbance_z` over the columns that have valid samples, each on its own valid samples
    (NaN = flagged not valid, or an axis the unit lacks); the window index is of that column."""
    best = (0.0, -1)
    for col in np.asarray(samples, dtype=np.float64).T:
        ok = col[np.isfinite(col)]
        if ok.size:
            best = max(best, disturbance_z(ok, window))
    return best


class DisturbanceWindows:
    """:func:`disturbance_valid` built as a dwell's samples arrive: per column and window of `window`
    samples its mean and the std of its first differences, so that the verdict at the dwell's end is
    a median over the windows, not a pass over every sample (the host's work between a dwell's end
    and the next move lets a time-scaled simulator's device time run on). Each column's windows are
    reduced as the batch reduces them (a contiguous column reshaped to windows), so :meth:`z` equals
    :func:`disturbance_valid` on the concatenated samples bit for bit. A column must be wholly valid
    or wholly NaN (an axis the unit lacks); one that mixes both (samples flagged not valid) makes
    :meth:`z` None, and the caller runs the batch test on the samples."""

    def __init__(self, window: int) -> None:
        self.window = int(window)
        self._valid: np.ndarray | None = None
        """Per column: True all samples valid so far, False all NaN."""
        self._carry: list[np.ndarray] = []
        self._means: list[list[np.ndarray]] = []
        self._diff_std: list[list[np.ndarray]] = []
        self.mixed = False

    def add(self, samples: np.ndarray) -> None:
        x = np.asarray(samples, dtype=np.float64)
        if self.mixed or x.shape[0] == 0:
            return
        finite = np.isfinite(x)
        valid, none = finite.all(axis=0), ~finite.any(axis=0)
        if np.any(~valid & ~none) or (self._valid is not None and np.any(valid != self._valid)):
            self.mixed = True
            return
        if self._valid is None:
            self._valid = valid
            cols = int(valid.sum())
            self._carry = [np.zeros(0)] * cols
            self._means, self._diff_std = [[] for _ in range(cols)], [[] for _ in range(cols)]
        for k, c in enumerate(np.flatnonzero(valid)):
            col = np.concatenate([self._carry[k], x[:, c]])
            n_win = col.size // self.window
            if n_win:
                blocks = col[: n_win * self.window].reshape(n_win, self.window, 1)
                self._means[k].append(blocks.mean(axis=1))
                self._diff_std[k].append(np.std(np.diff(blocks, axis=1), axis=1))
            self._carry[k] = col[n_win * self.window :]

    def z(self) -> tuple[float, int] | None:
        """(largest z, its window index) as :func:`disturbance_valid` gives it; None when a column
        mixed valid and NaN samples."""
        if self.mixed:
            return None
        best = (0.0, -1)
        for means_parts, std_parts in zip(self._means, self._diff_std, strict=True):
            if not means_parts or sum(len(m) for m in means_parts) < 3:
                continue
            best = max(best, _window_z(np.vstack(means_parts), np.vstack(std_parts), self.window, 0.0))
        return best


def invalid_problems(gyro_dph: np.ndarray, n: int, gyro_axes: str, max_lost_fraction: float) -> list[str]:
    """Too many samples flagged not valid on a gyro axis the fit needs: measured again like a dwell
    that lost them."""
    out = []
    for a in gyro_axes:
        bad = int(np.count_nonzero(np.isnan(gyro_dph[:, "xyz".index(a)])))
        if bad > max_lost_fraction * n:
            out.append(f"imu gyro {a}: {bad} of {n} samples flagged not valid (status bit cleared)")
    return out


def _counter_problems(idx: np.ndarray, stalls: list[int], rate: float,
                      limits: DwellLimits) -> list[str]:
    """Gaps and lost samples, from the device counters."""
    out = []
    gap = int(np.max(np.diff(idx))) - 1 if idx.size > 1 else 0
    lost = int(idx[-1] - idx[0] + 1 - idx.size)
    inside = [k for k in stalls if idx[0] < k <= idx[-1]]
    if inside:
        out.append(
            f"imu stream paused (silent) inside the dwell at sample {inside[0]}: a timeout or bytes lost "
            "on the line, its length unknown (the 7-bit sequence wraps)"
        )
    elif gap > limits.imu_max_gap_s * rate:
        out.append(f"imu gap of {gap} samples ({gap / rate:.3f} s device time) inside the dwell")
    elif lost > limits.max_lost_fraction * idx.size:
        out.append(f"imu lost {lost} of {lost + idx.size} samples")
    return out


@dataclass(frozen=True)
class DwellVerdict:
    """One stream's findings on a dwell: `counts` (gaps, lost or invalid samples) make the
    disturbance test moot, `disturbances` are reported only when no stream has a count problem."""

    counts: list[str]
    disturbances: list[str]


def imu_window(imu_rate_hz: float, limits: DwellLimits) -> int:
    """The IMU's disturbance window [samples]."""
    return max(10, int(round(limits.disturbance_window_s * float(imu_rate_hz))))


def imu_dwell_verdict(blocks: list[Any], *, imu_rate_hz: float, gyro_axes: str, stalls: list[int],
                      limits: DwellLimits, windows: DisturbanceWindows | None = None) -> DwellVerdict:
    """The IMU's share of why a dwell must be measured again (its ImuBlocks): a gap or too many lost
    samples (device sample counters; `stalls`: first index after each gap of unknown length), samples
    flagged not valid, or a disturbance in the gyro and accelerometer statistics. The sequencer
    works it out while the tilt sensor's dwell is still arriving. `windows`: the same blocks'
    DisturbanceWindows, kept as they arrived (gyro in °/h, then accelerometer), which spares the
    pass over the samples."""
    rate = float(imu_rate_hz)
    idx = np.concatenate([np.asarray(b.sample_index) for b in blocks])
    gyro = np.concatenate([np.asarray(b.gyro_rad_s) for b in blocks], axis=0) / DPH
    counts = _counter_problems(idx, stalls, rate, limits)
    counts += invalid_problems(gyro, idx.size, gyro_axes, limits.max_lost_fraction)
    if counts:
        return DwellVerdict(counts, [])
    w = imu_window(rate, limits)
    kept = windows.z() if windows is not None and windows.window == w else None
    if kept is None:
        imu_acc = np.concatenate([np.asarray(b.accel_g) for b in blocks], axis=0)
        kept = disturbance_valid(np.hstack([gyro, imu_acc]), w)
    z, j = kept
    if z <= DISTURBANCE_Z:
        return DwellVerdict([], [])
    return DwellVerdict([], [f"disturbance: IMU window {j} ({j * w / rate:.2f} s into the dwell) is "
                             f"{z:.1f} σ off the dwell's level"])


def accel_dwell_verdict(accel_block: Any, *, accel_rate_hz: float, limits: DwellLimits,
                        expected: int | None = None) -> DwellVerdict:
    """The tilt sensor's share of why a dwell must be measured again (its AccelBlock): fewer samples
    than `limits.accel_min_fraction` of the `expected`, too many lost, or a disturbance."""
    counter = np.asarray(accel_block.counter)
    a_lost = int(accel_block.lost_samples)
    if expected is not None and counter.size + a_lost < limits.accel_min_fraction * expected:
        return DwellVerdict([f"accelerometer stopped for the next move after {counter.size + a_lost} of its "
                             f"{expected} dwell samples (too few)"], [])
    if a_lost > limits.accel_max_lost_fraction * max(counter.size, 1):
        return DwellVerdict([f"accelerometer lost {a_lost} of {a_lost + counter.size} samples (too few)"], [])
    wa = max(5, int(round(2.0 * limits.disturbance_window_s * accel_rate_hz)))
    za, ja = disturbance_z(np.asarray(accel_block.accel_g), wa, floor=ACCEL_QUANTUM_G / np.sqrt(12.0))
    if za <= DISTURBANCE_Z:
        return DwellVerdict([], [])
    return DwellVerdict([], [f"disturbance: accelerometer window {ja} ({ja * wa / accel_rate_hz:.2f} s into "
                             f"its dwell) is {za:.1f} σ off"])


def combine_verdicts(*verdicts: DwellVerdict) -> list[str]:
    """Why a dwell must be measured again (empty if it is good): every stream's count problems, else
    every disturbance."""
    counts = [p for v in verdicts for p in v.counts]
    return counts or [p for v in verdicts for p in v.disturbances]

