"""Swaying-base gyrocompass: true north from a strapdown IMU on a rolling ship (inertial frame).

The method of the second seed paper (shared/papers/swaying-base-inertial-frame-north-finding,
"New north finding algorithm for strapdown compass based on FOG"; abstract steps 1–3), with
the improvements documented in docs/swaying.md:

1. fix the initial body-inertial frame i_b0 (= the IMU case frame at the first sample) and
   propagate C_b^{i_b0}(t) from the gyro delta angles with a coning correction — a log-depth
   parallel-prefix quaternion product, no per-sample Python loop;
2. carry the specific force into i_b0 as velocity increments (rotation + sculling compensated)
   and smooth them with a Blackman–Harris kernel that rejects the periodic sway and heave; in i_b0
   the smoothed specific force is gravity turning on a cone about the Earth's axis (paper abstract,
   step 2) plus the IMU's lever-arm term, whose sway products beat slowly enough to pass the kernel:
   it is linear in the arm with a kernel known from step 1 (docs/swaying.md eq. 4a), and the cone
   fits estimate the arm with the heading;
3. fit that cone: ``method="cone"`` (default) solves Wahba's problem between the smoothed
   vectors and the known cone (half-angle 90° − L, rate Ωe) — three unknowns; ``"cone-gls"``
   adds one generalized-least-squares step weighted by the measured noise (the optional fine
   alignment); ``method="circle"`` is the paper's free space-circle fit (plane normal by SVD);
4. project the Earth axis on the horizontal plane at the end of the window: true north; the
   attitude at t_end is C_{i_b0}^{n}(t_end)·C_b^{i_b0}(t_end) (paper abstract, step 3).

The 1σ comes from propagating the gyro and accelerometer white noise (measured from the data
itself, see `white_noise_density`) and optional bias priors through the fit (docs/swaying.md §5).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from northfinder.align.grades import IMU_GRADES
from northfinder.align.limits import LATITUDE_ADVICE, latitude_problem
from northfinder.align.strapdown import fill_lost_samples
from northfinder.constants import (
    DEG,
    DPH,
    OMEGA_EARTH_RAD_S,
    STANDARD_GRAVITY_M_S2,
    normal_gravity_m_s2,
    wrap_deg_180,
)
from northfinder.errors import InputError
from northfinder.rotations import coning_corrected_rotvec, euler_from_dcm, rotvec_to_dcm, skew

__all__ = [
    "SwayingSolution",
    "align_swaying",
    "align_swaying_block",
    "attitude_quaternions",
    "quat_prefix_product",
    "quat_to_dcm",
    "velocity_increments_ib0",
    "white_noise_density",
    "minimum_duration_s",
    "predicted_heading_std_deg",
    "grade_bias_prior",
]

KVH_GYRO_RANGE_DPS = 490.0
"""Gyro input range assumed by default: ±490 °/s (KVH 1750/1760/1775)."""
KVH_ACCEL_RANGE_G = 10.0
"""Accelerometer range assumed by default: ±10 g (KVH 1750)."""
METHODS = ("cone", "cone-gls", "circle")
"""cone: constrained fit (default); cone-gls: plus one generalized-least-squares step weighted by the
measured noise (what a Kalman filter on the same windows would reach); circle: the paper's free fit."""
_BH4 = (0.35875, 0.48829, 0.14128, 0.01168)  # Blackman–Harris 4-term coefficients
_BH4_MAIN_LOBE_BINS = 4.0  # half-width of its main lobe in 1/L_w; side lobes below −92 dB
LEVER_ARM_STD_M = 10.0
"""Prior 1σ per axis of the IMU's lever arm from the point the ship turns about [m] (an IMU within
~10 m of a ship's roll centre); the sway determines the arm far better where it observes it."""


# ---------------------------------------------------------------------------------------------
# Step 1: attitude of the body in the initial body-inertial frame
# ---------------------------------------------------------------------------------------------
def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a⊗b, batched; composes like DCMs: C(a⊗b) = C(a)·C(b)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _quat_from_rotvec(phi: np.ndarray) -> np.ndarray:
    """Unit quaternion of rotation vector φ: [cos(|φ|/2), sin(|φ|/2)·φ/|φ|]."""
    angle = np.linalg.norm(phi, axis=-1)
    half = 0.5 * angle
    small = angle < 1e-6
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half)[..., None], k[..., None] * phi], axis=-1)


