"""The estimator node with split input (``input_mode`` split): accelerometer and gyroscope on
their own ``sensor_msgs/Imu`` topics (``imu/accel``, ``imu/gyro``; RealSense remaps), each with
the other vector zero. Every gyro message is answered, with its stamp, with the estimate the
stream adapter computes from the same messages in the same order."""

from __future__ import annotations

import numpy as np
from rosharness import QOS, imu_msg, quat
from sensor_msgs.msg import Imu

from mkf_ros.ros.convert import quat_wxyz
from mkf_ros.stream.adapter import StreamAdapter

SPLIT = {
    "input_mode": "split",
    "qos_overrides./imu/gyro.subscription.reliability": "reliable",
    "qos_overrides./imu/gyro.subscription.depth": 2000,
    "qos_overrides./imu/accel.subscription.reliability": "reliable",
    "qos_overrides./imu/accel.subscription.depth": 2000,
}


def test_split_topics_drive_the_node(harness) -> None:
    h = harness(SPLIT)
    pub_g = h.cli.create_publisher(Imu, "imu/gyro", QOS)
    pub_a = h.cli.create_publisher(Imu, "imu/accel", QOS)
    assert h.spin_until(lambda: pub_g.get_subscription_count() > 0
                        and pub_a.get_subscription_count() > 0, 10.0)
    ref = StreamAdapter(input_mode="split")
    expected = []
    w = np.array([0.0, 0.0, 0.5])  # a turn about the vertical
    g = np.array([0.0, 0.0, 9.80665])
    n = 120
    for k in range(n):
        t = 100.0 + 0.01 * k
        if k % 4 == 0:  # accelerometer at a quarter of the gyro's rate, the same stamps
            want = h.est.received_acc + 1
            pub_a.publish(imu_msg(t, (0.0, 0.0, 0.0), g))
            assert h.spin_until(lambda want=want: h.est.received_acc >= want, 5.0)
            ref.on_accel(t, g)
        want = h.est.received_imu + 1
        pub_g.publish(imu_msg(t, w, (0.0, 0.0, 0.0)))
        assert h.spin_until(lambda want=want: h.est.received_imu >= want, 5.0)
        out = ref.on_gyro(t, w)
        if out is not None:
            expected.append((t, out.quat))
    assert h.spin_until(lambda: len(h.out) >= len(expected), 5.0)
    assert len(expected) == n and len(h.out) == n  # every gyro message answered
    for m, (t, q) in zip(h.out, expected, strict=True):
        stamp = m.header.stamp.sec + m.header.stamp.nanosec * 1e-9
        assert abs(stamp - t) < 1e-6
        np.testing.assert_allclose(quat(m), q, atol=1e-12)
        assert m.linear_acceleration_covariance[0] == -1.0  # on its own topic: not reported
    # the heading turned by the integrated rate (0.5 rad/s over the run)
    q_last = quat_wxyz(h.out[-1].orientation)
    yaw = 2.0 * np.arctan2(q_last[3], q_last[0])
    assert abs(yaw - 0.5 * 0.01 * (n - 1)) < 0.02
    assert h.est.received_acc == len(range(0, n, 4))
