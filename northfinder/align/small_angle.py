"""The conventional small-angle GNSS/INS alignment filter, for comparison with the paper's filter.

What: the same error-state filter, strapdown, measurements (antenna position and velocity with
the lever arm) and feedback as gnss_ins.SinCosFilter, but the attitude error is three small
angles φ in n: Ĉ_b^n = (I − [φ×])C_b^n, so δC·u = (Ĉu) × φ and φ̇ = −ω_in^n × φ − Ĉ δω (the
"psi-angle" model; Titterton & Weston eq 12.5–12.6, and the paper's "conventional small
misalignment" reference method, §2). It is linear only while |φ| ≪ 1 rad — which is the point:
the seed paper (§2, figs 3–5) reports it failing at large heading errors.

Attitude feedback (`attitude_feedback`), docs/gnss-alignment.md §8:
- "every-update" (default): after every 0.1 s update like the paper's eq 23,
  C_b^n ← exp([φ̂×])·Ĉ_b^n. Re-linearizing about each new estimate makes it an iterated filter,
  which is why it still converges from 45°–135°.
- "end": open loop on the attitude — the conventional configuration. Position, velocity, biases
  and lever arm are fed back every update; φ̂ stays in the error state (propagated by Φ) and the
  strapdown keeps the initial attitude, so the error model stays linearized about the coarse
  heading for the whole run. The reported attitude at each update is exp([φ̂×])·Ĉ_b^n, i.e. φ̂
  applied once, at that moment ("at the end" of a run stopped there).
- a float interval_s: the same, but φ̂ is fed back (and reset) at the first update at least
  interval_s after the previous attitude feedback — the periodic reset of many fielded systems.
Position/velocity stay closed loop in every mode: left open they would drift by ½·a_bias·t² and
that, not the attitude model, would dominate the comparison.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from northfinder.align.gnss_ins import (
    P_,
    GnssAlignConfig,
    GnssAlignResult,
    GnssSeries,
    ImuSeries,
    _ErrorStateFilter,
    _euler,
    run_alignment,
)
from northfinder.align.strapdown import ChunkSummary, Strapdown, skew3
from northfinder.errors import InputError
from northfinder.rotations import rotvec_to_dcm

DEFAULT_SMALL_ANGLE_HEADING_STD_DEG = 30.0
"""Prior heading 1σ used when the config says "unknown" (None): a small-angle filter needs a number."""

EVERY_UPDATE = "every-update"
OPEN_LOOP = "end"
AttitudeFeedback = str | float


def _check_feedback(mode: AttitudeFeedback) -> AttitudeFeedback:
    if isinstance(mode, str):
        if mode in (EVERY_UPDATE, OPEN_LOOP):
            return mode
    elif isinstance(mode, (int, float)) and math.isfinite(mode) and mode > 0.0:
        return float(mode)
    raise InputError(f"attitude_feedback={mode!r}: use 'every-update', 'end' or an interval in seconds > 0")


class SmallAngleFilter(_ErrorStateFilter):
    """Attitude error block φ = [φE, φN, φU] (small angles in n; φU is the heading error δψ)."""

    method = "small-angle"
    n_att = 3

    def __init__(self, ins: Strapdown, config: GnssAlignConfig, initial_heading_rad: float,
                 attitude_feedback: AttitudeFeedback = EVERY_UPDATE):
        self.attitude_mode = _check_feedback(attitude_feedback)
        self._t_last_feedback_s = ins.state.t_s
        self.reported_c_bn: list[np.ndarray] = []  # exp([φ̂×])Ĉ after each update (open-loop modes)
        super().__init__(ins, config, initial_heading_rad)

    def attitude_prior(self, heading_rad: float) -> np.ndarray:
        sd = self.cfg.heading_std_deg
        sd = DEFAULT_SMALL_ANGLE_HEADING_STD_DEG if sd is None else sd
        t = math.radians(self.cfg.tilt_std_deg) ** 2
        return np.diag([t, t, math.radians(sd) ** 2])

    def attitude_jacobian(self, u_b: np.ndarray) -> np.ndarray:
        """δC·u = −[φ×]Ĉu = [(Ĉu)×]φ."""
        return skew3(self.ins.state.c_bn @ np.asarray(u_b, float))

    def attitude_dynamics(self, F, G, s: ChunkSummary, w_in: np.ndarray) -> None:
        """φ̇ = −ω_in × φ − Ĉ δω (psi-angle model)."""
        c = self.ins.state.c_bn
        F[self.A, self.A] = -skew3(w_in)
        F[self.A, self.BG] = -c
        G[self.A, 0:3] = -c

    def attitude_feedback(self, x_att: np.ndarray) -> np.ndarray:
        """C = (I − [φ×])⁻¹Ĉ ≈ exp([φ×])Ĉ, orthonormal by construction; nothing left over.
        In the open-loop modes φ̂ is returned unapplied (it stays in the error state) unless the
        reset interval has elapsed."""
        mode = self.attitude_mode
        if mode == OPEN_LOOP:
            return np.asarray(x_att, float).copy()
        if mode != EVERY_UPDATE:
            t = self.ins.state.t_s
            if t - self._t_last_feedback_s < mode - 1e-9:
                return np.asarray(x_att, float).copy()
            self._t_last_feedback_s = t
        self.ins.set_attitude(rotvec_to_dcm(np.asarray(x_att, float)) @ self.ins.state.c_bn)
        return np.zeros(3)

    def update(self, pos_m, vel_m_s, pos_std_m, vel_std_m_s, dt_fix_s: float) -> np.ndarray:
        """The shared update (paper eq 15–21, feedback eq 23). With φ̂ kept in the state, a lever-arm
        feedback also moves the mean of δP: the antenna error δP + J(l̂a)φ + Ĉδla is unchanged, so
        δP' = δP + (J(l̂a_old) − J(l̂a_new))φ̂ (the mean counterpart of the reset Jacobian)."""
        if self.attitude_mode == EVERY_UPDATE:
            return super().update(pos_m, vel_m_s, pos_std_m, vel_std_m_s, dt_fix_s)
        j_old = self.attitude_jacobian(self.lever_arm_b_m)
        z = super().update(pos_m, vel_m_s, pos_std_m, vel_std_m_s, dt_fix_s)
        phi = self.x[self.A]
        self.x[P_] += (j_old - self.attitude_jacobian(self.lever_arm_b_m)) @ phi
        self.reported_c_bn.append(rotvec_to_dcm(phi) @ self.ins.state.c_bn)
        return z

    def heading_var(self) -> float:
        a = self.A.start + 2
        return float(self.P[a, a])


