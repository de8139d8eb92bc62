"""GNSS-aided strapdown alignment from any initial heading: the δsin/δcos filter of the seed paper.

Paper: Wang Zhiwei et al., "Initial alignment of GPS/INS moving base with large misalignment
angle", Piezoelectrics & Acoustooptics 40(3), 2018 (../shared/papers/gnss-ins-large-misalignment-
alignment.zh.txt), eq 1–23; the derivation in our frames is in docs/gnss-alignment.md.

What: an error-state Kalman filter around the strapdown mechanization (strapdown.py). The
attitude is split as C_b^n = C_h^n(ψ)·C_b^h(θ, γ) with C_h^n = Rz(−ψ) (eq 1). The heading error
is carried as η1 = sin ψ̂ − sin ψ, η2 = cos ψ̂ − cos ψ — the paper's δsin β, δcos β — in which
the attitude error δC = Ĉ_b^n − C_b^n is *exactly* linear at any heading error, and the small
tilt error as ε = (εx, εy) in the h frame (the paper's φx, φy). State (eq 22), 19 elements:

    x = [δP (3, ENU m), δV (3, m/s), η1, η2, εx, εy, δf (3, accel bias, b), δω (3, gyro bias, b),
         δla (3, lever arm, b)]                       all as "estimate − truth"

GNSS measures the antenna, at lever arm la^b from the IMU: position (eq 15–18) and velocity with
the body rate (eq 19–21). After every update every estimate is fed back and the state reset to
zero (eq 23); the attitude is re-orthonormalized.

Why: with the lever arm the position residual δC·la depends on the heading error directly, so
heading is observable from the first turn, and the sin/cos parametrization keeps the filter
linear where a small-angle filter (small_angle.py) is not.

Inputs as the drivers deliver them: IMU rate-format samples (`gyro_rad_s`, `accel_g`) at a known
rate with a sample index, and GNSS fixes of the antenna (time, local ENU position or lat/lon/alt,
ENU velocity, σ).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from northfinder.align.grades import imu_grade
from northfinder.align.strapdown import (
    ChunkSummary,
    LocalLevel,
    NavState,
    Strapdown,
    cross3,
    earth_rate_n,
    fill_lost_samples,
    increments_from_rates,
    skew3,
    transport_rate_n,
)
from northfinder.constants import DPH, STANDARD_GRAVITY_M_S2, normal_gravity_m_s2
from northfinder.errors import InputError
from northfinder.rotations import dcm_from_euler

# State layout shared by both filters: position, velocity, attitude block, biases, lever arm.
P_, V_ = slice(0, 3), slice(3, 6)


# ---------------------------------------------------------------------------------------------
# Inputs and outputs
# ---------------------------------------------------------------------------------------------
@dataclass
class ImuSeries:
    """IMU samples in rate format: sample with index k integrates [t0 + k/rate, t0 + (k+1)/rate].

    `gyro_rad_s` [n,3] (Δθ·rate for a delta-format IMU), `accel_g` [n,3] in standard g. Missing
    indices (lost samples: a line overrun, a dropped byte) are filled by linear interpolation
    between the samples either side, and `gap_variance` says how uncertain each filled sample is.
    """

    rate_hz: float
    gyro_rad_s: np.ndarray
    accel_g: np.ndarray
    sample_index: np.ndarray | None = None
    t0_s: float = 0.0

    @classmethod
    def from_increments(cls, dtheta_rad, dv_m_s, rate_hz: float, t0_s: float = 0.0) -> ImuSeries:
        """From Δθ [rad] and Δv [m/s] per sample (simulator output)."""
        return cls(rate_hz, np.asarray(dtheta_rad) * rate_hz,
                   np.asarray(dv_m_s) * rate_hz / STANDARD_GRAVITY_M_S2, None, t0_s)

    def _relative_index(self) -> np.ndarray | None:
        """Sample indices from 0 (None: no index, every sample present)."""
        if self.sample_index is None:
            return None
        idx = np.asarray(self.sample_index, dtype=np.int64)
        if np.any(np.diff(idx) <= 0):
            raise InputError("IMU sample_index must increase strictly (unwrap the sequence counter first)")
        return idx - idx[0]

    def increments(self) -> tuple[np.ndarray, np.ndarray]:
        """Dense (Δθ, Δv) from index 0 to the last index, gaps filled by linear interpolation."""
        dth, dv = increments_from_rates(self.gyro_rad_s, self.accel_g, self.rate_hz)
        idx = self._relative_index()
        if idx is None:
            return dth, dv
        return fill_lost_samples(idx, dth), fill_lost_samples(idx, dv)

    def gap_variance(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Variance [rad², (m/s)²] per dense sample and axis that the gap filling leaves in Δθ, Δv
        (None: no sample lost).

        Model: inside a gap the rate (specific force) is a Brownian bridge between the samples either
        side, so the error of the interpolated integral over a gap of span T has variance q·T³/12.
        q·T is taken as the larger of the rate's change across this gap and the mean squared change
        over the same lag in the received data (the structure function D(T)): the first covers a
        turn under way, the second one that started and ended unseen. The variance is spread evenly
        over the gap's filled samples, so any chunk holding the whole gap carries all of it.
        """
        idx = self._relative_index()
        if idx is None or len(idx) == idx[-1] + 1:
            return None
        gaps = np.nonzero(np.diff(idx) > 1)[0]
        n_dense = int(idx[-1]) + 1
        present = np.zeros(n_dense, dtype=bool)
        present[idx] = True
        var_th, var_v = np.zeros((n_dense, 3)), np.zeros((n_dense, 3))
        dt = 1.0 / float(self.rate_hz)
        structure: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for series, var in ((self.gyro_rad_s, var_th), (self.accel_g * STANDARD_GRAVITY_M_S2, var_v)):
            dense = np.full((n_dense, 3), np.nan)
            dense[idx] = series
            structure.clear()
            for g in gaps:
                a, b = int(idx[g]), int(idx[g + 1])
                lag = b - a
                if lag not in structure:
                    both = present[lag:] & present[:-lag]
                    d = (dense[lag:] - dense[:-lag])[both]
                    structure[lag] = np.mean(d**2, axis=0) if len(d) else np.zeros(3)
                change2 = np.maximum(structure[lag], (dense[b] - dense[a]) ** 2)
                span_s = lag * dt
                var[a + 1:b] = change2 * span_s**2 / 12.0 / (lag - 1)
        return var_th, var_v


