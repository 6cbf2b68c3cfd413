"""Gyro bias at rest (mkf_ros.core.gyrocal, docs/math.md §10.2): the mean and its standard error
against a known bias and noise; motion is refused with the reason."""

from __future__ import annotations

import numpy as np
import pytest

from mkf_ros.core.gyrocal import rest_bias

BIAS = np.array([0.01, -0.02, 0.005])
LIMITS = dict(max_gyro_stddev=0.02, max_acc_stddev=0.2)


def _still(n: int = 400, sigma: float = 0.004, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return (BIAS + rng.normal(scale=sigma, size=(n, 3)),
            np.array([0.0, 0.0, 9.81]) + rng.normal(scale=0.03, size=(n, 3)))


def test_bias_and_its_standard_error() -> None:
    g, a = _still()
    r = rest_bias(g, a, **LIMITS)
    np.testing.assert_allclose(r.stddev, 0.004 / np.sqrt(400), rtol=0.15)
    assert np.all(np.abs(r.bias - BIAS) < 4 * r.stddev)
    assert r.n == 400 and "σ" in r.summary()


def test_standard_error_is_honest_over_many_windows() -> None:
    """Over 200 windows the bias errors scatter as the reported σ says (|z| < 3 for 99 %)."""
    z = np.array([(r.bias - BIAS) / r.stddev for r in
                  (rest_bias(*_still(seed=k), **LIMITS) for k in range(200))])
    assert 0.8 < z.std() < 1.2
    assert np.mean(np.abs(z) < 3) > 0.98


def test_motion_is_refused() -> None:
    g, a = _still()
    g[:, 2] += 0.2 * np.sin(np.linspace(0, 6, len(g)))
    with pytest.raises(ValueError, match=r"moved.*gyro z"):
        rest_bias(g, a, **LIMITS)
    g, a = _still()
    a[:, 0] += 1.0 * np.sin(np.linspace(0, 20, len(a)))
    with pytest.raises(ValueError, match=r"moved.*accelerometer"):
        rest_bias(g, a, **LIMITS)


def test_too_few_samples_and_nan_rows() -> None:
    with pytest.raises(ValueError, match="at least 10"):
        rest_bias(np.zeros((5, 3)), None, **LIMITS)
    g, a = _still()
    g[::10] = np.nan
    assert rest_bias(g, a, **LIMITS).n == 360
