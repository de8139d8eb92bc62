"""Turntable estimators against a forward model written here from docs/CONVENTIONS.md.

The model below builds its own Rx, Ry, Rz and C_p^n = Rz(−ψ)Rx(θ)Ry(γ), C_b^p = Rz(α); it uses
neither northfinder.rotations nor northfinder.estimators.montecarlo.
"""

from __future__ import annotations

import numpy as np
import pytest

from northfinder import solve_heading
from northfinder.constants import OMEGA_EARTH_RAD_S, STANDARD_GRAVITY_M_S2, normal_gravity_m_s2
from northfinder.errors import InputError
from northfinder.estimators.harmonic import fit_harmonic
from northfinder.estimators.heading import solve_all_methods, solve_batch
from northfinder.estimators.limits import noise_limit_heading_std_deg, tilt_noise_factor

RAD_S_PER_DPH = np.pi / 180.0 / 3600.0


# --- independent forward model --------------------------------------------------------------
def _rx(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.moveaxis(np.array([[o, z, z], [z, c, -s], [z, s, c]]), (0, 1), (-2, -1))


def _ry(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.moveaxis(np.array([[c, z, s], [z, o, z], [-s, z, c]]), (0, 1), (-2, -1))


def _rz(a):
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.moveaxis(np.array([[c, -s, z], [s, c, z], [z, z, o]]), (0, 1), (-2, -1))


def attitude(heading_deg, tilt_deg, tilt_az_deg):
    """C_p^n (T, 3, 3) with the given heading, tilt and tilt azimuth; plus pitch, roll [deg].

    Pitch/roll from requiring C_p^n·e_z = [sinε sinζ, sinε cosζ, cosε] (the table normal leans
    toward the downhill azimuth ζ); checked below against the matrix itself.
    """
    psi, eps, zeta = (np.deg2rad(np.asarray(x, dtype=float)) for x in (heading_deg, tilt_deg, tilt_az_deg))
    d = zeta - psi
    pitch = np.arctan2(-np.sin(eps) * np.cos(d), np.cos(eps))
    roll = np.arcsin(np.sin(eps) * np.sin(d))
    c_pn = _rz(-psi) @ _rx(pitch) @ _ry(roll)
    z_n = c_pn[..., :, 2]
    want = np.stack([np.sin(eps) * np.sin(zeta), np.sin(eps) * np.cos(zeta), np.cos(eps)], axis=-1)
    assert np.allclose(z_n, want, atol=1e-13)
    return c_pn, np.rad2deg(pitch), np.rad2deg(roll)


def body_means(table_angle_deg, c_pn, latitude_deg):
    """Noise-free per-position means: gyro [deg/h] and specific force [g], shape (T, n, 3)."""
    lat = np.deg2rad(latitude_deg)
    w_n = OMEGA_EARTH_RAD_S * np.array([0.0, np.cos(lat), np.sin(lat)])
    f_n = np.array([0.0, 0.0, normal_gravity_m_s2(latitude_deg) / STANDARD_GRAVITY_M_S2])
    c_np = np.swapaxes(c_pn, -1, -2)
    c_bp = _rz(np.deg2rad(np.asarray(table_angle_deg, dtype=float)))  # (n, 3, 3), b → p
    c_pb = np.swapaxes(c_bp, -1, -2)
    w_b = np.einsum("nij,tjk,k->tni", c_pb, c_np, w_n) / RAD_S_PER_DPH
    f_b = np.einsum("nij,tjk,k->tni", c_pb, c_np, f_n)
    return w_b, f_b


def wrap180(x):
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


HEADINGS = np.arange(0.0, 360.0, 5.0)
TILT_AZ = np.arange(0.0, 331.0, 30.0)
ANGLES_4 = np.array([0.0, 90.0, 180.0, 270.0])
ANGLES_8_MEASURED = np.arange(8) * 45.0 + np.array([0.013, -0.21, 0.4, 0.07, -0.33, 0.12, 0.0, 0.25])


def grid(tilt_deg):
    psi, zeta = np.meshgrid(HEADINGS, TILT_AZ, indexing="ij")
    return psi.ravel(), np.full(psi.size, float(tilt_deg)), zeta.ravel()


def solve_grid(angles, latitude, tilt, three_axis, method="exact"):
    psi, eps, zeta = grid(tilt)
    c_pn, pitch, roll = attitude(psi, eps, zeta)
    w_b, f_b = body_means(angles, c_pn, latitude)
    if not three_axis:
        w_b, f_b = w_b[..., 1], f_b[..., 1]
    return solve_batch(angles, w_b, f_b, latitude, method), psi, pitch, roll, eps, zeta


# --- noise-free: exact, and the worst error of the paper's formulas -------------------------
@pytest.mark.parametrize("three_axis,angles", [(False, ANGLES_4), (True, ANGLES_8_MEASURED)])
@pytest.mark.parametrize("latitude", [-60.0, 0.0, 40.0, 75.0])
def test_exact_is_exact_over_the_grid(three_axis, angles, latitude):
    for tilt in (0.0, 0.5, 2.0, 5.0, 10.0):
        sol, psi, pitch, roll, eps, zeta = solve_grid(angles, latitude, tilt, three_axis)
        assert np.max(np.abs(wrap180(sol.heading_deg - psi))) < 1e-6
        assert np.all((sol.heading_deg >= 0.0) & (sol.heading_deg < 360.0))
        assert np.max(np.abs(sol.pitch_deg - pitch)) < 1e-6
        assert np.max(np.abs(sol.roll_deg - roll)) < 1e-6
        assert np.max(np.abs(sol.tilt_deg - eps)) < 1e-6
        if tilt > 0:
            assert np.max(np.abs(wrap180(sol.tilt_azimuth_deg - zeta))) < 1e-6
        # eq 3 is algebraically exact too when pitch and roll are exact
        assert np.max(np.abs(wrap180(sol.methods["coordinate_transform"] - psi))) < 1e-6


WORST_AT_10DEG_40N = {"coordinate_transform": 0.0, "vector": 0.8386, "eq11": 0.8198, "uncompensated": 8.729}
"""Worst |error| [deg] over the grid (heading step 5°, tilt azimuth step 30°), docs/estimators.md."""


@pytest.mark.parametrize("three_axis,angles", [(False, ANGLES_4), (True, ANGLES_8_MEASURED)])
def test_worst_error_of_the_paper_formulas_at_10deg_tilt(three_axis, angles):
    sol, psi, *_ = solve_grid(angles, 40.0, 10.0, three_axis)
    for method, worst in WORST_AT_10DEG_40N.items():
        got = np.max(np.abs(wrap180(sol.methods[method] - psi)))
        if worst == 0.0:
            assert got < 1e-9, method
        else:
            assert got == pytest.approx(worst, abs=6e-4), method


def test_vector_is_exact_with_single_axis_tilt_and_eq11_gives_the_in_plane_angle():
    tilt = 10.0
    psi = HEADINGS
    for rel in (0.0, 90.0, 180.0, 270.0):  # tilt along p-y (pitch only) or p-x (roll only)
        c_pn, pitch, roll = attitude(psi, np.full(psi.size, tilt), psi + rel)
        assert np.all(np.isclose(pitch, 0.0, atol=1e-12) | np.isclose(roll, 0.0, atol=1e-12))
        w_b, f_b = body_means(ANGLES_4, c_pn, 40.0)
        sol = solve_batch(ANGLES_4, w_b[..., 1], f_b[..., 1], 40.0)
        assert np.max(np.abs(wrap180(sol.methods["vector"] - psi))) < 1e-9
        # eq 11 returns the angle inside the tilted plane: tan ψ' = tan ψ · cos γ / cos θ
        p_r, r_r = np.deg2rad(psi), np.deg2rad(roll)
        in_plane = np.rad2deg(np.arctan2(np.sin(p_r) * np.cos(r_r), np.cos(p_r) * np.cos(np.deg2rad(pitch))))
        assert np.max(np.abs(wrap180(sol.methods["eq11"] - in_plane))) < 1e-9
    # the paper's "about 5 % of the tilt": worst in-plane error asin((1 − cos ε)/(1 + cos ε))
    c_pn, _, _ = attitude(psi, np.full(psi.size, tilt), psi + 90.0)
    w_b, f_b = body_means(ANGLES_4, c_pn, 40.0)
    eq11 = solve_batch(ANGLES_4, w_b[..., 1], f_b[..., 1], 40.0).methods["eq11"]
    worst = np.max(np.abs(wrap180(eq11 - psi)))
    c = np.cos(np.deg2rad(tilt))
    assert worst == pytest.approx(np.rad2deg(np.arcsin((1 - c) / (1 + c))), rel=0.02)
    assert 0.04 < worst / tilt < 0.05


def test_public_api_matches_the_batch_path_and_returns_floats():
    rng = np.random.default_rng(7)
    for _ in range(30):
        psi, eps, zeta = rng.uniform(0, 360), rng.uniform(0, 10), rng.uniform(0, 360)
        lat = rng.uniform(-70, 80)
        c_pn, pitch, roll = attitude([psi], [eps], [zeta])
        w_b, f_b = body_means(ANGLES_8_MEASURED, c_pn, lat)
        sol = solve_heading(ANGLES_8_MEASURED, w_b[0], f_b[0], lat)
        sol1 = solve_heading(ANGLES_8_MEASURED, w_b[0, :, 1], f_b[0, :, 1], lat, "coordinate_transform")
        for s in (sol, sol1):
            assert isinstance(s.heading_deg, float) and isinstance(s.heading_std_deg, float)
            assert abs(wrap180(s.heading_deg - psi)) < 1e-6
            assert s.pitch_deg == pytest.approx(pitch[0], abs=1e-6)
            assert s.roll_deg == pytest.approx(roll[0], abs=1e-6)
        sol2 = solve_heading(
            ANGLES_8_MEASURED, w_b[0, :, :2], f_b[0, :, :2], lat, gyro_std_dph=np.ones((8, 2))
        )
        assert abs(wrap180(sol2.heading_deg - psi)) < 1e-6 and np.isnan(sol2.accel_magnitude_g)
        assert set(sol.methods) == {"exact", "coordinate_transform", "vector", "eq11", "uncompensated"}
        assert solve_all_methods(ANGLES_8_MEASURED, w_b[0], f_b[0], lat) == sol.methods
        assert sol.as_dict()["heading_deg"] == sol.heading_deg


# --- the harmonic fit -------------------------------------------------------------------------
def test_harmonic_fit_recovers_coefficients_and_its_given_noise_covariance():
    alpha = np.deg2rad([3.0, 70.0, 150.0, 200.0, 290.0])
    v_x, v_y, r_x, r_y = 2.0, -5.0, 0.7, -0.3
    x = r_x + v_x * np.cos(alpha) + v_y * np.sin(alpha)
    y = r_y - v_x * np.sin(alpha) + v_y * np.cos(alpha)
    std = np.array([[0.1, 0.2], [0.1, 0.2], [0.3, 0.1], [0.1, 0.1], [0.2, 0.2]])
    fit = fit_harmonic(alpha, np.stack([x, y], axis=-1)[None], ("x", "y"), std=std)
    assert np.allclose(fit.coefficients[0], [v_x, v_y, r_x, r_y], atol=1e-12)
    assert fit.noise == "given"
    # covariance: (AᵀWA)⁻¹ built here by hand
    rows = [[np.cos(a), np.sin(a), 1, 0] for a in alpha] + [[-np.sin(a), np.cos(a), 0, 1] for a in alpha]
    a_mat, w = np.array(rows), 1.0 / np.concatenate([std[:, 0], std[:, 1]]) ** 2
    assert np.allclose(fit.covariance[0], np.linalg.inv(a_mat.T @ (a_mat * w[:, None])), rtol=1e-12)
    # paper's a, b for the y axis (eq 4)
    assert fit.a[0] == pytest.approx(v_y) and fit.b[0] == pytest.approx(-v_x)


def test_residual_covariance_matches_given_noise_on_average():
    rng = np.random.default_rng(3)
    alpha = np.deg2rad(np.arange(8) * 45.0)
    sigma = 0.05
    y = 1.0 + 0.3 * np.cos(alpha) - 0.2 * np.sin(alpha) + sigma * rng.standard_normal((4000, 8))
    fit = fit_harmonic(alpha, y[..., None], ("y",))
    assert fit.noise == "residuals" and fit.dof == 5
    # E[σ̂²] = σ²: the mean residual-based variance of v_y equals the given-noise one, 2σ²/n
    assert np.mean(fit.covariance[:, 1, 1]) == pytest.approx(2 * sigma**2 / 8, rel=0.03)
    assert np.std(fit.coefficients[:, 1]) == pytest.approx(np.sqrt(2 * sigma**2 / 8), rel=0.04)


# --- tilt from the accelerometer (eq 9) and the noise limit ----------------------------------
def test_single_axis_accelerometer_tilt_is_eq9():
    c_pn, _, _ = attitude([123.0], [7.0], [40.0])
    w_b, f_b = body_means(ANGLES_4, c_pn, 40.0)
    sol = solve_heading(ANGLES_4, w_b[0, :, 1], f_b[0, :, 1], 40.0)
    a_a, b_a = sol.accel_fit.a[0], sol.accel_fit.b[0]
    g_local = normal_gravity_m_s2(40.0) / STANDARD_GRAVITY_M_S2
    assert sol.tilt_deg == pytest.approx(np.rad2deg(np.arcsin(np.hypot(a_a, b_a) / g_local)), abs=1e-9)
    assert sol.tilt_deg == pytest.approx(7.0, abs=1e-9)
    assert sol.tilt_azimuth_deg == pytest.approx(40.0, abs=1e-9)


def test_noise_limit_formula():
    arw, t_total, lat = 0.012, 600.0, 40.0
    n_rad = arw * np.pi / 180.0 / 60.0
    level = n_rad / (OMEGA_EARTH_RAD_S * np.cos(np.deg2rad(lat))) * np.sqrt(2.0 / t_total)
    assert noise_limit_heading_std_deg(arw, t_total, lat) == pytest.approx(np.rad2deg(level), rel=1e-12)
    two = noise_limit_heading_std_deg(arw, t_total, lat, gyro_axes=2)
    assert two == pytest.approx(np.rad2deg(level) / np.sqrt(2))
    assert tilt_noise_factor(10.0, 90.0) == pytest.approx(1.0 / np.cos(np.deg2rad(10.0)))
    assert tilt_noise_factor(10.0, 0.0) == pytest.approx(1.0)


# --- bad input gives one clear InputError ---------------------------------------------------
_ONE_CELL = np.arange(24).reshape(8, 3) == 4


def _good():
    c_pn, _, _ = attitude([30.0], [3.0], [100.0])
    w_b, f_b = body_means(ANGLES_8_MEASURED, c_pn, 40.0)
    return ANGLES_8_MEASURED, w_b[0], f_b[0]


@pytest.mark.parametrize(
    "mutate,match",
    [
        (lambda a, w, f, k: (a[:2], w[:2], f[:2], k), "at least 3"),
        (lambda a, w, f, k: (a, np.where(_ONE_CELL, np.nan, w), f, k), "gyro_dph.*NaN"),
        (lambda a, w, f, k: (a, w, np.where(_ONE_CELL, np.inf, f), k), "accel_g.*NaN or inf"),
        (lambda a, w, f, k: (a, w, f * STANDARD_GRAVITY_M_S2, k), "far from the local gravity"),
        (lambda a, w, f, k: (a, w, f[:, 1] * 20.0, k), "horizontal specific force"),
        (lambda a, w, f, k: (a, w * RAD_S_PER_DPH, f, k), "deg/h"),
        (lambda a, w, f, k: (a, w, f, {"latitude_deg": 89.5}), "latitude"),
        (lambda a, w, f, k: (a, w, f, {"latitude_deg": -89.5}), "latitude"),
        (lambda a, w, f, k: (a, w, f, {"method": "magic"}), "method must be one of"),
        (lambda a, w, f, k: (a, w[:5], f, k), "gyro_dph: shape"),
        (lambda a, w, f, k: (a, w, f, {"bias_model": "linear", "sample_times_s": [1, 2]}), "sample_times_s"),
        (lambda a, w, f, k: (a, w, f, {"gyro_std_dph": np.ones(8)}), "gyro_std_dph: shape"),
    ],
)
def test_bad_input_raises_input_error(mutate, match):
    a, w, f, kw = mutate(*_good(), {})
    kw = {"latitude_deg": 40.0, **kw}
    with pytest.raises(InputError, match=match):
        solve_heading(a, w, f, **kw)


@pytest.mark.parametrize(
    "angles,three_axis",
    [
        (np.zeros(8), True),
        (np.zeros(8), False),
        (np.r_[0, 180, 0, 180, 0, 180, 0, 180.0], False),  # sin α never seen by one gyro
        (np.linspace(0.0, 3.0, 8), False),
    ],
)
def test_angle_sets_that_cannot_separate_cos_and_sin(angles, three_axis):
    c_pn, _, _ = attitude([30.0], [3.0], [100.0])
    w_b, f_b = body_means(angles, c_pn, 40.0)
    w, f = (w_b[0], f_b[0]) if three_axis else (w_b[0, :, 1], f_b[0, :, 1])
    with pytest.raises(InputError, match="cannot separate cos α and sin α"):
        solve_heading(angles, w, f, 40.0)


def test_opposite_positions_are_enough_for_a_two_axis_gyro():
    angles = np.r_[0, 180, 0, 180.0]  # b-x and b-y together see w_x and w_y at 0° and 180°
    c_pn, _, _ = attitude([30.0], [3.0], [100.0])
    w_b, f_b = body_means(angles, c_pn, 40.0)
    assert abs(wrap180(solve_heading(angles, w_b[0], f_b[0], 40.0).heading_deg - 30.0)) < 1e-6


def test_tilt_limit():
    c_pn, _, _ = attitude([30.0], [35.0], [100.0])
    w_b, f_b = body_means(ANGLES_4, c_pn, 40.0)
    with pytest.raises(InputError, match="tilt 35.00° exceeds the limit 30"):
        solve_heading(ANGLES_4, w_b[0], f_b[0], 40.0)
    sol = solve_heading(ANGLES_4, w_b[0], f_b[0], 40.0, tilt_limit_deg=40.0)
    assert abs(wrap180(sol.heading_deg - 30.0)) < 1e-6


def test_input_error_is_one_line():
    a, w, f = _good()
    with pytest.raises(InputError) as exc:
        solve_heading(a, w, f * STANDARD_GRAVITY_M_S2, 40.0)
    assert "\n" not in str(exc.value)


def test_residual_sigma_is_nan_without_degrees_of_freedom():
    c_pn, _, _ = attitude([30.0], [3.0], [100.0])
    angles = np.array([0.0, 120.0, 240.0])
    w_b, f_b = body_means(angles, c_pn, 40.0)
    sol = solve_heading(angles, w_b[0, :, 1], f_b[0, :, 1], 40.0)
    assert abs(wrap180(sol.heading_deg - 30.0)) < 1e-6 and np.isnan(sol.heading_std_deg)


def test_linear_bias_model_removes_an_exactly_linear_drift():
    c_pn, _, _ = attitude([77.0], [4.0], [200.0])
    w_b, f_b = body_means(ANGLES_8_MEASURED, c_pn, 40.0)
    times = np.arange(8) * 70.0 + 30.0
    drifting = w_b[0] + 3.0 * (times / 600.0)[:, None]  # 3 °/h per 10 min on every axis
    plain = solve_heading(ANGLES_8_MEASURED, drifting[:, 1], f_b[0, :, 1], 40.0)
    aware = solve_heading(
        ANGLES_8_MEASURED, drifting[:, 1], f_b[0, :, 1], 40.0, bias_model="linear", sample_times_s=times
    )
    assert abs(wrap180(plain.heading_deg - 77.0)) > 0.5
    assert abs(wrap180(aware.heading_deg - 77.0)) < 1e-6
    quad = solve_heading(
        ANGLES_8_MEASURED, drifting, f_b[0], 40.0, bias_model="quadratic", sample_times_s=times
    )
    assert abs(wrap180(quad.heading_deg - 77.0)) < 1e-6


def test_sample_count_weights_equal_std_weights():
    rng = np.random.default_rng(4)
    c_pn, _, _ = attitude([10.0], [2.0], [50.0])
    w_b, f_b = body_means(ANGLES_8_MEASURED, c_pn, 40.0)
    counts = rng.integers(500, 5000, size=8)
    noisy = w_b[0, :, 1] + rng.standard_normal(8) * 0.5 / np.sqrt(counts)
    by_count = solve_heading(ANGLES_8_MEASURED, noisy, f_b[0, :, 1], 40.0, sample_count=counts)
    by_std = solve_heading(ANGLES_8_MEASURED, noisy, f_b[0, :, 1], 40.0, gyro_std_dph=0.5 / np.sqrt(counts))
    equal = solve_heading(ANGLES_8_MEASURED, noisy, f_b[0, :, 1], 40.0)
    assert by_count.heading_deg == pytest.approx(by_std.heading_deg, abs=1e-9)
    assert abs(by_count.heading_deg - equal.heading_deg) > 1e-6


def test_as_dict_is_strict_json():
    import json

    c_pn, _, _ = attitude([30.0], [3.0], [100.0])
    angles = np.array([0.0, 120.0, 240.0])
    w_b, f_b = body_means(angles, c_pn, 40.0)
    d = solve_heading(angles, w_b[0, :, 1], f_b[0, :, 1], 40.0).as_dict()
    text = json.dumps(d, allow_nan=False)
    assert json.loads(text)["heading_std_deg"] is None and json.loads(text)["accel_magnitude_g"] is None
