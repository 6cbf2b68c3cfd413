"""The estimator's QoS profiles (one place: the node, the managed node and the benchmark's
stand-in republisher use them)."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def input_qos() -> QoSProfile:
    """Sensor-data policies (best effort, volatile) with a deeper queue than the profile's 5
    (200: 0.2 s at 1 kHz), so that a burst, or the node being descheduled on a busy machine,
    does not drop samples. A new object per call: QoS overrides modify it in place."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                      reliability=ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.VOLATILE)


def output_qos() -> QoSProfile:
    """Reliable, keep last 100 (what rviz, rosbag and robot_localization expect)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
