"""Swaying-base gyrocompass (northfinder.align.swaying) and its static baseline (align.coarse).

Data come from the independent forward model in tests/test_swaying_forward.py (closed-form
ship motion, quadrature increments, white noise at the grade's ARW). Fixed seeds; tolerances
come from the noise limit and from the physics stated next to each assertion.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_swaying_forward import (
    D2R,
    GRADES,
    OMEGA_E,
    REFERENCE,
    STILL,
    Sway,
    SwayingShip,
    heading_deg,
    simulate_imu,
)

from northfinder.align.coarse import coarse_align
from northfinder.align.swaying import (
    align_swaying,
    align_swaying_block,
    attitude_quaternions,
    minimum_duration_s,
    predicted_heading_std_deg,
    quat_prefix_product,
    quat_to_dcm,
    white_noise_density,
)
from northfinder.constants import wrap_deg_180
from northfinder.errors import InputError

LAT = 40.0
RATE_HZ = 50.0  # enough for 6–10 s sway; keeps 50 Monte Carlo runs of 300 s inside the budget
T_S = 300.0
N_RUNS = 50


def _run(seed: int, sway: Sway, grade_name: str, duration_s: float = T_S, lat: float = LAT):
    rng = np.random.default_rng(seed)
    ship = SwayingShip(rng.uniform(0.0, 360.0), lat, sway, rng.uniform(0.0, 2 * np.pi, 4))
    grade = GRADES[grade_name]
    gyro, accel = simulate_imu(ship, duration_s, RATE_HZ, grade, rng)
    truth = heading_deg(ship.c_b_n(np.array(duration_s)))
    return ship, gyro, accel, truth, grade


def _monte_carlo(sway: Sway, grade_name: str, n_runs: int, seed0: int, with_gls: bool = False):
    sw_err, sw_std, co_err, co_std, diff, gls_err = [], [], [], [], [], []
    for i in range(n_runs):
        _, gyro, accel, truth, grade = _run(seed0 + i, sway, grade_name)
        sol = align_swaying(gyro, accel, RATE_HZ, LAT, gyro_bias_dph=grade.gyro_bias_dph,
                            accel_bias_ug=grade.accel_bias_ug)
        co = coarse_align(gyro, accel, RATE_HZ, LAT)
        if with_gls:
            gls = align_swaying(gyro, accel, RATE_HZ, LAT, method="cone-gls",
                                gyro_bias_dph=grade.gyro_bias_dph, accel_bias_ug=grade.accel_bias_ug)
            gls_err.append(wrap_deg_180(gls.heading_deg - truth))
        sw_err.append(wrap_deg_180(sol.heading_deg - truth))
        sw_std.append(sol.heading_std_deg)
        co_err.append(wrap_deg_180(co.heading_deg - truth))
        co_std.append(co.heading_std_deg)
        diff.append(wrap_deg_180(sol.heading_deg - co.heading_deg))
    return {k: np.asarray(v, dtype=float) for k, v in
            dict(sw_err=sw_err, sw_std=sw_std, co_err=co_err, co_std=co_std, diff=diff,
                 gls_err=gls_err).items()}


@pytest.fixture(scope="module")
def reference_mc():
    return _monte_carlo(REFERENCE, "nav", N_RUNS, seed0=5000, with_gls=True)


@pytest.fixture(scope="module")
def still_mc():
    return _monte_carlo(STILL, "nav", 20, seed0=7000)


def _noise_limit_deg(grade, duration_s: float, lat: float = LAT) -> float:
    """find's limit σψ = N/(Ωe·cos L)·√(2/T) (docs/CONVENTIONS.md)."""
    n = grade.arw_deg_rt_h * D2R / 60.0
    return np.degrees(n / (OMEGA_E * np.cos(lat * D2R)) * np.sqrt(2.0 / duration_s))


