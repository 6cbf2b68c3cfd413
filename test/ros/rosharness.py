"""Harness for the estimator node tests: the node and a client node in one context, one
single-threaded executor, helpers to publish timestamped streams and to call the node's
services the way ``ros2 topic pub`` / ``ros2 param set`` would (from another node)."""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any, Protocol, TypeVar

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import Imu, MagneticField
from std_srvs.srv import Trigger

from mkf_ros.ros import convert
from mkf_ros.ros.estimator_node import EstimatorNode

RELIABLE_IN = {
    "qos_overrides./imu/data_raw.subscription.reliability": "reliable",
    "qos_overrides./imu/data_raw.subscription.depth": 2000,
    "qos_overrides./imu/mag.subscription.reliability": "reliable",
    "qos_overrides./imu/mag.subscription.depth": 2000,
}
QOS = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)


def spin_until(ex: Executor, cond: Callable[[], bool], timeout: float) -> bool:
    """Spin ``ex`` until ``cond()`` holds (True) or ``timeout`` seconds have passed (False);
    ``cond=lambda: False`` spins for ``timeout`` seconds, taking what is in flight."""
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            return False
        ex.spin_once(timeout_sec=0.01)
    return True


class _Closable(Protocol):
    def close(self) -> None: ...


C = TypeVar("C", bound=_Closable)


def closing_factory(make: Callable[..., C]) -> Iterator[Callable[..., C]]:
    """The body of a factory fixture (``yield from closing_factory(...)``): yields ``make``,
    remembering what it made, and closes every one of them after the test."""
    made: list[C] = []

    def tracked(*args: Any, **kwargs: Any) -> C:
        obj = make(*args, **kwargs)
        made.append(obj)
        return obj

    yield tracked
    for obj in made:
        obj.close()


def imu_msg(stamp: float, gyr: Sequence[float] | None, acc: Sequence[float] | None,
            frame: str = "imu_link") -> Imu:
    m = Imu()
    m.header.stamp = convert.sec_to_stamp(stamp) if stamp > 0 else m.header.stamp
    m.header.frame_id = frame
    if gyr is None:
        m.angular_velocity_covariance[0] = -1.0
    else:
        convert.set_vec(m.angular_velocity, np.asarray(gyr, float))
    if acc is None:
        m.linear_acceleration_covariance[0] = -1.0
    else:
        convert.set_vec(m.linear_acceleration, np.asarray(acc, float))
    return m


def mag_msg(stamp: float, mag: Sequence[float], frame: str = "imu_link") -> MagneticField:
    m = MagneticField()
    m.header.stamp = convert.sec_to_stamp(stamp)
    m.header.frame_id = frame
    convert.set_vec(m.magnetic_field, np.asarray(mag, float))
    return m