def quat_prefix_product(dq: np.ndarray) -> np.ndarray:
    """Ordered prefix products q_k = dq_0⊗dq_1⊗…⊗dq_k along axis 0 (Hillis–Steele scan).

    log2(n) vectorized passes instead of n sequential products: 300 000 samples take 19 passes.
    The Hamilton product is associative, so the result equals the sequential recursion up to
    rounding; the result is renormalized once at the end.
    """
    q = np.array(dq, dtype=float, copy=True)
    n = q.shape[0]
    step = 1
    while step < n:
        q[step:] = _quat_mul(q[:-step], q[step:])
        step *= 2
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_to_dcm(q: np.ndarray) -> np.ndarray:
    """Direction cosine matrix of unit quaternion(s) [w, x, y, z]."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def _quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """C(q)·v for batched q and v: v + 2w(r×v) + 2r×(r×v), r the vector part."""
    w = q[..., :1]
    r = q[..., 1:]
    t = 2.0 * np.cross(r, v)
    return v + w * t + np.cross(r, t)


def attitude_quaternions(dtheta_rad: np.ndarray) -> np.ndarray:
    """q_k = C_b(t_k)^{i_b0} for k = 0…n from n gyro delta angles [rad] (docs/swaying.md eq. 1–2).

    Each interval's rotation vector carries Savage's one-past-sample coning term
    φ_k = Δθ_k + Δθ_{k−1}×Δθ_k/12 (northfinder.rotations.coning_corrected_rotvec); the chain
    q_k = q_{k−1}⊗q(φ_k) is evaluated as a parallel prefix product.
    """
    dq = _quat_from_rotvec(coning_corrected_rotvec(dtheta_rad))
    q = np.empty((dq.shape[0] + 1, 4))
    q[0] = (1.0, 0.0, 0.0, 0.0)
    q[1:] = quat_prefix_product(dq)
    return q


def velocity_increments_ib0(q: np.ndarray, dtheta_rad: np.ndarray, dv_m_s: np.ndarray) -> np.ndarray:
    """Velocity increments carried into i_b0 [m/s], one per sample interval (docs/swaying.md eq. 3).

    Δv_k^{i_b0} = C_b(t_{k−1})^{i_b0}·(Δv_k + ½Δθ_k×Δv_k + (Δθ_{k−1}×Δv_k + Δv_{k−1}×Δθ_k)/12):
    the rotation compensation and Savage's two-sample sculling term, so that the sum over an
    interval is the integral of C_b^{i_b0}·f^b even while the body rolls.
    """
    corr = dv_m_s + 0.5 * np.cross(dtheta_rad, dv_m_s)
    corr[1:] += (np.cross(dtheta_rad[:-1], dv_m_s[1:]) + np.cross(dv_m_s[:-1], dtheta_rad[1:])) / 12.0
    return _quat_rotate(q[:-1], corr)


# ---------------------------------------------------------------------------------------------
# Noise measured from the data
# ---------------------------------------------------------------------------------------------
def white_noise_density(increments: np.ndarray, dt_s: float) -> np.ndarray:
    """White-noise density per axis [unit/√s] of integrated-sensor increments (Δθ or Δv).

    The 4th finite difference removes the smooth sway (a polynomial of degree 3 over five
    samples) and leaves white noise with variance 70·σ² (1+16+36+16+1); σ is taken from the
    median absolute deviation so that a few spikes do not inflate it. density = σ/√dt.
    """
    d4 = np.diff(np.asarray(increments, dtype=float), n=4, axis=0)
    mad = np.median(np.abs(d4 - np.median(d4, axis=0)), axis=0)
    sigma = 1.482602 * mad / np.sqrt(70.0)
    return sigma / np.sqrt(dt_s)


# ---------------------------------------------------------------------------------------------
# The solution
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SwayingSolution:
    """Attitude of the IMU case (b frame) at the END of the window, with 1σ and diagnostics."""

    heading_deg: float
    heading_std_deg: float
    pitch_deg: float
    roll_deg: float
    pitch_std_deg: float
    roll_std_deg: float
    duration_device_s: float
    method: str
    latitude_deg: float
    c_b_n: np.ndarray = field(repr=False)
    """C_b^n at t_end (ENU)."""
    earth_axis_ib0: np.ndarray = field(repr=False)
    """Unit Earth-axis direction in the i_b0 frame."""
    diagnostics: dict = field(default_factory=dict, repr=False)
    window_t_s: np.ndarray = field(default_factory=lambda: np.empty(0), repr=False)
    """Centre of each smoothing window [s from the window's start] (eq. 4–5)."""
    window_residual_m_s2: np.ndarray = field(default_factory=lambda: np.empty((0, 3)), repr=False)
    """Each window's specific force in i_b0 less the fitted model (the cone and the lever arm's
    sway, eq. 4a) [m/s², m × 3]; empty for the circle fit, which has no residual model."""


def grade_bias_prior(grade: str | None) -> dict[str, float]:
    """align_swaying's bias-prior keyword arguments for an IMU class (grades.IMU_GRADES: the turn-on
    biases — a fixed base cannot separate a gyro bias from the Earth rate, so it is the bias floor
    εE/(Ωe·cos L) the reported σ must carry — and the scale-factor asymmetry the sway rectifies into a
    bias, `_sway_rectified_bias_rad_s`); {} when the class is unknown."""
    g = IMU_GRADES.get(str(grade)) if grade else None
    if g is None:
        return {}
    return {"gyro_bias_dph": g.gyro_turn_on_dph, "accel_bias_ug": g.accel_turn_on_ug,
            "gyro_sf_asymmetry_ppm": g.gyro_sf_asymmetry_ppm}


def _sway_rectified_bias_rad_s(rate_rad_s: np.ndarray, asymmetry_ppm: float) -> np.ndarray:
    """1σ per body axis [rad/s] of the bias a scale-factor asymmetry A = (S₊ − S₋)/S makes of the sway.

    A rate ω reads (1 ± A/2)·ω by its sign, so the error (A/2)·|ω| has the mean (A/2)·mean|ω|: a constant
    bias while the ship sways (1 ppm on the reference roll's 5 °/s mean rate: 0.009 °/h, as large as a
    nav-grade turn-on bias) that no fit can tell from the Earth rate. mean|ω| is measured from the data."""
    return 0.5 * asymmetry_ppm * 1e-6 * np.mean(np.abs(rate_rad_s), axis=0)


def minimum_duration_s(max_sway_period_s: float) -> float:
    """Shortest window the fit accepts: two smoothing windows (4 periods each) end to end."""
    return 2.0 * _BH4_MAIN_LOBE_BINS * max_sway_period_s


def _kernel(n: int) -> np.ndarray:
    """Blackman–Harris 4-term window of n samples normalized to unit sum."""
    x = 2.0 * np.pi * (np.arange(n) + 0.5) / n
    w = _BH4[0] - _BH4[1] * np.cos(x) + _BH4[2] * np.cos(2 * x) - _BH4[3] * np.cos(3 * x)
    return w / w.sum()


def _up_n0(t_s: np.ndarray, latitude_rad: float) -> np.ndarray:
    """Local up at time t in n0, the ENU frame at t = 0 frozen in inertial space (docs eq. 5).

    Rodrigues rotation of up = [0,0,1] by Ωe·t about the Earth axis k = [0, cos L, sin L]:
    u(t) = cos(Ωt)·up + sin(Ωt)·k×up + (1 − cos Ωt)(k·up)·k — the cone of paper step 2.
    """
    a = OMEGA_EARTH_RAD_S * np.asarray(t_s, dtype=float)
    cl, sl = np.cos(latitude_rad), np.sin(latitude_rad)
    c, s = np.cos(a), np.sin(a)
    return np.stack([cl * s, (1.0 - c) * sl * cl, c + (1.0 - c) * sl * sl], axis=-1)


def _earth_rotation_n0_to_nt(t_s: float, latitude_rad: float) -> np.ndarray:
    """C_{n0}^{n(t)}: ENU at time t from the frozen ENU at t = 0 (Earth turned by Ωe·t)."""
    k = np.array([0.0, np.cos(latitude_rad), np.sin(latitude_rad)])
    a = OMEGA_EARTH_RAD_S * t_s
    kx = skew(k)
    r = np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)  # C_{n(t)}^{n0}
    return r.T