def _bias_floor_deg(grade, lat: float = LAT) -> float:
    """εE/(Ωe·cos L) for a 1σ turn-on bias εE."""
    return np.degrees(grade.gyro_bias_dph * D2R / 3600.0 / (OMEGA_E * np.cos(lat * D2R)))


# --- the must-show figures ------------------------------------------------------------------
def test_reference_scenario_nav_grade_beats_0p10_deg(reference_mc):
    """Reference sway, nav grade, 50 runs, 300 s: σψ ≤ 0.10° (the issue's target)."""
    err = reference_mc["sw_err"]
    sigma = err.std(ddof=1)
    print(f"\nswaying cone fit, nav, 300 s, {N_RUNS} runs: σψ = {sigma:.4f}°, mean = {err.mean():+.4f}°, "
          f"mean reported 1σ = {reference_mc['sw_std'].mean():.4f}°")
    assert sigma <= 0.10
    # The sample mean of 50 runs is unbiased within 4 standard errors.
    assert abs(err.mean()) <= 4.0 * sigma / np.sqrt(N_RUNS)


def test_reported_sigma_matches_monte_carlo_scatter(reference_mc):
    """The propagated 1σ agrees with the scatter: for 50 runs the sample σ has a ±10 % standard
    error, so the ratio must lie in [0.7, 1.4] (3 standard errors, plus room for the sway leakage
    that the propagation does not model)."""
    ratio = reference_mc["sw_err"].std(ddof=1) / np.sqrt(np.mean(reference_mc["sw_std"] ** 2))
    assert 0.7 <= ratio <= 1.4, ratio
    # And 1σ is not just a constant: it follows the grade's noise limit plus the bias floor.
    grade = GRADES["nav"]
    expected = np.hypot(_noise_limit_deg(grade, T_S), _bias_floor_deg(grade))
    assert 0.5 * expected <= reference_mc["sw_std"].mean() <= 2.0 * expected


def test_gls_fine_step_is_no_worse_and_gains_little(reference_mc):
    """The noise-weighted GLS step (batch form of a Kalman fine alignment on the same windows) is the
    best linear unbiased estimate for the modelled noise; its predicted white-noise σ is only ~5 % below the
    unweighted fit at 300 s (docs/swaying.md §6), which 50 runs cannot resolve. So: on the same
    data it must stay within 15 % of the cone fit, and the two must agree run by run."""
    s_cone = reference_mc["sw_err"].std(ddof=1)
    s_gls = reference_mc["gls_err"].std(ddof=1)
    print(f"\ncone σψ = {s_cone:.4f}°, cone-gls σψ = {s_gls:.4f}° (same {N_RUNS} runs)")
    assert s_gls <= 1.15 * s_cone
    assert np.std(reference_mc["gls_err"] - reference_mc["sw_err"]) < 0.5 * s_cone


def test_static_coarse_alignment_fails_under_sway(reference_mc):
    """Same data: the static TRIAD loses north. Physics: the mean sway rate over 300 s of a
    10°/8 s roll is up to A·ω/(ω·T) ≈ 6e-4 rad/s ≈ 8·Ωe, so the east direction is random."""
    co = reference_mc["co_err"]
    sw = reference_mc["sw_err"]
    rms_co = np.sqrt(np.mean(co**2))
    print(f"\nstatic coarse on the same data: rms ψ error = {rms_co:.2f}°, σψ = {co.std(ddof=1):.2f}°, "
          f"swaying rms = {np.sqrt(np.mean(sw**2)):.4f}°")
    assert rms_co > 10.0
    assert rms_co > 100.0 * np.sqrt(np.mean(sw**2))


