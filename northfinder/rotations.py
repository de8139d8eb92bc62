"""Rotation matrices and Euler angles, exactly as docs/CONVENTIONS.md defines them.

C_p^n = Rz(-ψ)·Rx(θ)·Ry(γ) maps platform (or body) vectors to East-North-Up; C_b^p = Rz(α)
for the table angle α. All functions accept scalars or arrays (leading batch dimensions).
"""

from __future__ import annotations

import numpy as np


def _stack(rows) -> np.ndarray:
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def rot_x(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return _stack([[o, z, z], [z, c, -s], [z, s, c]])


def rot_y(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return _stack([[c, z, s], [z, o, z], [-s, z, c]])


def rot_z(a) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return _stack([[c, -s, z], [s, c, z], [z, z, o]])


def dcm_from_euler(heading_rad, pitch_rad, roll_rad) -> np.ndarray:
    """C_p^n (p or b → ENU) from heading ψ, pitch θ, roll γ [rad]."""
    return rot_z(-np.asarray(heading_rad)) @ rot_x(pitch_rad) @ rot_y(roll_rad)


def euler_from_dcm(c_pn: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Heading ψ in [0, 2π), pitch θ, roll γ [rad] from C_p^n (inverse of dcm_from_euler)."""
    c = np.asarray(c_pn, dtype=float)
    pitch = np.arcsin(np.clip(c[..., 2, 1], -1.0, 1.0))
    roll = np.arctan2(-c[..., 2, 0], c[..., 2, 2])
    heading = np.mod(np.arctan2(c[..., 0, 1], c[..., 1, 1]), 2.0 * np.pi)
    return heading, pitch, roll


def tilt_and_azimuth(heading_rad, pitch_rad, roll_rad) -> tuple[np.ndarray, np.ndarray]:
    """Tilt ε = arccos(cosθ·cosγ) and tilt azimuth (heading of the downhill direction) [rad].

    The table normal p-z leans toward the downhill side, so the tilt azimuth is the azimuth of
    the horizontal projection of p-z in ENU: atan2(C_p^n[0,2], C_p^n[1,2]), in [0, 2π).
    Undefined (returned as 0) for a level table.
    """
    c = dcm_from_euler(heading_rad, pitch_rad, roll_rad)
    tilt = np.arccos(np.clip(np.cos(pitch_rad) * np.cos(roll_rad), -1.0, 1.0))
    azimuth = np.mod(np.arctan2(c[..., 0, 2], c[..., 1, 2]), 2.0 * np.pi)
    return tilt, np.where(tilt > 0.0, azimuth, 0.0)


def skew(v) -> np.ndarray:
    """Cross-product matrix [v×] (filled in place: it sits in the swaying fit's inner loop)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotvec_to_dcm(phi) -> np.ndarray:
    """Rodrigues: the rotation matrix of rotation vector φ [rad] (batched over leading dims)."""
    phi = np.asarray(phi, dtype=float)
    angle = np.linalg.norm(phi, axis=-1)[..., None, None]
    small = angle < 1e-8
    a2 = angle**2
    safe = np.where(small, 1.0, angle)
    s = np.where(small, 1.0 - a2 / 6.0, np.sin(safe) / safe)
    c = np.where(small, 0.5 - a2 / 24.0, (1.0 - np.cos(safe)) / safe**2)
    k = skew(phi)
    return np.eye(3) + s * k + c * (k @ k)


def dcm_to_rotvec(c) -> np.ndarray:
    """Inverse of rotvec_to_dcm for rotations below π."""
    c = np.asarray(c, dtype=float)
    cos_a = np.clip((np.trace(c, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos_a)
    v = np.stack(
        [c[..., 2, 1] - c[..., 1, 2], c[..., 0, 2] - c[..., 2, 0], c[..., 1, 0] - c[..., 0, 1]], axis=-1
    )
    sin_a = np.sin(angle)
    factor = np.where(angle < 1e-8, 0.5 + angle**2 / 12.0, angle / (2.0 * np.where(angle < 1e-8, 1.0, sin_a)))
    return v * factor[..., None]


def coning_corrected_rotvec(dtheta: np.ndarray) -> np.ndarray:
    """Per-interval rotation vectors from gyro delta angles with the one-previous-sample coning term.

    φ_k = Δθ_k + (1/12)·Δθ_{k-1} × Δθ_k (Savage's two-sample form with one past sample).
    `dtheta` has shape (n, 3); the first interval gets no correction.
    """
    dtheta = np.asarray(dtheta, dtype=float)
    phi = dtheta.copy()
    phi[1:] += np.cross(dtheta[:-1], dtheta[1:]) / 12.0
    return phi