def _wahba(f_ib0: np.ndarray, m_n0: np.ndarray) -> np.ndarray:
    """C_{n0}^{i_b0} minimizing Σ_j |F_j − C·M_j|² (docs/swaying.md eq. 6; Markley's SVD solution).

    B = Σ F_j M_jᵀ = U S Vᵀ → C = U·diag(1, 1, det U·det V)·Vᵀ.
    """
    b = f_ib0.T @ m_n0
    u, _, vt = np.linalg.svd(b)
    d = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _frame_from_axis_and_up(axis: np.ndarray, up: np.ndarray) -> np.ndarray:
    """C_{i_b0}^{n}: rows east, north, up; north = horizontal projection of the Earth axis."""
    up = up / np.linalg.norm(up)
    north = axis - (axis @ up) * up
    north /= np.linalg.norm(north)
    east = np.cross(north, up)
    return np.stack([east, north, up])


def _rotate_about(axis: np.ndarray, angle: float, v: np.ndarray) -> np.ndarray:
    kx = skew(axis)
    return (np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)) @ v


def _fit_cone(f_ib0, m_n0, t_end_s, latitude_rad):
    """Constrained cone fit (docs/swaying.md eq. 6–7): C_{i_b0}^{n(t_end)} and the Earth axis."""
    c_n0_ib0 = _wahba(f_ib0, m_n0)
    c_ib0_nt = _earth_rotation_n0_to_nt(t_end_s, latitude_rad) @ c_n0_ib0.T
    axis = c_n0_ib0 @ np.array([0.0, np.cos(latitude_rad), np.sin(latitude_rad)])
    return c_ib0_nt, axis


@dataclass(frozen=True)
class _LeverModel:
    """The lever-arm term of the smoothed specific force, F_j^lever = G_j·r (docs/swaying.md eq. 4a),
    and the prior that keeps r where the sway does not observe it: `ridge` = s²/σ_r² per axis."""

    g: np.ndarray
    """G_j [m,3,3] [1/s²]: the windows' second derivative of C_b^{i_b0}(t) (`_lever_kernels`)."""
    ridge: float

    def force(self, r: np.ndarray) -> np.ndarray:
        """G_j·r [m,3]: each window's lever-arm specific force for the arm r [m]."""
        return np.einsum("jik,k->ji", self.g, r)


def _lever_model(
    q: np.ndarray,
    starts: np.ndarray,
    h: np.ndarray,
    dt: float,
    f_win: np.ndarray,
    cov_phi: np.ndarray,
    cov_acc: np.ndarray,
    lever_arm_std_m: float,
) -> _LeverModel | None:
    """The lever-arm term for the cone fits, or None when `lever_arm_std_m` is 0 (not estimated).

    The prior σ_r enters as a ridge s²/σ_r², s² the modelled noise power of one window component
    (white noise and bias priors, docs/swaying.md §5): where the sway does not observe r (a still
    base: G ≈ 0) the estimate stays near 0 instead of fitting noise."""
    if lever_arm_std_m <= 0.0:
        return None
    m = f_win.shape[0]
    s_f = _block_skew(f_win)
    s2 = float(np.mean(np.diag(s_f @ cov_phi[: 3 * m, : 3 * m] @ s_f.T + cov_acc)))
    return _LeverModel(_lever_kernels(q, starts, h, dt), s2 / lever_arm_std_m**2)


def _lever_kernels(q: np.ndarray, starts: np.ndarray, h: np.ndarray, dt: float) -> np.ndarray:
    """G_j = Σ_c Δ²h_c·C_b^{i_b0}(t_c)/dt² [m,3,3]: a window's lever-arm specific force per metre of r.

    An IMU at r (body axes, fixed) from the point the sway turns about sees, in the inertial i_b0,
    the extra acceleration d²(C_b^{i_b0}·r)/dt² = C_b^{i_b0}(ω̇×r + ω×(ω×r)). Smoothed by h_j and summed
    by parts twice (h and h' vanish at a window's ends), it is Σ_c Δ²h_c·C(t_c)·r/dt²: only the
    attitude from step 1, no differentiated gyro. The sway's products beat at difference frequencies
    (roll 8 s × yaw 10 s → 40 s, × pitch 6 s → 24 s) inside the window's main lobe: this term is
    what leaks through the smoothing (docs/swaying.md §8). C at the interval centres: mean of the ends.
    The stencil reaches one centre past each end so that its weights sum to zero (C·r itself is metres;
    the second difference must see only its curvature); at the record's ends that centre is extrapolated
    linearly, which leaves h_0·a·dt² (h_0 ≈ 6e-5 of the peak, a the arm's acceleration).
    """
    c = quat_to_dcm(q)
    c_mid = 0.5 * (c[:-1] + c[1:]).reshape(-1, 9)
    c_mid = np.concatenate([2 * c_mid[:1] - c_mid[1:2], c_mid, 2 * c_mid[-1:] - c_mid[-2:-1]])  # −1 … n
    d2h = np.diff(np.concatenate([[0.0, 0.0], h, [0.0, 0.0]]), n=2) / dt**2  # centres −1 … lw
    lw = h.size
    return np.stack([d2h @ c_mid[s0: s0 + lw + 2] for s0 in starts]).reshape(-1, 3, 3)


def _fit_cone_lever(f_ib0, m_n0, lever: _LeverModel, iterations: int = 3):
    """Cone fit with the lever arm r estimated with it (docs/swaying.md eq. 6 amended by eq. 4a, which
    amends the paper's step 2 — the specific force carried into i_b0 is gravity on the cone plus the
    arm's d²(C_b^{i_b0}·r)/dt², not gravity alone): min Σ|F_j − C·M_j − G_j·r|² + ridge·|r|².
    Gauss–Newton from the Wahba solution on (δ, r), C ← C·exp([δ×]): r enters linearly, the rotation
    is sub-degree, so three steps converge. Returns (C_{n0}^{i_b0}, r [m])."""
    c = _wahba(f_ib0, m_n0)
    r = np.zeros(3)
    prior = np.hstack([np.zeros((3, 3)), np.sqrt(lever.ridge) * np.eye(3)])
    m_skew, g_rows = skew(m_n0), lever.g.reshape(-1, 3)
    for _ in range(iterations):
        a = np.concatenate([-(c @ m_skew).reshape(-1, 3), g_rows], axis=1)
        res = (f_ib0 - m_n0 @ c.T - lever.force(r)).ravel()
        step = np.linalg.lstsq(np.vstack([a, prior]), np.concatenate([res, -np.sqrt(lever.ridge) * r]),
                               rcond=None)[0]
        c = c @ rotvec_to_dcm(step[:3])
        r = r + step[3:]
    return c, r


