"""Earth model and rotations for the simulator, written from docs/CONVENTIONS.md.

firmware_sim imports nothing from northfinder, so this is its own, independent copy of the
frame conventions: n = East-North-Up, C_p^n = Rz(−ψ)·Rx(θ)·Ry(γ), C_b^p = Rz(α), WGS-84 Earth
rate and WGS-84 normal gravity (Somigliana, with the height correction). Every function takes
scalars or arrays (leading batch dimensions) and returns float64 arrays.
"""

from __future__ import annotations

import numpy as np

OMEGA_E_RAD_S = 7.2921150e-5
"""WGS-84 Earth rotation rate Ωe [rad/s]."""

A_M = 6378137.0
"""WGS-84 semi-major axis a [m]."""
F = 1.0 / 298.257223563
"""WGS-84 flattening f."""
E2 = F * (2.0 - F)
"""First eccentricity squared e²."""
GAMMA_E_M_S2 = 9.7803253359
"""Normal gravity on the equator γe [m/s²] (WGS-84)."""
GAMMA_P_M_S2 = 9.8321849378
"""Normal gravity at the poles γp [m/s²] (WGS-84)."""
SOMIGLIANA_K = 0.00193185265241
"""k = bγp/(aγe) − 1 of Somigliana's formula (published WGS-84 value)."""
M_RATIO = 0.00344978650684
"""m = ω²a²b/GM (published WGS-84 value), used by the height correction."""

G0_M_S2 = 9.80665
"""Standard gravity: the unit "g" of readings, not the local gravity."""

DEG = np.pi / 180.0
DPH = DEG / 3600.0
"""1 °/h in rad/s."""
EZ = np.array([0.0, 0.0, 1.0])


def normal_gravity_m_s2(latitude_deg, height_m=0.0) -> np.ndarray:
    """WGS-84 normal gravity γ(L, h): Somigliana on the ellipsoid, second-order height term.

    γ0 = γe(1 + k sin²L)/√(1 − e² sin²L);  γ = γ0[1 − 2/a (1 + f + m − 2f sin²L) h + 3h²/a²]
    (NIMA TR8350.2, eqs. 4-1 and 4-3). It already holds the centrifugal part of Earth's rotation.
    """
    s2 = np.sin(np.deg2rad(latitude_deg)) ** 2
    g0 = GAMMA_E_M_S2 * (1.0 + SOMIGLIANA_K * s2) / np.sqrt(1.0 - E2 * s2)
    h = np.asarray(height_m, dtype=float)
    return g0 * (1.0 - 2.0 / A_M * (1.0 + F + M_RATIO - 2.0 * F * s2) * h + 3.0 * h**2 / A_M**2)


def earth_rate_n_rad_s(latitude_rad) -> np.ndarray:
    """ω_ie^n = [0, Ωe cos L, Ωe sin L] (ENU) [rad/s], shape (..., 3)."""
    lat = np.asarray(latitude_rad, dtype=float)
    return np.stack([np.zeros_like(lat), OMEGA_E_RAD_S * np.cos(lat), OMEGA_E_RAD_S * np.sin(lat)], axis=-1)


def radii_m(latitude_rad) -> tuple[np.ndarray, np.ndarray]:
    """Meridian radius R_M and prime-vertical radius R_N of the WGS-84 ellipsoid [m]."""
    s2 = np.sin(np.asarray(latitude_rad, dtype=float)) ** 2
    w = np.sqrt(1.0 - E2 * s2)
    return A_M * (1.0 - E2) / w**3, A_M / w


def transport_rate_n_rad_s(vel_enu_m_s, latitude_rad, height_m) -> np.ndarray:
    """ω_en^n = [−v_N/(R_M+h), v_E/(R_N+h), v_E tan L/(R_N+h)]: the local-level frame's turn rate."""
    v = np.asarray(vel_enu_m_s, dtype=float)
    lat = np.asarray(latitude_rad, dtype=float)
    h = np.asarray(height_m, dtype=float)
    r_m, r_n = radii_m(lat)
    return np.stack(
        [-v[..., 1] / (r_m + h), v[..., 0] / (r_n + h), v[..., 0] * np.tan(lat) / (r_n + h)], axis=-1
    )


