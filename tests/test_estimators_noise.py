"""Statistics: Monte Carlo σψ against the noise limit, the reported 1σ, drift, the MC module.

White-noise trials are drawn here on top of the independent forward model of
tests/test_estimators.py (own rotation matrices), not from northfinder.estimators.montecarlo;
the Monte Carlo module is checked separately against that model and against theory.
Fixed seeds. Tolerances: 4000 trials give σ_MC a relative standard error of 1/√(2·4000) =
1.1 %, so the [0.95, 1.05] band is > 4 standard errors wide.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from test_estimators import attitude, body_means, wrap180

from northfinder.estimators import montecarlo as mc
from northfinder.estimators.heading import solve_batch
from northfinder.estimators.limits import noise_limit_heading_std_deg, per_position_std_dph

TRIALS = 4000
HEADING_DEG, TILT_AZ_DEG = 30.0, 90.0  # tilt azimuth 90° relative to north: the largest k


def _white_trials(rng, n, t_total, arw, lat, tilt, three_axis):
    angles = np.arange(n) * 360.0 / n
    c_pn, _, _ = attitude([HEADING_DEG], [tilt], [TILT_AZ_DEG])
    w_b, f_b = body_means(angles, c_pn, lat)
    sd = per_position_std_dph(arw, t_total / n)
    k = 3 if three_axis else 1
    cols = slice(None) if three_axis else slice(1, 2)
    gyro = w_b[:, :, cols] + sd * rng.standard_normal((TRIALS, n, k))
    accel = np.broadcast_to(f_b[:, :, cols], gyro.shape)
    if not three_axis:
        gyro, accel = gyro[..., 0], accel[..., 0]
    std = np.full((n, 3), sd) if three_axis else np.full(n, sd)
    return angles, gyro, accel, std


CELLS = list(itertools.product((4, 8, 24), (120.0, 600.0), (0.002, 0.012), (0.0, 40.0, 60.0), (0.0, 10.0)))


@pytest.mark.parametrize("three_axis", [False, True])
def test_monte_carlo_sigma_matches_the_noise_limit_in_every_cell(three_axis):
    rng = np.random.default_rng(20261122 + three_axis)
    bad = []
    for n, t_total, arw, lat, tilt in CELLS:
        angles, gyro, accel, std = _white_trials(rng, n, t_total, arw, lat, tilt, three_axis)
        sol = solve_batch(angles, gyro, accel, lat, gyro_std_dph=std)
        err = wrap180(sol.heading_deg - HEADING_DEG)
        sigma_mc = np.sqrt(np.mean(err**2))
        limit = noise_limit_heading_std_deg(arw, t_total, lat, tilt, TILT_AZ_DEG, 2 if three_axis else 1)
        ratio = sigma_mc / limit
        reported = np.sqrt(np.mean(sol.heading_std_deg**2)) / sigma_mc
        if not (0.95 <= ratio <= 1.05 and 0.9 <= reported <= 1.1):
            bad.append((n, t_total, arw, lat, tilt, round(ratio, 4), round(reported, 4)))
    assert not bad, bad


def test_tilted_bound_differs_from_the_level_formula_and_holds():
    """At 25° tilt toward east the level formula is 10 % low; the tilted bound k holds."""
    rng = np.random.default_rng(5)
    n, t_total, arw, lat, tilt = 8, 600.0, 0.012, 40.0, 25.0
    angles, gyro, accel, std = _white_trials(rng, n, t_total, arw, lat, tilt, False)
    sol = solve_batch(angles, gyro, accel, lat, gyro_std_dph=std)
    sigma_mc = np.std(wrap180(sol.heading_deg - HEADING_DEG))
    level = noise_limit_heading_std_deg(arw, t_total, lat)
    tilted = noise_limit_heading_std_deg(arw, t_total, lat, tilt, TILT_AZ_DEG)
    assert tilted / level == pytest.approx(1.0 / np.cos(np.deg2rad(tilt)))
    assert 0.95 <= sigma_mc / tilted <= 1.05
    assert sigma_mc / level > 1.05


def test_residual_sigma_is_unbiased_in_variance_but_scatters_at_n4():
    rng = np.random.default_rng(11)
    angles, gyro, accel, _ = _white_trials(rng, 4, 120.0, 0.012, 40.0, 0.0, False)
    sol = solve_batch(angles, gyro, accel, 40.0)
    sigma_mc = np.std(wrap180(sol.heading_deg - HEADING_DEG))
    rms_reported = np.sqrt(np.mean(sol.heading_std_deg**2))
    assert 0.9 <= rms_reported / sigma_mc <= 1.1
    # one degree of freedom: σ̂²/σ² ~ χ²₁, so the reported σ is below half the truth ≈ 38 % of the time
    frac_low = np.mean(sol.heading_std_deg < 0.5 * sigma_mc)
    assert 0.33 < frac_low < 0.43


# --- drift -------------------------------------------------------------------------------------
def _drift_rms(order, bias_model, gyro, n=8, seed=3):
    rng = np.random.default_rng(seed)
    idx = np.arange(n) if order == "natural" else mc.interleaved_order(n)
    plan = mc.Plan(mc.equally_spaced_deg(n)[idx], dwell_s=600.0 / n, gap_s=10.0)
    b = mc.simulate(rng, TRIALS, plan, HEADING_DEG, 1.0, 2.0, 40.0, gyro)
    sol = solve_batch(
        b.table_angle_deg, b.gyro_dph, b.accel_g, 40.0, bias_model=bias_model, sample_times_s=b.sample_times_s
    )
    return np.sqrt(np.mean(wrap180(sol.heading_deg - HEADING_DEG) ** 2))


def test_drift_aware_estimator_wins_where_drift_dominates():
    drift = mc.GyroNoise(arw_deg_rt_h=0.002, rrw_dph_rt_h=0.5)
    plain, aware = _drift_rms("natural", "constant", drift), _drift_rms("natural", "linear", drift)
    assert aware < 0.85 * plain
    plain_i, aware_i = (
        _drift_rms("interleaved", "constant", drift),
        _drift_rms("interleaved", "linear", drift),
    )
    assert aware_i < 0.95 * plain_i
    assert plain_i < 0.5 * plain  # the visiting order is the bigger lever
    gm = mc.GyroNoise(arw_deg_rt_h=0.002, gm_sigma_dph=0.05, gm_tau_s=300.0)
    assert _drift_rms("interleaved", "linear", gm) < _drift_rms("natural", "constant", gm)


def test_drift_model_costs_noise_when_white_noise_dominates():
    white = mc.GyroNoise(arw_deg_rt_h=0.012)
    assert _drift_rms("natural", "linear", white) > 1.15 * _drift_rms("natural", "constant", white)
    # with the interleaved order the linear term is nearly orthogonal to cos/sin: little cost
    assert _drift_rms("interleaved", "linear", white) < 1.05 * _drift_rms("interleaved", "constant", white)


# --- the Monte Carlo module ------------------------------------------------------------------------
def test_montecarlo_truth_matches_the_independent_forward_model():
    angles = np.array([0.0, 75.0, 180.0, 290.0])
    pitch, roll = mc.pitch_roll_for_tilt(123.0, 8.0, 250.0)
    c_pn, p_ref, r_ref = attitude([123.0], [8.0], [250.0])
    assert pitch == pytest.approx(p_ref[0]) and roll == pytest.approx(r_ref[0])
    w_mc, f_mc = mc.true_means(angles, 123.0, pitch, roll, -35.0)
    w_ref, f_ref = body_means(angles, c_pn, -35.0)
    assert np.allclose(w_mc / (np.pi / 180 / 3600), w_ref, rtol=0, atol=1e-12)
    assert np.allclose(f_mc, f_ref, rtol=0, atol=1e-15)


def test_montecarlo_noise_statistics_follow_their_definitions():
    rng = np.random.default_rng(9)
    plan = mc.Plan(mc.equally_spaced_deg(6), dwell_s=50.0, gap_s=8.0)
    b = mc.simulate(rng, 20000, plan, 0.0, 0.0, 0.0, 40.0, mc.GyroNoise(arw_deg_rt_h=0.01),
                    mc.AccelNoise(noise_ug_rt_hz=30.0), three_axis=True)  # fmt: skip
    w_true, f_true = mc.true_means(plan.table_angle_deg, 0.0, 0.0, 0.0, 40.0)
    assert np.std(b.gyro_dph - w_true / (np.pi / 180 / 3600)) == pytest.approx(
        0.01 * 60 / np.sqrt(50), rel=0.01
    )
    assert np.std(b.accel_g - f_true) == pytest.approx(30e-6 / np.sqrt(50), rel=0.01)
    # rate random walk: consecutive dwell means differ with variance q²(2T/3 + gap)
    q = 0.3 / 60.0
    b = mc.simulate(rng, 20000, plan, 0.0, 0.0, 0.0, 40.0, mc.GyroNoise(rrw_dph_rt_h=0.3))
    d = np.diff(b.gyro_dph - np.broadcast_to(w_true[..., 1] / (np.pi / 180 / 3600), b.gyro_dph.shape), axis=1)
    assert np.var(d) == pytest.approx(q**2 * (2 * 50.0 / 3 + 8.0), rel=0.03)
    # Gauss–Markov: a dwell mean has variance σ²·(2τ/T)·(1 − (τ/T)(1 − e^(−T/τ)))
    sig, tau, t = 0.05, 40.0, 50.0
    b = mc.simulate(rng, 20000, plan, 0.0, 0.0, 0.0, 40.0, mc.GyroNoise(gm_sigma_dph=sig, gm_tau_s=tau))
    m = b.gyro_dph - w_true[..., 1] / (np.pi / 180 / 3600)
    expect = sig**2 * (2 * tau / t) * (1 - (tau / t) * (1 - np.exp(-t / tau)))
    assert np.var(m) == pytest.approx(expect, rel=0.04)


def test_constant_biases_do_not_bias_the_heading():
    rng = np.random.default_rng(13)
    plan = mc.Plan(mc.equally_spaced_deg(8), dwell_s=30.0)
    pitch, roll = mc.pitch_roll_for_tilt(200.0, 5.0, 20.0)
    gyro = mc.GyroNoise(arw_deg_rt_h=0.005, bias_dph=0.5, bias_sigma_dph=1.0)
    accel = mc.AccelNoise(noise_ug_rt_hz=20.0, bias_ug=500.0, bias_sigma_ug=300.0)
    b = mc.simulate(rng, TRIALS, plan, 200.0, pitch, roll, 40.0, gyro, accel, three_axis=True)
    sol = solve_batch(
        b.table_angle_deg, b.gyro_dph, b.accel_g, 40.0, gyro_std_dph=b.gyro_std_dph, accel_std_g=b.accel_std_g
    )
    err = wrap180(sol.heading_deg - 200.0)
    assert abs(err.mean()) < 4.0 * err.std() / np.sqrt(TRIALS)
    assert 0.9 < np.sqrt(np.mean(sol.heading_std_deg**2)) / err.std() < 1.1
