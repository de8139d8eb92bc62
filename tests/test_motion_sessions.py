"""The per-sample fit over a resumed run's sessions (estimators.motion_sessions): one Earth rate,
one mount, a bias per session. Synthetic samples on a plan schedule (estimators.plan), white noise
of a known σ, so every tolerance is the fit's own σ."""

from __future__ import annotations

import numpy as np
import pytest

from northfinder.estimators import plan as P
from northfinder.estimators.motion_fit import RUN_TERMS, fit_motion_screened, motion_design
from northfinder.estimators.motion_sessions import fit_motion_sessions, session_design

AXES = ("x", "y")
TRUE = {"v_x": -6.8, "v_y": 9.45, "d_x": -0.01, "d_y": 0.08, "w_c": 0.03, "w_s": 0.0}
SIGMA_DPH = 3.8  # one sample's white noise (nav grade at 1 kHz)


def _schedule() -> tuple[np.ndarray, np.ndarray, int]:
    """α, ω of a positions+motion plan (8 × 5 s at 100 Hz) and the index of a rest sample in the
    third dwell, where the run is split into two sessions."""
    sch = P.schedule(P.PlanSpec("positions+motion", 8, 5.0), P.Stage(), 0.01)
    keep = sch.gyro_used
    alpha, omega, rest = sch.alpha_deg[keep], sch.omega_dps[keep], sch.rest[keep]
    starts = np.flatnonzero(np.diff(rest.astype(np.int8)) == 1) + 1  # first sample of each later rest
    return alpha, omega, int(starts[1] + 10)


def _samples(alpha, omega, session, biases, rng) -> np.ndarray:
    a_mat, names = session_design(alpha, omega, session, AXES, RUN_TERMS)
    x = np.array([TRUE.get(n, biases.get(n, 0.0)) for n in names])
    return (a_mat @ x + rng.normal(0.0, SIGMA_DPH, a_mat.shape[0])).reshape(len(AXES), -1).T


def test_a_bias_per_session_recovers_the_earth_rate_a_shared_bias_does_not():
    """Session 2 comes back with a turn-on bias 0.5 °/h away on each axis: the per-session fit's
    v_x, v_y are within 4σ (its own σ) of the truth, the fit that assumes one bias is off by more."""
    alpha, omega, cut = _schedule()
    session = np.where(np.arange(alpha.size) < cut, 1, 2)
    biases = {"R_x@1": 0.004, "R_y@1": -0.003, "R_x@2": 0.504, "R_y@2": -0.503}
    y = _samples(alpha, omega, session, biases, np.random.default_rng(7))
    fit, kept, dropped = fit_motion_sessions(alpha, omega, y, session, AXES)
    assert dropped == 0 and kept.all()
    assert fit.names[:2] == ("v_x", "v_y") and "R_x@1" in fit.names and "R_y@2" in fit.names
    sd = np.sqrt(np.diag(fit.covariance[0]))
    for j, name in enumerate(("v_x", "v_y")):
        assert abs(fit.coef(name)[0] - TRUE[name]) < 4.0 * sd[j]
    for name, b in biases.items():
        k = fit.names.index(name)
        assert abs(fit.coef(name)[0] - b) < 4.0 * sd[k]
    shared, _, _ = fit_motion_sessions(alpha, omega, y, np.ones_like(session), AXES)
    sd_shared = np.sqrt(np.diag(shared.covariance[0]))
    off = [abs(shared.coef(n)[0] - TRUE[n]) / sd_shared[j] for j, n in enumerate(("v_x", "v_y"))]
    assert max(off) > 4.0, off


def test_one_session_is_the_one_session_fit():
    """With every sample in one session the design and the fit are fit_motion_screened's."""
    alpha, omega, _ = _schedule()
    one = np.ones(alpha.size, dtype=int)
    a_mat, names = session_design(alpha, omega, one, AXES, RUN_TERMS)
    ref_mat, ref_names = motion_design(alpha, omega, AXES, RUN_TERMS)
    assert names == tuple(n + "@1" if n.startswith("R_") else n for n in ref_names)
    np.testing.assert_array_equal(a_mat, ref_mat)
    y = _samples(alpha, omega, one, {"R_x@1": 0.004, "R_y@1": -0.003}, np.random.default_rng(3))
    fit, _, _ = fit_motion_sessions(alpha, omega, y, one, AXES)
    ref, _, _ = fit_motion_screened(alpha, omega, y, AXES, terms=RUN_TERMS)
    np.testing.assert_allclose(fit.coefficients, ref.coefficients, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fit.covariance, ref.covariance, rtol=1e-9, atol=1e-18)


def test_a_knock_on_one_move_of_session_2_leaves_out_that_stretch_alone():
    """A 40 °/h knock on the first move of session 2: that stretch alone is left out."""
    alpha, omega, cut = _schedule()
    session = np.where(np.arange(alpha.size) < cut, 1, 2)
    y = _samples(alpha, omega, session, {}, np.random.default_rng(11))
    moving = np.flatnonzero((omega != 0) & (session == 2))
    first = moving[: np.argmax(np.diff(moving) > 1) + 1]
    y[first, 0] += 40.0
    fit, kept, dropped = fit_motion_sessions(alpha, omega, y, session, AXES)
    assert dropped == 1
    assert not kept[first].any() and kept[np.setdiff1d(np.arange(alpha.size), first)].all()


def test_mismatched_shapes_are_one_input_error():
    from northfinder.errors import InputError

    alpha, omega, _ = _schedule()
    with pytest.raises(InputError, match="sessions"):
        fit_motion_sessions(alpha, omega, np.zeros((alpha.size, 2)), np.ones(3), AXES)