def _fit_circle(f_ib0, t_win_s, t_end_s, latitude_rad):
    """The paper's space-circle fit (abstract, step 2; docs/swaying.md eq. 8): plane by SVD.

    The plane normal is the Earth axis, oriented so that gravity turns positively about it; the
    vertical at t_end is the last direction turned on by Ωe·(t_end − t_last) about that axis.
    Latitude is only used to reject the sign of a normal that points into the wrong hemisphere.
    """
    p = f_ib0 / np.linalg.norm(f_ib0, axis=1, keepdims=True)
    _, _, vt = np.linalg.svd(p - p.mean(axis=0))
    axis = vt[-1]
    if np.cross(p[0], p[-1]) @ axis < 0.0:
        axis = -axis
    up_end = _rotate_about(axis, OMEGA_EARTH_RAD_S * (t_end_s - t_win_s[-1]), p[-1])
    return _frame_from_axis_and_up(axis, up_end), axis


def _angles(c_b_n: np.ndarray) -> np.ndarray:
    h, p, r = euler_from_dcm(c_b_n)
    return np.array([h, p, r]) / DEG


def _gls_whitening(
    f_win: np.ndarray,
    m_win: np.ndarray,
    cov_phi: np.ndarray,
    cov_acc: np.ndarray,
    t_end: float,
    lat: float,
    lever: _LeverModel | None,
) -> np.ndarray:
    """Σ_f^(−1/2) of the GLS step (docs/swaying.md §6): Σ_f = S_f Σ_φ S_fᵀ + Σ_acc, plus the cone
    fit's residual power as white — sway that leaks through the smoothing is not noise, and the
    weighting must not amplify it. Reused by every solve."""
    m = f_win.shape[0]
    s_f = _block_skew(f_win)
    sigma_f = s_f @ cov_phi[: 3 * m, : 3 * m] @ s_f.T + cov_acc
    if lever is None:
        res0 = f_win - m_win @ _wahba(f_win, m_win).T
    else:
        c0, r0 = _fit_cone_lever(f_win, m_win, lever)
        res0 = f_win - m_win @ c0.T - lever.force(r0)
    sigma_f += np.eye(3 * m) * np.mean(res0**2)
    return np.linalg.inv(np.linalg.cholesky(sigma_f))


def _solver(
    method: str,
    m_win: np.ndarray,
    t_win: np.ndarray,
    t_end: float,
    lat: float,
    whiten: np.ndarray | None,
    c_b_ib0_end: np.ndarray,
    lever: _LeverModel | None,
) -> Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """solve(f, dφ_end) → (C_b^n at the end, Earth axis in i_b0, lever arm r [m]): the method's fit
    (docs/swaying.md §4: cone eq. 6–7 with the lever arm of eq. 4a when `lever` is given, circle eq. 8,
    GLS eq. 9 on F − G·r) on smoothed specific forces `f`, with an optional small attitude error dφ_end
    at the end (C = C_ib0^nt (I − [dφ×]) C_b^ib0); the Jacobians perturb both."""

    def solve(f: np.ndarray, dphi_end: np.ndarray | None = None):
        r = np.zeros(3)
        if method == "circle":
            c_ib0_nt, axis = _fit_circle(f, t_win, t_end, lat)
        elif lever is None:
            c_ib0_nt, axis = _fit_cone(f, m_win, t_end, lat)
        else:
            c_n0_ib0, r = _fit_cone_lever(f, m_win, lever)
            c_ib0_nt = _earth_rotation_n0_to_nt(t_end, lat) @ c_n0_ib0.T
            axis = c_n0_ib0 @ np.array([0.0, np.cos(lat), np.sin(lat)])
        if method == "cone-gls":
            f_sway_free = f if lever is None else f - lever.force(r)
            c_ib0_nt, axis = _gls_step(f_sway_free, m_win, c_ib0_nt, t_end, lat, whiten)
        tweak = np.eye(3) if dphi_end is None else np.eye(3) - skew(dphi_end)
        return c_ib0_nt @ tweak @ c_b_ib0_end, axis, r

    return solve


def _angle_cov_parts(
    solve: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]],
    f_win: np.ndarray,
    residual: np.ndarray | None,
    noise: _NoiseCov,
    lever: _LeverModel | None,
) -> dict[str, np.ndarray]:
    """Covariance of (heading, pitch, roll) by source, linearised through the fit (docs/swaying.md
    §5): white noise, the turn-on bias priors, the sway-rectified scale-factor asymmetry and the
    sway leakage."""
    g_map, jac_f = _jacobians(solve, f_win)
    cov_leak = _leakage_covariance(residual, f_win, *noise.total, lever)
    return {
        "white_noise": _angles_cov(g_map, jac_f, noise.white_phi, noise.white_acc),
        "bias_prior": _angles_cov(g_map, jac_f, noise.bias_phi, noise.bias_acc),
        "sf_asymmetry": g_map @ noise.rect_phi @ g_map.T,
        "sway_leakage": jac_f @ cov_leak @ jac_f.T,
    }


def _diagnostics(
    n: int,
    n_lost: int,
    rate_hz: float,
    window_s: float,
    n_windows: int,
    n_gyro: np.ndarray,
    n_acc: np.ndarray,
    peak_dps: np.ndarray,
    axis_elevation_deg: float,
    residual: np.ndarray | None,
    parts: dict[str, np.ndarray],
    lever_m: np.ndarray | None,
) -> dict[str, Any]:
    """What the solution was computed from (docs/swaying.md §5): samples, windows, the noise
    densities measured from the data, the fit residual, the estimated lever arm (None: not estimated)
    and the heading σ by source."""
    return {
        "n_samples": n,
        "lost_samples_filled": n_lost,
        "rate_hz": rate_hz,
        "smoothing_window_s": window_s,
        "n_windows": n_windows,
        "gyro_arw_deg_rt_h": (n_gyro / DEG * 60.0).tolist(),
        "accel_noise_ug_rt_hz": (n_acc / STANDARD_GRAVITY_M_S2 * 1e6).tolist(),
        "gyro_peak_dps": peak_dps.tolist(),
        "earth_axis_elevation_deg": axis_elevation_deg,
        "fit_residual_rms_ug": (float(np.sqrt(np.mean(residual**2))) / STANDARD_GRAVITY_M_S2 * 1e6
                                if residual is not None else None),
        "heading_std_parts_deg": {k: float(np.sqrt(max(v[0, 0], 0.0))) for k, v in parts.items()},
        "lever_arm_m": None if lever_m is None else lever_m.tolist(),
    }