def test_still_ship_agrees_with_noise_limit_and_coarse(still_mc):
    """No sway: both methods reach the gyrocompass noise level (order of magnitude of find's limit
    ⊕ the bias floor) and agree with each other within their combined 1σ."""
    grade = GRADES["nav"]
    limit = np.hypot(_noise_limit_deg(grade, T_S), _bias_floor_deg(grade))
    s_sw = np.sqrt(np.mean(still_mc["sw_err"] ** 2))
    s_co = np.sqrt(np.mean(still_mc["co_err"] ** 2))
    print(f"\nstill ship, nav, 300 s: swaying rms {s_sw:.4f}°, coarse rms {s_co:.4f}°, "
          f"find limit ⊕ bias floor {limit:.4f}°")
    assert limit / 3.0 <= s_sw <= 3.0 * limit
    assert limit / 3.0 <= s_co <= 3.0 * limit
    combined = np.sqrt(still_mc["sw_std"] ** 2 + still_mc["co_std"] ** 2)
    # Both see the same bias, so their difference is bounded by the white-noise parts: 4σ.
    assert np.all(np.abs(still_mc["diff"]) <= 4.0 * combined)


def test_predicted_sigma_is_bounded_by_the_gyrocompass_limit():
    """No estimator beats the increment estimator N/(Ωe·cosL·√T) (a random walk's slope is best
    estimated from its end points); the cone fit loses only the L_w the smoothing spends on its
    ramps and the √(6/5) of an unweighted slope fit to a random walk, so it stays within
    1.25·√(T/(T−L_w)) of the limit; GLS is never worse than OLS."""
    grade = GRADES["nav"]
    for t in (120.0, 300.0, 600.0):
        limit = np.degrees(grade.arw_deg_rt_h * D2R / 60.0 / (OMEGA_E * np.cos(LAT * D2R) * np.sqrt(t)))
        ols = predicted_heading_std_deg(t, LAT, grade.arw_deg_rt_h, grade.accel_noise_ug_rt_hz)
        gls = predicted_heading_std_deg(t, LAT, grade.arw_deg_rt_h, grade.accel_noise_ug_rt_hz,
                                        weighting="gls")
        assert limit <= gls <= ols * (1 + 1e-9)
        # The limit is the gyro's: compare the gyro-only figure with it.
        ols_gyro = predicted_heading_std_deg(t, LAT, grade.arw_deg_rt_h, 0.0)
        assert limit <= ols_gyro <= 1.25 * np.sqrt(t / (t - 40.0)) * limit


# --- pieces ---------------------------------------------------------------------------------
def test_parallel_prefix_equals_sequential_product():
    rng = np.random.default_rng(1)
    phi = rng.normal(0, 0.3, (1000, 3))
    q = attitude_quaternions(phi)
    c = np.eye(3)
    from northfinder.rotations import coning_corrected_rotvec, rotvec_to_dcm

    for p in coning_corrected_rotvec(phi):
        c = c @ rotvec_to_dcm(p)
    assert np.allclose(quat_to_dcm(q[-1]), c, atol=1e-12)
    assert quat_prefix_product(np.array([[1.0, 0, 0, 0]])).shape == (1, 4)


def test_attitude_matches_closed_form_with_coning():
    """300 s of reference sway at 50 Hz: C_b^{i_b0}(T) from the increments against the exact
    C_b0^n(0)ᵀ·C_n(T)^{n0}·C_b^n(T). The coning term leaves O(ω³·dt²) drift: bound 1e-7 rad."""
    ship = SwayingShip(10.0, LAT, REFERENCE, (0.3, 1.0, 2.0, 0.5))
    n = int(T_S * RATE_HZ)
    dth, _ = ship.increments(n, RATE_HZ)
    q = attitude_quaternions(dth)
    k = np.array([0.0, np.cos(ship.lat), np.sin(ship.lat)])
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = OMEGA_E * T_S
    r = np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx
    truth = ship.c_b_n(np.array(0.0)).T @ r @ ship.c_b_n(np.array(T_S))
    e = truth.T @ quat_to_dcm(q[-1])
    assert np.max(np.abs(e - np.eye(3))) < 1e-7


