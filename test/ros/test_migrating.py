"""docs/migrating.md's example config, config/imu_filter_madgwick.yaml, through the node: with it
the estimator publishes what imu_filter_madgwick computes (its equations, transcribed below from
Madgwick's report and imu_filter_madgwick's ENU conventions), TF included; without it, ours."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from rosharness import fake_tf2, imu_msg, mag_msg, quat, send_one_by_one

from mkf_ros.sim import simulate

pytestmark = pytest.mark.ros
REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "config" / "imu_filter_madgwick.yaml"
T0 = 100.0


# --- imu_filter_madgwick's filter (Madgwick 2010; ENU: gravity (0, 0, 1), field (0, b_xy, b_z)) --
def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _rot(q: np.ndarray) -> np.ndarray:
    """R(q), body → world, with the diagonal written 1 − 2(…) as in Madgwick's objective
    functions (his eq. 25, 29): the same matrix for a unit q, another gradient off the sphere."""
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _gradient(q: np.ndarray, d: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Jᵀ f of Madgwick's objective f(q) = R(q)ᵀ d − s; f is quadratic in q, so a central
    difference gives J exactly."""
    f = _rot(q).T @ d - s
    jac = np.column_stack([_rot(q + e).T @ d - _rot(q - e).T @ d for e in 0.5 * np.eye(4)])
    return jac.T @ f


def madgwick_reference(q: np.ndarray, t: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
                       mag: np.ndarray, gain: float) -> np.ndarray:
    """imu_filter_madgwick's MARG update from ``q`` at ``t[0]``: q̇ = ½ q ⊗ (0, ω) − gain ∇/‖∇‖
    with the field re-estimated from the estimate (h = R(q) m̂), q ← (q + q̇ Δt)/‖·‖."""
    out = [q]
    for k in range(1, len(t)):
        a = acc[k] / np.linalg.norm(acc[k])
        m = mag[k] / np.linalg.norm(mag[k])
        h = _rot(q) @ m
        g = _gradient(q, np.array([0.0, 0.0, 1.0]), a) + _gradient(
            q, np.array([0.0, math.hypot(h[0], h[1]), h[2]]), m)
        q_dot = 0.5 * _qmul(q, np.r_[0.0, gyr[k]]) - gain * g / np.linalg.norm(g)
        q = q + q_dot * (t[k] - t[k - 1])
        q = q / np.linalg.norm(q)
        out.append(q)
    return np.array(out)


def stateless_orientation(a: np.ndarray, m: np.ndarray) -> np.ndarray:
    """imu_filter_madgwick's start (StatelessOrientation, ENU): east H = m × a, north
    M = a × H; the rows of R (body → world) are H, M, a normalised."""
    up = a / np.linalg.norm(a)
    east = np.cross(m, up)
    east /= np.linalg.norm(east)
    return np.vstack([east, np.cross(up, east), up])


def test_the_madgwick_config_reproduces_imu_filter_madgwick(harness, monkeypatch) -> None:
    sent_tf = fake_tf2(monkeypatch)
    rec = simulate("slow_rotation", duration=2.0, rate=100.0, seed=4)
    h = harness(node_kwargs={"cli_args": ["--ros-args", "--params-file", str(CONFIG)]})
    msgs = []
    for k in range(len(rec.t)):  # imu_filter_madgwick fuses pairs: each field with its IMU sample
        msgs += [mag_msg(T0 + rec.t[k], rec.mag[k]), imu_msg(T0 + rec.t[k], rec.gyr[k],
                                                             rec.acc[k])]
    send_one_by_one(h, msgs)
    assert len(h.out) == len(rec.t) and h.est._exceptions == 0
    q = np.array([quat(m) for m in h.out])
    # the start: the closed-form orientation of the first pair
    w, x, y, z = q[0]
    r0 = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                   [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                   [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(r0, stateless_orientation(rec.acc[0], rec.mag[0]), atol=1e-12)
    # then every step: imu_filter_madgwick's update (gain 0.1), to rounding
    ref = madgwick_reference(q[0], T0 + rec.t, rec.gyr, rec.acc, rec.mag, gain=0.1)
    np.testing.assert_allclose(q, ref, atol=1e-12)
    # its orientation_covariance: diag(orientation_stddev²); rates and accelerations passed on
    for m, k in zip(h.out, range(len(rec.t)), strict=True):
        np.testing.assert_array_equal(m.orientation_covariance, np.diag([0.05**2] * 3).ravel())
        v = m.angular_velocity
        assert (v.x, v.y, v.z) == tuple(rec.gyr[k])
    # its TF: odom → the IMU frame, the orientation of each message
    assert len(sent_tf) == len(h.out)
    t = sent_tf[-1]
    assert (t.header.frame_id, t.child_frame_id) == ("odom", "imu_link")
    r = t.transform.rotation
    np.testing.assert_array_equal([r.w, r.x, r.y, r.z], q[-1])


def test_without_it_the_defaults_are_ours(harness, monkeypatch) -> None:
    """The same stream with the default parameters: no TF, the magnetometer not fused (use_mag
    false), the propagated covariance (not a fixed diagonal)."""
    sent_tf = fake_tf2(monkeypatch)
    rec = simulate("slow_rotation", duration=0.2, rate=100.0, seed=4)
    h = harness()
    msgs = []
    for k in range(len(rec.t)):
        msgs += [mag_msg(T0 + rec.t[k], rec.mag[k]), imu_msg(T0 + rec.t[k], rec.gyr[k],
                                                             rec.acc[k])]
    send_one_by_one(h, msgs)
    assert len(h.out) == len(rec.t) and sent_tf == []
    c = h.est.stream.counters
    assert c["mag_unused"] == len(rec.t) and c["mag_fused"] == 0
    cov = np.reshape(h.out[-1].orientation_covariance, (3, 3))
    assert cov[0, 1] != 0.0 and np.all(np.linalg.eigvalsh(cov) > 0)
