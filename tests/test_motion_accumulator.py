"""MotionFitAccumulator (estimators/motion_fit.py): the find's per-sample fit from the samples as
they arrive, against today's batch (place_samples + fit_motion_screened) on the same stream.

Equivalence: every sample's table angle and rate are the same calls on the same arrays (checked
through the counts and the fit); the least squares goes through QR factors per stretch instead of
(AᵀA)⁻¹Aᵀy over all samples, so coefficients and covariance agree to rounding, not bit for bit:
the bound used is 1e-9 of each coefficient's own 1σ (covariance entries 1e-9·σ_i·σ_j, residual
RMS 1e-9 relative) — rounding in either route is ~ε·cond(A)² ≤ 2e-16·1e8 relative (cond ≤
MAX_CONDITION = 1e4), and the noise limit is 1σ, so the two can never be told apart in a result.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from northfinder.errors import InputError
from northfinder.estimators import plan as P
from northfinder.estimators.motion_fit import (
    RUN_TERMS,
    MotionFitAccumulator,
    fit_motion_screened,
    place_samples,
)
from tests.test_motion_fit import _stream_with_dwells

RATE_HZ = 100.0


def _noisy_stream(seed: int = 11, knock: bool = False):
    sch, idx, gyro, dwells = _stream_with_dwells(RATE_HZ)
    noise_dph = P.GRADES["nav"].arw_deg_rt_h * 60.0 * math.sqrt(RATE_HZ)  # per-sample σ (ARW·60·√rate)
    rng = np.random.default_rng(seed)
    noisy = gyro + rng.normal(0.0, noise_dph, gyro.shape)
    if knock:  # 1 s, 300 °/h half-sine on x and y as the table starts its fourth move
        mid = dwells[3][1] - 1000 + int(np.argmax(sch.omega_dps[dwells[3][1] - 1000 :] > 0))
        pulse = 300.0 * np.sin(np.pi * np.arange(int(RATE_HZ)) / RATE_HZ)
        noisy[mid : mid + int(RATE_HZ), 0] += pulse
        noisy[mid : mid + int(RATE_HZ), 1] -= pulse
    return idx, noisy, dwells


def _accumulate(idx, gyro, dwells, chunk: int) -> MotionFitAccumulator:
    """Feed the stream in `chunk`-sample pieces; each dwell once its last sample has arrived."""
    acc = MotionFitAccumulator(RATE_HZ, ("x", "y"), RUN_TERMS)
    pending = list(dwells)
    peak = 0
    for lo in range(0, idx.size, chunk):
        acc.add_samples(idx[lo : lo + chunk], gyro[lo : lo + chunk])
        while pending and pending[0][1] <= idx[min(lo + chunk, idx.size) - 1]:
            acc.add_dwell(*pending.pop(0))
        peak = max(peak, acc.held_samples())
    acc.peak_held = peak
    return acc


def _assert_equivalent(batch, ours):
    sd = np.sqrt(np.diag(batch.covariance[0]))
    assert ours.names == batch.names and ours.dof == batch.dof and ours.noise == batch.noise
    np.testing.assert_array_less(np.abs(ours.coefficients[0] - batch.coefficients[0]), 1e-9 * sd)
    # covariance entries against σ_i·σ_j (entries that are 0 but for rounding, ~1e-21 here, have no
    # relative precision)
    np.testing.assert_array_less(np.abs(ours.covariance[0] - batch.covariance[0]), 1e-9 * np.outer(sd, sd))
    for ax in ("x", "y"):
        np.testing.assert_allclose(ours.residual_rms[ax], batch.residual_rms[ax], rtol=1e-9)


@pytest.mark.parametrize("chunk", [37, 216, 4096])
def test_same_fit_as_the_batch_on_the_same_stream(chunk):
    idx, gyro, dwells = _noisy_stream()
    alpha, omega, g, counts = place_samples(idx, gyro, dwells, RATE_HZ)
    batch, keep, dropped = fit_motion_screened(alpha, omega, g[:, :2])
    acc = _accumulate(idx, gyro, dwells, chunk)
    ours, ours_counts = acc.fit_screened()
    assert {k: ours_counts[k] for k in counts} == counts
    assert ours_counts["stretches_disturbed"] == dropped == 0
    assert ours_counts["samples_used"] == int(keep.sum())
    _assert_equivalent(batch, ours)
    # what it holds is one step of the plan (a move and a dwell), not the run
    gaps = [d1[0] - d0[1] for d0, d1 in zip(dwells[:-1], dwells[1:], strict=True)]
    step = max(b - a for a, b, _ in dwells) + max(gaps)
    assert acc.peak_held <= 2 * step + chunk < idx.size


def test_the_same_stretch_screened_out_after_a_knock():
    idx, gyro, dwells = _noisy_stream(knock=True)
    alpha, omega, g, _ = place_samples(idx, gyro, dwells, RATE_HZ)
    batch, keep, dropped = fit_motion_screened(alpha, omega, g[:, :2])
    ours, counts = _accumulate(idx, gyro, dwells, 500).fit_screened()
    assert dropped == counts["stretches_disturbed"] == 1
    assert counts["samples_used"] == int(keep.sum())
    _assert_equivalent(batch, ours)


def test_a_lost_sample_drops_its_stretch_as_place_samples_does():
    idx, gyro, dwells = _noisy_stream()
    keep = np.ones(idx.size, bool)
    keep[(dwells[2][1] + dwells[3][0]) // 2 - 1000] = False
    bad = gyro.copy()
    bad[(dwells[4][1] + dwells[5][0]) // 2 - 1000, 0] = np.nan
    idx, bad = idx[keep], bad[keep]
    alpha, omega, g, counts = place_samples(idx, bad, dwells, RATE_HZ)
    batch, _, _ = fit_motion_screened(alpha, omega, g[:, :2])
    ours, ours_counts = _accumulate(idx, bad, dwells, 1000).fit_screened()
    assert counts["stretches_dropped"] == ours_counts["stretches_dropped"] == 2
    assert {k: ours_counts[k] for k in counts} == counts
    _assert_equivalent(batch, ours)


def test_out_of_order_input_is_one_clear_error():
    acc = MotionFitAccumulator(RATE_HZ)
    acc.add_samples(np.arange(10), np.zeros((10, 3)))
    with pytest.raises(InputError, match="increase"):
        acc.add_samples(np.arange(5, 15), np.zeros((10, 3)))
    acc.add_dwell(0, 9, 0.0)
    with pytest.raises(InputError, match="time order"):
        acc.add_dwell(3, 4, 0.0)