def test_noise_density_is_measured_from_swaying_data():
    """ARW and accel noise recovered from the data within 5 % (σ of a MAD estimate over 15 000
    samples is ~1 %), despite the sway."""
    _, gyro, accel, _, grade = _run(11, REFERENCE, "kvh1760")
    dt = 1.0 / RATE_HZ
    arw = white_noise_density(gyro * dt, dt) * 60.0 / D2R
    acc = white_noise_density(accel * dt, dt) * 1e6
    assert np.allclose(arw, grade.arw_deg_rt_h, rtol=0.05)
    assert np.allclose(acc, grade.accel_noise_ug_rt_hz, rtol=0.05)


def test_noise_free_error_is_sway_leakage_only():
    """Perfect sensors: what is left is the smoothing's sway leakage — with the lever arm estimated
    (docs/swaying.md eq. 4a) under 0.001° (seen: 1e-5°; without it 0.002°); pitch and roll at t_end
    match the closed form to 0.01°. Also the southern hemisphere."""
    for lat in (LAT, -35.0):
        ship, gyro, accel, truth, _ = _run(21, REFERENCE, "perfect", lat=lat)
        sol = align_swaying(gyro, accel, RATE_HZ, lat)
        _, pitch, roll = ship.euler(np.array(T_S))
        assert abs(wrap_deg_180(sol.heading_deg - truth)) < 0.001
        assert sol.pitch_deg == pytest.approx(np.degrees(pitch), abs=0.01)
        assert sol.roll_deg == pytest.approx(np.degrees(roll), abs=0.01)
        assert sol.diagnostics["earth_axis_elevation_deg"] == pytest.approx(lat, abs=0.5)


def test_imu_block_input_and_lost_samples_filled():
    """The driver's ImuBlock with a 3-sample gap gives the same heading as the full record."""
    from northfinder.drivers.imu import ImuBlock

    _, gyro, accel, _, _ = _run(31, REFERENCE, "nav", duration_s=120.0)
    full = align_swaying(gyro, accel, RATE_HZ, LAT)
    keep = np.ones(gyro.shape[0], bool)
    keep[3000:3003] = False
    b = ImuBlock(sample_index=np.arange(gyro.shape[0])[keep] + 77, gyro_rad_s=gyro[keep], accel_g=accel[keep],
                 status=np.full(keep.sum(), 0x77, np.uint8), temperature_c=np.full(keep.sum(), 25.0),
                 lost_samples=3, rate_hz=RATE_HZ)
    sol = align_swaying_block(b, LAT)
    assert sol.diagnostics["lost_samples_filled"] == 3
    assert abs(wrap_deg_180(sol.heading_deg - full.heading_deg)) < 0.1 * full.heading_std_deg


def test_paper_circle_fit_runs_and_is_worse_than_cone():
    """The free space-circle fit of the paper on the same noise-free data: it must find north
    (within a few degrees) but the constrained cone fit must be closer."""
    _, gyro, accel, truth, _ = _run(41, REFERENCE, "perfect")
    circle = align_swaying(gyro, accel, RATE_HZ, LAT, method="circle")
    cone = align_swaying(gyro, accel, RATE_HZ, LAT, method="cone")
    e_circle = abs(wrap_deg_180(circle.heading_deg - truth))
    e_cone = abs(wrap_deg_180(cone.heading_deg - truth))
    assert e_circle < 5.0
    assert e_cone < e_circle
    # the windows' residuals the report draws are the fit's own: one row per window, their rms the
    # diagnostics' figure; the circle fit has no residual model, so none
    res = cone.window_residual_m_s2
    assert res.shape == (cone.window_t_s.size, 3) and cone.window_t_s.size == cone.diagnostics["n_windows"]
    assert np.sqrt(np.mean(res**2)) * 1e6 / 9.80665 == pytest.approx(cone.diagnostics["fit_residual_rms_ug"])
    assert circle.window_residual_m_s2.size == 0


# --- bad input: one clear line ----------------------------------------------------------------
def _one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and len(msg) < 300
    return msg


