"""mkf_ros.estimate(): the offline contract and its errors."""

from __future__ import annotations

import numpy as np
import pytest

import mkf_ros
from mkf_ros.sim import simulate


@pytest.fixture(scope="module")
def sim():
    return simulate("slow_rotation", duration=5, rate=100, seed=0)


def test_result_shapes_and_contents(sim) -> None:
    r = mkf_ros.estimate(sim.gyr, sim.acc, sim.mag, dt=0.01, estimate_gyro_bias=True)
    n = sim.t.size
    assert r.quat.shape == (n, 4) and r.cov.shape == (n, 3, 3) and r.omega.shape == (n, 3)
    assert r.bias.shape == (n, 3) and r.bias_std.shape == (n, 3) and r.initialized.all()
    np.testing.assert_allclose(np.linalg.norm(r.quat, axis=1), 1.0, atol=1e-12)
    assert (r.quat[:, 0] >= 0).all()
    assert r.params.use_mag is True  # giving mag implies use_mag
    assert r.counters["samples"] == n
    np.testing.assert_allclose(r.omega[-1], sim.omega[-1], atol=0.05)


def test_timestamps_equal_dt(sim) -> None:
    a = mkf_ros.estimate(sim.gyr, sim.acc, dt=0.01)
    b = mkf_ros.estimate(sim.gyr, sim.acc, timestamps=100.0 + sim.t)
    np.testing.assert_allclose(a.quat, b.quat, atol=1e-12)


def test_nan_rows_are_missing_samples(sim) -> None:
    """An asynchronous 10 Hz magnetometer is expressed with NaN rows."""
    mag = sim.mag.copy()
    mag[np.arange(mag.shape[0]) % 10 != 0] = np.nan
    acc = sim.acc.copy()
    acc[50] = 0.0
    r = mkf_ros.estimate(sim.gyr, acc, mag, dt=0.01)
    assert np.isfinite(r.quat).all() and np.isfinite(r.cov).all()
    assert r.counters["mag_missing"] == 450 and r.counters["acc_invalid"] == 1


@pytest.mark.parametrize("kwargs,match", [
    ({"gyr": np.zeros((10, 2))}, r"gyr must have shape \(N, 3\), got \(10, 2\)"),
    ({"acc": np.zeros((9, 3))}, r"acc has 9 samples, expected 10"),
    ({"mag": np.zeros((11, 3))}, r"mag has 11 samples, expected 10"),
    ({"acc": "abc"}, r"acc must be a numeric array"),
    ({"gyr_inf": 7}, r"gyr\[7\] contains an infinite value"),
    ({"dt": 0.0}, r"dt must be a positive finite number"),
    ({"dt": float("nan")}, r"dt must be a positive finite number"),
    ({"dt": None}, r"give exactly one of dt"),
    ({"timestamps": np.arange(10.0)}, r"give exactly one of dt"),
    ({"dt": None, "timestamps": np.r_[0, 1, 2, 2, 4, 5, 6, 7, 8, 9.0]},
     r"timestamps\[3\] = 2 is not after timestamps\[2\] = 2"),
    ({"dt": None, "timestamps": np.r_[0, 1, 2, np.nan, 4, 5, 6, 7, 8, 9.0]},
     r"timestamps\[3\] is not finite"),
    ({"dt": None, "timestamps": np.arange(9.0)}, r"timestamps must have shape \(10,\)"),
    ({"algorithm": "ekf"},
     r"algorithm must be one of mekf, mukf, euler_kf, euler_ukf, madgwick, got 'ekf'"),
    ({"gyro_noise": -1}, r"gyro_noise must be in \[1e-06, 10\] rad/s, got -1"),
    ({"turbo": True}, r"unknown filter parameter 'turbo'"),
    ({"use_mag": True}, r"use_mag=True needs mag"),
])
def test_bad_input_is_one_clear_error(kwargs: dict, match: str) -> None:
    args = {"gyr": np.zeros((10, 3)), "acc": np.tile([0, 0, 9.8], (10, 1)), "mag": None,
            "dt": 0.01}
    if "gyr_inf" in kwargs:
        args["gyr"][kwargs.pop("gyr_inf")] = np.inf
    args.update(kwargs)
    gyr, acc, mag = args.pop("gyr"), args.pop("acc"), args.pop("mag")
    with pytest.raises(ValueError, match=match):
        mkf_ros.estimate(gyr, acc, mag, **args)
