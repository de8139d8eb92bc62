"""Harmonic least squares over the table angle (paper eq 4–7), batched over trials.

A sensor on the turning table top sees the platform-frame vector v^p = [v_x, v_y, v_z] through
C_b^p = Rz(α) (docs/CONVENTIONS.md), so its b-x and b-y axes read

    x(α) = R_x + v_x·cos α + v_y·sin α
    y(α) = R_y − v_x·sin α + v_y·cos α

The y line is the paper's eq 4/5, y = R + a·cos α + b·sin α, with a = v_y and b = −v_x.
Both axes share v_x, v_y, so a 3-axis sensor is fitted jointly (separate biases). The fit is
the paper's eq 6–7, X̂ = (AᵀA)⁻¹AᵀY, generalised to weights and to a bias that drifts
polynomially in time (the drift-aware model). One pseudo-inverse serves every trial of a batch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from northfinder.errors import InputError

MAX_CONDITION = 1.0e3
"""Largest accepted condition number of the column-normalised design matrix."""

BIAS_MODELS = {"constant": 0, "linear": 1, "quadratic": 2}


@dataclass(frozen=True)
class HarmonicFit:
    """Fitted coefficients over a batch: shapes (T, p) and (T, p, p); T = 1 for one find.

    `names` are the parameter names ("v_x", "v_y", "R_y", "R1_y", …); `residual_rms` maps an
    axis name ("x", "y") to (T,) residual RMS in the input unit; `noise` is "given" when the
    covariance comes from the caller's per-position standard errors, else "residuals".
    """

    names: tuple[str, ...]
    coefficients: np.ndarray
    covariance: np.ndarray
    residual_rms: dict[str, np.ndarray]
    dof: int
    noise: str

    def coef(self, name: str) -> np.ndarray:
        """One coefficient over the batch, shape (T,)."""
        return self.coefficients[..., self.names.index(name)]

    @property
    def a(self) -> np.ndarray:
        """The paper's a = v_y (eq 4), the cos α coefficient of the b-y axis."""
        return self.coef("v_y")

    @property
    def b(self) -> np.ndarray:
        """The paper's b = −v_x (eq 4), the sin α coefficient of the b-y axis."""
        return -self.coef("v_x")


def design_matrix(
    alpha_rad: np.ndarray, axes: tuple[str, ...], time_s: np.ndarray | None = None, bias_order: int = 0
) -> tuple[np.ndarray, tuple[str, ...]]:
    """Design matrix A of eq 6 (rows: axis-major, n per axis) and its parameter names.

    Parameters: v_x, v_y, then per axis R_axis and, for bias_order ≥ 1, R{k}_axis multiplying
    τ^k with τ = (t − mean t)/half-span (dimensionless, for conditioning).
    """
    alpha = np.asarray(alpha_rad, dtype=float)
    n = alpha.size
    c, s = np.cos(alpha), np.sin(alpha)
    names = ["v_x", "v_y"]
    for ax in axes:
        names.append(f"R_{ax}")
        names += [f"R{k}_{ax}" for k in range(1, bias_order + 1)]
    if bias_order > 0:
        t = np.arange(n, dtype=float) if time_s is None else np.asarray(time_s, dtype=float)
        half_span = max(0.5 * float(np.ptp(t)), 1e-12)
        tau = (t - t.mean()) / half_span
    blocks = []
    for ax in axes:
        block = np.zeros((n, len(names)))
        block[:, 0], block[:, 1] = (c, s) if ax == "x" else (-s, c)
        j = names.index(f"R_{ax}")
        block[:, j] = 1.0
        for k in range(1, bias_order + 1):
            block[:, j + k] = tau**k
        blocks.append(block)
    return np.vstack(blocks), tuple(names)