def _mat(rows) -> np.ndarray:
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def rot_x(a) -> np.ndarray:
    """Rx(a) = [[1,0,0],[0,c,−s],[0,s,c]]."""
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return _mat([[o, z, z], [z, c, -s], [z, s, c]])


def rot_y(a) -> np.ndarray:
    """Ry(a) = [[c,0,s],[0,1,0],[−s,0,c]]."""
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return _mat([[c, z, s], [z, o, z], [-s, z, c]])


def rot_z(a) -> np.ndarray:
    """Rz(a) = [[c,−s,0],[s,c,0],[0,0,1]]."""
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return _mat([[c, -s, z], [s, c, z], [z, z, o]])


def c_pn(heading_rad, pitch_rad, roll_rad) -> np.ndarray:
    """C_p^n = Rz(−ψ)·Rx(θ)·Ry(γ): platform (or body) axes → ENU."""
    return rot_z(-np.asarray(heading_rad, dtype=float)) @ rot_x(pitch_rad) @ rot_y(roll_rad)


def zxy_rotation(z, x, y, z_dot, x_dot, y_dot, z_ddot, x_ddot, y_ddot):
    """Rotation C = Rz(z)·Rx(x)·Ry(y) with its body rate and body angular acceleration.

    ω (in the rotated frame) from CᵀĊ = [ω×]: ω = Ryᵀ Rxᵀ (ż e_z) + Ryᵀ (ẋ e_x) + ẏ e_y, i.e.
    ω = [cy ẋ − sy cx ż, sx ż + ẏ, sy ẋ + cy cx ż]; ω̇ is its exact time derivative.
    Returns (C [...,3,3], ω [...,3], ω̇ [...,3]). For an attitude, z = −ψ, x = θ, y = γ.
    """
    cx, sx, cy, sy = np.cos(x), np.sin(x), np.cos(y), np.sin(y)
    cz, sz = np.cos(z), np.sin(z)
    # Rz(z)·Rx(x)·Ry(y) multiplied out (batched 3×3 matmuls are slow in numpy)
    c = np.empty(np.shape(cx) + (3, 3))
    c[..., 0, 0] = cz * cy - sz * sx * sy
    c[..., 0, 1] = -sz * cx
    c[..., 0, 2] = cz * sy + sz * sx * cy
    c[..., 1, 0] = sz * cy + cz * sx * sy
    c[..., 1, 1] = cz * cx
    c[..., 1, 2] = sz * sy - cz * sx * cy
    c[..., 2, 0] = -cx * sy
    c[..., 2, 1] = sx
    c[..., 2, 2] = cx * cy
    w = np.stack([cy * x_dot - sy * cx * z_dot, sx * z_dot + y_dot, sy * x_dot + cy * cx * z_dot], axis=-1)
    w_dot = np.stack(
        [
            -sy * y_dot * x_dot
            + cy * x_ddot
            - (cy * y_dot * cx * z_dot - sy * sx * x_dot * z_dot + sy * cx * z_ddot),
            cx * x_dot * z_dot + sx * z_ddot + y_ddot,
            cy * y_dot * x_dot
            + sy * x_ddot
            - sy * y_dot * cx * z_dot
            - cy * sx * x_dot * z_dot
            + cy * cx * z_ddot,
        ],
        axis=-1,
    )
    return c, w, w_dot


def rot_z_transpose_apply(alpha, v) -> np.ndarray:
    """Rz(α)ᵀ·v without building matrices (C_p^b v for the table angle α), batched."""
    c, s = np.cos(alpha), np.sin(alpha)
    return np.stack(
        [c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2] + 0.0 * c], axis=-1
    )


def cross(a, b) -> np.ndarray:
    """a × b over the last axis (np.cross without its axis shuffling), broadcast."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def transpose_apply(c, v) -> np.ndarray:
    """Cᵀ·v for batched 3×3 matrices C [...,3,3] and vectors v [...,3]."""
    c = np.asarray(c)
    v = np.asarray(v)
    return c[..., 0, :] * v[..., 0:1] + c[..., 1, :] * v[..., 1:2] + c[..., 2, :] * v[..., 2:3]
