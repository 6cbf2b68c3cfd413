"""The estimator node runs the seed report's baselines (docs/baselines.md) and switches to and from
them at runtime through SetParameters, like any other algorithm."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rosharness import imu_msg, mag_msg, quat
from sensor_msgs.msg import Imu

from mkf_ros.evaluation.metrics import orientation_errors
from mkf_ros.sim import simulate

pytestmark = pytest.mark.ros
T0 = 100.0
CHAIN = ["mekf", "madgwick", "euler_kf", "euler_ukf", "mukf", "madgwick", "mekf"]


def test_switch_through_the_baselines_mid_stream(harness) -> None:
    """9D with a 25 Hz magnetometer (separate messages, so Madgwick's held-sample path is
    used), the algorithm switched every second: every switch is accepted, every IMU message
    still gives one finite output, and the estimate stays within 2° of the truth (sensor-noise
    level: 0.3° tilt and 1.1° heading per sample, see test/core/test_baselines.py)."""
    rec = simulate("slow_rotation", duration=len(CHAIN) * 1.0, rate=100.0, seed=6,
                   mag_rate=25.0)
    h = harness({"use_mag": True, "algorithm": CHAIN[0]})
    for i, algo in enumerate(CHAIN):
        if i:
            res = h.set(algorithm=algo)[0]
            assert res.successful, res.reason
            assert h.get("algorithm") == [algo]
            assert h.est.stream.filter.params.algorithm == algo
        msgs: list = []
        for k in range(100 * i, min(100 * (i + 1), len(rec.t))):
            msgs.append(imu_msg(T0 + rec.t[k], rec.gyr[k], rec.acc[k]))
            if not math.isnan(rec.mag[k, 0]):
                msgs.append(mag_msg(T0 + rec.t[k], rec.mag[k]))
        h.send(msgs)
        assert len(h.out) == sum(isinstance(m, Imu) for m in msgs) + 100 * i
    q = np.array([quat(m) for m in h.out])
    assert np.isfinite(q).all()
    assert all(np.isfinite(m.orientation_covariance).all() for m in h.out)
    err = np.degrees(orientation_errors(q[50:], rec.quat[50:len(q)])["total"])
    assert err.max() < 2.0, err.max()
    assert h.est._exceptions == 0
