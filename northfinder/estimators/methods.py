"""The five heading formulas, batched, in this project's conventions (docs/estimators.md).

Inputs are the fitted platform-frame Earth rate w^p_x, w^p_y [rad/s] (the harmonic
coefficients v_x, v_y of the gyro fit), the up vector u^p = C_n^p·[0, 0, 1] from the
accelerometer and the vertical Earth rate ω_H = Ωe·sin L. With C_n^p = Ry(−γ)Rx(−θ)Rz(ψ):

    w^p_x = ω_N(−sinψ cosγ + cosψ sinγ sinθ) − ω_H sinγ cosθ
    w^p_y = ω_N cosψ cosθ + ω_H sinθ
    u^p   = [−cosθ sinγ, sinθ, cosθ cosγ]

and the paper's b-y gyro coefficients are a = w^p_y, b = −w^p_x (eq 4). Every function returns
ψ in radians, wrapped to [0, 2π).
"""

from __future__ import annotations

import numpy as np

TWO_PI = 2.0 * np.pi


def _wrap(psi: np.ndarray) -> np.ndarray:
    out = np.mod(psi, TWO_PI)
    return np.where(out >= TWO_PI, 0.0, out)


def pitch_roll_from_up(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pitch θ = asin(u_y), roll γ = atan2(−u_x, u_z) [rad] from the up vector u^p (…, 3)."""
    u = np.asarray(u, dtype=float)
    return np.arcsin(np.clip(u[..., 1], -1.0, 1.0)), np.arctan2(-u[..., 0], u[..., 2])


def heading_uncompensated(w_x, w_y, u=None, omega_h=None) -> np.ndarray:
    """Paper eq 8: ψ = atan(b/a) = atan2(−w_x, w_y); ignores tilt (error ≈ tan L·ε)."""
    return _wrap(np.arctan2(-np.asarray(w_x), np.asarray(w_y)))


def heading_coordinate_transform(w_x, w_y, u, omega_h) -> np.ndarray:
    """Paper eq 3 (coordinate transform), with a = w_y, b = −w_x (eq 2 divided by n/2).

    ψ = atan2(b·cosθ + a·sinγ·sinθ − ω_H·sinγ, (a − ω_H·sinθ)·cosγ). Both arguments are the
    paper's numerator and denominator multiplied by cosθ·cosγ > 0, so atan2 gets the quadrant
    right. Algebraically exact in these conventions when θ and γ are exact.
    """
    a, b = np.asarray(w_y), -np.asarray(w_x)
    theta, gamma = pitch_roll_from_up(u)
    num = b * np.cos(theta) + a * np.sin(gamma) * np.sin(theta) - omega_h * np.sin(gamma)
    den = (a - omega_h * np.sin(theta)) * np.cos(gamma)
    return _wrap(np.arctan2(num, den))


def _compensated_ab(w_x, w_y, u, omega_h) -> tuple[np.ndarray, np.ndarray]:
    """a, b with the ω_H projection removed: the paper's correction in eq 10/11.

    In these conventions ω_H·u^p adds +ω_H·u_y to a and −ω_H·u_x to b (the paper writes
    −ω_H·sinε·cosζ, −ω_H·sinε·sinζ for its own ζ; the geometry here fixes the signs).
    """
    u = np.asarray(u, dtype=float)
    a = np.asarray(w_y) - omega_h * u[..., 1]
    b = -np.asarray(w_x) + omega_h * u[..., 0]
    return a, b


def heading_vector(w_x, w_y, u, omega_h) -> np.ndarray:
    """Paper eq 10 (vector method): ψ = atan2(b_c / cosθ_b, a_c / cosθ_a).

    θ_a = asin(u_y) is the elevation of the gyro axis p-y, θ_b = asin(−u_x) that of the
    orthogonal axis −p-x. Exact when pitch or roll is zero; with both non-zero the cross term
    −ω_N·cosψ·sinγ·sinθ in b_c and cosθ_b ≠ cosγ leave an error (docs/estimators.md).
    """
    u = np.asarray(u, dtype=float)
    a, b = _compensated_ab(w_x, w_y, u, omega_h)
    cos_a = np.sqrt(1.0 - np.clip(u[..., 1], -1, 1) ** 2)
    cos_b = np.sqrt(1.0 - np.clip(u[..., 0], -1, 1) ** 2)
    return _wrap(np.arctan2(b / cos_b, a / cos_a))


def heading_eq11(w_x, w_y, u, omega_h) -> np.ndarray:
    """Paper eq 11 (literature formula, flawed): ψ = atan2(b_c, a_c), the in-plane angle."""
    a, b = _compensated_ab(w_x, w_y, u, omega_h)
    return _wrap(np.arctan2(b, a))


def north_east_in_platform(w_x, w_y, u, omega_h) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal north N^p (scaled by ω_N) and east E^p = N^p × u^p from the fit and u^p.

    ω^p = ω_N·n^p + ω_H·u^p, so ω_N·n^p_xy = w^p_xy − ω_H·u^p_xy; n ⟂ u fixes
    N_z = −(N_x u_x + N_y u_y)/u_z. No small-angle step; the scale ω_N drops out of ψ.
    """
    u = np.asarray(u, dtype=float)
    nx = np.asarray(w_x) - omega_h * u[..., 0]
    ny = np.asarray(w_y) - omega_h * u[..., 1]
    nz = -(nx * u[..., 0] + ny * u[..., 1]) / u[..., 2]
    north = np.stack(np.broadcast_arrays(nx, ny, nz), axis=-1)
    east = np.cross(north, np.broadcast_to(u, north.shape))
    return north, east


def heading_exact(w_x, w_y, u, omega_h) -> np.ndarray:
    """Exact geometric heading (not in the paper; builds on eq 1 and eq 4).

    ψ is the azimuth of p-y: its east and north components are E^p_y and N^p_y, so
    ψ = atan2(E^p_y, N^p_y) with N, E from :func:`north_east_in_platform`.
    """
    north, east = north_east_in_platform(w_x, w_y, u, omega_h)
    return _wrap(np.arctan2(east[..., 1], north[..., 1]))


METHODS = {
    "exact": heading_exact,
    "coordinate_transform": heading_coordinate_transform,
    "vector": heading_vector,
    "eq11": heading_eq11,
    "uncompensated": heading_uncompensated,
}
"""Method name → function(w_x, w_y, u, ω_H) → ψ [rad]."""