def align_gnss_small_angle(imu: ImuSeries, gnss: GnssSeries, initial_heading_deg: float,
                           config: GnssAlignConfig | None = None, *,
                           attitude_feedback: AttitudeFeedback = EVERY_UPDATE) -> GnssAlignResult:
    """The same alignment with the conventional small-angle attitude error model.

    `attitude_feedback`: "every-update" (default, paper eq 23), "end" (open loop on attitude) or a
    reset interval in seconds; in the open-loop modes the history's attitude is exp([φ̂×])Ĉ."""
    mode = _check_feedback(attitude_feedback)
    made: list[SmallAngleFilter] = []

    def factory(ins: Strapdown, cfg: GnssAlignConfig, psi0_rad: float) -> SmallAngleFilter:
        made.append(SmallAngleFilter(ins, cfg, psi0_rad, attitude_feedback=mode))
        return made[-1]

    # the comparison runs as the paper's baseline: one pass from its prior, never restarted (so
    # `made` holds the one filter whose attitudes the history reports)
    one_pass = replace(config or GnssAlignConfig(), restart_below_deg=None)
    res = run_alignment(factory, imu, gnss, initial_heading_deg, one_pass)
    res.extra["attitude_feedback"] = mode
    if mode == EVERY_UPDATE:
        return res
    h = res.history
    euler = np.rad2deg(np.array([_euler(c) for c in made[0].reported_c_bn]).reshape(-1, 3))
    if len(euler) != len(h.t_s):  # one reported attitude per update, as run_alignment snapshots
        raise RuntimeError("small-angle filter: reported attitudes do not match the history")
    h.heading_deg, h.pitch_deg, h.roll_deg = euler[:, 0], euler[:, 1], euler[:, 2]
    res.heading_deg, res.pitch_deg, res.roll_deg = (float(v) for v in euler[-1])
    return res