class Harness:
    """An estimator node plus a client node, spun together by one executor."""

    def __init__(self, ctx: Any, params: dict[str, Any] | None = None, *,
                 reliable: bool = True, namespace: str | None = None,
                 node_kwargs: dict[str, Any] | None = None) -> None:
        overrides = dict(RELIABLE_IN if reliable else {}, **(params or {}))
        if namespace:
            overrides = {k.replace("./imu/", f".{namespace}/imu/"): v
                         for k, v in overrides.items()}
        self.ctx = ctx
        self.est = EstimatorNode(
            context=ctx, namespace=namespace,
            parameter_overrides=[Parameter(k, value=v) for k, v in overrides.items()],
            **(node_kwargs or {}))
        self.cli = Node("test_client", context=ctx, namespace=namespace)
        self.out: list[Imu] = []
        self.diag: list[DiagnosticArray] = []
        self.cli.create_subscription(Imu, "imu/data", self.out.append, QOS)
        self.cli.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10)
        self.pub_imu = self.cli.create_publisher(Imu, "imu/data_raw", QOS)
        self.pub_mag = self.cli.create_publisher(MagneticField, "imu/mag", QOS)
        # MKF_TEST_EXECUTOR=events runs the whole node suite under the EventsExecutor too
        if os.environ.get("MKF_TEST_EXECUTOR") == "events":
            from rclpy.experimental import EventsExecutor

            self.ex = EventsExecutor(context=ctx)
        else:
            self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.est)
        self.ex.add_node(self.cli)
        self.params = AsyncParameterClient(self.cli, self.est.get_fully_qualified_name())
        self.reset_cli = self.cli.create_client(
            Trigger, self.est.get_fully_qualified_name() + "/reset")
        self.spin_until(lambda: self.pub_imu.get_subscription_count() > 0
                        and self.pub_mag.get_subscription_count() > 0
                        and self.est._pub.get_subscription_count() > 0, 10.0)

    # --- spinning ----------------------------------------------------------------------------
    def spin_until(self, cond: Callable[[], bool], timeout: float = 5.0) -> bool:
        return spin_until(self.ex, cond, timeout)

    def spin_for(self, seconds: float) -> None:
        spin_until(self.ex, lambda: False, seconds)

    def received(self) -> int:
        return self.est.received_imu + self.est.received_mag

    def send(self, msgs: Sequence[Imu | MagneticField], timeout: float = 10.0) -> None:
        """Publish in order and spin until the node has taken every message."""
        want = self.received() + len(msgs)
        for i, m in enumerate(msgs):
            (self.pub_imu if isinstance(m, Imu) else self.pub_mag).publish(m)
            if i % 20 == 19:
                self.ex.spin_once(timeout_sec=0.0)
        assert self.spin_until(lambda: self.received() >= want, timeout), (
            f"node received {self.received()} of {want} messages")
        # let the client take the outputs of the last messages
        pub = self.est._published
        self.spin_until(lambda: len(self.out) >= pub, 2.0)

    def send_imu(self, stamps: Sequence[float], gyr: Any = (0.0, 0.0, 0.0),
                 acc: Any = (0.0, 0.0, 9.80665)) -> None:
        self.send([imu_msg(t, gyr, acc) for t in stamps])

    def send_recording(self, rec: Any, t0: float = 100.0, mag: bool = True) -> list[Any]:
        """A simulated recording: IMU every row, magnetometer on its non-NaN rows, in stamp
        order (the magnetometer after the IMU message of the same stamp). Returns the
        messages sent."""
        msgs = recording_messages(rec, t0, mag)
        self.send(msgs)
        return msgs

    # --- services ----------------------------------------------------------------------------
    def wait(self, fut: Any, timeout: float = 10.0) -> Any:
        assert self.spin_until(fut.done, timeout), "service call timed out"
        return fut.result()

    def set(self, **values: Any) -> list[Any]:
        """SetParameters from the client node; returns the SetParametersResult list."""
        assert self.params.wait_for_services(timeout_sec=10.0)
        fut = self.params.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        return list(self.wait(fut).results)

    def set_atomically(self, **values: Any) -> Any:
        assert self.params.wait_for_services(timeout_sec=10.0)
        fut = self.params.set_parameters_atomically(
            [Parameter(k, value=v) for k, v in values.items()])
        return self.wait(fut).result

    def get(self, *names: str) -> list[Any]:
        fut = self.params.get_parameters(list(names))
        return [parameter_value_to_python(v) for v in self.wait(fut).values]

    def reset(self) -> Any:
        assert self.reset_cli.wait_for_service(timeout_sec=10.0)
        return self.wait(self.reset_cli.call_async(Trigger.Request()))

    def close(self) -> None:
        self.ex.shutdown()
        self.est.destroy_node()
        self.cli.destroy_node()


def recording_messages(rec: Any, t0: float = 100.0, mag: bool = True) -> list[Any]:
    """The messages of :meth:`Harness.send_recording`, in publishing order."""
    msgs: list[Any] = []
    for k in range(len(rec.t)):
        msgs.append(imu_msg(t0 + rec.t[k], rec.gyr[k], rec.acc[k]))
        if mag and not math.isnan(rec.mag[k, 0]):
            msgs.append(mag_msg(t0 + rec.t[k], rec.mag[k]))
    return msgs


def record_arrival(stream: Any) -> list[str]:
    """The kinds (``"imu"``, ``"mag"``) of the samples the node hands to its adapter, in order:
    which of the two topics the executor served first. Only the order is recorded; a
    reference adapter is fed from the messages the test sent (:func:`reference_outputs`),
    so the node's message conversion is under test, not replayed."""
    kinds: list[str] = []
    # run_imu_event: the node's per-message path, and what on_imu and step_imu (its
    # message-object path) call
    run_imu_event, on_mag = stream.run_imu_event, stream.on_mag

    def imu(*args):
        kinds.append("imu")
        return run_imu_event(*args)

    def mag(*args):
        kinds.append("mag")
        return on_mag(*args)

    stream.run_imu_event, stream.on_mag = imu, mag
    return kinds


def _stamp(m: Any) -> float:
    return m.header.stamp.sec + m.header.stamp.nanosec * 1e-9


