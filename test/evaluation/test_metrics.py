"""mkf_ros.evaluation.metrics: step angles and the steps the gyro does not explain."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mkf_ros.evaluation.metrics import step_angles, unexplained_steps


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


def test_a_rate_change_explains_half_of_it_over_the_previous_interval():
    """The rate ramps from 20 to 40 rad/s between two readings 10 ms apart: the previous
    interval turned by the trapezoid, 0.30 rad, not the 0.20 of its reading; a filter that
    learns of it at the later reading moves the 0.10 into that step, whose own interval
    turns 0.40: a 0.50 rad step is explained, 0.51 leaves 0.01 unexplained."""
    t = np.array([0.0, 0.01, 0.02])
    gyr = np.array([[0.0, 0.0, 20.0], [0.0, 0.0, 20.0], [0.0, 0.0, 40.0]])
    u = unexplained_steps(_about_z([0.0, 0.2, 0.7]), t, gyr)
    np.testing.assert_allclose(u, [0.0, 0.0], atol=1e-12)
    u = unexplained_steps(_about_z([0.0, 0.2, 0.71]), t, gyr)
    np.testing.assert_allclose(u, [0.0, 0.01], atol=1e-12)


def test_missing_gyro_explains_nothing():
    t = np.array([0.0, 0.1])
    gyr = np.array([[0.0, 0.0, 1.0], [math.nan, math.nan, math.nan]])
    u = unexplained_steps(_about_z([0.0, 0.1]), t, gyr)
    np.testing.assert_allclose(u, [0.1], atol=1e-12)



def _axis(i: int, angle: float) -> np.ndarray:
    q = np.zeros(4)
    q[0], q[1 + i] = math.cos(angle / 2), math.sin(angle / 2)
    return q


def test_roll_pitch_yaw_inverts_z_y_x_composition():
    """q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll) (tf2's setRPY) gives back (roll, pitch, yaw)."""
    from mkf_ros.core.quaternion import qmul_np
    from mkf_ros.evaluation.metrics import roll_pitch_yaw

    rng = np.random.default_rng(5)
    angles = np.column_stack([rng.uniform(-3.1, 3.1, 50), rng.uniform(-1.5, 1.5, 50),
                              rng.uniform(-3.1, 3.1, 50)])
    q = np.array([qmul_np(_axis(2, y), qmul_np(_axis(1, p), _axis(0, r)))
                  for r, p, y in angles])
    np.testing.assert_allclose(roll_pitch_yaw(q), angles, atol=1e-9)
    np.testing.assert_allclose(roll_pitch_yaw(-q[0]), angles[0], atol=1e-9)  # sign ignored
    np.testing.assert_allclose(roll_pitch_yaw([math.cos(0.5), 0.0, math.sin(0.5), 0.0]),
                               [0.0, 1.0, 0.0], atol=1e-12)  # 1 rad pitch, literal


def test_a_dropped_message_explains_the_rate_between_its_neighbours():
    """Readings every 5 ms at 18.5 rad/s, then one 42 ms apart (messages dropped) reading
    4.4 rad/s (the AR.Drone bag's flip): the continuous rate went from one to the other over
    the gap, which turned by at least the trapezoid, ½ (18.5 + 4.4) × 0.042 = 0.4809 rad,
    plus the previous interval's ramp ½ × 14.1 × 0.005; the later reading's own 4.4 × 0.042
    would leave 0.30 rad "unexplained". A step beyond both is still reported."""
    t = np.array([0.0, 0.005, 0.010, 0.052])
    gyr = np.array([[0.0, 0.0, 18.5]] * 3 + [[0.0, 0.0, 4.4]])
    explained = 0.5 * (18.5 + 4.4) * 0.042 + 0.5 * 14.1 * 0.005
    yaw = np.array([0.0, 0.0925, 0.185, 0.185 + explained])
    np.testing.assert_allclose(unexplained_steps(_about_z(yaw), t, gyr), 0.0, atol=1e-12)
    yaw[3] += 0.1
    np.testing.assert_allclose(unexplained_steps(_about_z(yaw), t, gyr)[2], 0.1, atol=1e-12)

