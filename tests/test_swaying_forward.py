"""An independent forward model of a strapdown IMU on a swaying, moored ship (for the swaying tests).

Written from the geometry in shared/CONVENTIONS.md, not from northfinder's estimator code:
- attitude C_b^n(t) = Rz(−ψ(t))·Rx(θ(t))·Ry(γ(t)) with each Euler angle a sinusoid about its
  mean (ship roll is γ about the forward y axis, pitch θ about x, yaw about up);
- the body rate relative to n from the Euler rates, plus the Earth rate: ω_ib^b = ω_nb^b + C_n^b ω_ie^n;
- the IMU sits at a lever arm l^b from the ship's centre of rotation, which heaves along up:
  r^n = C_b^n l^b + h(t)·e_up, so a^n = C_b^n(ω̇×l + ω×(ω×l)) + ḧ·e_up, and the specific force is
  f^n = a^n + 2ω_ie^n×v^n + [0, 0, g] (moored: no transport rate; g = WGS-84 normal gravity);
- exact delta angles and velocity increments: 3-node Gauss–Legendre quadrature of ω_ib^b and
  f^b over each sample interval (what an integrating sensor outputs);
- white gyro noise at the grade's ARW, white accelerometer noise, optional turn-on biases.
The tests in this file check the model itself against closed-form facts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

OMEGA_E = 7.2921150e-5  # rad/s, WGS-84
G0 = 9.80665  # m/s² per g
D2R = np.pi / 180.0


@dataclass(frozen=True)
class Grade:
    """Sensor errors: ARW [°/√h], gyro bias 1σ [°/h], accel noise [µg/√Hz], accel bias 1σ [µg]."""

    arw_deg_rt_h: float
    gyro_bias_dph: float
    accel_noise_ug_rt_hz: float
    accel_bias_ug: float


GRADES = {
    "nav": Grade(0.002, 0.005, 20.0, 50.0),
    "kvh1760": Grade(0.012, 0.05, 80.0, 500.0),
    "tactical-mems": Grade(0.15, 1.0, 100.0, 1000.0),
    "perfect": Grade(0.0, 0.0, 0.0, 0.0),
}


@dataclass(frozen=True)
class Sway:
    """Amplitudes [deg, m], periods [s] of roll, pitch, yaw and heave; lever arm [m] in b."""

    roll_deg: float = 10.0
    roll_period_s: float = 8.0
    pitch_deg: float = 5.0
    pitch_period_s: float = 6.0
    yaw_deg: float = 3.0
    yaw_period_s: float = 10.0
    heave_m: float = 0.5
    heave_period_s: float = 7.0
    lever_arm_m: tuple[float, float, float] = (1.0, 2.0, 1.5)


REFERENCE = Sway()
STILL = Sway(0.0, 8.0, 0.0, 6.0, 0.0, 10.0, 0.0, 7.0, (1.0, 2.0, 1.5))


def somigliana_g(lat_deg: float) -> float:
    """WGS-84 normal gravity on the ellipsoid (Somigliana's closed form)."""
    s2 = np.sin(lat_deg * D2R) ** 2
    e2 = 6.69437999014e-3
    return 9.7803253359 * (1 + 0.00193185265241 * s2) / np.sqrt(1 - e2 * s2)


def _rz_neg(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, s, z], -1), np.stack([-s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


class SwayingShip:
    """Closed-form motion of one ship: heading ψ0 plus sinusoidal sway with the given phases."""

    def __init__(self, heading_deg: float, latitude_deg: float, sway: Sway, phases_rad=(0, 0, 0, 0)):
        self.psi0 = heading_deg * D2R
        self.lat = latitude_deg * D2R
        self.s = sway
        self.ph = np.asarray(phases_rad, dtype=float)
        self.g = somigliana_g(latitude_deg)
        self.w_ie_n = OMEGA_E * np.array([0.0, np.cos(self.lat), np.sin(self.lat)])
        self.lever = np.asarray(sway.lever_arm_m, dtype=float)

    def _sin(self, amp, period, phase, t, order):
        w = 2 * np.pi / period
        # d^k/dt^k of amp·sin(wt+phase) = amp·w^k·sin(wt+phase+kπ/2)
        return amp * w**order * np.sin(w * t + phase + order * np.pi / 2)

    def euler(self, t, order=0):
        """(ψ, θ, γ) or their time derivatives of the given order [rad, rad/s…]."""
        s, ph = self.s, self.ph
        psi = self._sin(s.yaw_deg * D2R, s.yaw_period_s, ph[2], t, order) + (self.psi0 if order == 0 else 0.0)
        theta = self._sin(s.pitch_deg * D2R, s.pitch_period_s, ph[1], t, order)
        gamma = self._sin(s.roll_deg * D2R, s.roll_period_s, ph[0], t, order)
        return psi, theta, gamma

    def c_b_n(self, t):
        psi, theta, gamma = self.euler(t)
        return _rz_neg(psi) @ _rx(theta) @ _ry(gamma)

    def omega_nb_b(self, t):
        """ω_nb^b = Ry(γ)ᵀ·(Rx(θ)ᵀ·[0,0,−ψ̇] + [θ̇,0,0]) + [0,γ̇,0] (from Cᵀ·Ċ = [ω×])."""
        psi, theta, gamma = self.euler(t)
        dpsi, dtheta, dgamma = self.euler(t, 1)
        z = np.zeros_like(t)
        v = np.einsum("...ji,...j->...i", _rx(theta), np.stack([z, z, -dpsi], -1))
        v = v + np.stack([dtheta, z, z], -1)
        v = np.einsum("...ji,...j->...i", _ry(gamma), v)
        return v + np.stack([z, dgamma, z], -1)

    def truth(self, t):
        """(ω_ib^b [rad/s], f^b [m/s²]) at times t (any shape)."""
        c = self.c_b_n(t)
        w = self.omega_nb_b(t)
        h = 1e-4
        wdot = (self.omega_nb_b(t + h) - self.omega_nb_b(t - h)) / (2 * h)
        s = self.s
        up = np.array([0.0, 0.0, 1.0])
        heave_v = self._sin(s.heave_m, s.heave_period_s, self.ph[3], t, 1)[..., None] * up
        heave_a = self._sin(s.heave_m, s.heave_period_s, self.ph[3], t, 2)[..., None] * up
        l = np.broadcast_to(self.lever, w.shape)
        v_n = np.einsum("...ij,...j->...i", c, np.cross(w, l)) + heave_v
        a_b = np.cross(wdot, l) + np.cross(w, np.cross(w, l))
        a_n = np.einsum("...ij,...j->...i", c, a_b) + heave_a
        f_n = a_n + 2 * np.cross(self.w_ie_n, v_n) + self.g * up
        f_b = np.einsum("...ji,...j->...i", c, f_n)
        w_ib = w + np.einsum("...ji,...j->...i", c, np.broadcast_to(self.w_ie_n, w.shape))
        return w_ib, f_b

    def increments(self, n: int, rate_hz: float):
        """Exact (Δθ [rad], Δv [m/s]) over the n intervals [(k−1)/rate, k/rate], k = 1…n."""
        dt = 1.0 / rate_hz
        x = np.sqrt(3.0 / 5.0)
        nodes = np.array([0.5 - x / 2, 0.5, 0.5 + x / 2])
        weights = np.array([5.0, 8.0, 5.0]) / 18.0
        t = (np.arange(n)[:, None] + nodes[None, :]) * dt
        w, f = self.truth(t)
        return np.einsum("q,nqc->nc", weights, w) * dt, np.einsum("q,nqc->nc", weights, f) * dt


def simulate_imu(ship: SwayingShip, duration_s: float, rate_hz: float, grade: Grade,
                 rng: np.random.Generator):
    """What the driver delivers: (gyro_rad_s [n,3], accel_g [n,3]) averaged over each interval."""
    n = int(round(duration_s * rate_hz))
    dt = 1.0 / rate_hz
    dth, dv = ship.increments(n, rate_hz)
    n_g = grade.arw_deg_rt_h * D2R / 60.0
    n_a = grade.accel_noise_ug_rt_hz * 1e-6 * G0
    b_g = rng.normal(0.0, 1.0, 3) * grade.gyro_bias_dph * D2R / 3600.0
    b_a = rng.normal(0.0, 1.0, 3) * grade.accel_bias_ug * 1e-6 * G0
    dth = dth + b_g * dt + rng.normal(0.0, 1.0, (n, 3)) * n_g * np.sqrt(dt)
    dv = dv + b_a * dt + rng.normal(0.0, 1.0, (n, 3)) * n_a * np.sqrt(dt)
    return dth / dt, dv / dt / G0


def heading_deg(c_b_n) -> float:
    """Azimuth of the horizontal projection of b-y, clockwise from north, [0, 360)."""
    return float(np.mod(np.degrees(np.arctan2(c_b_n[..., 0, 1], c_b_n[..., 1, 1])), 360.0))


# --- checks of the forward model itself --------------------------------------------------------
def test_still_ship_senses_earth_rate_and_gravity():
    ship = SwayingShip(30.0, 40.0, STILL)
    w, f = ship.truth(np.array([0.0, 100.0]))
    assert np.allclose(np.linalg.norm(w, axis=-1), OMEGA_E, rtol=1e-12)
    assert np.allclose(np.linalg.norm(f, axis=-1), somigliana_g(40.0), rtol=1e-12)
    # At heading 30° the body y axis sees Ωe·cosL·cos30° of the north component.
    assert w[0, 1] == pytest.approx(OMEGA_E * np.cos(40 * D2R) * np.cos(30 * D2R), rel=1e-12)


def test_increments_integrate_to_the_closed_form_attitude():
    """Chaining exp(Δθ) of the quadrature increments reproduces C_b^n(t) up to Earth rotation."""
    ship = SwayingShip(10.0, 40.0, REFERENCE, phases_rad=(0.3, 1.0, 2.0, 0.5))
    rate, n = 200.0, 2000
    dth, _ = ship.increments(n, rate)
    c = np.eye(3)
    for k in range(n):  # plain sequential integration: an independent reference, 2000 steps
        a = np.linalg.norm(dth[k])
        kx = np.array([[0, -dth[k, 2], dth[k, 1]], [dth[k, 2], 0, -dth[k, 0]], [-dth[k, 1], dth[k, 0], 0]])
        c = c @ (np.eye(3) + np.sin(a) / a * kx + (1 - np.cos(a)) / a**2 * kx @ kx)
    # Truth: C_b(t)^{b0-inertial} = C_b0^n(0)ᵀ·C_n(t)^{n0}·C_b^n(t) with Earth rotation about k.
    t = n / rate
    k = np.array([0.0, np.cos(ship.lat), np.sin(ship.lat)])
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = OMEGA_E * t
    r = np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx
    truth = ship.c_b_n(np.array(0.0)).T @ r @ ship.c_b_n(np.array(t))
    err = np.linalg.norm(truth.T @ c - np.eye(3))
    # Sequential integration without coning correction errs by O(ω²·dt) per second: bound it.
    assert err < 2e-5