def reference_outputs(adapter: Any, sent: Sequence[Any], kinds: Sequence[str]) -> list[Any]:
    """Feed ``adapter`` (a fresh :class:`~mkf_ros.stream.adapter.StreamAdapter`) the messages the
    test sent, read field by field from the message objects (what went on the wire), in the node's
    arrival order ``kinds`` (each topic in its own publishing order); returns the output of
    every IMU message (None where nothing was published)."""
    imus = iter([m for m in sent if isinstance(m, Imu)])
    mags = iter([m for m in sent if isinstance(m, MagneticField)])
    out = []
    for kind in kinds:
        if kind == "imu":
            m = next(imus)
            g, a = m.angular_velocity, m.linear_acceleration
            gyr = None if m.angular_velocity_covariance[0] == -1.0 else [g.x, g.y, g.z]
            acc = None if m.linear_acceleration_covariance[0] == -1.0 else [a.x, a.y, a.z]
            out.append(adapter.on_imu(_stamp(m), gyr, acc))
        else:
            m = next(mags)
            f = m.magnetic_field
            adapter.on_mag(_stamp(m), [f.x, f.y, f.z])
    return out


def assert_message_is(m: Imu, inp: Imu, ref: Any) -> None:
    """The published ``m`` carries the reference adapter's estimate ``ref`` for input ``inp``,
    field by field (REP-145: x, y, z, w; covariance row-major; input header, rate and
    specific force passed through when the source is ``input``), to the last bit."""
    assert (m.header.stamp.sec, m.header.stamp.nanosec, m.header.frame_id) == (
        inp.header.stamp.sec, inp.header.stamp.nanosec, inp.header.frame_id)
    o = m.orientation
    np.testing.assert_array_equal([o.w, o.x, o.y, o.z], ref.quat)
    np.testing.assert_array_equal(np.asarray(m.orientation_covariance),
                                  np.asarray(ref.cov).reshape(9))
    for field in ("angular_velocity", "linear_acceleration"):
        a, b = getattr(m, field), getattr(inp, field)
        assert (a.x, a.y, a.z) == (b.x, b.y, b.z), field


def quat(m: Imu) -> np.ndarray:
    return convert.quat_wxyz(m.orientation)


def finite(m: Imu) -> bool:
    vals = [m.orientation.x, m.orientation.y, m.orientation.z, m.orientation.w,
            *m.orientation_covariance, *m.angular_velocity_covariance,
            *m.linear_acceleration_covariance, m.angular_velocity.x, m.angular_velocity.y,
            m.angular_velocity.z, m.linear_acceleration.x, m.linear_acceleration.y,
            m.linear_acceleration.z]
    return all(math.isfinite(v) for v in vals)


# --- node vs ``mkf process``: the same bag's messages, one at a time ---------------------------
def bag_messages(path: Any, topics: Sequence[str]) -> list[Imu | MagneticField]:
    """The messages of ``topics`` in ``path`` (any format :class:`~mkf_ros.bags.reader.BagReader`
    reads, ROS 1 converted to CDR), in recording order (as the reader yields them: log time,
    what ``mkf play`` publishes), deserialised to rclpy ``Imu`` / ``MagneticField`` objects."""
    from rclpy.serialization import deserialize_message

    from mkf_ros.bags import cdr
    from mkf_ros.bags.reader import BagReader, normalize_topic

    cls = {cdr.IMU.msgtype: Imu, cdr.MAGNETIC_FIELD.msgtype: MagneticField}
    with BagReader(path) as br:
        names = [normalize_topic(t) for t in topics]
        types = {n: cls[br.topics[n].msgtype] for n in names}
        return [deserialize_message(raw, types[topic])
                for topic, _, raw in br.messages(names)]


def send_one_by_one(h: Harness, msgs: Sequence[Imu | MagneticField],
                    timeout: float = 10.0) -> None:
    """Publish ``msgs`` one at a time, each taken by the node before the next is published:
    the node sees them in exactly this order whatever the executor does with its two
    subscriptions."""
    for m in msgs:
        h.send([m], timeout)


def output_arrays(msgs: Sequence[Imu]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stamps (ns), orientations [w, x, y, z] and covariances (9) of published messages."""
    st = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs],
                  dtype=np.int64)
    q = np.array([[m.orientation.w, m.orientation.x, m.orientation.y, m.orientation.z]
                  for m in msgs], dtype=float).reshape(-1, 4)
    cov = np.array([np.asarray(m.orientation_covariance) for m in msgs],
                   dtype=float).reshape(-1, 9)
    return st, q, cov


def fake_tf2(monkeypatch: Any) -> list:
    """A stand-in ``tf2_ros`` (its wheel is not on PyPI): the transforms the node sends."""
    import sys
    import types

    sent: list = []

    class TransformBroadcaster:
        def __init__(self, node) -> None:
            self.node = node

        def sendTransform(self, t) -> None:
            sent.append(t)

    mod = types.ModuleType("tf2_ros")
    mod.TransformBroadcaster = TransformBroadcaster
    monkeypatch.setitem(sys.modules, "tf2_ros", mod)
    return sent
