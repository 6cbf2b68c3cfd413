"""A separate client process driving a running ``estimator`` the way ``ros2 topic pub``,
``ros2 param set`` and ``ros2 service call`` would. Prints one JSON line with what it saw.

    python proc_client.py NODE_FQN [--imu-rate HZ] [--seconds S]

Run by test/proc_session.py, for test_process.py and test_packaging.py (the colcon-installed
executable).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosharness import spin_until
from sensor_msgs.msg import Imu, MagneticField
from std_srvs.srv import Trigger

from mkf_ros.ros import convert
from mkf_ros.sim import simulate


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("node")
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--imu-rate", type=float, default=100.0)
    ap.add_argument("--timeout", type=float, default=60.0)
    a = ap.parse_args()
    rclpy.init()
    node = Node("proc_client")
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    out: list[Imu] = []
    node.create_subscription(Imu, "imu/data", out.append, qos)
    pub = node.create_publisher(Imu, "imu/data_raw", qos)
    pub_mag = node.create_publisher(MagneticField, "imu/mag", qos)
    params = AsyncParameterClient(node, a.node)
    reset = node.create_client(Trigger, a.node + "/reset")
    end = time.monotonic() + a.timeout
    result: dict = {}

    def wait(cond) -> bool:  # every wait shares the one deadline
        return spin_until(ex, cond, end - time.monotonic())

    def call(fut):
        assert wait(fut.done), "service call timed out"
        return fut.result()

    try:
        assert params.wait_for_services(timeout_sec=a.timeout), "no parameter services"
        assert wait(lambda: pub.get_subscription_count() > 0
                          and pub_mag.get_subscription_count() > 0
                          and pub.get_subscription_count() > 0), "estimator not subscribed"
        assert wait(lambda: node.count_publishers("imu/data") > 0), "no imu/data"
        rec = simulate("slow_rotation", duration=a.seconds, rate=a.imu_rate, seed=2,
                       mag_rate=a.imu_rate / 2)
        t0 = 1000.0
        period = 1.0 / a.imu_rate

        def stream(k0: int, k1: int) -> None:
            start = time.monotonic()
            for k in range(k0, k1):
                m = Imu()
                m.header.stamp = convert.sec_to_stamp(t0 + rec.t[k])
                m.header.frame_id = "imu_link"
                convert.set_vec(m.angular_velocity, rec.gyr[k])
                convert.set_vec(m.linear_acceleration, rec.acc[k])
                pub.publish(m)
                if not math.isnan(rec.mag[k, 0]):
                    mm = MagneticField()
                    mm.header = m.header
                    convert.set_vec(mm.magnetic_field, rec.mag[k])
                    pub_mag.publish(mm)
                while time.monotonic() < start + (k - k0 + 1) * period:
                    ex.spin_once(timeout_sec=0.001)

        half = len(rec.t) // 2
        stream(0, half)
        r = call(params.set_parameters([Parameter("algorithm", value="mukf")])).results[0]
        result["set_algorithm"] = [r.successful, r.reason]
        r = call(params.set_parameters([Parameter("chart", value="xyz")])).results[0]
        result["set_bad_chart"] = [r.successful, r.reason]
        got = call(params.get_parameters(["algorithm", "use_mag"])).values
        result["get"] = [got[0].string_value, got[1].bool_value]
        r = call(reset.call_async(Trigger.Request()))
        result["reset"] = [r.success, r.message]
        stream(half, len(rec.t))
        wait(lambda: len(out) >= len(rec.t))
        result["sent"] = len(rec.t)
        result["received"] = len(out)
        result["frame_id"] = out[-1].header.frame_id if out else ""
        result["finite"] = all(
            math.isfinite(v) for m in out for v in (m.orientation.w, m.orientation.x,
                                                    *m.orientation_covariance))
        result["ok"] = True
    except AssertionError as e:
        result["ok"] = False
        result["error"] = str(e)
    print(json.dumps(result), flush=True)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if result.get("ok") else 1


if __name__ == "__main__":
    sys.exit(main())
