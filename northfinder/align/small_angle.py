"""The conventional small-angle GNSS/INS alignment filter, for comparison with the paper's filter.

What: the same error-state filter, strapdown, measurements (antenna position and velocity with
the lever arm) and feedback as gnss_ins.SinCosFilter, but the attitude error is three small
angles φ in n: Ĉ_b^n = (I − [φ×])C_b^n, so δC·u = (Ĉu) × φ and φ̇ = −ω_in^n × φ − Ĉ δω (the
"psi-angle" model; Titterton & Weston eq 12.5–12.6, and the paper's "conventional small
misalignment" reference method, §2). It is linear only while |φ| ≪ 1 rad — which is the point:
the seed paper (§2, figs 3–5) reports it failing at large heading errors.

Feedback after every update like the paper's eq 23: C_b^n ← exp([φ̂×])·Ĉ_b^n.
"""

from __future__ import annotations

import math

import numpy as np

from northfinder.align.gnss_ins import (
    GnssAlignConfig,
    GnssAlignResult,
    GnssSeries,
    ImuSeries,
    _ErrorStateFilter,
    run_alignment,
)
from northfinder.align.strapdown import ChunkSummary, skew3
from northfinder.rotations import rotvec_to_dcm

DEFAULT_SMALL_ANGLE_HEADING_STD_DEG = 30.0
"""Prior heading 1σ used when the config says "unknown" (None): a small-angle filter needs a number."""


class SmallAngleFilter(_ErrorStateFilter):
    """Attitude error block φ = [φE, φN, φU] (small angles in n; φU is the heading error δψ)."""

    method = "small-angle"
    n_att = 3

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
        """C = (I − [φ×])⁻¹Ĉ ≈ exp([φ×])Ĉ, orthonormal by construction; nothing left over."""
        self.ins.set_attitude(rotvec_to_dcm(np.asarray(x_att, float)) @ self.ins.state.c_bn)
        return np.zeros(3)

    def heading_var(self) -> float:
        a = self.A.start + 2
        return float(self.P[a, a])


def align_gnss_small_angle(imu: ImuSeries, gnss: GnssSeries, initial_heading_deg: float,
                           config: GnssAlignConfig | None = None) -> GnssAlignResult:
    """The same alignment with the conventional small-angle attitude error model."""
    return run_alignment(SmallAngleFilter, imu, gnss, initial_heading_deg, config)
