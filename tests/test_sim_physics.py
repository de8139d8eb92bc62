"""firmware_sim physics against expectations written here, independently of the code under test.

The expected Earth rate, gravity and rotations below are re-derived in this file from
docs/CONVENTIONS.md (explicit matrices, Somigliana by hand); tolerances come from the noise
model (ARW and duration) or from the size of the terms a check deliberately leaves out.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from firmware_sim.physics.sensors import (
    ACCEL_PRESETS,
    GYRO_PRESETS,
    AccelErrors,
    AccelModel,
    Float32Carry,
    GyroErrors,
    GyroModel,
    accel_errors,
    gyro_errors,
)
from firmware_sim.physics.table import TableMotion
from firmware_sim.physics.world import Sinusoid, Site, SwayingPlatform, World

D = math.pi / 180.0
OMEGA_E = 7.2921150e-5
G0 = 9.80665
LAT, HEADING, PITCH, ROLL = 40.0, 30.0, 1.5, -2.0


# ---------------------------------------------------------------------------------------------
# independent expectations (CONVENTIONS.md written out by hand)
# ---------------------------------------------------------------------------------------------
def somigliana(lat_deg: float, h_m: float = 0.0) -> float:
    """WGS-84 normal gravity, TR8350.2 eq. 4-1 with the 4-3 height series."""
    a, f, ge, gp = 6378137.0, 1 / 298.257223563, 9.7803253359, 9.8321849378
    b = a * (1 - f)
    e2 = f * (2 - f)
    s2 = math.sin(lat_deg * D) ** 2
    k = b * gp / (a * ge) - 1
    m = 0.00344978650684
    g = ge * (1 + k * s2) / math.sqrt(1 - e2 * s2)
    return g * (1 - 2 / a * (1 + f + m - 2 * f * s2) * h_m + 3 * h_m**2 / a**2)


def c_bn(heading_deg: float, pitch_deg: float, roll_deg: float, alpha_deg: float = 0.0) -> np.ndarray:
    """C_b^n = Rz(−ψ)·Rx(θ)·Ry(γ)·Rz(α), each matrix spelled out."""
    p, t, r, a = -heading_deg * D, pitch_deg * D, roll_deg * D, alpha_deg * D
    rz = np.array([[math.cos(p), -math.sin(p), 0], [math.sin(p), math.cos(p), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]])
    ry = np.array([[math.cos(r), 0, math.sin(r)], [0, 1, 0], [-math.sin(r), 0, math.cos(r)]])
    ra = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    return rz @ rx @ ry @ ra


def earth_rate_b(lat_deg, heading_deg, pitch_deg, roll_deg, alpha_deg=0.0) -> np.ndarray:
    w_n = OMEGA_E * np.array([0.0, math.cos(lat_deg * D), math.sin(lat_deg * D)])
    return c_bn(heading_deg, pitch_deg, roll_deg, alpha_deg).T @ w_n


def gyro_matrix(e: GyroErrors | AccelErrors) -> np.ndarray:
    m = np.eye(3) + np.diag(np.asarray(e.scale_factor_ppm) * 1e-6)
    xy, xz, yx, yz, zx, zy = np.asarray(e.misalignment_urad) * 1e-6
    return m + np.array([[0, xy, xz], [yx, 0, yz], [zx, zy, 0]])


def static_world(alpha_deg: float = 0.0, **table_kw) -> World:
    table = TableMotion(power_on_deg=alpha_deg, **table_kw)
    return World.static(LAT, HEADING, PITCH, ROLL, table=table)


# ---------------------------------------------------------------------------------------------
# Must show: 60 s at rest, nav grade, 1000 Hz
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def nav_60s():
    rate, seconds, alpha_deg = 1000, 60, 137.2345
    world = static_world(alpha_deg)
    gyro = GyroModel(GYRO_PRESETS["nav"], rate, 20261122)
    accel = AccelModel(ACCEL_PRESETS["nav"], rate, 20261123)
    sum_dtheta, sum_dv = np.zeros(3), np.zeros(3)
    for block in range(seconds):  # one device second per block, as a device loop would
        dth, dv = world.increments(block * 1.0, rate, 1.0 / rate)
        sum_dtheta += gyro.apply(dth).sum(axis=0)
        sum_dv += accel.apply(dv).sum(axis=0)
    return {"seconds": seconds, "alpha_deg": alpha_deg, "dtheta": sum_dtheta, "dv": sum_dv}


def test_nav_gyro_mean_is_earth_rate_projection(nav_60s):
    e = GYRO_PRESETS["nav"]
    t = nav_60s["seconds"]
    truth = earth_rate_b(LAT, HEADING, PITCH, ROLL, nav_60s["alpha_deg"])
    expected = gyro_matrix(e) @ truth + np.asarray(e.bias_dph) * D / 3600
    mean = nav_60s["dtheta"] / t
    n = np.asarray(e.arw_deg_rt_h) * D / 60  # rad/√s
    sigma = np.sqrt(
        (n / math.sqrt(t)) ** 2  # white noise averaged over T
        + (np.asarray(e.bias_instability_dph) * D / 3600) ** 2  # GM state (≤ its stationary σ)
        + (np.asarray(e.rrw_dph_rt_h) * D / 3600 / 60) ** 2 * t / 3  # mean of a random walk
    )
    assert np.all(np.abs(mean - expected) < 3 * sigma), (mean - expected) / sigma
    # the check has teeth: a 1° heading error moves the horizontal axes by far more than 3σ
    wrong = gyro_matrix(e) @ earth_rate_b(LAT, HEADING + 1.0, PITCH, ROLL, nav_60s["alpha_deg"])
    assert np.max(np.abs(mean - wrong - np.asarray(e.bias_dph) * D / 3600) / sigma) > 3


def test_nav_accelerometer_magnitude_is_normal_gravity(nav_60s):
    e = ACCEL_PRESETS["nav"]
    t = nav_60s["seconds"]
    mean = nav_60s["dv"] / t
    f_est = np.linalg.solve(gyro_matrix(e), mean - np.asarray(e.bias_ug) * 1e-6 * G0)
    sigma_axis = np.hypot(np.asarray(e.noise_ug_rt_hz) / math.sqrt(t), e.bias_instability_ug) * 1e-6 * G0
    sigma = float(np.max(sigma_axis))  # the magnitude's σ ≤ the largest axis σ
    g = somigliana(LAT)
    assert abs(np.linalg.norm(f_est) - g) < 3 * sigma, (np.linalg.norm(f_est) - g) / sigma
    assert abs(G0 - g) > 30 * sigma  # standard gravity would fail: the test resolves the site
    # and it points along the body up-axis of this tilted table
    expected_dir = c_bn(HEADING, PITCH, ROLL, nav_60s["alpha_deg"]).T @ np.array([0.0, 0.0, 1.0])
    assert np.linalg.norm(f_est / np.linalg.norm(f_est) - expected_dir) < 3 * sigma / g * math.sqrt(3)


def test_ninety_degree_move_sums_to_ninety_plus_earth_rate():
    rate = 1000
    world = static_world(0.0)
    e = GYRO_PRESETS["nav"]
    gyro = GyroModel(e, rate, 5)
    t_cmd = 1.0
    t_end = world.table.command_move(t_cmd, math.pi / 2)
    n = int(math.ceil((t_end + 3.0) * rate))  # from rest to rest, ringing included
    total = np.zeros(3)
    for k0 in range(0, n, 700):  # odd block size on purpose
        m = min(700, n - k0)
        total += gyro.apply(world.increments(k0 / rate, m, 1.0 / rate)[0]).sum(axis=0)
    duration = n / rate
    enc = world.table.encoder_rad(np.array([0.0, duration]))
    earth_z = earth_rate_b(LAT, HEADING, PITCH, ROLL)[2]  # b-z = p-z: α does not change it
    true_z = (enc[1] - enc[0]) + earth_z * duration
    expected = (1 + e.scale_factor_ppm[2] * 1e-6) * true_z + e.bias_dph[2] * D / 3600 * duration
    step = world.table.encoder_step_rad
    noise = e.arw_deg_rt_h[2] * D / 60 * math.sqrt(duration)
    drift = e.bias_instability_dph[2] * D / 3600 * duration
    misalign = 1e-5 * OMEGA_E * duration  # |M_zx|,|M_zy| ≤ 1e-5 times the horizontal rates
    tol = step / 2 + 3 * math.hypot(noise, drift) + misalign
    assert abs(total[2] - expected) < tol, (total[2] - expected) / tol
    assert abs(enc[1] - math.pi / 2) <= step / 2


def test_ideal_increments_across_move_are_exact():
    world = static_world(0.0)
    t_end = world.table.command_move(0.5, math.radians(90.0))
    n = int((t_end + 4.0) * 500)
    dth, _ = world.increments(0.0, n, 1 / 500)
    earth_z = earth_rate_b(LAT, HEADING, PITCH, ROLL)[2]
    alpha = world.table.kinematics(np.array([0.0, n / 500]))[0]  # the top, ringing (1e-10 rad) included
    assert dth[:, 2].sum() == pytest.approx(alpha[1] - alpha[0] + earth_z * n / 500, abs=1e-13)
    assert alpha[1] - alpha[0] == pytest.approx(math.pi / 2, abs=1e-9)


# ---------------------------------------------------------------------------------------------
# truth against independent formulas
# ---------------------------------------------------------------------------------------------
def test_truth_tilted_platform_matches_hand_written_formula():
    for heading, pitch, roll, alpha, lat in [
        (30.0, 1.5, -2.0, 137.0, 40.0),
        (300.0, -5.0, 3.0, -45.0, -33.9),
    ]:
        world = World.static(lat, heading, pitch, roll, height_m=250.0, table=TableMotion(power_on_deg=alpha))
        w, f = world.truth(np.array([0.0, 10.0]))
        cbn = c_bn(heading, pitch, roll, alpha)
        w_exp = earth_rate_b(lat, heading, pitch, roll, alpha)
        f_exp = cbn.T @ np.array([0.0, 0.0, somigliana(lat, 250.0)])
        np.testing.assert_allclose(w, [w_exp, w_exp], rtol=0, atol=1e-17)
        # 1e-10: this file derives Somigliana's k from γp; the code uses the published k (1e-12 apart)
        np.testing.assert_allclose(f, [f_exp, f_exp], rtol=0, atol=1e-10)


def test_increments_match_fine_quadrature_of_truth_on_swaying_base_with_moving_table():
    sway = SwayingPlatform(
        heading_deg=80.0, pitch_deg=1.0, roll_deg=-1.0,
        roll=(Sinusoid(3.0, 8.0, 10.0),), pitch=(Sinusoid(2.0, 6.0, 40.0),), yaw=(Sinusoid(1.0, 11.0),),
        heave=(Sinusoid(0.3, 7.0),), surge=(Sinusoid(0.2, 9.0, 20.0),),
    )  # fmt: skip
    world = World(Site(35.0, 10.0), sway, TableMotion(power_on_deg=10.0))
    world.table.command_move(0.2, math.radians(40.0))
    r = np.array([0.15, -0.05, 0.02])
    t0, n, dt = 0.0, 300, 0.01  # spans accel, cruise and decel knots
    dth, dv = world.increments(t0, n, dt, r)
    # midpoint rule on sub-intervals of 25 µs; the profile's knots (0.2, 0.45, 1.95, 2.2 s) fall on
    # sub-interval edges, so its acceleration steps cost the reference nothing: error O(h²) < 1e-10
    fine = 400
    tt = t0 + dt * (np.arange(n * fine) + 0.5) / fine
    w, f = world.truth(tt, r)
    # nav noise per 10 ms sample: 5.8e-8 rad and 9.8e-6 m/s; the integration must sit far below
    np.testing.assert_allclose(dth, w.reshape(n, fine, 3).mean(axis=1) * dt, rtol=0, atol=1e-10)
    np.testing.assert_allclose(dv, f.reshape(n, fine, 3).mean(axis=1) * dt, rtol=0, atol=1e-9)


def test_swaying_rates_match_finite_differences_of_attitude():
    sway = SwayingPlatform(
        heading_deg=200.0, pitch_deg=2.0, roll_deg=1.0,
        roll=(Sinusoid(5.0, 7.0, 30.0), Sinusoid(1.0, 2.5)), pitch=(Sinusoid(3.0, 5.0, 70.0),),
        yaw=(Sinusoid(2.0, 13.0, 15.0),),
    )  # fmt: skip
    world = World(Site(50.0), sway)
    world.add_disturbance(3.0, 1.0, 0.5)
    t = np.linspace(0.0, 6.0, 241) + 0.0123  # off the bump's edges, where ω̈ has a step
    h = 1e-5
    for tt in (t, np.linspace(3.05, 3.95, 37)):  # plain sway, then inside the bump
        c, w, wd = world.attitude(tt)
        cp, wp, _ = world.attitude(tt + h)
        cm, wm, _ = world.attitude(tt - h)
        k = np.einsum("...ji,...jk->...ik", c, (cp - cm) / (2 * h))  # CᵀĊ = [ω×]
        w_fd = np.stack([k[..., 2, 1], k[..., 0, 2], k[..., 1, 0]], axis=-1)
        np.testing.assert_allclose(w, w_fd, rtol=0, atol=1e-8)
        np.testing.assert_allclose(wd, (wp - wm) / (2 * h), rtol=0, atol=1e-6)
    # and the gyro truth is Earth rate plus that body rate (table at α = 0, no lever arm)
    world.table = TableMotion(power_on_deg=0.0)
    c, w_np, _ = world.attitude(t)
    w_ib, f = world.truth(t)
    w_ie = OMEGA_E * np.array([0.0, math.cos(50 * D), math.sin(50 * D)])
    np.testing.assert_allclose(w_ib, np.einsum("...ji,j->...i", c, w_ie) + w_np, rtol=0, atol=1e-15)
    np.testing.assert_allclose(f, np.einsum("...ji,j->...i", c, [0, 0, somigliana(50.0)]), atol=1e-9)


def test_lever_arm_centripetal_and_tangential():
    world = static_world(0.0, speed_deg_s=60.0, accel_deg_s2=30.0)
    world.table.command_move(0.0, math.radians(700.0))  # 2 s accel, cruise from 2 s to 11.7 s
    r = np.array([0.2, 0.0, 0.0])
    t = np.array([1.0, 9.0])  # accelerating; cruising 7 s after the last knot (ringing e^-23)
    _, rate, acc = world.table.kinematics(t)  # the top: profile plus a little ringing
    _, rate_plan, acc_plan = world.table.motor_kinematics(t)
    _, f_r = world.truth(t, r)
    _, f_0 = world.truth(t, np.zeros(3))
    lever = f_r - f_0
    earth_terms = 2 * np.abs(rate) * OMEGA_E * 0.2 + OMEGA_E**2 * 0.2  # cross terms with Earth rate
    # cruise: centripetal α̇²·r toward the axis, nothing tangential (ringing long gone)
    assert rate_plan[1] == pytest.approx(math.radians(60.0), rel=1e-12)
    assert lever[1, 0] == pytest.approx(-(rate[1] ** 2) * 0.2, abs=earth_terms[1])
    assert abs(lever[1, 1]) < earth_terms[1]
    # accelerating: tangential α̈·r along +y, plus the centripetal of the rate reached so far
    assert acc_plan[0] == pytest.approx(math.radians(30.0), rel=1e-12)
    assert lever[0, 1] == pytest.approx(acc[0] * 0.2, abs=earth_terms[0] + 1e-9)
    assert lever[0, 0] == pytest.approx(-(rate[0] ** 2) * 0.2, abs=earth_terms[0])


# ---------------------------------------------------------------------------------------------
# table motion
# ---------------------------------------------------------------------------------------------
def test_trapezoid_home_stop_stall_and_encoder():
    table = TableMotion(speed_deg_s=20.0, accel_deg_s2=80.0, power_on_deg=123.4, encoder_step_deg=1e-4)
    assert math.degrees(float(table.encoder_rad(0.0))) == pytest.approx(123.4, abs=1e-9)
    end = table.home(2.0)
    assert end == pytest.approx(2.0 + 123.4 / 20.0 + 20.0 / 80.0)
    t = np.linspace(2.0, end, 2001)
    _, v, a = table.motor_kinematics(t)
    assert np.max(np.abs(v)) == pytest.approx(math.radians(20.0))
    assert np.max(np.abs(a)) == pytest.approx(math.radians(80.0))
    assert table.is_moving(3.0) and not table.is_moving(end + 0.01)
    assert float(table.encoder_rad(end)) == 0.0
    # a target off the encoder grid reads to the nearest step
    end = table.command_move(end + 1.0, math.radians(10.00003))
    assert math.degrees(float(table.encoder_rad(end + 5))) == pytest.approx(10.0, abs=1e-12)
    # stop mid-move: decelerate at 80 °/s² from 20 °/s → 0.25 s and 2.5° further
    t_go = end + 2.0
    table.command_move(t_go, math.radians(100.0))
    t_stop = t_go + 2.0
    p_stop = float(table.motor_kinematics(t_stop)[0][()])
    t_rest = table.stop(t_stop)
    assert t_rest - t_stop == pytest.approx(0.25)
    assert math.degrees(table.target_rad - p_stop) == pytest.approx(2.5)
    # a stalled move ends short of its target
    start = float(table.motor_kinematics(t_rest + 1)[0][()])
    end = table.command_move(t_rest + 1.0, math.radians(200.0), stall_fraction=0.5)
    final = float(table.motor_kinematics(end + 1)[0][()])
    frac = (final - start) / (math.radians(200.0) - start)
    assert table.stalled and 0.5 < frac < 0.55


def test_ringing_is_seen_by_the_gyro_and_decays_with_its_time_constant():
    world = static_world(0.0, ringing_amplitude_deg=0.005, ringing_freq_hz=10.0, ringing_decay_s=0.3)
    t_end = world.table.command_move(0.0, math.radians(45.0))
    rate = 1000
    dth, _ = world.increments(t_end, 3 * rate, 1 / rate)
    wz = dth[:, 2] * rate - earth_rate_b(LAT, HEADING, PITCH, ROLL)[2]
    first, later, late = (np.sqrt(np.mean(wz[a : a + 500] ** 2)) for a in (100, 1100, 2500))
    # amplitude ≈ 0.005° × 2π·10 Hz ≈ 0.31 °/s right after the stop: far above nav noise
    assert first > math.radians(0.1)
    assert later / first == pytest.approx(math.exp(-1.0 / 0.3), rel=0.02)
    assert late < math.radians(0.5 / 3600)  # below 0.5 °/h after 2.5 s
    # the encoder (motor side) does not ring: it reads the target
    assert np.all(world.table.encoder_rad(t_end + np.linspace(0, 1, 11)) == world.table.encoder_rad(t_end))


# ---------------------------------------------------------------------------------------------
# sensor models
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("grade", sorted(GYRO_PRESETS))
def test_models_are_independent_of_block_split_and_deterministic(grade):
    rng = np.random.default_rng(0)
    dth = rng.standard_normal((5000, 3)) * 1e-5 + 7e-8
    dv = rng.standard_normal((5000, 3)) * 1e-4 + [0, 0, 9.8e-3]
    g_one = GyroModel(gyro_errors(grade), 1000, 42).apply(dth)
    a_one = AccelModel(accel_errors(grade), 1000, 42).apply(dv)
    g, a = GyroModel(gyro_errors(grade), 1000, 42), AccelModel(accel_errors(grade), 1000, 42)
    cuts = [0, 1, 2, 999, 1036, 4999, 5000]
    g_parts = np.concatenate([g.apply(dth[i:j]) for i, j in zip(cuts[:-1], cuts[1:], strict=True)])
    a_parts = np.concatenate([a.apply(dv[i:j]) for i, j in zip(cuts[:-1], cuts[1:], strict=True)])
    assert np.array_equal(g_one, g_parts)
    assert np.array_equal(a_one, a_parts)
    assert not np.array_equal(g_one, GyroModel(gyro_errors(grade), 1000, 43).apply(dth))


def test_world_increments_independent_of_block_split():
    world = static_world(0.0)
    world.table.command_move(0.3, math.radians(30.0))
    whole = world.increments(0.0, 4000, 1e-3, (0.1, 0.0, 0.0))
    parts = [
        world.increments(k0 * 1e-3, m, 1e-3, (0.1, 0.0, 0.0))
        for k0, m in ((0, 333), (333, 2667), (3000, 1000))
    ]
    for i in range(2):
        # same times up to float rounding; Δα terms are differences of α ≈ 0.5 rad: ~1e-16 rad apart
        np.testing.assert_allclose(np.concatenate([p[i] for p in parts]), whole[i], rtol=1e-12, atol=1e-15)


def _reference_float32_carry(x: np.ndarray) -> np.ndarray:
    out, r = [], [0.0, 0.0, 0.0]
    for row in x.tolist():
        v = [row[i] + r[i] for i in range(3)]
        q = struct.unpack("3f", struct.pack("3f", *v))
        r = [v[i] - q[i] for i in range(3)]
        out.append(q)
    return np.array(out)


def test_float32_quantization_carries_its_residual():
    rng = np.random.default_rng(3)
    x = np.concatenate([np.full((20000, 3), 1e-7 / 3), rng.standard_normal((5000, 3)) * 1e-8 + 5e-8])
    x[21000:21100] *= 1e4  # a move: magnitudes jump across many binades and back
    q = Float32Carry(3)
    out = np.concatenate([q.apply(x[:7]), q.apply(x[7:12345]), q.apply(x[12345:])])
    assert np.array_equal(out, _reference_float32_carry(x))
    assert np.array_equal(out.astype(np.float32).astype(float), out)  # every value is a float32
    ulp = np.spacing(np.float32(np.abs(x[-1]).max()))
    carried = np.abs(out.sum(axis=0) - x.sum(axis=0))
    naive = np.abs(x.astype(np.float32).astype(float)[:20000].sum(axis=0) - x[:20000].sum(axis=0))
    assert np.all(carried <= ulp)
    assert np.all(naive > 100 * ulp)  # without the carry a constant input drifts


def test_white_noise_and_gauss_markov_statistics():
    rate, n = 1000, 200_000
    arw = 0.5
    g = GyroModel(GyroErrors(arw_deg_rt_h=arw, float32_delta=False), rate, 11)
    out = g.apply(np.zeros((n, 3)))
    sigma = arw * D / 60 * math.sqrt(1 / rate)
    assert np.std(out, axis=0) == pytest.approx(np.full(3, sigma), rel=4 / math.sqrt(2 * n))
    a = AccelModel(AccelErrors(noise_ug_rt_hz=(50.0, 100.0, 200.0)), rate, 13)
    out = a.apply(np.zeros((n, 3)))
    sigma = np.array([50.0, 100.0, 200.0]) * 1e-6 * G0 * math.sqrt(1 / rate)  # m/s per sample
    assert np.std(out, axis=0) == pytest.approx(sigma, rel=4 / math.sqrt(2 * n))
    tau, bi = 0.05, 100.0
    g = GyroModel(GyroErrors(bias_instability_dph=bi, bi_correlation_s=tau, float32_delta=False), rate, 12)
    b = g.apply(np.zeros((n, 3))) * rate / (D / 3600)  # °/h
    n_eff = n / (2 * tau * rate)  # independent samples of a first-order GM process
    assert np.std(b, axis=0) == pytest.approx(np.full(3, bi), rel=4 / math.sqrt(2 * n_eff))
    lag1 = [np.corrcoef(b[:-1, i], b[1:, i])[0, 1] for i in range(3)]
    assert lag1 == pytest.approx([math.exp(-1 / (tau * rate))] * 3, abs=1e-3)


def test_nav_bias_instability_stays_well_below_the_white_noise_limit():
    """8 positions × 30 s at 40° N (+ 3 s per move): the heading error from the nav GM bias alone."""
    e = GYRO_PRESETS["nav"]
    rate, n_pos, dwell, move = 10, 8, 30.0, 3.0  # the GM process only: 10 Hz resolves it
    runs = 400
    alphas = np.arange(n_pos) * 2 * math.pi / n_pos
    horizontal = OMEGA_E * math.cos(LAT * D)
    per = int((dwell + move) * rate)
    errors = []
    for seed in range(runs):
        bi_only = GyroErrors(
            bias_instability_dph=e.bias_instability_dph,
            bi_correlation_s=e.bi_correlation_s,
            float32_delta=False,
        )
        g = GyroModel(bi_only, rate, seed)
        b = g.apply(np.zeros((n_pos * per, 3)))[:, 1].reshape(n_pos, per) * rate
        y = horizontal * np.cos(alphas) + b[:, int(move * rate) :].mean(axis=1)  # heading 0
        a = np.column_stack([np.ones(n_pos), np.cos(alphas), np.sin(alphas)])
        c0, ca, cs = np.linalg.lstsq(a, y, rcond=None)[0]
        errors.append(math.atan2(cs, ca))
    sigma_bi = float(np.std(errors))
    limit = e.arw_deg_rt_h[1] * D / 60 / horizontal * math.sqrt(2 / (n_pos * dwell))
    assert math.degrees(limit) == pytest.approx(0.0545, abs=0.001)
    assert sigma_bi < 0.3 * limit, (math.degrees(sigma_bi), math.degrees(limit))


def test_presets_and_custom_values():
    assert set(GYRO_PRESETS) == set(ACCEL_PRESETS) == {"nav", "kvh1760", "tactical-mems", "consumer",
                                                        "stim300"}
    arw = {k: v.arw_deg_rt_h for k, v in GYRO_PRESETS.items()}
    bi = {k: v.bias_instability_dph for k, v in GYRO_PRESETS.items()}
    assert arw == {
        "nav": (0.002,) * 3,
        "kvh1760": (0.012,) * 3,
        "tactical-mems": (0.15,) * 3,
        "consumer": (1.0,) * 3,
        "stim300": (0.15,) * 3,  # TS1524 rev.31 Table 5-3
    }
    assert bi == {
        "nav": (0.005,) * 3,
        "kvh1760": (0.05,) * 3,
        "tactical-mems": (0.5,) * 3,
        "consumer": (10.0,) * 3,
        "stim300": (0.3,) * 3,
    }
    custom = gyro_errors("nav", arw_deg_rt_h=(0.001, 0.002, 0.003))
    assert custom.arw_deg_rt_h == (0.001, 0.002, 0.003) and custom.bias_instability_dph == (0.005,) * 3
    with pytest.raises(ValueError, match="gyro grade 'navy' unknown; use one of nav, kvh1760"):
        gyro_errors("navy")
    with pytest.raises(ValueError, match="site latitude_deg = 91"):
        Site(91.0)


def test_site_gravity_and_southern_hemisphere():
    for lat, h in [(0.0, 0.0), (40.0, 0.0), (-33.9, 1200.0), (90.0, 0.0)]:
        assert Site(lat, h).gravity_m_s2 == pytest.approx(somigliana(lat, h), abs=1e-9)
    w, _ = World.static(-40.0, 0.0, table=TableMotion(power_on_deg=0.0)).truth(np.array([0.0]))
    assert w[0, 2] < 0 < w[0, 1]  # Earth rate points down-north in the south


class EastboundCar:
    """A trajectory through the PlatformMotion hook: level, heading east, constant speed."""

    is_static = False

    def __init__(self, speed_m_s: float) -> None:
        self.speed_m_s = speed_m_s

    def kinematics(self, t_s, site):
        from firmware_sim.physics.world import PlatformKinematics

        t = np.asarray(t_s, dtype=float)
        c = np.broadcast_to(c_bn(90.0, 0.0, 0.0), t.shape + (3, 3))
        z = np.zeros(t.shape + (3,))
        v = np.zeros(t.shape + (3,))
        v[..., 0] = self.speed_m_s
        return PlatformKinematics(c, z, z, v, z)


def test_trajectory_hook_coriolis_and_transport_rate():
    lat, h, v = 45.0, 100.0, 30.0
    world = World(Site(lat, h), EastboundCar(v), TableMotion(power_on_deg=0.0))
    w, f = world.truth(np.array([0.0, 1.0]))
    a, e2 = 6378137.0, (1 / 298.257223563) * (2 - 1 / 298.257223563)
    r_n = a / math.sqrt(1 - e2 * math.sin(lat * D) ** 2)  # prime-vertical radius
    w_ie = OMEGA_E * np.array([0.0, math.cos(lat * D), math.sin(lat * D)])
    w_en = np.array([0.0, v / (r_n + h), v * math.tan(lat * D) / (r_n + h)])
    v_n = np.array([v, 0.0, 0.0])
    f_n = np.cross(2 * w_ie + w_en, v_n) + np.array([0.0, 0.0, somigliana(lat, h)])
    cbn = c_bn(90.0, 0.0, 0.0)
    np.testing.assert_allclose(w[0], cbn.T @ (w_ie + w_en), rtol=0, atol=1e-18)
    np.testing.assert_allclose(f[0], cbn.T @ f_n, rtol=0, atol=1e-10)
    # Coriolis 2Ωe sinL·v (3.1 mm/s²) plus the transport term v² tanL/(R_N + h) (0.14 mm/s²), to
    # the right of travel: body x points south
    side = (2 * OMEGA_E * math.sin(lat * D) + v * math.tan(lat * D) / (r_n + h)) * v
    assert f[0, 0] == pytest.approx(-side, rel=1e-9)
    assert abs(f[0, 0] + 2 * OMEGA_E * math.sin(lat * D) * v) > 1e-4  # the transport term counts


def test_disturbance_is_local_and_absent_faults_change_nothing():
    plain = static_world(10.0)
    bumped = static_world(10.0)
    bumped.add_disturbance(5.0, 0.5, 0.2)
    for t0 in (0.0, 6.0):  # before and after the bump: bit-identical to the plain world
        a, b = (
            plain.increments(t0, 1000, 1e-3, (0.1, 0.0, 0.0)),
            bumped.increments(t0, 1000, 1e-3, (0.1, 0.0, 0.0)),
        )
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    a, b = plain.increments(5.0, 500, 1e-3), bumped.increments(5.0, 500, 1e-3)
    rate_dph = np.abs(b[0] - a[0]).max() * 1000 / (D / 3600)
    assert rate_dph > 1000  # a 0.2° bump at 2 Hz swings the rate by degrees per second
    # and it leaves the attitude where it was
    c_end = bumped.attitude(np.array([5.5]))[0][0]
    np.testing.assert_allclose(c_end, c_bn(HEADING, PITCH, ROLL), atol=1e-12)