def check_conditioning(a_matrix: np.ndarray, weights: np.ndarray, what: str) -> float:
    """Raise InputError when the table angles (and times) cannot separate cos α and sin α.

    Columns are scaled by their ideal norms (√(Σw/2) for cos/sin, √Σw for bias terms), not by
    their own, so a column that is ~0 (all α at 0° and 180°: sin α ≈ 1e-16) stays ~0. The
    condition number is then 1 for equally spaced positions.
    """
    aw = a_matrix * np.sqrt(weights)[:, None]
    total = float(np.sum(weights))
    scale = np.full(a_matrix.shape[1], np.sqrt(total))
    scale[:2] = np.sqrt(total / 2.0)
    cond = float(np.linalg.cond(aw / scale))
    if not np.isfinite(cond) or cond > MAX_CONDITION:
        raise InputError(
            f"{what}: the table angles cannot separate cos α and sin α (condition number {cond:.3g} > "
            f"{MAX_CONDITION:.0e}); use positions spread over the circle, e.g. equally spaced"
        )
    return cond


def fit_harmonic(
    alpha_rad: np.ndarray,
    values: np.ndarray,
    axes: tuple[str, ...],
    *,
    std: np.ndarray | None = None,
    sample_count: np.ndarray | None = None,
    time_s: np.ndarray | None = None,
    bias_model: str = "constant",
    what: str = "fit",
) -> HarmonicFit:
    """Weighted least squares of eq 6–7 over a batch.

    `values` has shape (T, n, k) with k = len(axes) (column j is axis axes[j]). `std` (n, k) is
    the standard error of each position mean: rows are weighted by 1/std² and the covariance is
    (AᵀWA)⁻¹ (noise "given"). Otherwise rows are weighted by `sample_count` (or equally) and the
    covariance is σ̂²(AᵀWA)⁻¹ with σ̂² the weighted residual variance over m − p degrees of
    freedom; with a single axis at n = 4 that is 1 degree of freedom, so σ̂ itself scatters by
    about ±70 % from find to find (NaN when m = p).
    """
    if bias_model not in BIAS_MODELS:
        raise InputError(f"bias_model must be one of {sorted(BIAS_MODELS)}, got {bias_model!r}")
    order = BIAS_MODELS[bias_model]
    y = np.asarray(values, dtype=float)
    trials, n, k = y.shape
    a_mat, names = design_matrix(alpha_rad, axes, time_s, order)
    m, p = a_mat.shape
    if m <= p - 1 or n < 3 + order:
        raise InputError(
            f"{what}: {n} positions are too few for the '{bias_model}' bias model (need ≥ {3 + order})"
        )
    if std is not None:
        sd = np.broadcast_to(np.asarray(std, dtype=float), (n, k))
        if not np.all(np.isfinite(sd)) or np.any(sd <= 0.0):
            raise InputError(f"{what}: standard errors must be finite and > 0")
        w = (1.0 / sd**2).T.reshape(m)
    elif sample_count is not None:
        cnt = np.asarray(sample_count, dtype=float).reshape(n)
        if not np.all(np.isfinite(cnt)) or np.any(cnt <= 0):
            raise InputError(f"{what}: sample counts must be finite and > 0")
        w = np.tile(cnt / cnt.mean(), k)
    else:
        w = np.ones(m)
    check_conditioning(a_mat, w, what)
    aw = a_mat * w[:, None]
    normal_inv = np.linalg.inv(a_mat.T @ aw)
    pinv = normal_inv @ aw.T  # (p, m): one matrix for every trial
    y_rows = y.transpose(0, 2, 1).reshape(trials, m)
    coef = y_rows @ pinv.T
    resid = y_rows - coef @ a_mat.T
    dof = m - p
    r_axes = resid.reshape(trials, k, n)
    rms = {ax: np.sqrt(np.mean(r_axes[:, j, :] ** 2, axis=-1)) for j, ax in enumerate(axes)}
    if std is not None:
        cov = np.broadcast_to(normal_inv, (trials, p, p)).copy()
        noise = "given"
    else:
        s2 = np.sum(w * resid**2, axis=-1) / dof if dof > 0 else np.full(trials, np.nan)
        cov = s2[:, None, None] * normal_inv
        noise = "residuals"
    return HarmonicFit(names, coef, cov, rms, dof, noise)
