"""Strapdown inertial mechanization in East-North-Up, from delta angles and velocity increments.

What: attitude C_b^n, velocity v^n and position (local ENU metres, see LocalLevel) integrated from an IMU's
integrated outputs Δθ^b, Δv^b at a fixed rate, with Earth rate ω_ie^n, transport rate ω_en^n,
WGS-84 normal gravity (northfinder.constants), Coriolis, and the two-sample (one previous sample)
coning and sculling corrections (Savage, "Strapdown inertial navigation integration algorithm
design", JGCD 1998, parts 1–2; Titterton & Weston, Strapdown Inertial Navigation Technology,
2nd ed., eq 11.12 and 11.35).

Why a per-sample Python loop: the state is sequential and a GNSS/INS filter feeds corrections
back every 0.1 s, so the integration runs in short chunks. The loop works on Python floats
only (no numpy call per sample); the n-frame rotation (Earth + transport rate, ≤ 1e-4 rad/s) is
applied once per chunk of at most `chunk` samples, which is exact far below any sensor noise.
Everything that can be vectorized (bias removal, coning and sculling terms) is done per call in
numpy.

Conventions (docs/CONVENTIONS.md): b is x right, y forward, z up; n is ENU; C_b^n =
Rz(−ψ)Rx(θ)Ry(γ); accelerometers measure f^b = C_n^b(a^n − g^n).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from northfinder.constants import (
    OMEGA_EARTH_RAD_S,
    STANDARD_GRAVITY_M_S2,
    WGS84_A_M,
    WGS84_E2,
    normal_gravity_m_s2,
)
from northfinder.errors import InputError


def earth_radii_m(lat_rad: float) -> tuple[float, float]:
    """Meridian R_M and prime-vertical R_N radii of curvature of the WGS-84 ellipsoid [m]."""
    s2 = math.sin(lat_rad) ** 2
    w = math.sqrt(1.0 - WGS84_E2 * s2)
    return WGS84_A_M * (1.0 - WGS84_E2) / w**3, WGS84_A_M / w


def earth_rate_n(lat_rad: float) -> np.ndarray:
    """ω_ie^n = [0, Ωe cos L, Ωe sin L] [rad/s]."""
    return np.array([0.0, OMEGA_EARTH_RAD_S * math.cos(lat_rad), OMEGA_EARTH_RAD_S * math.sin(lat_rad)])


def transport_rate_n(lat_rad: float, h_m: float, v_enu_m_s) -> np.ndarray:
    """ω_en^n = [−v_N/(R_M+h), v_E/(R_N+h), v_E tan L/(R_N+h)] [rad/s] (Titterton & Weston eq 3.76)."""
    r_m, r_n = earth_radii_m(lat_rad)
    ve, vn = float(v_enu_m_s[0]), float(v_enu_m_s[1])
    return np.array([-vn / (r_m + h_m), ve / (r_n + h_m), ve * math.tan(lat_rad) / (r_n + h_m)])


def dcm_to_quat(c: np.ndarray) -> np.ndarray:
    """Unit quaternion [w, x, y, z] of a rotation matrix (Shepperd's method)."""
    c = np.asarray(c, dtype=float)
    tr = c[0, 0] + c[1, 1] + c[2, 2]
    cands = np.array([tr, c[0, 0], c[1, 1], c[2, 2]])
    i = int(np.argmax(cands))
    if i == 0:
        w = 0.5 * math.sqrt(1.0 + tr)
        q = [w, (c[2, 1] - c[1, 2]) / (4 * w), (c[0, 2] - c[2, 0]) / (4 * w), (c[1, 0] - c[0, 1]) / (4 * w)]
    elif i == 1:
        x = 0.5 * math.sqrt(1.0 + 2 * c[0, 0] - tr)
        q = [(c[2, 1] - c[1, 2]) / (4 * x), x, (c[0, 1] + c[1, 0]) / (4 * x), (c[0, 2] + c[2, 0]) / (4 * x)]
    elif i == 2:
        y = 0.5 * math.sqrt(1.0 + 2 * c[1, 1] - tr)
        q = [(c[0, 2] - c[2, 0]) / (4 * y), (c[0, 1] + c[1, 0]) / (4 * y), y, (c[1, 2] + c[2, 1]) / (4 * y)]
    else:
        z = 0.5 * math.sqrt(1.0 + 2 * c[2, 2] - tr)
        q = [(c[1, 0] - c[0, 1]) / (4 * z), (c[0, 2] + c[2, 0]) / (4 * z), (c[1, 2] + c[2, 1]) / (4 * z), z]
    q = np.array(q)
    return q / np.linalg.norm(q) * (1.0 if q[0] >= 0 else -1.0)


def quat_to_dcm(q) -> np.ndarray:
    """Rotation matrix of a unit quaternion [w, x, y, z]."""
    w, x, y, z = (float(v) for v in q)
    return np.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
        ]
    )


