"""The per-sample motion fit (docs/estimators.md §10): the z-gyro angle pinned to the encoder, the
misalignment term δ·ω estimated or cancelled, and what ignoring it costs. The synthetic data come
from tools/plan_vs_limit.py's own forward model (CONVENTIONS.md frames, written out there)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from northfinder.errors import InputError
from northfinder.estimators import plan as P
from northfinder.estimators.motion_fit import fit_motion, motion_design, table_angle_from_z
from tests.helpers import load_tool

TOOL = load_tool("plan_vs_limit")
LAT, TILT, HEADING = 40.0, 2.0, 37.0
ONE_WAY = P.Stage(return_to_start=False)


def _one_way_plan() -> P.PlanSpec:
    return P.PlanSpec("positions+motion", 8, P.positions_dwell_for(240.0, 8, ONE_WAY))


def _headings(spec, stage, sensor, err, trials, terms, seed=5, rate_hz=50.0):
    sch = P.schedule(spec, stage, 1.0 / rate_hz)
    rng = np.random.default_rng(seed)
    gyro, accel = TOOL.simulate_samples(rng, trials, sch, sensor, err, HEADING, LAT, TILT, 90.0)
    return TOOL.headings_motion(sch, gyro, accel, sensor, LAT, terms) - HEADING


def test_z_gyro_angle_is_pinned_to_the_encoder_and_takes_out_the_scale_factor():
    """300 ppm scale factor + 100 ppm asymmetry on z, a 0.3 °/h z bias: the angle through every move
    stays on the true one (the pin removes scale and asymmetry move by move)."""
    sch = P.schedule(_one_way_plan(), ONE_WAY, 0.01)
    quiet = replace(P.GRADES["nav"], arw_deg_rt_h=1e-9, bias_instability_dph=0.0, rrw_dph_rt_h=0.0)
    err = TOOL.MotionErrors(sf_z_ppm=300.0, sf_z_asym_ppm=100.0, bias_dph=(0.0, 0.0, 0.3))
    gyro, _ = TOOL.simulate_samples(np.random.default_rng(1), 1, sch, quiet, err, HEADING, LAT, TILT, 90.0)
    enc = np.where(sch.rest, sch.alpha_deg, np.nan)
    alpha, omega = table_angle_from_z(gyro[0, :, 2], sch.dt_s, enc)
    assert np.max(np.abs(alpha - sch.alpha_deg)) < 2e-3  # deg, from a half-sample rate step at most
    moving = ~sch.rest
    assert np.max(np.abs(omega[moving] - sch.omega_dps[moving])) < 1e-3
    # without the pin (raw integral) the scale factor alone leaves 315° × 400 ppm = 0.13°
    raw = np.cumsum(gyro[0, :, 2] / 3600.0 - np.mean(gyro[0, sch.rest, 2] / 3600.0)) * sch.dt_s
    assert abs(raw[-1] - sch.alpha_deg[-1]) > 0.1


def test_ignoring_the_misalignment_is_biased_and_the_full_fit_is_not_noise_free():
    """δ = 2e-4 rad on x (−1.5e-4 on y), one-way stop-and-go with motion samples, no noise: the
    fit without motion terms is off by far more than the nav σ; the full fit by nothing."""
    quiet = replace(P.GRADES["nav"], arw_deg_rt_h=1e-7, bias_instability_dph=0.0, rrw_dph_rt_h=0.0,
                    accel_noise_ug_rt_hz=0.0)  # fmt: skip
    err = TOOL.MotionErrors()
    ignored = _headings(_one_way_plan(), ONE_WAY, quiet, err, 1, ())
    full = _headings(_one_way_plan(), ONE_WAY, quiet, err, 1, ("misalignment",))
    sigma = P.predict(_one_way_plan(), P.GRADES["nav"], LAT, TILT, ONE_WAY).sigma_deg
    assert abs(ignored[0]) > 1.5 * sigma, ignored
    assert abs(full[0]) < 0.01 * sigma, full
    # and with δ = 0 the fit without motion terms is right: the bias is δ's
    none = _headings(_one_way_plan(), ONE_WAY, quiet, replace(err, delta_x=0.0, delta_y=0.0), 1, ())
    assert abs(none[0]) < 0.01 * sigma


def test_monte_carlo_bias_with_and_without_motion_terms():
    """Nav noise, 150 trials: ignoring δ = 2e-4 is biased by many standard errors; the full fit's
    bias is within 3 standard errors of 0 (the standard error is σ/√trials)."""
    nav, err, trials = P.GRADES["nav"], TOOL.MotionErrors(), 150
    ignored = _headings(_one_way_plan(), ONE_WAY, nav, err, trials, ())
    full = _headings(_one_way_plan(), ONE_WAY, nav, err, trials, ("misalignment",), seed=6)
    se_ign = np.std(ignored, ddof=1) / math.sqrt(trials)
    se_full = np.std(full, ddof=1) / math.sqrt(trials)
    assert abs(np.mean(ignored)) > 6 * se_ign
    assert abs(np.mean(full)) < 3 * se_full


def test_the_sweep_cancels_the_misalignment_by_closing_its_path():
    """A sweep turns both ways and ends where it began (the return move): over the closed path
    ∫ω dt = 0 and ∫ω·cos α dt = ∫cos α dα = 0 (likewise sin), so the δ·ω column is orthogonal to
    the bias and the harmonic and even the fit that ignores δ is unbiased (noise-free); the full
    fit too. (A one-way plan does not close its path: see the test above.)"""
    quiet = replace(P.GRADES["nav"], arw_deg_rt_h=1e-7, bias_instability_dph=0.0, rrw_dph_rt_h=0.0,
                    accel_noise_ug_rt_hz=0.0)  # fmt: skip
    stage = P.Stage()
    sweep = P.PlanSpec("sweep", 4, P.sweep_dwell_for(240.0, 4, stage), "zigzag")
    sigma = P.predict(sweep, P.GRADES["nav"], LAT, TILT, stage).sigma_deg
    ignored = _headings(sweep, stage, quiet, TOOL.MotionErrors(), 1, ())
    full = _headings(sweep, stage, quiet, TOOL.MotionErrors(), 1, ("misalignment",))
    # both within 2 % of σ (as the continuous sweep this plan replaced): what is left, the same with
    # and without the δ columns, is not δ's
    assert abs(ignored[0]) < 0.02 * sigma, ignored
    assert abs(full[0]) < 0.02 * sigma, full
    sch = P.schedule(sweep, stage, 0.02)
    used = sch.gyro_used  # what the fit sees: the first rest to the rest after the return
    a_mat, names = motion_design(sch.alpha_deg[used], sch.omega_dps[used], ("x", "y"))
    cols = a_mat / np.linalg.norm(a_mat, axis=0)
    gram = cols.T @ cols
    d = [names.index("d_x"), names.index("d_y")]
    others = [i for i in range(len(names)) if i not in d]
    assert np.max(np.abs(gram[np.ix_(d, others)])) < 0.01


def test_motion_terms_without_motion_are_one_clear_error():
    alpha = np.repeat([0.0, 90.0, 180.0, 270.0], 10)
    gyro = np.zeros((alpha.size, 2))
    with pytest.raises(InputError, match="no motion"):
        fit_motion(alpha, np.zeros_like(alpha), gyro)
    with pytest.raises(InputError, match="start and end at rest"):
        table_angle_from_z(np.zeros(5), 0.01, np.array([np.nan, 0, 0, 0, 0]))
    with pytest.raises(InputError, match="motion terms"):
        motion_design(alpha, np.zeros_like(alpha), ("x", "y"), ("tumble",))


def _stream_with_dwells(rate_hz: float = 100.0):
    """A sample-indexed stream of the one-way plan: indices from 1000, the dwells (the rest samples
    that are not the settle part) as (first, last, encoder)."""
    sch = P.schedule(_one_way_plan(), ONE_WAY, 1.0 / rate_hz)
    quiet = replace(P.GRADES["nav"], arw_deg_rt_h=1e-9, bias_instability_dph=0.0, rrw_dph_rt_h=0.0)
    err = TOOL.MotionErrors(sf_z_ppm=300.0, sf_z_asym_ppm=100.0, bias_dph=(0.0, 0.0, 0.3))
    gyro, _ = TOOL.simulate_samples(np.random.default_rng(2), 1, sch, quiet, err, HEADING, LAT, TILT, 90.0)
    idx = np.arange(sch.alpha_deg.size) + 1000
    # a dwell = the last `dwell_s` of every rest stretch (the settle/restart before it counts as motion)
    n_dwell = int(round(_one_way_plan().dwell_s * rate_hz))
    stops = np.flatnonzero(np.diff(np.r_[sch.rest.astype(int), 0]) == -1)
    dwells = [(int(idx[b - n_dwell + 1]), int(idx[b]), float(sch.alpha_deg[b])) for b in stops]
    return sch, idx, gyro[0], dwells


def test_place_samples_puts_every_sample_between_dwells_at_its_angle():
    """The run's layout (dwells with encoder readings, the stream between them) gives every sample
    its table angle: on the true angle within the half-sample step, with the true rate."""
    from northfinder.estimators.motion_fit import place_samples

    sch, idx, gyro, dwells = _stream_with_dwells()
    alpha, omega, g, counts = place_samples(idx, gyro, dwells, 100.0)
    first, last = dwells[0][0] - 1000, dwells[-1][1] - 1000
    truth_alpha = sch.alpha_deg[first : last + 1]
    assert counts["rest"] + counts["motion"] == last - first + 1 and counts["stretches_dropped"] == 0
    assert alpha.size == truth_alpha.size
    # the samples come back in stream order (dwell, stretch, dwell, …): sample for sample, within
    # the bounds of test_z_gyro_angle_is_pinned_to_the_encoder… (same grid, same errors)
    assert np.max(np.abs(alpha - truth_alpha)) < 2e-3
    assert np.max(np.abs(omega - sch.omega_dps[first : last + 1])) < 1e-3


def test_place_samples_leaves_out_a_stretch_with_a_lost_or_invalid_sample():
    """A lost sample (index gap) or a NaN in a stretch between two dwells: that stretch cannot be
    integrated and is dropped; the dwells on both sides and the other stretches stay."""
    from northfinder.estimators.motion_fit import place_samples

    sch, idx, gyro, dwells = _stream_with_dwells()
    _, _, _, full = place_samples(idx, gyro, dwells, 100.0)
    mid = (dwells[2][1] + dwells[3][0]) // 2 - 1000
    keep = np.ones(idx.size, bool)
    keep[mid] = False
    _, _, _, lost = place_samples(idx[keep], gyro[keep], dwells, 100.0)
    assert lost["stretches_dropped"] == 1 and lost["rest"] == full["rest"]
    stretch = dwells[3][0] - dwells[2][1] - 1
    assert lost["motion"] == full["motion"] - stretch
    bad = gyro.copy()
    bad[(dwells[4][1] + dwells[5][0]) // 2 - 1000, 0] = np.nan
    _, _, _, invalid = place_samples(idx, bad, dwells, 100.0)
    assert invalid["stretches_dropped"] == 1
    with pytest.raises(InputError, match="two dwells"):
        place_samples(idx, gyro, dwells[:1], 100.0)


def test_a_knock_while_the_table_turns_is_screened_out():
    """A 1 s knock (a 300 °/h half-sine on x and y) while the table turns: the dwells would be
    re-measured for it, the motion samples are not — the screened fit leaves that stretch out and
    lands within 3σ of the truth, the unscreened one does not; with no knock nothing is left out."""
    from northfinder.estimators.motion_fit import RUN_TERMS, fit_motion_screened, place_samples

    rate = 100.0
    sch, idx, gyro, dwells = _stream_with_dwells(rate)
    noise_dph = P.GRADES["nav"].arw_deg_rt_h * 60.0 * math.sqrt(rate)  # per-sample σ (ARW·60·√rate)
    rng = np.random.default_rng(11)
    noisy = gyro + rng.normal(0.0, noise_dph, gyro.shape) * np.array([1.0, 1.0, 0.0])
    alpha, omega, g, _ = place_samples(idx, noisy, dwells, rate)
    fit0, keep0, dropped0 = fit_motion_screened(alpha, omega, g[:, :2])
    assert dropped0 == 0 and keep0.all()
    knocked = noisy.copy()
    mid = dwells[3][1] - 1000 + int(np.argmax(sch.omega_dps[dwells[3][1] - 1000 :] > 0))  # the move's start
    pulse = 300.0 * np.sin(np.pi * np.arange(int(rate)) / rate)
    knocked[mid : mid + int(rate), 0] += pulse
    knocked[mid : mid + int(rate), 1] -= pulse
    alpha, omega, g, _ = place_samples(idx, knocked, dwells, rate)
    screened, _, dropped = fit_motion_screened(alpha, omega, g[:, :2])
    plain = fit_motion(alpha, omega, g[:, :2], terms=RUN_TERMS)
    assert dropped == 1
    truth = fit0.coefficients[0, :2]  # the fit of the same noise without the knock
    sd = np.sqrt(np.diag(screened.covariance[0])[:2])
    assert np.all(np.abs(screened.coefficients[0, :2] - truth) < 3.0 * sd)
    assert np.any(np.abs(plain.coefficients[0, :2] - truth) > 3.0 * sd)
