"""Quaternion algebra (docs/math.md §1)."""

from __future__ import annotations

import numpy as np
from core_strategies import unit_quaternions, vectors
from hypothesis import given, settings

from mkf_ros.core.quaternion import (
    angle_between,
    q_from_rotvec,
    q_omega,
    qconj,
    qconj_mul,
    qmul,
    qnormalize,
    rotate,
    rotate_inv,
    rotmat,
    rotmat_np,
    skew,
)


def test_hamilton_units() -> None:
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    np.testing.assert_allclose(qmul(i, j), k)  # ij = k (Hamilton, not Shuster's ⊗, §1.1)
    np.testing.assert_allclose(qmul(j, i), -k)
    np.testing.assert_allclose(qmul(i, i), [-1, 0, 0, 0])


@settings(max_examples=200, deadline=None)
@given(unit_quaternions(), unit_quaternions(), vectors())
def test_rotation_matrix_properties(p: np.ndarray, q: np.ndarray, v: np.ndarray) -> None:
    R = rotmat(q)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0.999999
    np.testing.assert_allclose(rotmat(qmul(p, q)), rotmat(p) @ R, atol=1e-12)  # R(p*q) = R(p)R(q)
    np.testing.assert_allclose(rotmat(-q), R, atol=1e-15)
    np.testing.assert_allclose(rotmat(qconj(q)), R.T, atol=1e-15)
    # (0, v_E) = q * (0, v_B) * q*  ⇔  v_E = R(q) v_B   (§1.2)
    vq = qmul(qmul(q, np.r_[0.0, v]), qconj(q))
    np.testing.assert_allclose(vq[1:], rotate(q, v), atol=1e-12)
    np.testing.assert_allclose(rotate_inv(q, rotate(q, v)), v, atol=1e-12)
    np.testing.assert_allclose(qconj_mul(p, q), qmul(qconj(p), q), atol=1e-15)
    np.testing.assert_allclose(rotmat_np(q[None])[0], R, atol=1e-15)
    np.testing.assert_allclose(skew(v) @ p[1:], np.cross(v, p[1:]), atol=1e-15)


def test_rotation_frame_convention() -> None:
    """A +90° yaw maps the body x axis to the world y axis (body → world, §1.2)."""
    q = q_from_rotvec(np.array([0.0, 0.0, np.pi / 2]))
    np.testing.assert_allclose(rotate(q, np.array([1.0, 0, 0])), [0, 1, 0], atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(vectors(scale=5.0))
def test_q_omega_is_the_exponential(w: np.ndarray) -> None:
    dt = 0.01
    q = q_omega(w, dt)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-14
    np.testing.assert_allclose(angle_between(q, np.array([1.0, 0, 0, 0])),
                               np.linalg.norm(w) * dt, atol=1e-12)
    # ten steps of a constant rate equal one step of ten times the length (right increments)
    qs = np.array([1.0, 0, 0, 0])
    for _ in range(10):
        qs = qnormalize(qmul(qs, q))
    np.testing.assert_allclose(angle_between(qs, q_omega(w, 10 * dt)), 0.0, atol=1e-7)


def test_q_omega_small_rate_is_finite() -> None:
    for w in (np.zeros(3), np.full(3, 1e-300), np.array([1e-9, 0, 0])):
        q = q_omega(w, 0.01)
        assert np.all(np.isfinite(q))
        np.testing.assert_allclose(q[1:], w * 0.005, atol=1e-20)


def test_up_in_body_is_the_world_vertical_in_body_axes() -> None:
    """``up_in_body_t(q) = R(q)ᵀ e_z`` (numpy's rotation matrix), bit for bit the third row
    of ``rotmat_t``."""
    from mkf_ros.core.quaternion import rotmat_np, rotmat_t, up_in_body_t

    rng = np.random.default_rng(7)
    for _ in range(100):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        u = np.array(up_in_body_t(tuple(q)))
        np.testing.assert_allclose(u, rotmat_np(q).T @ [0.0, 0.0, 1.0], atol=1e-15)
        assert tuple(u) == rotmat_t(tuple(q))[2]