@dataclass
class GnssSeries:
    """GNSS fixes of the ANTENNA: device time [s], local ENU position [m] about `origin`, ENU velocity
    [m/s] and their 1σ per axis. `origin` = (lat_deg, lon_deg, h_m) of the local ENU frame."""

    t_s: np.ndarray
    pos_enu_m: np.ndarray
    vel_enu_m_s: np.ndarray
    pos_std_m: np.ndarray
    vel_std_m_s: np.ndarray
    origin: tuple[float, float, float]

    @classmethod
    def from_geodetic(cls, t_s, lat_deg, lon_deg, alt_m, vel_enu_m_s, *, pos_std_m=(0.5, 0.5, 1.0),
                      vel_std_m_s=(0.05, 0.05, 0.05), origin=None) -> GnssSeries:
        """From receiver lat/lon/alt; the origin defaults to the first fix."""
        lat, lon, alt = (np.asarray(a, dtype=float) for a in (lat_deg, lon_deg, alt_m))
        origin = origin or (float(lat[0]), float(lon[0]), float(alt[0]))
        ll = LocalLevel(math.radians(origin[0]), math.radians(origin[1]), origin[2])
        pos = ll.to_enu(np.deg2rad(lat), np.deg2rad(lon), alt)
        n = len(lat)
        return cls(np.asarray(t_s, float), pos, np.asarray(vel_enu_m_s, float),
                   np.broadcast_to(np.asarray(pos_std_m, float), (n, 3)).copy(),
                   np.broadcast_to(np.asarray(vel_std_m_s, float), (n, 3)).copy(), origin)

    def local_level(self) -> LocalLevel:
        return LocalLevel(math.radians(self.origin[0]), math.radians(self.origin[1]), self.origin[2])


@dataclass
class GnssAlignConfig:
    """Priors and noise of the alignment filters (defaults: a KVH-1760-class IMU, a code GNSS).

    heading_std_deg None means "heading unknown": the sin/cos filter then starts from the moments
    of a uniform heading error; the small-angle filter needs a number (default 30° for it).
    lever_arm_std_m 0 keeps the lever arm fixed at `lever_arm_b_m` (not estimated).
    `converged_std_deg`: converged_after_s is the first time after which the heading 1σ stays
    below it until the end.
    """

    heading_std_deg: float | None = None
    tilt_std_deg: float = 0.5
    vel_std_m_s: float = 0.1
    lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    lever_arm_std_m: float = 1.0
    gyro_bias_std_dph: float = 1.0
    accel_bias_std_ug: float = 1000.0
    gyro_arw_deg_sqrt_h: float = 0.05
    accel_vrw_ug_sqrt_hz: float = 300.0
    gyro_bias_rw_dph_sqrt_s: float = 0.001
    accel_bias_rw_ug_sqrt_s: float = 1.0
    level_s: float = 5.0
    converged_std_deg: float = 1.0
    still_speed_m_s: float = 0.2
    still_force_sigmas: float = 4.0
    """Standing also needs the IMU's horizontal specific force (heading aside) within this many σ of
    zero: the heading becomes observable with the first acceleration, before the fix speed shows it."""
    restart_below_deg: float | None = 5.0
    """Heading unknown or its prior wider than restart_prior_factor × this: once the heading 1σ falls
    below this, the filter starts again from the still start with a Gaussian prior (run_alignment);
    None: one pass from the prior."""
    restart_prior_factor: float = 2.0
    """The restarted prior's 1σ over the first pass's σ at the restart (see run_alignment)."""
    noise_source: str = "default"
    """Where the IMU noise and bias figures came from: "default" (the conservative figures above, for
    an IMU whose grade is not known) or "grade <name>" (IMU_GRADES, `for_imu_grade`)."""

    @classmethod
    def for_imu_grade(cls, grade: str | None, **kwargs) -> GnssAlignConfig:
        """A config with the IMU grade's data-sheet figures (grades.IMU_GRADES) when the grade is known;
        the conservative defaults (noise_source "default") when `grade` is None or empty.

        From the grade: the noise densities; the turn-on biases as the bias priors; the bias
        instability B with its correlation time τ as a random walk of density B·√(2/τ) (the
        Gauss–Markov process's driving noise: exact over t ≪ τ, conservative beyond)."""
        if not grade:
            return cls(**kwargs)
        g = imu_grade(grade)
        k = math.sqrt(2.0 / g.bias_correlation_s)
        values = {
            "gyro_arw_deg_sqrt_h": g.arw_deg_sqrt_h,
            "accel_vrw_ug_sqrt_hz": g.vrw_ug_sqrt_hz,
            "gyro_bias_std_dph": g.gyro_turn_on_dph,
            "accel_bias_std_ug": g.accel_turn_on_ug,
            "gyro_bias_rw_dph_sqrt_s": g.gyro_bias_instability_dph * k,
            "accel_bias_rw_ug_sqrt_s": g.accel_bias_instability_ug * k,
        }
        return cls(**{**values, "noise_source": f"grade {grade}", **kwargs})


@dataclass
class GnssAlignHistory:
    """Filter time histories, one row per GNSS update (arrays)."""

    t_s: np.ndarray
    heading_deg: np.ndarray
    heading_std_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray
    pos_enu_m: np.ndarray
    pos_std_m: np.ndarray
    vel_enu_m_s: np.ndarray
    lever_arm_m: np.ndarray
    lever_arm_std_m: np.ndarray
    gyro_bias_dph: np.ndarray
    gyro_bias_std_dph: np.ndarray
    accel_bias_ug: np.ndarray
    accel_bias_std_ug: np.ndarray
    innovation: np.ndarray


