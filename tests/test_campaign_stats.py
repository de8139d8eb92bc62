"""Campaign statistics on synthetic data whose answers are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from northfinder.estimators.campaign_stats import deviation_deg, method_statistics, spread, step_statistics


def test_deviation_wraps_across_north():
    assert deviation_deg(359.99, 0.01) == pytest.approx(-0.02)
    assert deviation_deg(0.01, 359.99) == pytest.approx(0.02)
    assert deviation_deg(190.0, 10.0) == pytest.approx(-180.0)  # [−180, 180)


def test_spread_known_answers_in_degrees_and_arc_minutes():
    # ±1′ alternating, plus a 0.5′ bias: mean 0.5′, sample std sqrt(4/3)′, RMS sqrt(1.25)′, max 1.5′
    dev = (np.array([1.0, -1.0, 1.0, -1.0]) + 0.5) / 60.0
    s = spread(dev, [1.0 / 60.0] * 4)
    assert s["n"] == 4
    assert s["mean_arcmin"] == pytest.approx(0.5)
    assert s["std_arcmin"] == pytest.approx(math.sqrt(4.0 / 3.0))
    assert s["rms_arcmin"] == pytest.approx(math.sqrt(1.25))
    assert s["max_abs_arcmin"] == pytest.approx(1.5)
    assert s["mean_deg"] == pytest.approx(0.5 / 60.0)
    assert s["mean_reported_sigma_arcmin"] == pytest.approx(1.0)
    assert s["observed_over_reported"] == pytest.approx(math.sqrt(4.0 / 3.0))


def test_one_run_has_no_std_and_no_ratio():
    s = spread([0.01], [0.02])
    assert s["std_deg"] is None and s["observed_over_reported"] is None
    assert s["rms_deg"] == pytest.approx(0.01) and s["max_abs_deg"] == pytest.approx(0.01)


def _runs(rng: np.random.Generator, n: int, sigma_deg: float, refs: list[float]) -> list[dict]:
    """Finds at each reference: exact ~ N(ref, σ), vector = exact + 0.1°, eq11 = exact − 0.2°."""
    out = []
    for step, ref in enumerate(refs):
        for k in range(n):
            h = (ref + rng.normal(0.0, sigma_deg)) % 360.0
            out.append(
                {
                    "index": step * n + k,
                    "step": step,
                    "reference_deg": ref,
                    "heading_std_deg": sigma_deg,
                    "methods": {"exact": h, "vector": (h + 0.1) % 360.0, "eq11": (h - 0.2) % 360.0},
                }
            )
    return out


def test_method_statistics_recover_the_drawn_spread_and_offsets():
    sigma = 0.01
    n_per = 1000
    runs = _runs(np.random.default_rng(15), n_per, sigma, [0.0, 120.0, 359.995])
    stats = method_statistics(runs, "exact")
    assert list(stats) == ["exact", "vector", "eq11"]  # the METHODS order
    n = 3 * n_per
    # the sample std of n normal draws has relative sd 1/sqrt(2(n-1)); the mean's sd is σ/sqrt(n): 5 sd
    rel = 5.0 / math.sqrt(2 * (n - 1))
    for name, offset in (("exact", 0.0), ("vector", 0.1), ("eq11", -0.2)):
        s = stats[name]
        assert s["n"] == n
        assert s["std_deg"] == pytest.approx(sigma, rel=rel)
        assert s["mean_deg"] == pytest.approx(offset, abs=5 * sigma / math.sqrt(n))
        assert s["rms_deg"] == pytest.approx(math.hypot(offset, sigma), rel=rel)
    assert stats["exact"]["observed_over_reported"] == pytest.approx(1.0, rel=rel)
    assert "mean_reported_sigma_deg" not in stats["vector"]  # only the main method reports a σ


def test_step_statistics_one_row_per_reference():
    runs = _runs(np.random.default_rng(3), 50, 0.02, [10.0, 200.0])
    for r in runs[50:]:  # a 0.05° bias at the second heading only
        r["methods"]["exact"] += 0.05
    steps = step_statistics(runs, "exact")
    assert [s["reference_deg"] for s in steps] == [10.0, 200.0]
    assert [s["n"] for s in steps] == [50, 50]
    tol = 5 * 0.02 / math.sqrt(50)
    assert steps[0]["mean_deg"] == pytest.approx(0.0, abs=tol)
    assert steps[1]["mean_deg"] == pytest.approx(0.05, abs=tol)
