"""Physical constants and unit conversions, per docs/CONVENTIONS.md (WGS-84)."""

from __future__ import annotations

import numpy as np

OMEGA_EARTH_RAD_S = 7.2921150e-5
"""Earth rotation rate Ωe, WGS-84 [rad/s]."""

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
_GAMMA_E = 9.7803253359  # normal gravity at the equator [m/s²]
_SOMIGLIANA_K = 0.00193185265241
_M = 0.00344978650684  # ω²a²b/GM

STANDARD_GRAVITY_M_S2 = 9.80665
"""Conventional g used to convert accelerometer readings in g to m/s²."""

DEG = np.pi / 180.0
DPH = DEG / 3600.0
"""1 deg/h in rad/s."""


def normal_gravity_m_s2(latitude_deg, height_m=0.0):
    """WGS-84 normal gravity (Somigliana) at geodetic latitude and ellipsoidal height."""
    s2 = np.sin(np.deg2rad(latitude_deg)) ** 2
    g0 = _GAMMA_E * (1.0 + _SOMIGLIANA_K * s2) / np.sqrt(1.0 - WGS84_E2 * s2)
    h = np.asarray(height_m, dtype=float)
    free_air = 2.0 / WGS84_A_M * (1.0 + WGS84_F + _M - 2.0 * WGS84_F * s2)
    return g0 * (1.0 - free_air * h + 3.0 * h**2 / WGS84_A_M**2)


def earth_rate_enu_rad_s(latitude_deg) -> np.ndarray:
    """ω_ie^n = [0, Ωe·cos L, Ωe·sin L] in East-North-Up [rad/s]."""
    lat = np.deg2rad(latitude_deg)
    return np.array([0.0, OMEGA_EARTH_RAD_S * np.cos(lat), OMEGA_EARTH_RAD_S * np.sin(lat)])


def arw_to_rad_sqrt_s(arw_deg_sqrt_h):
    """Angle random walk in °/√h → white-noise density N in rad/√s."""
    return np.asarray(arw_deg_sqrt_h) * DEG / 60.0


def wrap_deg_180(angle_deg):
    """Wrap to [-180, 180)."""
    return (np.asarray(angle_deg) + 180.0) % 360.0 - 180.0


def wrap_deg_360(angle_deg):
    """Wrap to [0, 360)."""
    out = np.mod(np.asarray(angle_deg, dtype=float), 360.0)
    return np.where(out >= 360.0, 0.0, out)


def radii_of_curvature_m(latitude_deg):
    """WGS-84 meridian R_M and prime-vertical R_N radii of curvature [m] at geodetic latitude."""
    s2 = np.sin(np.deg2rad(latitude_deg)) ** 2
    w = np.sqrt(1.0 - WGS84_E2 * s2)
    return WGS84_A_M * (1.0 - WGS84_E2) / w**3, WGS84_A_M / w
