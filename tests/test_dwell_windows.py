"""estimators.dwell.DisturbanceWindows: the dwell's disturbance test built as the samples arrive
equals the batch test on the whole dwell, bit for bit, however the samples are chunked."""

from __future__ import annotations

import numpy as np
import pytest

from northfinder.estimators.dwell import DisturbanceWindows, disturbance_valid


@pytest.mark.parametrize("seed", range(12))
def test_chunked_windows_equal_the_batch_test(seed):
    rng = np.random.default_rng(seed)
    n, w = int(rng.integers(50, 6000)), int(rng.integers(10, 150))
    x = rng.normal(size=(n, 6)) * rng.uniform(0.1, 10, size=6) + rng.uniform(-5, 5, size=6)
    if seed % 3 == 0:
        x[:, 2] = np.nan  # an axis the unit lacks
    if seed % 2 == 0:
        x[n // 2 : n // 2 + w, 1] += 8.0  # a bump the test must find in the same window
    windows = DisturbanceWindows(w)
    pos = 0
    while pos < n:
        k = int(rng.integers(1, 700))
        windows.add(x[pos : pos + k])
        pos += k
    assert windows.z() == disturbance_valid(x, w)


def test_a_column_mixing_valid_and_flagged_samples_leaves_it_to_the_batch_test():
    x = np.random.default_rng(1).normal(size=(500, 3))
    x[7, 0] = np.nan
    windows = DisturbanceWindows(20)
    windows.add(x[:250])
    windows.add(x[250:])
    assert windows.z() is None
    whole = DisturbanceWindows(20)
    whole.add(np.where(np.isnan(x), 0.0, x)[:250])
    whole.add(np.full((250, 3), np.nan))  # a column turning all-NaN in a later chunk is mixed too
    assert whole.z() is None
