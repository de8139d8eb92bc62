"""The per-sample fit over a resumed run's sessions, whose sample counters do not join.

docs/estimators.md §10, "Sessions". A resumed find has one raw IMU log per session; each session's
samples are placed between its own dwells (motion_fit.place_samples, eq M1) and all of them go into
one least squares of eq M2 whose Earth rate, misalignment and wobble are shared and whose bias is
one per session (:func:`session_design`). Pure numpy.
"""

from __future__ import annotations

import numpy as np

from northfinder.errors import InputError
from northfinder.estimators.harmonic import HarmonicFit
from northfinder.estimators.motion_fit import DISTURBED_K, RUN_TERMS, _check_condition, motion_design


def session_design(
    alpha_deg, omega_dps, session, axes: tuple[str, ...], terms: tuple[str, ...] = RUN_TERMS
) -> tuple[np.ndarray, tuple[str, ...]]:
    """motion_design (eq M2) over the samples of several sessions: v_x, v_y (the Earth rate), the
    misalignment and the wobble shared, the bias R_<axis> one per session (`R_<axis>@<s>`).

    Why the bias per session: the sessions' samples are not one record. A new power-on draws a new
    turn-on bias, and even a gyro left on drifts over a gap whose length nothing device-side gives
    (the KVH's sequence counter is 7 bits). What stays is the unit on its mount (δ, the wobble)
    and the Earth rate in the platform frame — the heading."""
    a_mat, names = motion_design(alpha_deg, omega_dps, axes, terms)
    sess = np.asarray(session)
    ids = np.unique(sess)
    rows_of = np.tile(sess, len(axes))  # rows are axis-major (motion_design)
    cols, out = [], []
    for j, name in enumerate(names):
        if name.startswith("R_"):
            for s in ids:
                cols.append(np.where(rows_of == s, a_mat[:, j], 0.0))
                out.append(f"{name}@{int(s)}")
        else:
            cols.append(a_mat[:, j])
            out.append(name)
    return np.column_stack(cols), tuple(out)


def _fit_design(a_mat: np.ndarray, names: tuple[str, ...], rows: np.ndarray,
                axes: tuple[str, ...]) -> tuple[HarmonicFit, np.ndarray]:
    """Least squares of one batch (T = 1) on a given design, noise from the residuals; the fit and
    its residuals (axis-major as `rows`)."""
    _check_condition(a_mat, names)
    normal_inv = np.linalg.inv(a_mat.T @ a_mat)
    coef = normal_inv @ (a_mat.T @ rows)
    resid = rows - a_mat @ coef
    m = rows.size // len(axes)
    dof = rows.size - len(names)
    rms = {ax: np.array([np.sqrt(np.mean(resid[j * m : (j + 1) * m] ** 2))]) for j, ax in enumerate(axes)}
    cov = (float(np.sum(resid**2)) / dof * normal_inv)[None]
    return HarmonicFit(names, coef[None], cov, rms, dof, "residuals"), resid


def fit_motion_sessions(
    alpha_deg, omega_dps, gyro_dph, session, axes: tuple[str, ...] = ("x", "y"), *,
    terms: tuple[str, ...] = RUN_TERMS, k_sigma: float = DISTURBED_K,
) -> tuple[HarmonicFit, np.ndarray, int]:
    """fit_motion_screened over the samples of several sessions (`session` (m,): each sample's
    session number) on session_design: one Earth rate, one mount, a bias per session. A stretch is
    a run of motion samples within one session; the same screening rule (the worst disturbed
    stretch left out, one at a time). Returns (fit, samples kept, stretches left out)."""
    alpha = np.asarray(alpha_deg, dtype=float)
    w = np.asarray(omega_dps, dtype=float)
    y = np.asarray(gyro_dph, dtype=float)
    sess = np.asarray(session)
    k = len(axes)
    if y.shape != (w.size, k) or alpha.shape != w.shape or sess.shape != w.shape:
        raise InputError(f"motion fit: gyro {y.shape} does not match {w.size} angles × {axes} and sessions")
    if not np.all(np.isfinite(y)):
        raise InputError("motion fit: gyro samples contain NaN or inf")
    a_all, names = session_design(alpha, w, sess, axes, terms)
    rows_all = y.T.reshape(-1)
    rest = w == 0.0
    label = np.cumsum(np.r_[0, (np.diff(rest.astype(np.int8)) != 0) | (np.diff(sess) != 0)])
    keep = np.ones(w.size, dtype=bool)
    dropped = 0
    while True:
        sel = np.tile(keep, k)
        fit, _ = _fit_design(a_all[sel], names, rows_all[sel], axes)
        if not np.any(rest):
            return fit, keep, dropped
        r2 = np.sum((rows_all - a_all @ fit.coefficients[0]).reshape(k, w.size) ** 2, axis=0)
        floor = float(np.mean(r2[rest]))
        worst, worst_excess = None, 0.0
        for lab in np.unique(label[keep & ~rest]):
            in_stretch = label == lab
            n = int(in_stretch.sum())
            excess = (np.mean(r2[in_stretch]) / floor - 1.0) / (k_sigma * np.sqrt(2.0 / (n * k)))
            if excess > max(1.0, worst_excess):
                worst, worst_excess = in_stretch, excess
        if worst is None:
            return fit, keep, dropped
        keep &= ~worst
        dropped += 1
