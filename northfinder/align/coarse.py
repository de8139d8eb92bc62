"""Static analytic coarse alignment: the baseline the swaying-base method is compared with.

On a base at rest the gyros see only the Earth rate and the accelerometers only gravity:
ω_ie^n = [0, Ωe·cos L, Ωe·sin L], f^n = [0, 0, g] (docs/CONVENTIONS.md, "What the sensors
measure"). Averaging both over a window and solving the two-vector (TRIAD) problem gives
C_b^n directly — the classical analytic coarse alignment (docs/swaying.md §7, eq. 10; see the
initial-alignment chapters of Britting, "Inertial Navigation Systems Analysis", 1971, and of
Titterton & Weston, "Strapdown Inertial Navigation Technology", 2nd ed.). On a swaying base
the mean body rate of the sway does not vanish over a window that is not a whole number of
periods and dwarfs Ωe (7.3e-5 rad/s), so the heading is lost: tests/test_swaying.py and
tools/reproduce_swaying_paper.py show it with numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from northfinder.align.limits import LATITUDE_ADVICE, latitude_problem
from northfinder.align.swaying import white_noise_density
from northfinder.constants import DEG, OMEGA_EARTH_RAD_S
from northfinder.errors import InputError
from northfinder.rotations import euler_from_dcm

__all__ = ["CoarseSolution", "coarse_align"]


@dataclass(frozen=True)
class CoarseSolution:
    """Attitude of the b frame from the window means, with the noise-only 1σ of the heading."""

    heading_deg: float
    heading_std_deg: float
    pitch_deg: float
    roll_deg: float
    duration_device_s: float
    c_b_n: np.ndarray = field(repr=False)
    diagnostics: dict = field(default_factory=dict, repr=False)


def coarse_align(
    gyro_rad_s: np.ndarray, accel_g: np.ndarray, rate_hz: float, latitude_deg: float
) -> CoarseSolution:
    """TRIAD on the window means of ω^b and f^b (docs/swaying.md eq. 10).

    up^b = f̄/|f̄|, east^b = (ω̄ × f̄)/|ω̄ × f̄| (ω_ie × up points east), north^b = up × east;
    C_n^b = [east^b, north^b, up^b] as columns, C_b^n its transpose. The 1σ propagates the
    white gyro noise measured from the data (the mean rate has σ = N/√T per axis) into the east
    gyro's share: σψ = N/(Ωe·cos L·√T), the noise limit of a single-position gyrocompass.
    """
    w = np.asarray(gyro_rad_s, dtype=float)
    f = np.asarray(accel_g, dtype=float)
    if w.ndim != 2 or w.shape[1] != 3 or f.shape != w.shape or w.shape[0] < 5:
        raise InputError(
            f"coarse alignment needs gyro and accel arrays of shape [n≥5, 3]; got {w.shape}, {f.shape}")
    if not np.any(f):
        raise InputError(
            "the IMU delivers no accelerometer data (all zero): coarse alignment needs accelerometers")
    if latitude_problem(latitude_deg):
        raise InputError(f"latitude {latitude_deg:g}: {LATITUDE_ADVICE}")
    w_mean = w.mean(axis=0)
    f_mean = f.mean(axis=0)
    up = f_mean / np.linalg.norm(f_mean)
    east = np.cross(w_mean, f_mean)
    east /= np.linalg.norm(east)
    north = np.cross(up, east)
    c_n_b = np.stack([east, north, up], axis=1)
    c_b_n = c_n_b.T
    heading, pitch, roll = euler_from_dcm(c_b_n)
    dt = 1.0 / rate_hz
    duration_s = w.shape[0] * dt
    n_gyro = white_noise_density(w * dt, dt)
    omega_h = OMEGA_EARTH_RAD_S * np.cos(latitude_deg * DEG)
    std = float(np.sqrt(np.mean(n_gyro**2)) / (omega_h * np.sqrt(duration_s)))
    still = _base_still(w, rate_hz, n_gyro)
    return CoarseSolution(
        heading_deg=float(heading / DEG),
        heading_std_deg=std / DEG,
        pitch_deg=float(pitch / DEG),
        roll_deg=float(roll / DEG),
        duration_device_s=duration_s,
        c_b_n=c_b_n,
        diagnostics={"mean_rate_dph": (w_mean / DEG * 3600.0).tolist(),
                     "earth_rate_dph": OMEGA_EARTH_RAD_S / DEG * 3600.0,
                     "base_still": still},
    )


def _base_still(w: np.ndarray, rate_hz: float, n_gyro: np.ndarray) -> bool:
    """Whether the 1 s means of the rate scatter no more than the white noise explains (5σ, worst axis).

    Only then is the noise-limit σ the heading's uncertainty; on a moving base the window mean carries
    the motion, whose residue no σ from the data describes (docs/swaying.md §7)."""
    k = max(1, int(round(rate_hz)))
    blocks = w[: (w.shape[0] // k) * k].reshape(-1, k, 3).mean(axis=1)
    if blocks.shape[0] < 2:
        return True
    scatter = blocks.std(axis=0, ddof=1)
    return bool(np.all(scatter <= 5.0 * n_gyro * np.sqrt(rate_hz / k)))