def _step2_windows(
    q: np.ndarray, dtheta: np.ndarray, dv: np.ndarray, lw: int, dt: float, lat: float, g: float
) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Step 2 (docs/swaying.md §3): velocity increments in i_b0, smoothed by Blackman–Harris windows
    of `lw` samples at a hop of lw/4: (window starts, kernel, (f, M, t) of every window)."""
    dv_ib0 = velocity_increments_ib0(q, dtheta, dv)
    hop = max(1, lw // 4)
    starts = np.arange(0, dv.shape[0] - lw + 1, hop)
    h = _kernel(lw)
    return starts, h, _smooth_windows(dv_ib0, starts, h, dt, lat, g)


def _check_duration(duration_s: float, max_sway_period_s: float) -> None:
    """The window must hold two smoothing windows (docs/swaying.md §3, `minimum_duration_s`)."""
    t_min = minimum_duration_s(max_sway_period_s)
    if duration_s < t_min:
        raise InputError(
            f"window of {duration_s:.1f} s is too short for the swaying alignment: it needs at least "
            f"{t_min:.0f} s (two smoothing windows of 4 × the {max_sway_period_s:g} s longest sway period); "
            "use 300 s for ~0.05° with a navigation-grade IMU")


def _checked_inputs(
    gyro: np.ndarray,
    accel_g: np.ndarray,
    rate_hz: float,
    latitude_deg: float,
    gyro_is_delta: bool,
    valid: np.ndarray | None,
    method: str,
    gyro_range_dps: float,
    accel_range_g: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refuse input that cannot give a meaningful heading (InputError saying why); the gyro as rates
    [rad/s], the specific force [g] and each gyro axis's peak [°/s]."""
    gyro = np.asarray(gyro, dtype=float)
    accel_g = np.asarray(accel_g, dtype=float)
    if gyro.ndim != 2 or gyro.shape[1] != 3 or accel_g.shape != gyro.shape:
        raise InputError(f"swaying alignment needs gyro and accel arrays of shape [n,3]; got {gyro.shape} "
                         f"and {accel_g.shape}")
    if not rate_hz or rate_hz <= 0:
        raise InputError(f"swaying alignment needs the IMU sample rate; got rate_hz={rate_hz}")
    if method not in METHODS:
        raise InputError(f"unknown swaying method '{method}': use one of {', '.join(METHODS)}")
    if latitude_problem(latitude_deg):
        raise InputError(f"latitude {latitude_deg:g}: {LATITUDE_ADVICE}")
    _check_valid(valid)
    if not np.all(np.isfinite(gyro)) or not np.all(np.isfinite(accel_g)):
        raise InputError("IMU data contain NaN or infinite values: check the driver's decoding")
    if not np.any(accel_g):
        raise InputError("the IMU delivers no accelerometer data (all zero): the swaying alignment needs "
                         "a 3-axis accelerometer — use an IMU with accelerometers")
    rate = gyro if not gyro_is_delta else gyro / (1.0 / rate_hz)  # per-sample delta angles → rad/s
    peak_dps = np.max(np.abs(rate), axis=0) / DEG
    if np.any(peak_dps >= 0.999 * gyro_range_dps):
        ax = "xyz"[int(np.argmax(peak_dps))]
        raise InputError(f"gyro {ax} reached {peak_dps.max():.1f} °/s, the ±{gyro_range_dps:g} °/s range: "
                         "the sway saturates the gyro — align in calmer sea or with a wider-range IMU")
    if np.any(np.abs(accel_g) >= 0.999 * accel_range_g):
        raise InputError(f"accelerometer reached the ±{accel_range_g:g} g range: the motion saturates it")
    return rate, accel_g, peak_dps


def align_swaying(
    gyro: np.ndarray,
    accel_g: np.ndarray,
    rate_hz: float,
    latitude_deg: float,
    *,
    gyro_is_delta: bool = False,
    sample_index: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    method: str = "cone",
    max_sway_period_s: float = 10.0,
    height_m: float = 0.0,
    gyro_bias_dph: float = 0.0,
    accel_bias_ug: float = 0.0,
    gyro_range_dps: float = KVH_GYRO_RANGE_DPS,
    accel_range_g: float = KVH_ACCEL_RANGE_G,
    lever_arm_std_m: float = LEVER_ARM_STD_M,
    gyro_sf_asymmetry_ppm: float = 0.0,
) -> SwayingSolution:
    """Heading, pitch, roll of a strapdown IMU on a swaying base at the end of the window.

    Inputs are what the IMU driver delivers (`ImuBlock`): `gyro` [n,3] as rates [rad/s]
    (`gyro_rad_s`) or, with ``gyro_is_delta``, delta angles [rad] per sample; `accel_g` [n,3]
    specific force in g (1 g = 9.80665 m/s²) averaged over each sample interval; `rate_hz` the
    sample rate; `valid` bool [n,6] the IMU's own per-axis validity (`ImuBlock.valid`). `method`:
    "cone" (constrained fit, default), "cone-gls" (plus a noise-weighted GLS step, the batch form of
    a Kalman fine alignment), "circle" (the paper's free circle fit).
    `max_sway_period_s` sets the smoothing window (4 periods) that rejects sway;
    `gyro_bias_dph` / `accel_bias_ug` are 1σ priors of the turn-on biases (they cannot be
    separated from north and are only added to the reported 1σ; 0 = white noise only);
    `gyro_sf_asymmetry_ppm` the 1σ scale-factor asymmetry, whose rectified sway is one more such bias.
    `lever_arm_std_m`: 1σ prior per axis of the IMU's lever arm from the point the ship turns about;
    the cone fits estimate the arm from the sway (docs/swaying.md eq. 4a) and remove its acceleration;
    0 = not estimated (the fit before issue 16). The estimate is `diagnostics["lever_arm_m"]`.
    Raises InputError for input that cannot give a meaningful heading.
    """
    rate, accel_g, peak_dps = _checked_inputs(
        gyro, accel_g, rate_hz, latitude_deg, gyro_is_delta, valid, method, gyro_range_dps, accel_range_g
    )
    dt = 1.0 / rate_hz
    n_lost = 0
    if sample_index is not None:
        rate, accel_g, n_lost = _fill_gaps(np.asarray(sample_index), rate, accel_g)
    n = rate.shape[0]
    duration_s = n * dt
    _check_duration(duration_s, max_sway_period_s)
    lat = latitude_deg * DEG
    g = float(normal_gravity_m_s2(latitude_deg, height_m))
    dtheta = rate * dt
    dv = accel_g * (STANDARD_GRAVITY_M_S2 * dt)
    q = attitude_quaternions(dtheta)  # Step 1: C_b^{i_b0}(t_k), k = 0…n (docs/swaying.md §2)
    lw = int(round(_BH4_MAIN_LOBE_BINS * max_sway_period_s * rate_hz))
    starts, h, (f_win, m_win, t_win) = _step2_windows(q, dtheta, dv, lw, dt, lat, g)
    t_end = duration_s
    c_b_ib0_end = quat_to_dcm(q[-1])
    # noise measured from the data (docs/swaying.md §5): it weights the GLS step and gives the 1σ
    n_gyro = white_noise_density(dtheta, dt)  # rad/√s per body axis
    n_acc = white_noise_density(dv, dt)  # m/s/√s per body axis
    rect = _sway_rectified_bias_rad_s(rate, gyro_sf_asymmetry_ppm)
    noise = _noise_covariances(starts, h, t_win, t_end, dt, q, n_gyro, n_acc, gyro_bias_dph * DPH,
                               accel_bias_ug * 1e-6 * STANDARD_GRAVITY_M_S2, rect)
    cov_phi, cov_acc = noise.total
    lever = _lever_model(q, starts, h, dt, f_win, cov_phi, cov_acc, lever_arm_std_m) \
        if method != "circle" else None
    whiten = _gls_whitening(f_win, m_win, cov_phi, cov_acc, t_end, lat, lever) \
        if method == "cone-gls" else None
    solve = _solver(method, m_win, t_win, t_end, lat, whiten, c_b_ib0_end, lever)
    c_b_n, axis, lever_m = solve(f_win)
    angles = _angles(c_b_n)
    residual = None  # the circle fit has no residual model
    if method != "circle":
        cone = (c_b_ib0_end @ c_b_n.T @ _earth_rotation_n0_to_nt(t_end, lat) @ m_win.T).T
        residual = f_win - cone - (0.0 if lever is None else lever.force(lever_m))
    parts = _angle_cov_parts(solve, f_win, residual, noise, lever)
    std = np.sqrt(np.maximum(np.diag(sum(parts.values())), 0.0))
    diag = _diagnostics(
        n, n_lost, rate_hz, lw * dt, len(starts), n_gyro, n_acc, peak_dps,
        float(np.arcsin(np.clip(axis @ c_b_ib0_end @ c_b_n[2], -1, 1)) / DEG), residual, parts,
        None if lever is None else lever_m,
    )
    return SwayingSolution(
        heading_deg=float(angles[0]),
        heading_std_deg=float(std[0]),
        pitch_deg=float(angles[1]),
        roll_deg=float(angles[2]),
        pitch_std_deg=float(std[1]),
        roll_std_deg=float(std[2]),
        duration_device_s=float(duration_s),
        method=method,
        latitude_deg=float(latitude_deg),
        c_b_n=c_b_n,
        earth_axis_ib0=axis,
        diagnostics=diag,
        window_t_s=t_win,
        window_residual_m_s2=np.empty((0, 3)) if residual is None else residual,
    )


