"""Monte Carlo of per-position means for a turntable north find, vectorized over trials.

A statistical model, not a device emulator (that is firmware_sim): for each trial it draws the
mean gyro rate and specific force at every table position from

    gyro  = Earth rate seen by the b axis + constant bias + drift averaged over the dwell + white
    accel = gravity seen by the b axis + constant bias + white

Units at the edges follow docs/CONVENTIONS.md: ARW in °/√h (σ of a mean over T seconds is
ARW·60/√T °/h), rate random walk in °/h/√h, accelerometer noise in µg/√Hz with σ of a mean
over T seconds = density/√T, biases in °/h and µg. The drift is integrated over each dwell,
with the move/settle gap between dwells, so a wandering bias aliases into the harmonic the
way it does on the bench. Solve the batch with northfinder.estimators.heading.solve_batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from northfinder.constants import DPH, STANDARD_GRAVITY_M_S2, earth_rate_enu_rad_s, normal_gravity_m_s2
from northfinder.rotations import dcm_from_euler, rot_z


@dataclass(frozen=True)
class GyroNoise:
    """Gyro error model per axis. `white_dph` adds a white σ per position mean directly."""

    arw_deg_rt_h: float = 0.0
    white_dph: float = 0.0
    bias_dph: float = 0.0
    bias_sigma_dph: float = 0.0
    rrw_dph_rt_h: float = 0.0
    gm_sigma_dph: float = 0.0
    gm_tau_s: float = 600.0


@dataclass(frozen=True)
class AccelNoise:
    """Accelerometer error model per axis. `white_g` adds a white σ per position mean directly."""

    noise_ug_rt_hz: float = 0.0
    white_g: float = 0.0
    bias_ug: float = 0.0
    bias_sigma_ug: float = 0.0


@dataclass(frozen=True)
class Plan:
    """Table angles in measurement order, dwell per position and move/settle gap between dwells."""

    table_angle_deg: np.ndarray
    dwell_s: float
    gap_s: float = 0.0

    @property
    def n(self) -> int:
        return int(np.size(self.table_angle_deg))

    @property
    def mid_times_s(self) -> np.ndarray:
        """Mid-dwell time of each position [s] (what `sample_times_s` wants)."""
        return np.arange(self.n) * (self.dwell_s + self.gap_s) + 0.5 * self.dwell_s

    @property
    def total_dwell_s(self) -> float:
        return self.n * self.dwell_s


@dataclass(frozen=True)
class Batch:
    """Simulated means: gyro_dph, accel_g of shape (T, n) (b-y) or (T, n, 3); stds of the white part."""

    table_angle_deg: np.ndarray
    gyro_dph: np.ndarray
    accel_g: np.ndarray
    gyro_std_dph: np.ndarray | None
    accel_std_g: np.ndarray | None
    sample_times_s: np.ndarray


def equally_spaced_deg(n: int, start_deg: float = 0.0) -> np.ndarray:
    """α_i = α_0 + i·360°/n, i = 0…n−1 (docs/CONVENTIONS.md)."""
    return start_deg + np.arange(n) * 360.0 / n


def interleaved_order(n: int) -> np.ndarray:
    """A visiting order of n equally spaced positions that keeps slow drift out of the harmonic.

    Opposite positions are visited back to back (0°, 180°, …), so a bias that moves slowly
    enters mostly the constant term; for n a power of two this is the bit-reversal order
    0, 180, 90, 270, 45, 225, … . Returns indices into equally_spaced_deg(n).
    """
    bits = int(np.log2(n)) if n > 0 else 0
    if n > 1 and 2**bits == n:
        idx = np.arange(n)
        rev = np.zeros(n, dtype=int)
        for b in range(bits):
            rev |= ((idx >> b) & 1) << (bits - 1 - b)
        return rev
    half = n // 2
    order = [k for i in range(half) for k in (i, i + half)] if n % 2 == 0 else list(range(n))
    return np.asarray(order)


def true_means(table_angle_deg, heading_deg, pitch_deg, roll_deg, latitude_deg, height_m=0.0):
    """Noise-free b-frame means: (T, n, 3) gyro [rad/s] and specific force [g] (broadcast truths)."""
    c_pn = dcm_from_euler(
        *(np.deg2rad(np.atleast_1d(x).astype(float)) for x in (heading_deg, pitch_deg, roll_deg))
    )
    c_np = np.swapaxes(c_pn, -1, -2)
    w_p = c_np @ earth_rate_enu_rad_s(latitude_deg)
    g_g = float(normal_gravity_m_s2(latitude_deg, height_m)) / STANDARD_GRAVITY_M_S2
    f_p = c_np @ np.array([0.0, 0.0, g_g])
    c_bp_t = np.swapaxes(rot_z(np.deg2rad(np.asarray(table_angle_deg, dtype=float))), -1, -2)  # C_p^b
    return np.einsum("nij,tj->tni", c_bp_t, w_p), np.einsum("nij,tj->tni", c_bp_t, f_p)


def pitch_roll_for_tilt(heading_deg, tilt_deg, tilt_azimuth_deg) -> tuple[np.ndarray, np.ndarray]:
    """Pitch and roll [deg] that give tilt ε with tilt azimuth ζ at heading ψ.

    From C_p^n·e_z = [sinε sinζ, sinε cosζ, cosε]: sinγ = sinε·sin(ζ−ψ),
    sinθ·cosγ = −sinε·cos(ζ−ψ), cosθ·cosγ = cosε.
    """
    e, d = np.deg2rad(tilt_deg), np.deg2rad(np.asarray(tilt_azimuth_deg) - np.asarray(heading_deg))
    pitch = np.arctan2(-np.sin(e) * np.cos(d), np.cos(e))
    roll = np.arcsin(np.sin(e) * np.sin(d))
    return np.rad2deg(pitch), np.rad2deg(roll)


def _drift_means(rng, trials, k, plan: Plan, g: GyroNoise, substeps: int) -> np.ndarray:
    """Dwell-averaged bias drift (T, n, k) [°/h]: rate random walk (exact) + Gauss–Markov."""
    n, dwell, gap = plan.n, plan.dwell_s, plan.gap_s
    out = np.zeros((trials, n, k))
    if g.rrw_dph_rt_h > 0.0:
        q = g.rrw_dph_rt_h / np.sqrt(3600.0)  # °/h per √s
        # Over a dwell of length T the pair (W(T), mean of W over [0, T]) is Gaussian with
        # var T, T/3 and covariance T/2; gaps add an independent increment.
        z1, z2, z3 = rng.standard_normal((3, trials, n, k))
        end = np.sqrt(dwell) * z1
        mean_rel = end / 2.0 + np.sqrt(dwell / 12.0) * z2
        step = end + np.sqrt(gap) * z3
        start = np.cumsum(step, axis=1) - step
        out += q * (start + mean_rel)
    if g.gm_sigma_dph > 0.0:
        h = dwell / substeps
        phi_h, phi_gap = np.exp(-h / g.gm_tau_s), np.exp(-gap / g.gm_tau_s)
        x = g.gm_sigma_dph * rng.standard_normal((trials, k))
        for i in range(n):
            acc = 0.5 * x
            for j in range(substeps):
                x = phi_h * x + g.gm_sigma_dph * np.sqrt(1.0 - phi_h**2) * rng.standard_normal((trials, k))
                acc += x if j < substeps - 1 else 0.5 * x
            out[:, i, :] += acc / substeps  # trapezoid over the dwell
            x = phi_gap * x + g.gm_sigma_dph * np.sqrt(1.0 - phi_gap**2) * rng.standard_normal((trials, k))
    return out


def simulate(
    rng: np.random.Generator,
    trials: int,
    plan: Plan,
    heading_deg,
    pitch_deg,
    roll_deg,
    latitude_deg: float,
    gyro: GyroNoise = GyroNoise(),
    accel: AccelNoise = AccelNoise(),
    three_axis: bool = False,
    substeps: int = 16,
) -> Batch:
    """Draw `trials` finds; truths broadcast over trials (scalars or (T,) arrays)."""
    k = 3 if three_axis else 1
    n = plan.n
    w_true, f_true = true_means(plan.table_angle_deg, heading_deg, pitch_deg, roll_deg, latitude_deg)
    w_true = np.broadcast_to(w_true / DPH, (trials, n, 3))
    f_true = np.broadcast_to(f_true, (trials, n, 3))
    cols = slice(None) if three_axis else slice(1, 2)
    white_dph = float(np.hypot(gyro.arw_deg_rt_h * 60.0 / np.sqrt(plan.dwell_s), gyro.white_dph))
    gy = w_true[..., cols] + gyro.bias_dph
    gy = gy + gyro.bias_sigma_dph * rng.standard_normal((trials, 1, k))
    gy = gy + white_dph * rng.standard_normal((trials, n, k))
    if gyro.rrw_dph_rt_h > 0.0 or gyro.gm_sigma_dph > 0.0:
        gy = gy + _drift_means(rng, trials, k, plan, gyro, substeps)
    white_g = float(np.hypot(accel.noise_ug_rt_hz * 1e-6 / np.sqrt(plan.dwell_s), accel.white_g))
    ac = f_true[..., cols] + accel.bias_ug * 1e-6
    ac = ac + accel.bias_sigma_ug * 1e-6 * rng.standard_normal((trials, 1, k))
    ac = ac + white_g * rng.standard_normal((trials, n, k))
    squeeze = (lambda a: a) if three_axis else (lambda a: a[..., 0])
    return Batch(
        table_angle_deg=np.asarray(plan.table_angle_deg, dtype=float),
        gyro_dph=squeeze(gy),
        accel_g=squeeze(ac),
        gyro_std_dph=squeeze(np.full((n, k), white_dph)) if white_dph > 0.0 else None,
        accel_std_g=squeeze(np.full((n, k), white_g)) if white_g > 0.0 else None,
        sample_times_s=plan.mid_times_s,
    )
