"""``sensor_msgs`` messages ↔ arrays.

The core uses quaternions ``[w, x, y, z]``; ROS messages store ``x, y, z, w``. The reordering
happens here and nowhere else. Imu.msg conventions (REP-145): a covariance of all zeros means
"unknown"; element 0 = -1 means "this field is not reported" (such a field is passed to the
filter as missing and published with covariance[0] = -1 again).
"""

from __future__ import annotations

import numpy as np
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Quaternion, TransformStamped, Vector3
from sensor_msgs.msg import Imu, MagneticField

from mkf_ros.evaluation.metrics import roll_pitch_yaw
from mkf_ros.stream import rep145
from mkf_ros.stream.adapter import StreamOutput


def stamp_to_sec(stamp: Time) -> float:
    """``builtin_interfaces/Time`` → seconds (float)."""
    return stamp.sec + stamp.nanosec * 1e-9


def sec_to_stamp(t: float) -> Time:
    """Seconds → ``builtin_interfaces/Time`` (rounded to the nanosecond)."""
    ns = round(t * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def vec(v: Vector3) -> np.ndarray:
    return np.array((v.x, v.y, v.z))


def set_vec(msg: Vector3, v: np.ndarray) -> None:
    msg.x, msg.y, msg.z = float(v[0]), float(v[1]), float(v[2])


def quat_wxyz(q: Quaternion) -> np.ndarray:
    """``geometry_msgs/Quaternion`` (x, y, z, w) → ``[w, x, y, z]``."""
    return np.array((q.w, q.x, q.y, q.z))


def set_quat(msg: Quaternion, q_wxyz: np.ndarray) -> None:
    """``[w, x, y, z]`` → ``geometry_msgs/Quaternion`` (x, y, z, w)."""
    msg.w, msg.x, msg.y, msg.z = (float(q_wxyz[0]), float(q_wxyz[1]), float(q_wxyz[2]),
                                  float(q_wxyz[3]))


def imu_to_arrays(msg: Imu) -> tuple[float, np.ndarray | None, np.ndarray | None]:
    """``(stamp_s, gyr rad/s, acc m/s²)``; a field whose covariance[0] is -1 is None."""
    g = None if rep145.not_reported(msg.angular_velocity_covariance[0]) else \
        vec(msg.angular_velocity)
    a = None if rep145.not_reported(msg.linear_acceleration_covariance[0]) else \
        vec(msg.linear_acceleration)
    return stamp_to_sec(msg.header.stamp), g, a


def mag_to_array(msg: MagneticField) -> tuple[float, np.ndarray]:
    """``(stamp_s, field T)``; NaN components mean "not reported" (REP-145)."""
    return stamp_to_sec(msg.header.stamp), vec(msg.magnetic_field)


def fill_imu(out: Imu, inp: Imu, est: StreamOutput, angular_velocity_stddev: float,
             linear_acceleration_stddev: float) -> Imu:
    """Write the estimate into ``out`` (reused between calls): header of the input,
    orientation and its covariance from the filter, angular velocity per the chosen source,
    linear acceleration passed through; covariances per :mod:`mkf_ros.stream.rep145`."""
    out.header = inp.header
    set_quat(out.orientation, est.quat)
    out.orientation_covariance = np.ascontiguousarray(est.cov, dtype=float).reshape(9)
    w, a = est.angular_velocity, est.linear_acceleration
    set_vec(out.angular_velocity, np.zeros(3) if w is None else w)
    out.angular_velocity_covariance = rep145.published_covariance(
        w, est.angular_velocity_cov, inp.angular_velocity_covariance, angular_velocity_stddev,
        est.angular_velocity_cov_add)
    set_vec(out.linear_acceleration, np.zeros(3) if a is None else a)
    out.linear_acceleration_covariance = rep145.published_covariance(
        a, None, inp.linear_acceleration_covariance, linear_acceleration_stddev)
    return out


def rpy(q_wxyz: np.ndarray) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad; fixed axes x-y-z, as tf2's getRPY) of ``[w, x, y, z]``
    (:func:`mkf_ros.evaluation.metrics.roll_pitch_yaw`)."""
    r, p, y = roll_pitch_yaw(q_wxyz).tolist()
    return r, p, y


def transform(stamp: Time, parent: str, child: str, q_wxyz: np.ndarray) -> TransformStamped:
    """A rotation-only ``TransformStamped`` parent → child."""
    t = TransformStamped()
    t.header.stamp = stamp
    t.header.frame_id = parent
    t.child_frame_id = child
    set_quat(t.transform.rotation, q_wxyz)
    return t
