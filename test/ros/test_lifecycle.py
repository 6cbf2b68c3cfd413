"""The managed estimator (mkf_ros.ros.lifecycle) driven through its lifecycle services from a
client node, as a lifecycle manager would: it starts unconfigured; parameters set then take
effect at configure; it publishes only while active; cleanup removes its topics; invalid
transitions are refused."""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosharness import imu_msg, spin_until
from sensor_msgs.msg import Imu

from mkf_ros.ros.lifecycle import EstimatorLifecycleNode

QOS = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
RELIABLE_IN = {"qos_overrides./imu/data_raw.subscription.reliability": "reliable",
               "qos_overrides./imu/data_raw.subscription.history": "keep_all"}


class Managed:
    """A managed estimator and a client node with the lifecycle service clients."""

    def __init__(self, ctx: Any) -> None:
        self.est = EstimatorLifecycleNode(
            context=ctx, warm=False,
            parameter_overrides=[Parameter(k, value=v) for k, v in RELIABLE_IN.items()])
        self.cli = Node("lifecycle_client", context=ctx)
        name = self.est.get_fully_qualified_name()
        self.change = self.cli.create_client(ChangeState, f"{name}/change_state")
        self.get = self.cli.create_client(GetState, f"{name}/get_state")
        self.params = AsyncParameterClient(self.cli, name)
        self.out: list[Imu] = []
        self.cli.create_subscription(Imu, "imu/data", self.out.append, QOS)
        self.pub = self.cli.create_publisher(Imu, "imu/data_raw", QOS)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.est)
        self.ex.add_node(self.cli)
        assert self.change.wait_for_service(10.0) and self.get.wait_for_service(10.0)
        self.t = 100.0

    def wait(self, fut: Any) -> Any:
        assert spin_until(self.ex, fut.done, 10.0), "service call timed out"
        return fut.result()

    def state(self) -> str:
        return str(self.wait(self.get.call_async(GetState.Request())).current_state.label)

    def transition(self, tid: int) -> bool:
        return bool(self.wait(self.change.call_async(
            ChangeState.Request(transition=Transition(id=tid)))).success)

    def feed(self, n: int = 50) -> int:
        """Publish ``n`` level-at-rest IMU messages (stamps continue), spin a while; returns
        how many imu/data messages arrived meanwhile."""
        before = len(self.out)
        for _ in range(n):
            self.t += 0.01
            self.pub.publish(imu_msg(self.t, (0.0, 0.0, 0.0), (0.0, 0.0, 9.80665)))
        spin_until(self.ex, lambda: len(self.out) >= before + n, 3.0)
        return len(self.out) - before

    def close(self) -> None:
        self.ex.shutdown()
        self.est.destroy_node()
        self.cli.destroy_node()


@pytest.fixture
def managed(ros_context: Any) -> Iterator[Managed]:
    m = Managed(ros_context)
    yield m
    m.close()


def test_starts_unconfigured_without_topics(managed: Managed) -> None:
    assert managed.state() == "unconfigured"
    spin_until(managed.ex, lambda: False, 0.3)
    assert managed.pub.get_subscription_count() == 0
    assert managed.cli.count_publishers("/imu/data") == 0


def test_full_lifecycle(managed: Managed) -> None:
    m = managed
    # a parameter set while unconfigured takes effect at configure
    res = m.wait(m.params.set_parameters([Parameter("world_frame", value="ned")]))
    assert res.results[0].successful
    assert m.transition(Transition.TRANSITION_CONFIGURE) and m.state() == "inactive"
    assert spin_until(m.ex, lambda: m.pub.get_subscription_count() > 0
                      and m.cli.count_publishers("/imu/data") > 0, 10.0)
    assert m.feed() == 0, "an inactive node must not publish"

    assert m.transition(Transition.TRANSITION_ACTIVATE) and m.state() == "active"
    assert m.feed() == 50
    # level at rest, start-up heading: ENU identity, which in NED is 180° about (1, 1, 0)/√2
    q = m.out[-1].orientation
    s = math.sqrt(0.5)
    np.testing.assert_allclose(np.abs([q.w, q.x, q.y, q.z]), [0.0, s, s, 0.0], atol=1e-3)

    assert m.transition(Transition.TRANSITION_DEACTIVATE) and m.state() == "inactive"
    assert m.feed() == 0
    assert m.transition(Transition.TRANSITION_ACTIVATE)
    assert m.feed() == 50

    assert m.transition(Transition.TRANSITION_DEACTIVATE)
    assert m.transition(Transition.TRANSITION_CLEANUP) and m.state() == "unconfigured"
    assert spin_until(m.ex, lambda: m.pub.get_subscription_count() == 0
                      and m.cli.count_publishers("/imu/data") == 0, 10.0)
    # and again, now in ENU
    m.wait(m.params.set_parameters([Parameter("world_frame", value="enu")]))
    assert m.transition(Transition.TRANSITION_CONFIGURE)
    assert m.transition(Transition.TRANSITION_ACTIVATE)
    assert spin_until(m.ex, lambda: m.pub.get_subscription_count() > 0, 10.0)
    assert m.feed() == 50
    q = m.out[-1].orientation
    np.testing.assert_allclose(np.abs([q.w, q.x, q.y, q.z]), [1.0, 0.0, 0.0, 0.0], atol=1e-3)

    assert m.transition(Transition.TRANSITION_ACTIVE_SHUTDOWN)
    assert m.state() == "finalized"


def test_invalid_transition_and_parameter_are_refused(managed: Managed) -> None:
    m = managed
    assert not m.transition(Transition.TRANSITION_ACTIVATE)  # not configured yet
    assert m.state() == "unconfigured"
    res = m.wait(m.params.set_parameters([Parameter("world_frame", value="ecef")]))
    assert not res.results[0].successful and "world_frame" in res.results[0].reason
    assert m.transition(Transition.TRANSITION_CONFIGURE)
    assert m.wait(m.get.call_async(GetState.Request())).current_state.id == \
        State.PRIMARY_STATE_INACTIVE
