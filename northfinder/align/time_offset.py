"""The IMU–GNSS time offset from the data: IMU heading change against GNSS course over ground.

What: refine a coarse start of IMU sample 0 in GNSS time (host receive stamps, off by up to a few
hundred ms on a late, jittery link) to a few ms, from the signals themselves, with an honest σ.

Why this signal: a heading-independent quantity both sensors see. The IMU's heading change is
Ψ(t) = −∫(ω·u − Ωe sin L) dt (gyro projected on the vertical u of the still start, less Earth's
vertical rate); the receiver's course over ground χ = atan2(vE, vN) follows it up to a constant
(the unknown heading) — so the unknown heading is a nuisance constant, not an input.

The lever arm cannot be ignored: an antenna r_fwd ahead of the IMU moves sideways at ψ̇·r_fwd, so
its course leads the heading by ≈ r_fwd·ψ̇/v — the same shape as a time shift of r_fwd/v (0.15 s
for 1.5 m at 10 m/s). The model therefore carries the lever arm as two nuisance coefficients:

    χ_k = Ψ(t_k − τ) + c_seg + d_seg·(t_k − t_seg) + r_fwd·(−ω_up/v)_k + r_up·(ω_fwd/v)_k + e_k

(lateral antenna velocity (ω×r)_x = ω_fwd·r_up − ω_up·r_fwd, divided by the speed), with one
constant and one slope per segment of at most SEGMENT_S (absorbs gyro bias, the Earth-rate and
tilt approximations; a gap or a stop starts a new segment, where the course is undefined). Only
epochs at ≥ MIN_SPEED_M_S count, weighted by v² (the course's noise is σ_v/v).

τ is found by profile least squares (Seber & Wild, "Nonlinear Regression", 1989, §2.2.2 and
§5.2: concentrate the linear parameters out, search the one nonlinear parameter): the weighted
residual sum of squares S(τ) on a grid over ±search_s, then a parabola through S near its minimum
(sub-sample refinement). σ_τ² = σ̂² / a with S(τ) ≈ S_min + a(τ − τ̂)² and σ̂² = S_min/(n − p) —
the Gauss–Newton covariance of the profile (Seber & Wild §2.1) — inflated by the lag-1
autocorrelation ρ of the residuals, (1 + ρ)/(1 − ρ) (the AR(1) effective sample size: Bretherton
et al., J. Climate 12, 1999, eq. 31), since a real receiver's velocity noise is not white.

When the data hold no timing information (the vehicle never turned while moving, too few moving
epochs, the minimum at the edge of the search, a σ above MAX_STD_S) it raises NoTimeInformation
saying which, rather than returning a number.

Pure numpy: no serial, CAN or rich here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from northfinder.align.strapdown import fill_lost_samples
from northfinder.constants import OMEGA_EARTH_RAD_S

MIN_SPEED_M_S = 3.0
"""Below this the course over ground is noise (σ_v/v = 0.05/3 rad ≈ 1° for a 0.05 m/s receiver)."""
SEGMENT_S = 20.0
"""Longest stretch with one heading constant and slope: gyro bias and the fixed-vertical
approximation drift slowly; 20 s keeps them linear while an S-turn (12 s) stays in one piece."""
MIN_TURN_RATE_RAD_S = 0.02
"""The vehicle must turn at least this fast while moving somewhere in the window (≈ 1.1 °/s)."""
MIN_EPOCHS = 50
MAX_STD_S = 0.05
"""A σ above this is no information worth using (the host stamps are better)."""
MAX_FILLED_SAMPLES = 5
"""Lost IMU samples beyond this many in a row (20 ms at 250 Hz) break the heading integral: the
epochs whose search window touches such a gap are left out and a new segment starts after it
(its constant takes up the heading change the gap lost)."""
LEVEL_S = 5.0
"""The still start (gnss_ins.GnssAlignConfig.level_s) whose mean specific force gives the vertical."""
SEARCH_S = 2.0
"""Half-width of the search around the coarse offset: host stamps of a reader that polls the GNSS
between IMU reads were 0.72 s off at 25× on a loaded host (one turn of an S lasts 6 s, so ±2 s
still holds one minimum)."""
COARSE_STEP_S = 0.02
FINE_HALF_S = 0.03
FINE_STEP_S = 0.003
"""The coarse grid finds the minimum to ±10 ms; the parabola is fitted on the fine grid about it."""


class NoTimeInformation(ValueError):
    """The data cannot give the offset (the message says why); the caller keeps its coarse value."""


@dataclass(frozen=True)
class TimeOffset:
    """The refined start of IMU sample 0 in GNSS time and what it rests on."""

    t0_s: float
    """Start of IMU sample index 0 in GNSS time."""
    std_s: float
    correction_s: float
    """t0_s − the coarse t0 given."""
    epochs: int
    segments: int
    lever_fwd_up_m: tuple[float, float]
    """The fitted lever-arm nuisance (forward, up) [m]: a plausibility check, not an estimate to use."""
    residual_rms_deg: float
    """RMS course residual, weighted by v² like the fit."""
    autocorr: float
    search_s: float

    def as_dict(self) -> dict[str, float | int | list[float]]:
        return {
            "t0_s": self.t0_s,
            "std_s": self.std_s,
            "correction_s": self.correction_s,
            "epochs": self.epochs,
            "segments": self.segments,
            "lever_fwd_up_m": list(self.lever_fwd_up_m),
            "residual_rms_deg": self.residual_rms_deg,
            "residual_autocorr": self.autocorr,
            "search_s": self.search_s,
        }


@dataclass(frozen=True)
class _Imu:
    """Dense IMU signals on sample boundaries/midpoints (index from the first sample)."""

    rate_hz: float
    index0: int
    psi_rad: np.ndarray  # heading change at boundaries 0 … N (N + 1 values)
    w_up: np.ndarray  # rate about the vertical at midpoints (N values)
    w_fwd: np.ndarray  # rate about the horizontal forward axis at midpoints
    gaps: np.ndarray  # [g, 2] lost stretches longer than MAX_FILLED_SAMPLES: (first, end) dense index


def _imu_signals(gyro_rad_s, accel_g, sample_index, rate_hz: float, latitude_deg: float) -> _Imu:
    """Gaps filled linearly; the vertical from the mean specific force of the still start."""
    gyro = np.asarray(gyro_rad_s, float)
    acc = np.asarray(accel_g, float)
    idx = np.arange(len(gyro)) if sample_index is None else np.asarray(sample_index, np.int64)
    rel = idx - idx[0]
    gyro = fill_lost_samples(idx, gyro)
    n_level = max(1, min(len(acc), int(round(LEVEL_S * rate_hz))))
    up = acc[:n_level].mean(axis=0)
    up = up / np.linalg.norm(up)
    fwd = np.array([0.0, 1.0, 0.0]) - up[1] * up
    fwd = fwd / np.linalg.norm(fwd)
    w_up, w_fwd = gyro @ up, gyro @ fwd
    psi_rate = -(w_up - OMEGA_EARTH_RAD_S * math.sin(math.radians(latitude_deg)))
    psi = np.concatenate([[0.0], np.cumsum(psi_rate) / rate_hz])
    jump = np.flatnonzero(np.diff(rel) > MAX_FILLED_SAMPLES + 1)
    gaps = np.column_stack([rel[jump] + 1, rel[jump + 1]]).reshape(-1, 2)
    return _Imu(float(rate_hz), int(idx[0]), psi, w_up, w_fwd, gaps)


def _segments(t_s: np.ndarray, imu_gap: np.ndarray) -> np.ndarray:
    """Segment number per epoch: a new one after a gap (> 2.5 epoch spacings), an IMU gap (the
    count of IMU gaps before the epoch changes) or SEGMENT_S."""
    dt = np.diff(t_s)
    step = np.median(dt) if len(dt) else 1.0
    seg = np.zeros(len(t_s), dtype=np.int64)
    start = t_s[0] if len(t_s) else 0.0
    for k in range(1, len(t_s)):
        new = dt[k - 1] > 2.5 * step or t_s[k] - start > SEGMENT_S or imu_gap[k] != imu_gap[k - 1]
        seg[k] = seg[k - 1] + int(new)
        if new:
            start = t_s[k]
    return seg


def _unwrap_by_segment(course: np.ndarray, seg: np.ndarray) -> np.ndarray:
    out = course.copy()
    for s in np.unique(seg):
        m = seg == s
        out[m] = np.unwrap(course[m])
    return out


class _Profile:
    """S(τ): the weighted residual sum of squares with the linear parameters concentrated out."""

    def __init__(self, imu: _Imu, t_s, course, speed, t0_coarse_s: float) -> None:
        self.imu, self.t_s, self.t0c = imu, t_s, t0_coarse_s
        gaps_before = np.searchsorted(imu.gaps[:, 0], (t_s - t0_coarse_s) * imu.rate_hz)
        self.seg = _segments(t_s, gaps_before)
        self.y = _unwrap_by_segment(course, self.seg)
        self.sw = speed  # √weight: the course noise is σ_v / v
        self.inv_v = 1.0 / speed
        n_seg = int(self.seg[-1]) + 1
        self.nuis = np.zeros((len(t_s), 2 * n_seg))
        rows = np.arange(len(t_s))
        t_rel = t_s - np.array([t_s[self.seg == s][0] for s in range(n_seg)])[self.seg]
        self.nuis[rows, 2 * self.seg] = 1.0
        self.nuis[rows, 2 * self.seg + 1] = t_rel
        self.n_seg = n_seg
        # the segment columns do not depend on τ: project them out once (Frisch–Waugh–Lovell), so
        # each τ costs a projection and a 2-column fit instead of a (2·segments + 2)-column one
        self.q, _ = np.linalg.qr(self.nuis * self.sw[:, None])

    def _resid(self, x: np.ndarray) -> np.ndarray:
        return x - self.q @ (self.q.T @ x)

    def fit(self, tau: float) -> tuple[float, np.ndarray, np.ndarray]:
        """(S, the two lever-arm coefficients, weighted residuals) at offset τ."""
        pos = (self.t_s - self.t0c - tau) * self.imu.rate_hz  # IMU boundary position (fractional)
        bnd = np.arange(len(self.imu.psi_rad))
        mid = np.arange(len(self.imu.w_up)) + 0.5
        psi = np.interp(pos, bnd, self.imu.psi_rad)
        w_up = np.interp(pos, mid, self.imu.w_up)
        w_fwd = np.interp(pos, mid, self.imu.w_fwd)
        a = self._resid(np.column_stack([-w_up * self.inv_v, w_fwd * self.inv_v]) * self.sw[:, None])
        b = self._resid((self.y - psi) * self.sw)
        coef, *_ = np.linalg.lstsq(a, b, rcond=None)
        r = b - a @ coef
        return float(r @ r), coef, r


def _usable_epochs(imu: _Imu, gnss_t_s, vel_enu, t0_coarse_s: float, search_s: float):
    """Moving epochs with a velocity whose IMU position stays inside the data over the search."""
    t = np.asarray(gnss_t_s, float)
    v = np.asarray(vel_enu, float).reshape(-1, 3)
    speed = np.hypot(v[:, 0], v[:, 1])
    n = len(imu.w_up)
    lo = t0_coarse_s + search_s + LEVEL_S  # after the still start's levelling window
    hi = t0_coarse_s - search_s + n / imu.rate_hz
    ok = np.isfinite(speed) & (speed >= MIN_SPEED_M_S) & (t >= lo) & (t <= hi)
    pos = (t - t0_coarse_s) * imu.rate_hz
    reach = search_s * imu.rate_hz + 1.0
    for first, end in imu.gaps.tolist():  # no epoch whose IMU position may fall in a gap
        ok &= (pos + reach < first) | (pos - reach > end)
    return t[ok], np.arctan2(v[ok, 0], v[ok, 1]), speed[ok]


def _parabola(taus: np.ndarray, s: np.ndarray) -> tuple[float, float]:
    """Vertex and curvature a of S ≈ S_min + a(τ − τ̂)² fitted through the fine grid."""
    c2, c1, _ = np.polyfit(taus, s, 2)
    if c2 <= 0.0:
        raise NoTimeInformation("the course residual has no minimum in time (flat or concave)")
    return float(-c1 / (2.0 * c2)), float(c2)


def estimate_time_offset(
    gyro_rad_s,
    accel_g,
    sample_index,
    rate_hz: float,
    gnss_t_s,
    gnss_vel_enu_m_s,
    latitude_deg: float,
    t0_coarse_s: float,
    search_s: float = SEARCH_S,
) -> TimeOffset:
    """Refine `t0_coarse_s`, the start of the FIRST given IMU sample in GNSS time, from the data.

    The sample with index i integrates [t0 + (i − i_first)/rate, t0 + (i − i_first + 1)/rate];
    missing indices are filled linearly. GNSS epochs carry the antenna's velocity (E, N, ·) at
    gnss_t_s (NaN: lost). Raises NoTimeInformation when the data cannot tell (module doc).
    """
    imu = _imu_signals(gyro_rad_s, accel_g, sample_index, rate_hz, latitude_deg)
    t, course, speed = _usable_epochs(imu, gnss_t_s, gnss_vel_enu_m_s, t0_coarse_s, search_s)
    if len(t) < MIN_EPOCHS:
        raise NoTimeInformation(
            f"only {len(t)} GNSS epochs at ≥ {MIN_SPEED_M_S:g} m/s after the still start "
            f"(need {MIN_EPOCHS}): the vehicle did not drive long enough"
        )
    pos = (t - t0_coarse_s) * rate_hz
    turn = np.abs(np.interp(pos, np.arange(len(imu.w_up)) + 0.5, imu.w_up))
    if turn.max() < MIN_TURN_RATE_RAD_S:
        raise NoTimeInformation(
            f"the vehicle never turned while moving (yaw rate ≤ {math.degrees(turn.max()):.2f} °/s): "
            "course and heading change carry no timing"
        )
    prof = _Profile(imu, t, course, speed, t0_coarse_s)
    coarse = np.arange(-search_s, search_s + 0.5 * COARSE_STEP_S, COARSE_STEP_S)
    s_coarse = np.array([prof.fit(float(x))[0] for x in coarse])
    k = int(np.argmin(s_coarse))
    if k == 0 or k == len(coarse) - 1:
        raise NoTimeInformation(
            f"the best IMU–GNSS offset lies at the edge of the ±{search_s:g} s search around the "
            "host stamps: the coarse estimate is further off than that, or the data are inconsistent"
        )
    fine = coarse[k] + np.arange(-FINE_HALF_S, FINE_HALF_S + 0.5 * FINE_STEP_S, FINE_STEP_S)
    s_fine = np.array([prof.fit(float(x))[0] for x in fine])
    tau, curv = _parabola(fine, s_fine)
    s_min, coef, resid = prof.fit(tau)
    dof = len(t) - (2 * prof.n_seg + 2) - 1
    rho = float(np.clip(np.corrcoef(resid[:-1], resid[1:])[0, 1], 0.0, 0.95)) if len(resid) > 2 else 0.0
    std = math.sqrt(s_min / max(dof, 1) / curv * (1.0 + rho) / (1.0 - rho))
    if not math.isfinite(std) or std > MAX_STD_S:
        raise NoTimeInformation(
            f"the data give the IMU–GNSS offset only to ±{std * 1e3:.0f} ms (1σ): too few turns at speed"
        )
    rms_rad = math.sqrt(s_min / float(np.sum(speed**2)))
    return TimeOffset(
        t0_s=t0_coarse_s + tau,
        std_s=std,
        correction_s=tau,
        epochs=len(t),
        segments=prof.n_seg,
        lever_fwd_up_m=(float(coef[-2]), float(coef[-1])),
        residual_rms_deg=math.degrees(rms_rad),
        autocorr=rho,
        search_s=float(search_s),
    )


__all__ = ["NoTimeInformation", "TimeOffset", "estimate_time_offset"]
