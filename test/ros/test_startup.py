"""The estimator node starts and publishes when its kernel cache directory cannot be written
(a read-only home in a container, another user's directory): one warning, no error (the node
must start wherever it is installed)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from mkf_ros.ros import convert

pytestmark = pytest.mark.ros


def test_estimator_starts_with_an_unwritable_kernel_cache(ros_context: Any, tmp_path: Path) -> None:
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu

    blocker = tmp_path / "a-file"  # a path under a regular file: unwritable even for root
    blocker.write_text("")
    cache = blocker / "mkf_ros"
    env = dict(os.environ, MKF_ROS_CACHE_DIR=str(cache))
    node = Node("startup_probe", context=ros_context)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(Imu, "imu/data_raw", qos)
    got: list[Imu] = []
    node.create_subscription(Imu, "imu/data", got.append, qos)
    log = tmp_path / "estimator.log"
    with log.open("w") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mkf_ros.ros.estimator_main", "--ros-args",
             "-p", "qos_overrides./imu/data_raw.subscription.reliability:=reliable"],
            env=env, stdout=out, stderr=subprocess.STDOUT)
    try:
        from rclpy.executors import SingleThreadedExecutor

        ex = SingleThreadedExecutor(context=ros_context)
        ex.add_node(node)
        msg = Imu()
        msg.header.frame_id = "imu_link"
        msg.linear_acceleration.z = 9.81
        while not got:  # bounded by the pytest timeout; the node's exit ends it early
            assert proc.poll() is None, f"estimator exited ({proc.returncode}):\n{log.read_text()}"
            msg.header.stamp = convert.sec_to_stamp(time.time())
            pub.publish(msg)
            ex.spin_once(timeout_sec=0.01)
    finally:
        proc.terminate()
        proc.wait(30)
    q = got[0].orientation
    assert all(math.isfinite(v) for v in (q.x, q.y, q.z, q.w))
    text = log.read_text()
    warnings = [ln for ln in text.splitlines() if "not writable" in ln]
    assert len(warnings) == 1 and str(cache) in warnings[0], text