def test_sway_that_saturates_the_gyro():
    violent = Sway(roll_deg=30.0, roll_period_s=0.35)  # peak rate 30°·2π/0.35 s ≈ 540 °/s > 490 °/s
    _, gyro, accel, _, _ = _run(51, violent, "perfect", duration_s=90.0)
    with pytest.raises(InputError) as exc:
        align_swaying(gyro, accel, RATE_HZ, LAT)
    msg = _one_line(exc)
    assert "490" in msg and "saturat" in msg


def test_too_short_says_how_long_is_needed():
    _, gyro, accel, _, _ = _run(52, REFERENCE, "nav", duration_s=60.0)
    with pytest.raises(InputError) as exc:
        align_swaying(gyro, accel, RATE_HZ, LAT)
    msg = _one_line(exc)
    assert f"{minimum_duration_s(10.0):.0f} s" in msg and "60.0 s" in msg


def test_imu_without_accelerometers():
    _, gyro, accel, _, _ = _run(53, REFERENCE, "nav", duration_s=90.0)
    with pytest.raises(InputError) as exc:
        align_swaying(gyro, np.zeros_like(accel), RATE_HZ, LAT)
    assert "accelerometer" in _one_line(exc)
    valid = np.zeros((gyro.shape[0], 6), bool)
    valid[:, :3] = True  # the IMU flags its gyros valid, its accelerometers not (ImuBlock.valid)
    with pytest.raises(InputError) as exc:
        align_swaying(gyro, accel, RATE_HZ, LAT, valid=valid)
    assert "accelerometer" in _one_line(exc)
    with pytest.raises(InputError):
        coarse_align(gyro, np.zeros_like(accel), RATE_HZ, LAT)


# --- issue 16: the σ covers sway leakage and the bias floor; the coarse row has no false σ -------
def test_lever_arm_is_the_sway_leakage_and_is_estimated():
    """The cause of the 120 s leakage (docs/swaying.md §8): the IMU's lever arm r from the point the
    ship turns about. In i_b0 it adds d²(C_b^{i_b0}·r)/dt², whose sway products beat at 24 s and 40 s
    and pass the 40 s window. Perfect sensors, 120 s, three seeds: with the arm not estimated
    (`lever_arm_std_m=0`, the fit before the fix) the largest error exceeds 0.01° (seen 0.020°); with
    it estimated every error is < 0.001° (seen ≤ 1e-4°) and the arm's x and z come out within 2 cm
    of the forward model's (1, 2, 1.5) m (its y, along the roll axis, is seen only by the 5° pitch
    and 3° yaw: it is not asserted). Southern hemisphere included."""
    old, new = [], []
    for seed, lat in ((21, LAT), (22, LAT), (23, -35.0)):
        _, gyro, accel, truth, _ = _run(seed, REFERENCE, "perfect", duration_s=120.0, lat=lat)
        before = align_swaying(gyro, accel, RATE_HZ, lat, lever_arm_std_m=0.0)
        sol = align_swaying(gyro, accel, RATE_HZ, lat)
        old.append(abs(wrap_deg_180(before.heading_deg - truth)))
        new.append(abs(wrap_deg_180(sol.heading_deg - truth)))
        lever = sol.diagnostics["lever_arm_m"]
        assert lever[0] == pytest.approx(REFERENCE.lever_arm_m[0], abs=0.02)
        assert lever[2] == pytest.approx(REFERENCE.lever_arm_m[2], abs=0.02)
        assert before.diagnostics["lever_arm_m"] is None
    print(f"\n120 s perfect sensors: |error| lever arm not estimated {np.round(old, 4)}, estimated "
          f"{np.round(new, 5)}")
    assert max(old) > 0.01
    assert max(new) < 0.001


