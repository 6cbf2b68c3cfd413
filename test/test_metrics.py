"""mkf_ros.metrics: step angles and the steps the gyro does not explain."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mkf_ros.metrics import step_angles, unexplained_steps


def _about_z(angles: np.ndarray) -> np.ndarray:
    a = np.asarray(angles, dtype=float)
    return np.column_stack([np.cos(a / 2), 0 * a, 0 * a, np.sin(a / 2)])


def test_step_angles_ignore_quaternion_sign():
    q = _about_z(np.radians([0.0, 10.0, 30.0]))
    q[1] *= -1.0
    np.testing.assert_allclose(np.degrees(step_angles(q)), [10.0, 20.0], atol=1e-9)


def test_a_turn_the_gyro_reports_is_explained_and_a_jump_is_not():
    t = np.arange(101) * 0.01
    gyr = np.tile([0.0, 0.0, 1.0], (101, 1))  # 1 rad/s about z
    yaw = t.copy()
    yaw[60:] += math.radians(10.0)  # one 10° jump on top of the turn
    u = unexplained_steps(_about_z(yaw), t, gyr)
    assert u.shape == (100,)
    np.testing.assert_allclose(np.delete(u, 59), 0.0, atol=1e-9)
    assert math.degrees(u[59]) == pytest.approx(10.0, abs=1e-9)


def test_missing_gyro_explains_nothing():
    t = np.array([0.0, 0.1])
    gyr = np.array([[0.0, 0.0, 1.0], [math.nan, math.nan, math.nan]])
    u = unexplained_steps(_about_z([0.0, 0.1]), t, gyr)
    np.testing.assert_allclose(u, [0.1], atol=1e-12)