@dataclass
class GnssAlignResult:
    """Final alignment: heading with 1σ, attitude, lever arm, biases, convergence time, histories."""

    method: str
    heading_deg: float
    heading_std_deg: float
    pitch_deg: float
    roll_deg: float
    lever_arm_m: np.ndarray
    lever_arm_std_m: np.ndarray
    gyro_bias_dph: np.ndarray
    accel_bias_ug: np.ndarray
    pos_enu_m: np.ndarray
    converged_after_s: float | None
    start_s: float
    history: GnssAlignHistory
    extra: dict = field(default_factory=dict)
    restart: dict | None = None
    """Heading unknown and restarted (run_alignment): `t_s` (the first pass's last update),
    `coarse_heading_deg`/`coarse_std_deg` (its estimate there), `initial_heading_deg`/`prior_std_deg`
    (the second pass's start)."""


# ---------------------------------------------------------------------------------------------
# The error-state filter machinery shared with the small-angle filter
# ---------------------------------------------------------------------------------------------
class _ErrorStateFilter:
    """Error-state Kalman filter around a Strapdown; subclasses define the attitude error block."""

    method = "?"
    n_att = 0

    def __init__(self, ins: Strapdown, config: GnssAlignConfig, initial_heading_rad: float):
        self.ins = ins
        self.cfg = config
        na = self.n_att
        self.A = slice(6, 6 + na)
        self.BA = slice(6 + na, 9 + na)
        self.BG = slice(9 + na, 12 + na)
        self.LA = slice(12 + na, 15 + na)
        self.n = 15 + na
        self.lever_arm_b_m = np.asarray(config.lever_arm_b_m, dtype=float).copy()
        self.estimate_lever = config.lever_arm_std_m > 0.0
        p0 = np.zeros(self.n)
        p0[V_] = config.vel_std_m_s**2
        p0[self.BA] = (config.accel_bias_std_ug * 1e-6 * STANDARD_GRAVITY_M_S2) ** 2
        p0[self.BG] = (config.gyro_bias_std_dph * DPH) ** 2
        p0[self.LA] = config.lever_arm_std_m**2
        self.P = np.diag(p0)
        self.x = np.zeros(self.n)  # error-state mean: zero after feedback except what could not be applied
        self.P[self.A, self.A] = self.attitude_prior(initial_heading_rad)
        self.omega_nb_b = np.zeros(3)
        self.force_z2 = 0.0  # squared Mahalanobis size of the last chunk's horizontal specific force
        self.heading_moved_rad = 0.0  # sum of the heading corrections fed back (run_alignment's restart)

    # -- subclass hooks --------------------------------------------------------------------------
    def attitude_prior(self, heading_rad: float) -> np.ndarray:
        raise NotImplementedError

    def attitude_jacobian(self, u_b: np.ndarray) -> np.ndarray:
        """J with δC·u ≈ J·x_att (3 × n_att), for a body vector u."""
        raise NotImplementedError

    def attitude_dynamics(self, F, G, s: ChunkSummary, w_in: np.ndarray) -> None:
        """Fill the attitude rows of F and the gyro-noise columns of G."""
        raise NotImplementedError

    def attitude_feedback(self, x_att: np.ndarray) -> np.ndarray:
        """Correct Ĉ_b^n; return the part of x_att that the correction could not apply (normally 0)."""
        raise NotImplementedError

    def heading_var(self) -> float:
        raise NotImplementedError

    def attitude_reset_jacobian(self, c_before: np.ndarray, c_after: np.ndarray) -> np.ndarray:
        """∂x_att(after the feedback)/∂x_att(before): identity unless the error frame moves."""
        return np.eye(self.n_att)

    # -- time update -----------------------------------------------------------------------------
    def predict(self, s: ChunkSummary, gap_var: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Covariance propagation over one IMU chunk: Φ = exp(F·Δt) (3rd-order series), Q = G Qc Gᵀ Δt.

        `gap_var`: the variance [rad², (m/s)²] per body axis of the chunk's Δθ and Δv that lost
        samples left (ImuSeries.gap_variance), added as gyro and accelerometer noise of the chunk.

        Velocity error equation: paper eq 14 with δC from eq 7, in our frames
        δV̇ = δC f^b + Ĉ δf − (2ω_ie + ω_en) × δV + δg (docs/gnss-alignment.md §3).
        """
        if s.dt_s <= 0.0:
            return
        st = self.ins.state
        c = st.c_bn
        lat, h = self.ins.origin.lat_h(st.pos_enu_m)
        w_ie = earth_rate_n(lat)
        w_en = transport_rate_n(lat, h, st.v_enu_m_s)
        n, dt = self.n, s.dt_s
        F = np.zeros((n, n))
        G = np.zeros((n, 12))
        F[P_, V_] = np.eye(3)
        F[V_, V_] = -skew3(2.0 * w_ie + w_en)
        F[5, 2] = 2.0 * float(normal_gravity_m_s2(math.degrees(lat), h)) / self.ins.origin.k_n
        F[V_, self.A] = self.attitude_jacobian(s.f_b_m_s2)
        F[V_, self.BA] = c
        G[V_, 3:6] = c
        self.attitude_dynamics(F, G, s, w_ie + w_en)
        G[self.BA, 6:9] = np.eye(3)
        G[self.BG, 9:12] = np.eye(3)
        cfg = self.cfg
        qc = np.concatenate([
            np.full(3, (cfg.gyro_arw_deg_sqrt_h * math.pi / 180.0 / 60.0) ** 2),
            np.full(3, (cfg.accel_vrw_ug_sqrt_hz * 1e-6 * STANDARD_GRAVITY_M_S2) ** 2),
            np.full(3, (cfg.accel_bias_rw_ug_sqrt_s * 1e-6 * STANDARD_GRAVITY_M_S2) ** 2),
            np.full(3, (cfg.gyro_bias_rw_dph_sqrt_s * DPH) ** 2),
        ])
        fdt = F * dt
        phi = np.eye(n) + fdt @ (np.eye(n) + fdt @ (np.eye(n) + fdt / 3.0) / 2.0)
        q = (G * qc) @ G.T * dt
        if gap_var is not None:
            q += (G[:, 0:3] * gap_var[0]) @ G[:, 0:3].T + (G[:, 3:6] * gap_var[1]) @ G[:, 3:6].T
        self.P = phi @ self.P @ phi.T + 0.5 * (phi @ q @ phi.T + q)
        self.x = phi @ self.x
        if not self.estimate_lever:
            self.P[self.LA, :] = 0.0
            self.P[:, self.LA] = 0.0
        # body rate at the chunk's end (last sample), not the chunk mean: a 50 ms lag would shrink
        # the lever-arm velocity of a 1–2 Hz body motion by 5–20 % and bias the lever arm estimate
        self.omega_nb_b = s.omega_end_b_rad_s - c.T @ (w_ie + w_en)
        self.force_z2 = self._horizontal_force_z2(F, s, qc)

    def _horizontal_force_z2(self, F: np.ndarray, s: ChunkSummary, qc: np.ndarray) -> float:
        """(Ĉf)_hᵀ S⁻¹ (Ĉf)_h for the chunk's mean specific force: S is the variance the horizontal
        force has from everything but the heading (tilt, accelerometer bias: F's velocity rows without
        the heading columns; the accelerometer noise over the chunk). A still vehicle's is chi-square
        with 2 degrees of freedom; an accelerating one's is large."""
        f_h = (self.ins.state.c_bn @ s.f_b_m_s2)[0:2]
        h = F[3:5].copy()
        heading = self.heading_rows()
        if heading is not None:
            h[:, heading] = 0.0
        h[:, P_] = 0.0
        h[:, V_] = 0.0
        cov = h @ self.P @ h.T + np.eye(2) * qc[3] / s.dt_s
        return float(f_h @ np.linalg.solve(cov, f_h))

    # -- measurement update ----------------------------------------------------------------------
    def update(self, pos_m, vel_m_s, pos_std_m, vel_std_m_s, dt_fix_s: float) -> np.ndarray:
        """GNSS antenna position and velocity update with the lever arm (paper eq 15–21), then
        feedback of every estimate (eq 23). Returns the innovation [6]."""
        st = self.ins.state
        c = st.c_bn
        la = self.lever_arm_b_m
        w_la = cross3(self.omega_nb_b, la)
        v_ant = st.v_enu_m_s + c @ w_la
        # eq 17: δP_meas = P̂ + Ĉ l̂a − P_GNSS (extrapolated to the fix time within one IMU sample)
        z = np.concatenate([st.pos_enu_m + c @ la + v_ant * dt_fix_s - pos_m, v_ant - vel_m_s])
        H = np.zeros((6, self.n))
        H[0:3, P_] = np.eye(3)
        H[0:3, self.A] = self.attitude_jacobian(la)  # eq 18: δC·la
        H[0:3, self.LA] = c  # eq 18: Ĉ δla
        H[3:6, V_] = np.eye(3)
        H[3:6, self.A] = self.attitude_jacobian(w_la)  # eq 21: δC (ω_nb^b × la)
        H[3:6, self.LA] = c @ skew3(self.omega_nb_b)  # eq 21: Ĉ (ω_nb^b ×) δla
        H[3:6, self.BG] = -c @ skew3(la)  # gyro bias in ω_nb^b × la
        R = np.diag(np.concatenate([np.asarray(pos_std_m, float) ** 2, np.asarray(vel_std_m_s, float) ** 2]))
        R += self.second_order_noise()
        S = H @ self.P @ H.T + R
        K = np.linalg.solve(S, H @ self.P).T
        held = self.heading_rows()
        if held is not None and self.standing(vel_m_s, vel_std_m_s) and not self.accelerating():
            # Standing still: nothing observes the heading (the antenna is fixed whatever the heading,
            # and the lever arm term δC·l̂a only trades against δP); what the update would move it by
            # is noise and linearization error. Consider, not estimate, the heading there (Schmidt):
            # its gain rows are zero, the Joseph form below keeps P consistent with that gain.
            K[held] = 0.0
        x = self.x + K @ (z - H @ self.x)
        ikh = np.eye(self.n) - K @ H
        self.P = ikh @ self.P @ ikh.T + K @ R @ K.T  # Joseph form
        j_old, c_old = self.attitude_jacobian(self.lever_arm_b_m), c.copy()
        self.feedback(x)
        g_att = self.attitude_reset_jacobian(c_old, self.ins.state.c_bn)
        # Reset Jacobian: the feedback changes Ĉ and l̂a, so the same antenna error is split
        # differently, δP' + J(l̂a')x_att + Ĉ'δla = δP + J(l̂a)x_att + Ĉδla. Without this the
        # correlations that say "the antenna is known to the GNSS σ" break at every reset and a
        # still vehicle's heading random-walks on GNSS noise (docs/gnss-alignment.md §5).
        g = np.eye(self.n)
        g[P_, self.A] += j_old - self.attitude_jacobian(self.lever_arm_b_m)
        g[P_, self.LA] += c_old - self.ins.state.c_bn
        g[self.A, self.A] = g_att
        self.P = g @ self.P @ g.T
        return z

    def accelerating(self) -> bool:
        """The last chunk's horizontal specific force is beyond `still_force_sigmas` of what tilt, bias
        and noise give a still vehicle (the heading is observable through δC·f)."""
        return self.force_z2 > self.cfg.still_force_sigmas**2

    def standing(self, vel_m_s, vel_std_m_s) -> bool:
        """The fix says the vehicle stands: horizontal speed below `still_speed_m_s` (or 4σ of its noise
        if larger), measured well enough to tell (horizontal σ below `still_speed_m_s`; the Up σ is
        irrelevant — NMEA has no vertical velocity)."""
        sd_h = float(np.max(np.asarray(vel_std_m_s, float)[:2]))
        still = self.cfg.still_speed_m_s
        return sd_h < still and math.hypot(vel_m_s[0], vel_m_s[1]) < max(still, 4.0 * sd_h)

    def second_order_noise(self) -> np.ndarray:
        """Measurement covariance of what the linear model drops; zero here (SinCosFilter adds it)."""
        return np.zeros((6, 6))

    def heading_rows(self) -> slice | None:
        """Rows of the heading states held (not estimated) while standing still; None: not held."""
        return None

    def tilt_rows(self) -> slice | None:
        """Rows of the two tilt states (level_prior); None: the filter keeps independent priors."""
        return None

    def level_prior(self, f_level_b_m_s2: np.ndarray, level_s: float) -> None:
        """The tilt prior a coarse level leaves: correlated with the accelerometer bias, not independent.

        Levelled on the mean specific force f̄ of a still window, the INS's horizontal specific force is
        zero by construction, so its error δC·f̄ + Ĉδf (tilt and bias; the filter's velocity rows) is only
        the accelerometer noise averaged over the window, VRW²/T per axis — whatever the bias. With the
        bias prior P_b: ε = −A⁻¹(B δf) + A⁻¹n (A, B: those rows' tilt and bias columns), i.e.
        P_εε = A⁻¹(B P_b Bᵀ + Σ_n)A⁻ᵀ, P_εf = −A⁻¹B P_b. Independent priors (tilt 0.5°, bias 1 mg) let the
        still start's velocity updates move the tilt on GNSS noise (up to 3 mg of horizontal force after 5 s),
        which the first accelerations then read as heading error."""
        tilt = self.tilt_rows()
        if tilt is None:
            return
        jac = self.attitude_jacobian(f_level_b_m_s2)[0:2]
        a = jac[:, tilt.start - self.A.start : tilt.stop - self.A.start]
        b = self.ins.state.c_bn[0:2]
        a_inv = np.linalg.inv(a)
        p_b = self.P[self.BA, self.BA]
        sd_n = self.cfg.accel_vrw_ug_sqrt_hz * 1e-6 * STANDARD_GRAVITY_M_S2 / math.sqrt(level_s)
        self.P[tilt, tilt] = a_inv @ (b @ p_b @ b.T + np.eye(2) * sd_n**2) @ a_inv.T
        self.P[tilt, self.BA] = -a_inv @ b @ p_b
        self.P[self.BA, tilt] = self.P[tilt, self.BA].T

    def feedback(self, x: np.ndarray) -> None:
        """Paper eq 23: every estimate corrects the INS and the sensors; the error state resets to 0
        (but for what the attitude correction could not apply, see SinCosFilter.attitude_feedback)."""
        st = self.ins.state
        st.pos_enu_m = st.pos_enu_m - x[P_]
        st.v_enu_m_s = st.v_enu_m_s - x[V_]
        self.x = np.zeros(self.n)
        psi_before = _heading_split(st.c_bn)[0]
        self.x[self.A] = self.attitude_feedback(x[self.A])
        moved = _heading_split(self.ins.state.c_bn)[0] - psi_before
        self.heading_moved_rad += math.remainder(moved, 2.0 * math.pi)
        self.ins.accel_bias_m_s2 = self.ins.accel_bias_m_s2 + x[self.BA]
        self.ins.gyro_bias_rad_s = self.ins.gyro_bias_rad_s + x[self.BG]
        if self.estimate_lever:
            self.lever_arm_b_m = self.lever_arm_b_m - x[self.LA]


def _heading_split(c_bn: np.ndarray) -> tuple[float, np.ndarray]:
    """ψ and C_b^h = Rz(ψ)·C_b^n (paper eq 1: C_b^n = C_h^n C_b^h with C_h^n = Rz(−ψ))."""
    psi = math.atan2(c_bn[0, 1], c_bn[1, 1])
    c, s = math.cos(psi), math.sin(psi)
    return psi, np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ c_bn


class SinCosFilter(_ErrorStateFilter):
    """The paper's filter: attitude error block [η1, η2, εx, εy] (eq 7–8, 13, 22)."""

    method = "sincos"
    n_att = 4

    def attitude_prior(self, heading_rad: float) -> np.ndarray:
        """Second moments of (sin δψ, 1 − cos δψ) for δψ ~ N(0, σ²) or uniform, rotated into η."""
        sd = self.cfg.heading_std_deg
        if sd is None:
            m_s2, m_c2 = 0.5, 1.5  # uniform δψ: E[sin²] = ½, E[(1 − cos)²] = 3/2
        else:
            v = math.radians(sd) ** 2
            m_s2 = 0.5 * (1.0 - math.exp(-2.0 * v))
            m_c2 = 1.0 - 2.0 * math.exp(-0.5 * v) + 0.5 * (1.0 + math.exp(-2.0 * v))
        # [sin δψ, 1 − cos δψ] = Rot·[η1, η2], Rot = [[ĉ, −ŝ], [ŝ, ĉ]] (docs/gnss-alignment.md §2)
        c, s = math.cos(heading_rad), math.sin(heading_rad)
        rot = np.array([[c, -s], [s, c]])
        out = np.zeros((4, 4))
        out[0:2, 0:2] = rot.T @ np.diag([m_s2, m_c2]) @ rot
        out[2:4, 2:4] = np.eye(2) * math.radians(self.cfg.tilt_std_deg) ** 2
        return out

    def attitude_jacobian(self, u_b: np.ndarray) -> np.ndarray:
        """δC·u = D·C_b^h·u (eq 7) with D of eq 8 in our frames:
        D = [[η2, η1, −(ĉεy − ŝεx)], [−η1, η2, ŝεy + ĉεx], [εy, −εx, 0]]."""
        psi, c_bh = _heading_split(self.ins.state.c_bn)
        c, s = math.cos(psi), math.sin(psi)
        ux, uy, uz = c_bh @ np.asarray(u_b, float)
        return np.array([
            [uy, ux, s * uz, -c * uz],
            [-ux, uy, c * uz, s * uz],
            [0.0, 0.0, -uy, ux],
        ])

    def attitude_dynamics(self, F, G, s: ChunkSummary, w_in: np.ndarray) -> None:
        """Attitude error equation (paper eq 9–13), derived for ENU / clockwise ψ:
        η̇1 = ψ̇η2 + ĉ·δψ̇,  η̇2 = −ψ̇η1 − ŝ·δψ̇,  δψ̇ = −(C_b^h δω)_z + (φ_n × ω_in)_z,
        ε̇ = ψ̇ [−εy, εx] − (C_b^h δω)_xy − Rz(ψ̂)(R_δ − I)ω_in + ω_U [εy, −εx]."""
        psi, c_bh = _heading_split(self.ins.state.c_bn)
        psi -= 0.5 * s.dheading_rad  # mid-chunk heading
        c, sn = math.cos(psi), math.sin(psi)
        rate = s.dheading_rad / s.dt_s
        we, wn, wu = w_in
        a = self.A.start
        E, T = slice(a, a + 2), slice(a + 2, a + 4)
        g_vec = np.array([c, -sn])
        rz_minus = np.array([[c, sn], [-sn, c]])  # Rz(−ψ̂) on the horizontal: φ_n = Rz(−ψ̂) ε
        rz_plus = rz_minus.T
        # η block
        F[E, E] = rate * np.array([[0.0, 1.0], [-1.0, 0.0]])
        F[E, T] = np.outer(g_vec, np.array([wn, -we]) @ rz_minus)
        F[E, self.BG] = -np.outer(g_vec, c_bh[2])
        G[E, 0:3] = -np.outer(g_vec, c_bh[2])
        # ε block; (R_δ − I)ω_in horizontal is linear in η: columns d/dη1, d/dη2
        j_eta = np.array([[-sn * we + c * wn, -c * we - sn * wn], [-c * we - sn * wn, sn * we - c * wn]])
        F[T, T] = rate * np.array([[0.0, -1.0], [1.0, 0.0]]) + wu * np.array([[0.0, 1.0], [-1.0, 0.0]])
        F[T, E] = -rz_plus @ j_eta
        F[T, self.BG] = -c_bh[0:2]
        G[T, 0:3] = -c_bh[0:2]

    def attitude_feedback(self, x_att: np.ndarray) -> np.ndarray:
        """Paper eq 23: C_b^n = Ĉ_b^n − D·Ĉ_b^h, then orthonormalized.

        The estimate η̂ need not lie on the circle |(ŝ − η̂1, ĉ − η̂2)| = 1 that true headings do;
        orthonormalizing projects it, so the heading moves by Δ = (sin ψ̂ − sin ψ̂', cos ψ̂ − cos ψ̂')
        instead of η̂. The remainder η̂ − Δ stays in the state (it is the error of the new heading
        as the filter estimates it), which keeps the covariance honest while the error is large."""
        eta1, eta2, ex, ey = x_att
        c_bn = self.ins.state.c_bn
        psi, c_bh = _heading_split(c_bn)
        c, s = math.cos(psi), math.sin(psi)
        if math.hypot(s - eta1, c - eta2) < 0.5:
            # (sin ψ, cos ψ) estimated near the origin: the heading is not determined yet (a still
            # start); keep the heading, carry η̂, correct only the tilt.
            eta1, eta2 = 0.0, 0.0
        d = np.array([
            [eta2, eta1, -(c * ey - s * ex)],
            [-eta1, eta2, s * ey + c * ex],
            [ey, -ex, 0.0],
        ])
        self.ins.set_attitude(c_bn - d @ c_bh)  # set_attitude orthonormalizes
        psi_new = _heading_split(self.ins.state.c_bn)[0]
        applied = np.array([s - math.sin(psi_new), c - math.cos(psi_new)])
        return np.array([x_att[0] - applied[0], x_att[1] - applied[1], 0.0, 0.0])

    def attitude_reset_jacobian(self, c_before: np.ndarray, c_after: np.ndarray) -> np.ndarray:
        """ε lives in the h frame of the *estimated* heading, so a heading correction Δψ̂ rotates it:
        ε' = Rz(ψ̂')Rz(−ψ̂)ε = Rz(Δψ̂)ε (large at the first corrections from a large error); η is
        only shifted by the correction, its covariance is unchanged."""
        d = _heading_split(c_after)[0] - _heading_split(c_before)[0]
        out = np.eye(4)
        out[2:4, 2:4] = [[math.cos(d), -math.sin(d)], [math.sin(d), math.cos(d)]]
        return out

    def second_order_noise(self) -> np.ndarray:
        """Covariance of the terms eq 18 and 21 drop: −δC·δla (position) and −δC(ω_nb × δla) (velocity).

        Both are products of two error states. While the heading and the lever arm are both uncertain
        they are metres — far above the GNSS noise — and a filter that ignores them claims a σ its
        errors do not keep (4.9σ just after convergence). With J(u) = Σ_i u_i J(e_i) linear in u and
        independent zero-mean errors, Cov = Σ_ij (W P_la Wᵀ)_ij J(e_i) P_att J(e_j)ᵀ, W = I or [ω_nb×].
        """
        out = np.zeros((6, 6))
        if not self.estimate_lever:
            return out
        p_att, p_la = self.P[self.A, self.A], self.P[self.LA, self.LA]
        jac = [self.attitude_jacobian(e) for e in np.eye(3)]
        for rows, w in ((slice(0, 3), np.eye(3)), (slice(3, 6), skew3(self.omega_nb_b))):
            p_u = w @ p_la @ w.T
            out[rows, rows] = sum(p_u[i, j] * jac[i] @ p_att @ jac[j].T for i in range(3) for j in range(3))
        return out

    def heading_rows(self) -> slice:
        """η1, η2."""
        return slice(self.A.start, self.A.start + 2)

    def tilt_rows(self) -> slice:
        """εx, εy."""
        return slice(self.A.start + 2, self.A.start + 4)

    def heading_var(self) -> float:
        """Var of sin δψ = ĉη1 − ŝη2 (≈ δψ once small)."""
        psi, _ = _heading_split(self.ins.state.c_bn)
        g = np.array([math.cos(psi), -math.sin(psi)])
        a = self.A.start
        return float(g @ self.P[a : a + 2, a : a + 2] @ g)


# ---------------------------------------------------------------------------------------------
# The run loop shared by both filters
# ---------------------------------------------------------------------------------------------
def coarse_level(dv_m_s: np.ndarray) -> tuple[float, float]:
    """Pitch and roll [rad] from the mean specific force of a still period: f^b = C_n^b [0, 0, g]
    gives f_x = −g cosθ sinγ, f_y = g sinθ, f_z = g cosθ cosγ."""
    f = np.asarray(dv_m_s, float).mean(axis=0)
    return math.atan2(f[1], math.hypot(f[0], f[2])), math.atan2(-f[0], f[2])


@dataclass
class _Pass:
    """One filter pass over the fixes: its update rows, the filter as it ended, its start time."""

    rows: list
    flt: _ErrorStateFilter
    start_s: float
    stopped_early: bool


@dataclass(frozen=True)
class _PassData:
    """What every pass reads: the IMU increments (lost samples filled) and their gap variance, the
    fixes after the levelling window in time order, the levelling window's length in samples."""

    dth: np.ndarray
    dv: np.ndarray
    gaps: tuple[np.ndarray, np.ndarray] | None
    imu_t0_s: float
    rate_hz: float
    order: np.ndarray
    k_level: int
    gnss: GnssSeries

    @classmethod
    def of(cls, imu: ImuSeries, gnss: GnssSeries, level_s: float) -> _PassData:
        dth, dv = imu.increments()
        rate = float(imu.rate_hz)
        n_imu = dth.shape[0]
        t_fix = np.asarray(gnss.t_s, dtype=float)
        order = np.argsort(t_fix)
        k_level = int(round(level_s * rate))
        if k_level < 1 or k_level > n_imu:
            raise InputError(f"level_s={level_s} s needs IMU data; the IMU covers {n_imu / rate:.1f} s")
        t_start_min = imu.t0_s + k_level / rate
        order = order[t_fix[order] >= t_start_min - 1e-9]
        if len(order) < 2:
            raise InputError(
                "GNSS: fewer than 2 fixes after the levelling window — check the receiver has a fix"
            )
        return cls(dth, dv, imu.gap_variance(), float(imu.t0_s), rate, order, k_level, gnss)


def _run_pass(filter_cls, data: _PassData, initial_heading_deg: float, cfg: GnssAlignConfig,
              stop_below_deg: float | None = None) -> _Pass:
    """Level on the still start, then run the filter over the fixes: to the end, or to the first update
    whose heading 1σ is below `stop_below_deg`."""
    dth, dv, gaps, rate, gnss, order = data.dth, data.dv, data.gaps, data.rate_hz, data.gnss, data.order
    n_imu, k_level = dth.shape[0], data.k_level
    t_fix = np.asarray(gnss.t_s, dtype=float)
    pitch, roll = coarse_level(dv[:k_level])
    psi0 = math.radians(initial_heading_deg)
    c0 = dcm_from_euler(psi0, pitch, roll)
    origin = gnss.local_level()
    j0 = order[0]
    la0 = np.asarray(cfg.lever_arm_b_m, float)
    k_cur = int(math.floor((t_fix[j0] - data.imu_t0_s) * rate + 1e-9))
    state = NavState(gnss.pos_enu_m[j0] - c0 @ la0, gnss.vel_enu_m_s[j0].copy(), c0,
                     data.imu_t0_s + k_cur / rate)
    start_s = state.t_s
    ins = Strapdown(state, rate, origin)
    ins._prev_dtheta, ins._prev_dv = dth[k_cur - 1].copy(), dv[k_cur - 1].copy()
    flt = filter_cls(ins, cfg, psi0)
    flt.level_prior(dv[:k_level].mean(axis=0) * rate, cfg.level_s)
    # The INS position starts at the first fix minus Ĉ l̂a, so δP0 = −δC·l̂a − Ĉ·δla + n0 (eq 17 read
    # backwards): correlated with the attitude and lever-arm errors, not independent of them.
    j_att = flt.attitude_jacobian(la0)
    p_att, p_la = flt.P[flt.A, flt.A], flt.P[flt.LA, flt.LA]
    flt.P[P_, P_] = j_att @ p_att @ j_att.T + c0 @ p_la @ c0.T + np.diag(gnss.pos_std_m[j0] ** 2)
    flt.P[P_, flt.A] = -j_att @ p_att
    flt.P[flt.A, P_] = flt.P[P_, flt.A].T
    flt.P[P_, flt.LA] = -c0 @ p_la
    flt.P[flt.LA, P_] = flt.P[P_, flt.LA].T
    rows = []
    for j in order[1:]:
        k_to = min(int(math.floor((t_fix[j] - data.imu_t0_s) * rate + 1e-9)), n_imu)
        if k_to <= k_cur:
            continue
        summary = ins.propagate(dth[k_cur:k_to], dv[k_cur:k_to])
        gap_var = None
        if gaps is not None:
            gap_var = (gaps[0][k_cur:k_to].sum(axis=0), gaps[1][k_cur:k_to].sum(axis=0))
        k_cur = k_to
        flt.predict(summary, gap_var)
        z = flt.update(gnss.pos_enu_m[j], gnss.vel_enu_m_s[j], gnss.pos_std_m[j], gnss.vel_std_m_s[j],
                       t_fix[j] - ins.state.t_s)
        rows.append(_snapshot(flt, z))
        if stop_below_deg is not None and rows[-1][2] < stop_below_deg:
            return _Pass(rows, flt, start_s, True)
        if k_cur >= n_imu:
            break
    return _Pass(rows, flt, start_s, False)


def run_alignment(filter_cls, imu: ImuSeries, gnss: GnssSeries, initial_heading_deg: float,
                  config: GnssAlignConfig | None = None) -> GnssAlignResult:
    """Level on the still start, then run the filter over every GNSS fix; return the histories.

    Heading unknown (`heading_std_deg` None, the uniform prior) or a prior wider than 2 × 5°: the first
    pass runs until the heading 1σ falls below `restart_below_deg` (within ~2 s of motion), then the
    filter starts again from the still start at the initial heading plus every heading correction the
    first pass fed back, with a Gaussian prior of `restart_prior_factor` × that σ. Why: the first pass's
    large corrections (up to 180° in a second) leave errors in the tilt and the accelerometer bias that
    the linearized covariance does not hold (a noise-free run from 150° off: −0.028° at 30 s of motion,
    0.54σ, for every seed alike), so from an unknown start the σ was too small at 30–120 s; a start
    within a few degrees leaves none (docs/gnss-alignment.md §13). `restart_below_deg` None: one pass
    (align_gnss_small_angle runs the comparison filter so). The history is
    the first pass's up to the restart and the second's after it: each row uses only the data up to its
    time. The second pass uses the data before the restart twice; with a prior of 2σ that adds a quarter
    of the information it holds (its σ there 0.89 × the first pass's), and by convergence (σ < 1°
    against a ≥ 5° prior) under 4 %."""
    cfg = config or GnssAlignConfig()
    data = _PassData.of(imu, gnss, cfg.level_s)
    if _starts_wide(cfg):
        first = _run_pass(filter_cls, data, initial_heading_deg, cfg, cfg.restart_below_deg)
        if not first.stopped_early:
            return _result(first, cfg, None)
        t_c, coarse_deg, coarse_std = first.rows[-1][0:3]  # _snapshot: t, heading, its 1σ
        psi2 = (initial_heading_deg + math.degrees(first.flt.heading_moved_rad)) % 360.0
        prior_std = cfg.restart_prior_factor * coarse_std
        second = _run_pass(filter_cls, data, psi2, replace(cfg, heading_std_deg=prior_std))
        second.rows = first.rows + [r for r in second.rows if r[0] > t_c + 1e-9]
        restart = {"t_s": float(t_c), "coarse_heading_deg": float(coarse_deg),
                   "coarse_std_deg": float(coarse_std), "initial_heading_deg": float(psi2),
                   "prior_std_deg": float(prior_std)}
        return _result(second, cfg, restart)
    return _result(_run_pass(filter_cls, data, initial_heading_deg, cfg), cfg, None)


def _starts_wide(cfg: GnssAlignConfig) -> bool:
    """The heading prior is unknown, or wider than the restart's own prior could be (2 × 5°)."""
    if cfg.restart_below_deg is None:
        return False
    wide = cfg.restart_prior_factor * cfg.restart_below_deg
    return cfg.heading_std_deg is None or cfg.heading_std_deg > wide


def _result(run: _Pass, cfg: GnssAlignConfig, restart: dict | None) -> GnssAlignResult:
    """The last update's estimates, the convergence time and the histories of a pass."""
    hist = GnssAlignHistory(*[np.array(col) for col in zip(*run.rows, strict=True)])
    thr = cfg.converged_std_deg
    above = np.nonzero(hist.heading_std_deg >= thr)[0]
    if len(hist.t_s) == 0 or (len(above) and above[-1] == len(hist.t_s) - 1):
        converged = None
    else:
        first = above[-1] + 1 if len(above) else 0
        converged = float(hist.t_s[first] - run.start_s)
    return GnssAlignResult(
        method=run.flt.method,
        heading_deg=float(hist.heading_deg[-1]),
        heading_std_deg=float(hist.heading_std_deg[-1]),
        pitch_deg=float(hist.pitch_deg[-1]),
        roll_deg=float(hist.roll_deg[-1]),
        lever_arm_m=hist.lever_arm_m[-1].copy(),
        lever_arm_std_m=hist.lever_arm_std_m[-1].copy(),
        gyro_bias_dph=hist.gyro_bias_dph[-1].copy(),
        accel_bias_ug=hist.accel_bias_ug[-1].copy(),
        pos_enu_m=hist.pos_enu_m[-1].copy(),
        converged_after_s=converged,
        start_s=run.start_s,
        history=hist,
        extra={"noise_source": cfg.noise_source, "gyro_arw_deg_sqrt_h": cfg.gyro_arw_deg_sqrt_h,
               "accel_vrw_ug_sqrt_hz": cfg.accel_vrw_ug_sqrt_hz},
        restart=restart,
    )


def _snapshot(flt: _ErrorStateFilter, z: np.ndarray) -> tuple:
    ins = flt.ins
    st = ins.state
    psi, pitch, roll = _euler(st.c_bn)
    d = np.sqrt(np.diag(flt.P))
    g_ug = 1e6 / STANDARD_GRAVITY_M_S2
    return (
        st.t_s,
        math.degrees(psi),
        math.degrees(math.sqrt(max(flt.heading_var(), 0.0))),
        math.degrees(pitch),
        math.degrees(roll),
        st.pos_enu_m.copy(),
        d[P_].copy(),
        st.v_enu_m_s.copy(),
        flt.lever_arm_b_m.copy(),
        d[flt.LA].copy(),
        ins.gyro_bias_rad_s / DPH,
        d[flt.BG] / DPH,
        ins.accel_bias_m_s2 * g_ug,
        d[flt.BA] * g_ug,
        z.copy(),
    )


def _euler(c: np.ndarray) -> tuple[float, float, float]:
    """ψ in [0, 2π), θ, γ of C_b^n = Rz(−ψ)Rx(θ)Ry(γ)."""
    return (math.atan2(c[0, 1], c[1, 1]) % (2 * math.pi), math.asin(max(-1.0, min(1.0, c[2, 1]))),
            math.atan2(-c[2, 0], c[2, 2]))


def align_gnss(imu: ImuSeries, gnss: GnssSeries, initial_heading_deg: float,
               config: GnssAlignConfig | None = None) -> GnssAlignResult:
    """GNSS-aided alignment from any initial heading with the paper's δsin/δcos filter (eq 1–23)."""
    return run_alignment(SinCosFilter, imu, gnss, initial_heading_deg, config)