def test_lever_arm_estimate_leaves_a_still_base_alone():
    """On a still base G_j ≈ 0: the arm is unobservable and the ridge (prior 10 m) keeps it from
    fitting noise — the heading and its σ move by < 1 % of the σ against the fit without the arm."""
    _, gyro, accel, _, _ = _run(9101, STILL, "nav", duration_s=120.0)
    before = align_swaying(gyro, accel, RATE_HZ, LAT, lever_arm_std_m=0.0)
    sol = align_swaying(gyro, accel, RATE_HZ, LAT)
    assert abs(wrap_deg_180(sol.heading_deg - before.heading_deg)) < 0.01 * before.heading_std_deg
    assert sol.heading_std_deg == pytest.approx(before.heading_std_deg, rel=0.01)


def test_sigma_covers_sway_leakage_at_120_s():
    """At 120 s the smoothing let the lever arm's sway through (docs/swaying.md §8: the white-noise σ
    was ~20 % low there); the fit now estimates the arm, and the σ adds what its residual still
    holds beyond the modelled noise. Over 30 runs the scatter / rms reported σ lies in [0.75, 1.3]
    (±3 standard errors of a 30-run σ). At 60 s (a 30 s window, periods ≤ 7.5 s) the 8 s roll and
    10 s yaw products leak far more: without the arm the leakage part dominates and the error is
    > 0.5°; with it the error falls to within 3 of its σ and below a third of the error before. On a
    still ship the leakage part is nil (< 1 % of the white part: the residual is noise)."""
    err, std = [], []
    for i in range(30):
        _, gyro, accel, truth, grade = _run(9000 + i, REFERENCE, "nav", duration_s=120.0)
        sol = align_swaying(gyro, accel, RATE_HZ, LAT, gyro_bias_dph=grade.gyro_bias_dph,
                            accel_bias_ug=grade.accel_bias_ug)
        err.append(wrap_deg_180(sol.heading_deg - truth))
        std.append(sol.heading_std_deg)
    scatter, rms_std = np.std(err, ddof=1), np.sqrt(np.mean(np.square(std)))
    ratio = scatter / rms_std
    print(f"\n120 s, 30 runs: scatter {scatter:.4f}°, rms σ {rms_std:.4f}°, ratio {ratio:.2f}")
    assert 0.75 <= ratio <= 1.3
    ship, gyro, accel, truth, grade = _run(9050, REFERENCE, "nav", duration_s=60.0)
    before = align_swaying(gyro, accel, RATE_HZ, LAT, max_sway_period_s=7.5, lever_arm_std_m=0.0)
    sol = align_swaying(gyro, accel, RATE_HZ, LAT, max_sway_period_s=7.5)
    parts = before.diagnostics["heading_std_parts_deg"]
    err_before = abs(wrap_deg_180(before.heading_deg - truth))
    err60 = abs(wrap_deg_180(sol.heading_deg - truth))
    print(f"60 s: error {err_before:.3f}° → {err60:.3f}°, σ {before.heading_std_deg:.3f}° → "
          f"{sol.heading_std_deg:.3f}°, parts {sol.diagnostics['heading_std_parts_deg']}")
    assert parts["sway_leakage"] > parts["white_noise"] and err_before > 0.5
    assert err60 <= 3.0 * sol.heading_std_deg and err60 < err_before / 3.0
    _, gyro, accel, _, _ = _run(9100, STILL, "nav", duration_s=120.0)
    parts = align_swaying(gyro, accel, RATE_HZ, LAT).diagnostics["heading_std_parts_deg"]
    assert parts["sway_leakage"] < 0.01 * parts["white_noise"]


def test_coarse_sigma_only_on_a_still_base():
    """The coarse alignment's σ is the still-base noise limit: it says whether the base was still
    (1 s rate means scatter within 5× the measured noise), which the run uses to print no σ under
    sway (it printed 0.034° next to a −35° error)."""
    _, gyro, accel, _, _ = _run(9200, REFERENCE, "nav", duration_s=120.0)
    assert coarse_align(gyro, accel, RATE_HZ, LAT).diagnostics["base_still"] is False
    _, gyro, accel, _, _ = _run(9201, STILL, "nav", duration_s=120.0)
    assert coarse_align(gyro, accel, RATE_HZ, LAT).diagnostics["base_still"] is True