def predicted_heading_std_deg(
    duration_s: float,
    latitude_deg: float,
    arw_deg_rt_h: float,
    accel_noise_ug_rt_hz: float = 0.0,
    *,
    max_sway_period_s: float = 10.0,
    weighting: str = "ols",
    grid_hz: float = 10.0,
) -> float:
    """White-noise 1σ of the cone-fit heading for a level, still geometry (docs/swaying.md §6).

    ``weighting="ols"`` is the default cone fit (unweighted Wahba, eq. 6, covariance by the
    sandwich formula); ``"gls"`` the noise-weighted step (eq. 9), i.e. what a Kalman filter on
    the same windows can reach. Used to size windows and to show what a fine alignment can gain.
    """
    dt = 1.0 / grid_hz
    n = int(round(duration_s * grid_hz))
    lat = latitude_deg * DEG
    g = float(normal_gravity_m_s2(latitude_deg))
    lw = int(round(_BH4_MAIN_LOBE_BINS * max_sway_period_s * grid_hz))
    if n < 2 * lw:
        raise InputError(f"{duration_s:g} s is shorter than {minimum_duration_s(max_sway_period_s):.0f} s")
    starts = np.arange(0, n - lw + 1, max(1, lw // 4))
    h = _kernel(lw)
    _, m_win, t_win = _smooth_windows(np.zeros((n, 3)), starts, h, dt, lat, g)
    q = np.zeros((n + 1, 4))
    q[:, 0] = 1.0
    n_g = np.full(3, arw_deg_rt_h * DEG / 60.0)
    n_a = np.full(3, accel_noise_ug_rt_hz * 1e-6 * STANDARD_GRAVITY_M_S2)
    noise = _noise_covariances(starts, h, t_win, duration_s, dt, q, n_g, n_a)
    cov_phi, cov_acc = noise.white_phi, noise.white_acc
    m = m_win.shape[0]
    s_f = _block_skew(m_win)
    sigma = s_f @ cov_phi[: 3 * m, : 3 * m] @ s_f.T + cov_acc
    a = np.concatenate([-skew(mj) for mj in m_win])  # C = I: the n0 and i_b0 axes coincide
    if weighting == "gls":
        cov = np.linalg.inv(a.T @ np.linalg.pinv(sigma, rcond=1e-12) @ a)
    elif weighting == "ols":
        pa = np.linalg.pinv(a)
        cov = pa @ sigma @ pa.T
    else:
        raise InputError(f"unknown weighting '{weighting}': use 'ols' or 'gls'")
    return float(np.sqrt(cov[2, 2]) / DEG)  # rotation about up = heading (level, small angles)


def align_swaying_block(
    block, latitude_deg: float, *, rate_hz: float | None = None, **kwargs
) -> SwayingSolution:
    """`align_swaying` on a `northfinder.drivers.imu.ImuBlock` (or any object with sample_index,
    gyro_rad_s, accel_g, valid and rate_hz; `rate_hz` overrides the block's)."""
    rate_hz = rate_hz if rate_hz is not None else getattr(block, "rate_hz", None)
    return align_swaying(block.gyro_rad_s, block.accel_g, rate_hz, latitude_deg,
                         sample_index=getattr(block, "sample_index", None),
                         valid=getattr(block, "valid", None), **kwargs)


def _check_valid(valid) -> None:
    """The IMU's own per-axis validity (bool [n, 6]: gyro x y z, accel x y z; ImuBlock.valid, from
    whatever status word the model has): each triad valid in at least half the samples."""
    if valid is None:
        return
    valid = np.asarray(valid, dtype=bool)
    if valid.size == 0:
        return
    if np.mean(valid[:, 3:6].all(axis=1)) < 0.5:
        raise InputError("the IMU reports no valid accelerometers (flagged not valid): the swaying "
                         "alignment needs a 3-axis accelerometer — use an IMU with accelerometers")
    if np.mean(valid[:, 0:3].all(axis=1)) < 0.5:
        raise InputError("the IMU reports fewer than 3 valid gyros: the swaying alignment needs a 3-axis "
                         "gyro")


def _fill_gaps(sample_index: np.ndarray, rate: np.ndarray, accel_g: np.ndarray, max_gap: int = 10):
    """Put samples on the contiguous device index; fill gaps of ≤ max_gap samples linearly."""
    if sample_index.shape[0] != rate.shape[0]:
        raise InputError("sample_index and gyro arrays differ in length")
    steps = np.diff(sample_index)
    if np.any(steps <= 0):
        raise InputError("IMU sample_index is not strictly increasing: the block is not one recording")
    if np.all(steps == 1):
        return rate, accel_g, 0
    if steps.max() - 1 > max_gap:
        raise InputError(f"the IMU lost {int(steps.max() - 1)} consecutive samples inside the window: the "
                         f"attitude cannot be integrated across a gap longer than {max_gap} samples — "
                         "record again (check the serial link)")
    out_r, out_a = fill_lost_samples(sample_index, rate), fill_lost_samples(sample_index, accel_g)
    return out_r, out_a, int(out_r.shape[0] - sample_index.size)


def _block_skew(f_win: np.ndarray) -> np.ndarray:
    """blockdiag([F_j×]) [3m, 3m]: maps window attitude errors Φ_j to specific-force errors."""
    m = f_win.shape[0]
    s = np.zeros((3 * m, 3 * m))
    for j in range(m):
        s[3 * j: 3 * j + 3, 3 * j: 3 * j + 3] = skew(f_win[j])
    return s


def _smooth_windows(dv_ib0, starts, h, dt, lat, g):
    """(F_j [m,3], M_j [m,3], window centres [m]) of eq. 4–5: one dot product per window.

    A loop over the m windows (tens to hundreds), not over samples: it keeps memory at one
    window instead of m × L_w × 3 for an hour at 1000 Hz.
    """
    lw = h.size
    k = np.arange(lw)
    f_win = np.empty((starts.size, 3))
    m_win = np.empty((starts.size, 3))
    for j, s0 in enumerate(starts):
        f_win[j] = h @ dv_ib0[s0: s0 + lw] / dt
        m_win[j] = g * (h @ _up_n0((s0 + k + 0.5) * dt, lat))
    t_win = (starts + (k + 0.5) @ h) * dt
    return f_win, m_win, t_win


@dataclass(frozen=True)
class _NoiseCov:
    """The windows' noise covariances by source (docs/swaying.md §5), in i_b0 axes: the attitude
    error φ of every window and of t_end [3(m+1)]², the accelerometer's [3m]²."""

    white_phi: np.ndarray
    white_acc: np.ndarray
    bias_phi: np.ndarray
    bias_acc: np.ndarray
    rect_phi: np.ndarray
    """The sway-rectified scale-factor asymmetry: one more constant gyro bias."""

    @property
    def total(self) -> tuple[np.ndarray, np.ndarray]:
        return self.white_phi + self.bias_phi + self.rect_phi, self.white_acc + self.bias_acc


def _noise_covariances(starts, h, t_win, t_end, dt, q, n_gyro, n_acc, gyro_bias=0.0, accel_bias=0.0,
                       rect_bias=None) -> _NoiseCov:
    """Covariances of the noise the windows see (docs/swaying.md §5), all in i_b0 axes, by source.

    The attitude random walk φ(t) driven by the gyro white noise has Cov(φ(s), φ(t)) = Q·min(s,t);
    a constant gyro bias prior adds φ = b·t. A window sees Φ_j = ∫h_j φ, so
    Cov(Φ_i, Φ_j) = Q·∫H_i H_j dτ with H_j(τ) = ∫_τ^T h_j (tail integral), because
    min(s,t) = ∫ 1[τ<s]·1[τ<t] dτ; the end attitude sees φ(t_end) (H = 1 up to t_end).
    The accelerometer white noise gives Cov(A_i, A_j) = Q_a·∫h_i h_j dt, its bias prior a
    constant. `rect_bias` [rad/s]: per body axis, a further constant gyro bias 1σ (the sway-rectified
    scale-factor asymmetry, `_sway_rectified_bias_rad_s`). The last block of the φ covariances is
    φ(t_end).
    """
    m = starts.size
    lw = h.size
    n = q.shape[0] - 1
    # Rotate per-axis body noise into i_b0 (the body sways, so average over the record).
    c = quat_to_dcm(q[1:: max(1, n // 200)])

    def in_ib0(per_axis: np.ndarray) -> np.ndarray:
        return np.einsum("kij,j,klj->il", c, per_axis**2, c) / c.shape[0]

    # Kernels on a coarse grid of D samples (≥ 40 cells per window) for the Brownian covariance.
    d = max(1, lw // 40)
    n_c = n // d
    hc = np.zeros((m + 1, n_c + 1))
    for j, s0 in enumerate(starts):
        np.add.at(hc[j], (s0 + np.arange(lw)) // d, h)
    tail = np.cumsum(hc[:, ::-1], axis=1)[:, ::-1]  # H_j at the start of each coarse cell
    tail[m] = 1.0
    tail[m, n_c:] = 0.0
    step = d * dt
    k_phi = tail @ tail.T * step
    k_phi[m, m] = t_end
    t_all = np.append(t_win, t_end)
    k_bias = np.outer(t_all, t_all)
    k_acc = hc[:m] @ hc[:m].T / step
    rect = np.zeros((3, 3)) if rect_bias is None else in_ib0(np.asarray(rect_bias))
    return _NoiseCov(
        white_phi=np.kron(k_phi, in_ib0(n_gyro)),
        white_acc=np.kron(k_acc, in_ib0(n_acc)),
        bias_phi=np.kron(k_bias, np.eye(3) * gyro_bias**2),
        bias_acc=np.kron(np.ones((m, m)), np.eye(3) * accel_bias**2),
        rect_phi=np.kron(k_bias, rect),
    )


def _gls_step(f_win, m_n0, c_ib0_nt, t_end_s, lat, whiten):
    """One Gauss–Newton step of the generalized least squares min Σ rᵀΣ⁻¹r about the Wahba solution.

    Linearized model (docs/swaying.md eq. 9): F_j − Ĉ M_j = −Ĉ[M_j×]δ + e_j, Cov(e) = Σ; the
    batch form of a Kalman filter/smoother that carries the same three misalignment states.
    """
    r_nt = _earth_rotation_n0_to_nt(t_end_s, lat)
    c_n0_ib0 = c_ib0_nt.T @ r_nt
    a = -(c_n0_ib0 @ skew(m_n0)).reshape(-1, 3)  # rows of −C[M_j×], window after window
    r = (f_win - m_n0 @ c_n0_ib0.T).ravel()
    aw = whiten @ a
    rw = whiten @ r
    delta = np.linalg.lstsq(aw, rw, rcond=None)[0]
    c_n0_ib0 = c_n0_ib0 @ rotvec_to_dcm(delta)
    axis = c_n0_ib0 @ np.array([0.0, np.cos(lat), np.sin(lat)])
    return r_nt @ c_n0_ib0.T, axis


def _jacobians(solve, f_win):
    """Maps of the window errors onto (heading, pitch, roll) [deg] (docs/swaying.md §5).

    A window sees e_j = [F_j×]Φ_j + A_j; the end attitude sees φ(t_end). The Jacobian of the
    angles with respect to F_j and φ(t_end) is taken by central differences of the fit itself
    (3m + 3 evaluations of a closed-form solution), so the same code serves every method.
    Returns (g_map for [Φ; φ(t_end)], jac_f for A).
    """
    m = f_win.shape[0]
    scale_f = 1e-6 * np.linalg.norm(f_win[0])
    scale_p = 1e-6
    jac_f = np.zeros((3, 3 * m))
    jac_p = np.zeros((3, 3))
    for j in range(m):
        for a in range(3):
            df = np.zeros_like(f_win)
            df[j, a] = scale_f
            jac_f[:, 3 * j + a] = _angle_diff(_angles(solve(f_win + df)[0]), _angles(solve(f_win - df)[0])) \
                / (2 * scale_f)
    for a in range(3):
        dp = np.zeros(3)
        dp[a] = scale_p
        jac_p[:, a] = _angle_diff(_angles(solve(f_win, dp)[0]), _angles(solve(f_win, -dp)[0])) / (2 * scale_p)
    return np.hstack([jac_f @ _block_skew(f_win), jac_p]), jac_f


def _angles_cov(g_map, jac_f, cov_phi, cov_acc):
    """Covariance of (heading, pitch, roll) [deg²] from the window noise covariances."""
    return g_map @ cov_phi @ g_map.T + jac_f @ cov_acc @ jac_f.T


def _propagate(solve, f_win, cov_phi, cov_acc):
    """1σ of heading, pitch, roll [deg] by first-order propagation (docs/swaying.md §5)."""
    g_map, jac_f = _jacobians(solve, f_win)
    return np.sqrt(np.maximum(np.diag(_angles_cov(g_map, jac_f, cov_phi, cov_acc)), 0.0))


def _residual_dof(f_win: np.ndarray, u: np.ndarray, lever: _LeverModel | None) -> tuple[float, float]:
    """Degrees of freedom the cone fit leaves in its residual across and along the windows' verticals u_j.

    The fit's linearised design is [−[F_j×] | G_j] (three rotation angles, and the lever arm when it is
    estimated, with its ridge Λ); for errors of equal power p per component the residual keeps
    p·tr(S(I − H)) along a block projector S, H = A(AᵀA + Λ)⁺Aᵀ the hat matrix. Rotations move F_j only
    across it, so without the lever arm this is (2m − 3, m)."""
    m = f_win.shape[0]
    a = np.concatenate([-skew(fj) for fj in f_win])
    ridge = np.zeros(3)
    if lever is not None:
        a = np.hstack([a, lever.g.reshape(-1, 3)])
        ridge = np.concatenate([ridge, np.full(3, lever.ridge)])
    s_along = np.zeros((3 * m, 3 * m))
    for j in range(m):
        s_along[3 * j: 3 * j + 3, 3 * j: 3 * j + 3] = np.outer(u[j], u[j])
    inv = np.linalg.pinv(a.T @ a + np.diag(ridge))
    h_along = float(np.trace(inv @ a.T @ s_along @ a))
    h_all = float(np.trace(inv @ a.T @ a))
    return 2.0 * m - (h_all - h_along), m - h_along


def _leakage_covariance(residual, f_win, cov_phi, cov_acc, lever):
    """Covariance of what the windows carry beyond the modelled errors: sway leakage (and any other
    unmodelled error — scale factor, misalignment — that the cone fit leaves in its residual), measured
    from the data.

    Split along each window's specific force u_j = F_j/|F_j| (≈ the vertical, where heave leaks and
    heading is not) and across it (where the heading is): per part, the residual power corrected for
    the fitted parameters (`_residual_dof`: the rotation and the lever arm) minus what the modelled noise
    and bias priors put there, and Cov_j = p_across·(I − u_j u_jᵀ) + p_along·u_j u_jᵀ, independent from
    window to window (choices measured against the Monte Carlo scatter in docs/swaying.md §5). Zero for
    the circle fit (no residual model) or where the modelled errors explain the residual.
    """
    m = f_win.shape[0]
    if residual is None or m < 2:
        return np.zeros((3 * m, 3 * m))
    u = f_win / np.linalg.norm(f_win, axis=1, keepdims=True)
    s_f = _block_skew(f_win)
    model = s_f @ cov_phi[: 3 * m, : 3 * m] @ s_f.T + cov_acc
    blocks = np.stack([model[3 * j: 3 * j + 3, 3 * j: 3 * j + 3] for j in range(m)])
    along_model = float(np.mean(np.einsum("ji,jik,jk->j", u, blocks, u)))
    across_model = float(np.mean(np.trace(blocks, axis1=1, axis2=2))) - along_model
    r_along = np.einsum("ji,ji->j", residual, u)
    dof_across, dof_along = _residual_dof(f_win, u, lever)
    p_along = float(np.sum(r_along**2)) / max(dof_along, 1.0) - along_model
    p_across = float(np.sum(residual**2) - np.sum(r_along**2)) / max(dof_across, 1.0) - across_model / 2.0
    p_across, p_along = max(p_across, 0.0), max(p_along, 0.0)
    out = np.zeros((3 * m, 3 * m))
    for j in range(m):
        uu = np.outer(u[j], u[j])
        out[3 * j: 3 * j + 3, 3 * j: 3 * j + 3] = p_across * (np.eye(3) - uu) + p_along * uu
    return out


def _angle_diff(a_deg: np.ndarray, b_deg: np.ndarray) -> np.ndarray:
    """a − b in degrees, wrapped to [−180, 180) (heading crosses 0/360)."""
    return wrap_deg_180(np.asarray(a_deg) - np.asarray(b_deg))
