"""The white-noise accuracy limit of a turntable north find, level and tilted (docs/estimators.md)."""

from __future__ import annotations

import numpy as np

from northfinder.constants import DEG, OMEGA_EARTH_RAD_S


def tilt_noise_factor(tilt_deg, tilt_azimuth_deg):
    """k = √(1 + (tan ε · sin ζ)²) ≥ 1: how much a tilt ε with azimuth ζ amplifies heading noise.

    The exact heading depends on the fitted (w_x, w_y) through a gradient of norm
    |E^p_xy − E^p_z·u^p_xy/u^p_z| / (Ωe cos L) = √(1 + (E^p_z/u^p_z)²) / (Ωe cos L), and
    E^p_z / u^p_z = sinε·sinζ / cosε (east component of the table normal over its up component).
    """
    eps = np.deg2rad(tilt_deg)
    return np.sqrt(1.0 + (np.tan(eps) * np.sin(np.deg2rad(tilt_azimuth_deg))) ** 2)


def noise_limit_heading_std_deg(
    arw_deg_rt_h, total_dwell_s, latitude_deg, tilt_deg=0.0, tilt_azimuth_deg=0.0, gyro_axes: int = 1
):
    """σψ = N/(Ωe·cos L)·√(2/T_total)·k/√(axes) [deg] for n ≥ 3 equally spaced positions.

    N = ARW·(π/180)/60 [rad/√s] (docs/CONVENTIONS.md); k = :func:`tilt_noise_factor`
    (k = 1 level, giving the CONVENTIONS.md formula); `gyro_axes` = 2 when the b-x and b-y
    gyros are fitted jointly (each measures w_x, w_y with variance 2N²/T_total).
    """
    n_rad = np.asarray(arw_deg_rt_h, dtype=float) * DEG / 60.0
    lat = np.deg2rad(latitude_deg)
    sigma = n_rad / (OMEGA_EARTH_RAD_S * np.cos(lat)) * np.sqrt(2.0 / np.asarray(total_dwell_s, dtype=float))
    return np.rad2deg(sigma * tilt_noise_factor(tilt_deg, tilt_azimuth_deg) / np.sqrt(gyro_axes))


def per_position_std_dph(arw_deg_rt_h, dwell_s):
    """Standard error of one position's mean rate [deg/h] for white noise: ARW·60/√dwell."""
    return np.asarray(arw_deg_rt_h, dtype=float) * 60.0 / np.sqrt(np.asarray(dwell_s, dtype=float))