def skew3(v) -> np.ndarray:
    """[v×] of one 3-vector (cheaper than the batched rotations.skew in per-update code)."""
    x, y, z = (float(a) for a in v)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def cross3(a, b) -> np.ndarray:
    """a × b for two 3-vectors (np.cross costs ~20 µs per call on single vectors)."""
    ax, ay, az = (float(v) for v in a)
    bx, by, bz = (float(v) for v in b)
    return np.array([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise a × b for (n, 3) arrays."""
    return np.column_stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                            a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]])


def orthonormalize(c: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (polar decomposition via SVD): the paper's eq 23 re-orthogonalization."""
    u, _, vt = np.linalg.svd(c)
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    return r


def fill_lost_samples(sample_index, values) -> np.ndarray:
    """`values` [n, k] at strictly increasing device indices → one row per index from the first to
    the last, each lost sample linearly interpolated between its neighbours (every align estimator
    fills a line's lost samples this way; how much it trusts the filling is its own business)."""
    idx = np.asarray(sample_index, dtype=np.int64)
    v = np.asarray(values, dtype=float)
    dense = np.arange(idx[0], idx[-1] + 1)
    return np.column_stack([np.interp(dense, idx, v[:, i]) for i in range(v.shape[1])])


def increments_from_rates(gyro_rad_s, accel_g, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Δθ [rad] and Δv [m/s] per sample from rate-format IMU output (rate × dt, accel in g × g0 × dt).

    A KVH in DELTA format already integrates; the driver delivers `gyro_rad_s` = Δθ·rate, so this
    inverts that exactly. 1 g = 9.80665 m/s² (docs/CONVENTIONS.md project notes).
    """
    dt = 1.0 / float(rate_hz)
    return np.asarray(gyro_rad_s, float) * dt, np.asarray(accel_g, float) * (STANDARD_GRAVITY_M_S2 * dt)


@dataclass
class NavState:
    """Navigation solution: position in local ENU metres about the origin, ENU velocity, C_b^n, time."""

    pos_enu_m: np.ndarray
    v_enu_m_s: np.ndarray
    c_bn: np.ndarray
    t_s: float = 0.0

    def copy(self) -> NavState:
        return NavState(self.pos_enu_m.copy(), self.v_enu_m_s.copy(), self.c_bn.copy(), self.t_s)


@dataclass
class ChunkSummary:
    """What a filter needs from one propagation call: mean body rate and specific force, heading
    change, and the body rate of the last sample (for lever-arm velocities at the chunk's end)."""

    dt_s: float
    omega_ib_b_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))
    f_b_m_s2: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dheading_rad: float = 0.0
    omega_end_b_rad_s: np.ndarray = field(default_factory=lambda: np.zeros(3))


class Strapdown:
    """ENU strapdown integrator; `propagate(dtheta, dv)` advances the state through samples.

    The sensor biases `gyro_bias_rad_s` and `accel_bias_m_s2` are subtracted before integration:
    a filter sets them when it feeds back its estimates (paper eq 23).
    """

    def __init__(self, state: NavState, rate_hz: float, origin: LocalLevel, *, chunk: int = 25):
        if rate_hz <= 0:
            raise InputError(f"IMU rate must be positive, got {rate_hz} Hz")
        self.state = state.copy()
        self.origin = origin
        self.rate_hz = float(rate_hz)
        self.dt_s = 1.0 / self.rate_hz
        self.chunk = int(chunk)
        self.gyro_bias_rad_s = np.zeros(3)
        self.accel_bias_m_s2 = np.zeros(3)
        self._q = dcm_to_quat(self.state.c_bn)
        self._prev_dtheta = np.zeros(3)
        self._prev_dv = np.zeros(3)

    # -- attitude access -------------------------------------------------------------------------
    def set_attitude(self, c_bn: np.ndarray) -> None:
        """Replace C_b^n (after a filter correction); re-orthonormalized first."""
        c = orthonormalize(np.asarray(c_bn, float))
        self.state.c_bn = c
        self._q = dcm_to_quat(c)

    def heading_rad(self) -> float:
        """ψ in [0, 2π) of the current C_b^n."""
        c = self.state.c_bn
        return math.atan2(c[0, 1], c[1, 1]) % (2.0 * math.pi)

    # -- integration -----------------------------------------------------------------------------
    def propagate(self, dtheta_rad: np.ndarray, dv_m_s: np.ndarray) -> ChunkSummary:
        """Integrate n samples of Δθ^b [rad] and Δv^b [m/s] (shape (n, 3)); return a summary."""
        dtheta = np.asarray(dtheta_rad, dtype=float).reshape(-1, 3) - self.gyro_bias_rad_s * self.dt_s
        dv = np.asarray(dv_m_s, dtype=float).reshape(-1, 3) - self.accel_bias_m_s2 * self.dt_s
        n = dtheta.shape[0]
        if n == 0:
            return ChunkSummary(0.0)
        # Coning (rotation vector) and sculling (velocity) with one previous sample:
        # φ_k = Δθ_k + 1/12 Δθ_{k-1}×Δθ_k ; Δv_k' = Δv_k + ½ Δθ_k×Δv_k + 1/12 (Δθ_{k-1}×Δv_k + Δv_{k-1}×Δθ_k)
        prev_th = np.vstack([self._prev_dtheta, dtheta[:-1]])
        prev_dv = np.vstack([self._prev_dv, dv[:-1]])
        phi = dtheta + _cross_rows(prev_th, dtheta) / 12.0
        scul = _cross_rows(prev_th, dv) + _cross_rows(prev_dv, dtheta)
        dv_c = dv + 0.5 * _cross_rows(dtheta, dv) + scul / 12.0
        self._prev_dtheta = dtheta[-1].copy()
        self._prev_dv = dv[-1].copy()
        # Quaternion of each body rotation vector, 4th-order series (|φ| ≲ 1e-2 rad per sample).
        a2 = np.einsum("ij,ij->i", phi, phi)
        qw = 1.0 - a2 / 8.0 + a2 * a2 / 384.0
        qv = phi * (0.5 - a2 / 48.0)[:, None]
        body_q = np.column_stack([qw, qv]).tolist()
        dvb = dv_c.tolist()
        psi0 = self.heading_rad()
        for k0 in range(0, n, self.chunk):
            self._chunk(body_q[k0 : k0 + self.chunk], dvb[k0 : k0 + self.chunk])
        dpsi = (self.heading_rad() - psi0 + math.pi) % (2.0 * math.pi) - math.pi
        t = n * self.dt_s
        return ChunkSummary(t, dtheta.sum(axis=0) / t, dv.sum(axis=0) / t, dpsi, dtheta[-1] / self.dt_s)

    def _chunk(self, body_q: list, dvb: list) -> None:
        s = self.state
        dt = self.dt_s
        m = len(body_q)
        lat, h = self.origin.lat_h(s.pos_enu_m)
        w_ie = earth_rate_n(lat)
        w_en = transport_rate_n(lat, h, s.v_enu_m_s)
        w_in = w_ie + w_en
        g = float(normal_gravity_m_s2(math.degrees(lat), h))
        cor = cross3(2.0 * w_ie + w_en, s.v_enu_m_s)
        # Gravity/Coriolis velocity increment per sample (held over the ≤ 0.1 s chunk).
        gx, gy, gz = (-cor[0] * dt, -cor[1] * dt, (-g - cor[2]) * dt)
        # q is rotated for the n-frame motion only at the chunk's end, so at sample j of the chunk
        # the attitude lags the current n by ω_in·j·dt; with the usual half-sample term the velocity
        # transform is (I − [ζ_j×]) C_b^n(k−1) Δv_k', ζ_j = ω_in·(j + ½)·dt.
        wx, wy, wz = (w_in * dt).tolist()
        zx, zy, zz = 0.5 * wx, 0.5 * wy, 0.5 * wz
        w, x, y, z = self._q.tolist()
        ve, vn, vu = s.v_enu_m_s.tolist()
        se = sn = su = 0.0  # Σ velocity for the position update (trapezoid)
        for (bw, bx, by, bz), (ax, ay, az) in zip(body_q, dvb, strict=True):
            # Δv^n = (I − ½[ζ×]) C_b^n(k−1) Δv_k'
            c00 = w * w + x * x - y * y - z * z
            c01 = 2 * (x * y - w * z)
            c02 = 2 * (x * z + w * y)
            c10 = 2 * (x * y + w * z)
            c11 = w * w - x * x + y * y - z * z
            c12 = 2 * (y * z - w * x)
            c20 = 2 * (x * z - w * y)
            c21 = 2 * (y * z + w * x)
            c22 = w * w - x * x - y * y + z * z
            ux = c00 * ax + c01 * ay + c02 * az
            uy = c10 * ax + c11 * ay + c12 * az
            uz = c20 * ax + c21 * ay + c22 * az
            ux, uy, uz = ux - (zy * uz - zz * uy), uy - (zz * ux - zx * uz), uz - (zx * uy - zy * ux)
            zx += wx
            zy += wy
            zz += wz
            ve0, vn0, vu0 = ve, vn, vu
            ve += ux + gx
            vn += uy + gy
            vu += uz + gz
            se += 0.5 * (ve0 + ve)
            sn += 0.5 * (vn0 + vn)
            su += 0.5 * (vu0 + vu)
            # q ← q ⊗ q(φ_k)
            w, x, y, z = (
                w * bw - x * bx - y * by - z * bz,
                w * bx + x * bw + y * bz - z * by,
                w * by - x * bz + y * bw + z * bx,
                w * bz + x * by - y * bx + z * bw,
            )
        # n-frame rotation over the chunk: q ← q(−ω_in·T) ⊗ q
        rx, ry, rz = (-w_in * (m * dt) * 0.5).tolist()
        w, x, y, z = (
            w - rx * x - ry * y - rz * z,
            rx * w + x + ry * z - rz * y,
            ry * w + y + rz * x - rx * z,
            rz * w + z + rx * y - ry * x,
        )
        norm = math.sqrt(w * w + x * x + y * y + z * z)
        self._q = np.array([w, x, y, z]) / norm
        s.pos_enu_m = s.pos_enu_m + np.array([se, sn, su]) * dt
        s.v_enu_m_s = np.array([ve, vn, vu])
        s.c_bn = quat_to_dcm(self._q)
        s.t_s += m * dt


class LocalLevel:
    """Local ENU metres about an origin (L0, λ0, h0), curvilinear: E = Δλ(R_N+h0)cosL0, N = ΔL(R_M+h0).

    The INS integrates its position in these metres (latitude for Earth rate, transport rate and
    gravity is L0 + N/(R_M+h0)), GNSS fixes are converted with the same map, and the filter's δP is
    in these metres. Over a few km the map differs from the ellipsoid by ≲ 0.1 m, far inside the
    GNSS noise, and since the INS and the receiver share it their differences are exact.
    """

    def __init__(self, lat0_rad: float, lon0_rad: float = 0.0, h0_m: float = 0.0):
        self.lat0, self.lon0, self.h0 = float(lat0_rad), float(lon0_rad), float(h0_m)
        r_m, r_n = earth_radii_m(self.lat0)
        self.k_n = r_m + self.h0
        self.k_e = (r_n + self.h0) * math.cos(self.lat0)

    def lat_h(self, enu_m) -> tuple[float, float]:
        """Geodetic latitude [rad] and height [m] at a local position (what Earth rate and g need)."""
        return self.lat0 + float(enu_m[1]) / self.k_n, self.h0 + float(enu_m[2])

    def to_enu(self, lat_rad, lon_rad, h_m) -> np.ndarray:
        """Geodetic → local ENU [m] (arrays broadcast; last axis = E, N, U)."""
        return np.stack(
            [
                (np.asarray(lon_rad) - self.lon0) * self.k_e,
                (np.asarray(lat_rad) - self.lat0) * self.k_n,
                np.asarray(h_m, dtype=float) - self.h0,
            ],
            axis=-1,
        )

    def from_enu(self, enu_m) -> tuple:
        """Local ENU [m] → (lat_rad, lon_rad, h_m)."""
        enu = np.asarray(enu_m, dtype=float)
        return (self.lat0 + enu[..., 1] / self.k_n, self.lon0 + enu[..., 0] / self.k_e, self.h0 + enu[..., 2])
