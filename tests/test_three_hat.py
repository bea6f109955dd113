"""The three-cornered hat of bench/three_hat.py against signals whose quality is known."""
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from three_hat import common_signal  # noqa: E402


def _series(gains, noise, n=40000, seed=0):
    rng = np.random.default_rng(seed)
    s = np.cumsum(rng.standard_normal(n)) * 0.05 + rng.standard_normal(n)     # slow and fast parts
    s = (s - s.mean()) / s.std()
    return np.stack([g * s + e * rng.standard_normal(n) for g, e in zip(gains, noise)])


def test_correlations_and_gains_match_the_construction():
    gains, noise = (1.0, 0.6, 2.0), (0.2, 0.5, 1.5)
    out = common_signal(_series(gains, noise))
    want_rho = [g / np.hypot(g, e) for g, e in zip(gains, noise)]
    np.testing.assert_allclose(out["rho"], want_rho, atol=0.01)
    for i in range(3):
        for j in range(3):
            assert out["gain"][i, j] == pytest.approx(gains[i] / gains[j], rel=0.03)


def test_a_noisy_reference_bounds_the_correlation_and_attenuates_the_slope():
    # a perfect measurement (0 noise) against a noisy reference: r = rho of the reference, slope rho² g_i / g_j
    x = _series((1.0, 1.0, 1.0), (0.0, 0.7, 0.3), seed=1)
    r = np.corrcoef(x[0], x[1])[0, 1]
    out = common_signal(x)
    assert r == pytest.approx(out["rho"][1], abs=0.01)
    assert np.polyfit(x[1], x[0], 1)[0] == pytest.approx(out["rho"][1] ** 2 * out["gain"][0, 1], rel=0.03)
    assert out["gain"][0, 1] == pytest.approx(1.0, rel=0.03)


def test_refuses_other_than_three_series():
    with pytest.raises(ValueError, match="three series"):
        common_signal(np.zeros((2, 10)))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(0.1, 10.0), min_size=3, max_size=3), st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3))
def test_rho_does_not_change_with_each_series_units(scales, offsets):
    x = _series((1.0, 0.8, 1.3), (0.3, 0.6, 0.4), n=2000, seed=2)
    y = x * np.array(scales)[:, None] + np.array(offsets)[:, None]
    np.testing.assert_allclose(common_signal(y)["rho"], common_signal(x)["rho"], atol=1e-9)
