"""The node's interface beyond the estimate: ~/reset, /diagnostics, TF, debug topics, QoS,
namespaces and the covariance fields of imu/data."""

from __future__ import annotations

import math
import sys
import time

import numpy as np
import pytest
from geometry_msgs.msg import Vector3Stamped
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosharness import assert_message_is, fake_tf2, imu_msg, mag_msg, quat
from sensor_msgs.msg import Imu
from std_msgs.msg import Bool

from mkf_ros.core.quaternion import qconj_np
from mkf_ros.ros.convert import quat_wxyz
from mkf_ros.stream.adapter import INPUT_CHECK_MESSAGES

pytestmark = pytest.mark.ros
T0 = 100.0
OK, WARN, ERROR = b"\x00", b"\x01", b"\x02"


def statuses(h):
    return [s for d in h.diag for s in d.status if s.name.startswith("estimator")]


def values(status) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def test_reset_service(harness) -> None:
    h = harness()
    h.send_imu([T0 + 0.01 * k for k in range(50)], gyr=(0.0, 0.0, 1.0))
    assert quat(h.out[-1])[3] > 0.2
    res = h.reset()
    assert res.success and "re-initialising" in res.message
    assert not h.est.stream.initialized and h.est.stream.counters["resets"] == 1
    h.send_imu([T0 + 0.5])
    np.testing.assert_allclose(quat(h.out[-1]), [1, 0, 0, 0], atol=1e-12)


class FakeMonotonic:
    """Stands in for the estimator module's ``time``: ``monotonic()`` is set by the test (the
    node's rates and silences are wall-clock measures; the test decides the wall clock)."""

    def __init__(self, t: float) -> None:
        self.t = t

    def monotonic(self) -> float:
        return self.t

    def __getattr__(self, name: str):
        return getattr(time, name)


def test_diagnostics_report(harness, monkeypatch) -> None:
    """Event-driven: the diagnostics timer is not left to the wall clock (its period is an
    hour); the test advances the node's clock and runs the timer's callback itself, so the
    reported rates are exact: 50 IMU messages in 0.5 s are 100.0 Hz, then 20 in 0.25 s 80.0."""
    from mkf_ros.ros import estimator_node

    clock = FakeMonotonic(1000.0)
    monkeypatch.setattr(estimator_node, "time", clock)
    h = harness({"diagnostics_period": 3600.0, "estimate_gyro_bias": True})
    h.send_imu([T0 + 0.01 * k for k in range(50)], gyr=(0.0, 0.0, 0.01))  # exactly 0 is named
    clock.t += 0.5
    h.est._on_timer()
    assert h.spin_until(lambda: len(statuses(h)) >= 1, 10.0)
    st = statuses(h)[-1]
    assert st.name == "estimator: attitude estimator" and st.hardware_id == "imu_link"
    assert st.level == OK, st.message
    assert st.message == "running, heading relative to the start-up heading"
    v = values(st)
    assert v["imu rate (Hz)"] == "100.0" and v["published rate (Hz)"] == "100.0"
    assert v["imu_received"] == "50"
    assert v["initialised"] == "true" and v["magnetometer"] == "disabled"
    assert v["imu topic"] == "/imu/data_raw" and v["algorithm / chart"] == "mekf / rp"
    sd = [float(x) for x in v["orientation stddev x/y/z, world axes (deg)"].split(" / ")]
    cov = h.est.stream.filter.covariance
    np.testing.assert_allclose(sd, np.degrees(np.sqrt(np.diag(cov))), rtol=1e-2, atol=1e-3)
    assert float(v["orientation covariance trace (rad^2)"]) == pytest.approx(
        np.trace(cov), rel=1e-2)
    assert "gyro bias stddev (rad/s)" in v
    for key in ("imu_out_of_order", "acc_implausible", "mag_too_old", "resets"):
        assert v[key] == "0"
    # the next period: 20 more messages in 0.25 s
    h.send_imu([T0 + 0.5 + 0.01 * k for k in range(20)])
    clock.t += 0.25
    h.est._on_timer()
    assert h.spin_until(lambda: len(statuses(h)) >= 2, 10.0)
    v = values(statuses(h)[-1])
    assert v["imu rate (Hz)"] == "80.0" and v["imu_received"] == "70"


def test_silent_inputs_named_with_resolved_topics(harness, capfd) -> None:
    h = harness({"diagnostics_period": 0.2, "input_timeout": 0.3, "use_mag": True},
                namespace="/robot1")
    assert h.spin_until(lambda: any(s.level == WARN for s in statuses(h)), 3.0)
    st = [s for s in statuses(h) if s.level == WARN][-1]
    assert "no data on /robot1/imu/data_raw" in st.message
    assert "no data on /robot1/imu/mag" in st.message
    err = capfd.readouterr().err
    assert "no data on /robot1/imu/data_raw" in err


def test_not_initialised_says_why(harness) -> None:
    h = harness({"diagnostics_period": 0.2})
    h.send_imu([T0 + 0.01 * k for k in range(10)], acc=(0.0, 0.0, 1.0))  # in g, not m/s²
    assert h.spin_until(lambda: any("not initialised" in s.message for s in statuses(h)), 3.0)
    st = next(s for s in statuses(h) if "not initialised" in s.message)
    assert st.level == WARN
    assert "accelerometer magnitude 1 m/s² is far from gravity" in st.message
    assert "units of g" in st.message


def test_input_without_accelerometer_is_named_once(harness, capfd) -> None:
    """A gyro-only topic (accelerometer zero) cannot give an orientation: nothing is published,
    /diagnostics says why at ERROR, and the log says it once (not every period)."""
    h = harness({"diagnostics_period": 0.1})
    n = INPUT_CHECK_MESSAGES + 10
    h.send_imu([T0 + 0.01 * k for k in range(n)], gyr=(0.0, 0.0, 0.3), acc=(0.0, 0.0, 0.0))
    text = ("no usable accelerometer reading (zero, invalid, not reported or far from gravity) "
            f"in all {n} IMU messages on /imu/data_raw: is this a gyro-only topic?")
    assert h.spin_until(lambda: sum(text in s.message for s in statuses(h)) >= 3, 5.0)
    assert all(s.level == ERROR for s in statuses(h) if text in s.message)
    assert h.out == []
    assert capfd.readouterr().err.count("is this a gyro-only topic?") == 1


def test_zero_gyro_and_orientation_carrying_input_are_named_once(harness, capfd) -> None:
    """An input whose angular velocity is exactly zero (an accelerometer-only topic?) and whose
    messages carry an orientation (an estimator's output?) is still filtered, and both are
    named: WARN in /diagnostics, once in the log."""
    h = harness({"diagnostics_period": 0.1})
    msgs = []
    for k in range(INPUT_CHECK_MESSAGES + 10):
        m = imu_msg(T0 + 0.01 * k, (0.0, 0.0, 0.0), (0.0, 0.0, 9.80665))
        m.orientation.z, m.orientation.w = math.sin(0.25), math.cos(0.25)
        m.orientation_covariance[0] = 1e-4
        msgs.append(m)
    h.send(msgs)
    assert len(h.out) == len(msgs)
    zero = "is this an accelerometer-only topic?"
    ori = "/imu/data_raw already carries an orientation (orientation_covariance[0] is not -1)"
    assert h.spin_until(lambda: sum(zero in s.message and ori in s.message
                                    for s in statuses(h)) >= 3, 5.0)
    assert all(s.level == WARN for s in statuses(h) if zero in s.message)
    err = capfd.readouterr().err
    assert err.count(zero) == 1 and err.count(ori) == 1


def test_tf_follows_the_message(harness, monkeypatch) -> None:
    """publish_tf (at run time): fixed_frame → IMU frame, the message's rotation (yaw offset
    included), the IMU stamp; reverse_tf broadcasts the inverse, frames swapped."""
    sent = fake_tf2(monkeypatch)
    h = harness({"yaw_offset": 0.3, "fixed_frame": "odom"})
    h.send_imu([T0, T0 + 0.01], gyr=(0.1, 0.0, 0.2), acc=(1.0, 0.5, 9.7))
    assert sent == []  # default false
    assert h.set(publish_tf=True)[0].successful
    h.send_imu([T0 + 0.02])
    t, m = sent[-1], h.out[-1]
    assert (t.header.frame_id, t.child_frame_id) == ("odom", "imu_link")
    assert t.header.stamp == m.header.stamp
    np.testing.assert_array_equal(quat_wxyz(t.transform.rotation), quat(m))
    assert h.set(reverse_tf=True)[0].successful
    h.send_imu([T0 + 0.03])
    t, m = sent[-1], h.out[-1]
    assert (t.header.frame_id, t.child_frame_id) == ("imu_link", "odom")
    np.testing.assert_allclose(quat_wxyz(t.transform.rotation), qconj_np(quat(m)), atol=1e-15)


def test_tf_without_tf2_warns(harness, monkeypatch, capfd) -> None:
    monkeypatch.setitem(sys.modules, "tf2_ros", None)  # import fails
    h = harness({"publish_tf": True})
    h.send_imu([T0, T0 + 0.01])
    assert len(h.out) == 2
    assert "publish_tf is true but tf2_ros cannot be imported" in capfd.readouterr().err


def test_debug_topics(harness) -> None:
    h = harness({"publish_debug_topics": True, "estimate_gyro_bias": True})
    rpy, bias = [], []
    h.cli.create_subscription(Vector3Stamped, "imu/rpy/filtered", rpy.append, 50)
    h.cli.create_subscription(Vector3Stamped, "imu/gyro_bias", bias.append, 50)
    assert h.spin_until(lambda: h.est._debug["rpy"].get_subscription_count() > 0
                        and h.est._debug["bias"].get_subscription_count() > 0)
    roll = 0.3
    h.send_imu([T0 + 0.01 * k for k in range(5)],
               acc=(0.0, 9.80665 * math.sin(roll), 9.80665 * math.cos(roll)))
    assert h.spin_until(lambda: len(rpy) == 5 and len(bias) == 5)
    assert rpy[-1].vector.x == pytest.approx(roll, abs=1e-3)
    assert rpy[-1].header.frame_id == "imu_link"


def test_debug_topics_raw_orientation_and_steady_state(harness) -> None:
    """imu/rpy/raw (imu_filter_madgwick's): roll, pitch, yaw from this accelerometer sample and
    the latest magnetometer sample alone, published with use_mag once a field sample came;
    imu/steady_state (imu_complementary_filter's, std_msgs/Bool): the rest detector, false
    until the sensor has been still for rest_time, false again once it turns."""
    h = harness({"publish_debug_topics": True, "use_mag": True, "rest_time": 0.5,
                 "yaw_offset": 0.2})
    raw, steady = [], []
    h.cli.create_subscription(Vector3Stamped, "imu/rpy/raw", raw.append, 500)
    h.cli.create_subscription(Bool, "imu/steady_state", steady.append, 500)
    assert h.spin_until(lambda: h.est._debug["rpy_raw"].get_subscription_count() > 0
                        and h.est._debug["steady"].get_subscription_count() > 0)
    roll, g = 0.3, 9.80665
    acc = (0.0, g * math.sin(roll), g * math.cos(roll))  # R = Rx(roll): a = Rᵀ (0, 0, g)
    north = np.array([0.0, 20e-6, -40e-6])  # ENU: the field points north and down
    c, s = math.cos(roll), math.sin(roll)
    field = np.array([[1, 0, 0], [0, c, s], [0, -s, c]]) @ north  # Rᵀ m: body x points east
    h.send_imu([T0 + 0.01 * k for k in range(5)], acc=acc)
    assert h.spin_until(lambda: len(steady) == 5) and raw == []  # no field sample yet
    msgs = []
    for k in range(5, 105):  # 1 s at rest, a field sample every 10th IMU sample
        msgs.append(imu_msg(T0 + 0.01 * k, (0.0, 0.0, 0.0), acc))
        if k % 10 == 5:
            msgs.append(mag_msg(T0 + 0.01 * k, field))
    h.send(msgs)
    assert h.spin_until(lambda: len(raw) == 99 and len(steady) == 105)
    for r in raw:  # the yaw offset applies as to imu/data (heading 0 is east in ENU)
        np.testing.assert_allclose([r.vector.x, r.vector.y, r.vector.z], [roll, 0.0, 0.2],
                                   atol=1e-9)
    assert raw[0].header.stamp == h.out[6].header.stamp
    flags = [m.data for m in steady]
    assert not any(flags[:40]) and all(flags[70:])  # still for rest_time (0.5 s), then rest
    h.send_imu([T0 + 1.05 + 0.01 * k for k in range(20)], gyr=(0.0, 0.0, 1.0), acc=acc)
    assert h.spin_until(lambda: len(steady) == 125)
    assert not any(m.data for m in steady[-15:])


@pytest.mark.parametrize("publisher_reliability",
                         [ReliabilityPolicy.BEST_EFFORT, ReliabilityPolicy.RELIABLE])
def test_default_qos_takes_best_effort_and_reliable(harness, publisher_reliability) -> None:
    h = harness(reliable=False)
    assert h.get("qos_overrides./imu/data_raw.subscription.reliability") == ["best_effort"]
    pub = h.cli.create_publisher(Imu, "imu/data_raw",
                                 QoSProfile(depth=10, reliability=publisher_reliability))
    assert h.spin_until(lambda: pub.get_subscription_count() > 0)
    for k in range(5):
        pub.publish(imu_msg(T0 + 0.01 * k, (0, 0, 0), (0, 0, 9.8)))
        h.spin_for(0.02)
    assert h.spin_until(lambda: len(h.out) == 5)


def test_covariances_copied_filled_or_estimated(harness) -> None:
    h = harness({"angular_velocity_stddev": 0.01, "linear_acceleration_stddev": 0.2})
    unknown = imu_msg(T0, (0.1, 0.0, 0.0), (0.0, 0.0, 9.8))
    known = imu_msg(T0 + 0.01, (0.1, 0.0, 0.0), (0.0, 0.0, 9.8))
    known.angular_velocity_covariance = np.diag([1e-6, 2e-6, 3e-6]).reshape(9)
    known.linear_acceleration_covariance = np.diag([1e-3, 2e-3, 3e-3]).reshape(9)
    h.send([unknown, known])
    a, b = h.out
    np.testing.assert_allclose(a.angular_velocity_covariance, np.diag([1e-4] * 3).reshape(9))
    np.testing.assert_allclose(a.linear_acceleration_covariance, np.diag([0.04] * 3).reshape(9))
    np.testing.assert_array_equal(b.angular_velocity_covariance, known.angular_velocity_covariance)
    np.testing.assert_array_equal(b.linear_acceleration_covariance,
                                  known.linear_acceleration_covariance)
    assert b.angular_velocity.x == 0.1  # the input, as received
    assert h.set(angular_velocity_source="estimate")[0].successful
    h.send([imu_msg(T0 + 0.02, (0.1, 0.0, 0.0), (0.0, 0.0, 9.8))])
    c = h.out[-1]
    assert c.angular_velocity.x == pytest.approx(h.est.stream.filter.omega[0])
    cov = np.reshape(c.angular_velocity_covariance, (3, 3))
    assert np.all(np.linalg.eigvalsh(cov) > 0)  # the filter's rate covariance


def test_big_endian_input_takes_the_message_path(harness) -> None:
    """Input that is not little-endian CDR (a big-endian publisher) cannot take the raw fast
    path: the node deserialises it with rclpy and answers through message objects. The
    estimate is the ROS-free adapter's on the samples sent, field by field, to the last bit,
    like the little-endian path's."""
    from rclpy.serialization import serialize_message
    from rosbags.typesys import Stores, get_typestore
    from rosharness import record_arrival, recording_messages, reference_outputs

    from mkf_ros.sim import simulate
    from mkf_ros.stream.adapter import StreamAdapter

    ts = get_typestore(Stores.ROS2_JAZZY)

    def big_endian(m) -> bytes:
        name = "sensor_msgs/msg/Imu" if isinstance(m, Imu) else "sensor_msgs/msg/MagneticField"
        le = serialize_message(m)
        assert le[:2] == b"\x00\x01"  # CDR little endian
        be = bytes(ts.serialize_cdr(ts.deserialize_cdr(le, name), name, little_endian=False))
        assert be[:2] == b"\x00\x00"  # CDR big endian
        return be

    rec = simulate("slow_rotation", duration=0.5, rate=100.0, seed=2, mag_rate=50.0)
    sent = recording_messages(rec, T0)
    params = {"use_mag": True}
    outs = {}
    for ns, wire in (("/le", None), ("/be", big_endian)):
        h = harness(params, namespace=ns)
        kinds = record_arrival(h.est.stream)
        slow: list[int] = []  # IMU messages that took the message-object path
        h.est._on_imu_msg = lambda msg, s=slow, f=h.est._on_imu_msg: (s.append(1), f(msg))[1]
        if wire is None:
            h.send(sent)
        else:
            for m in sent:
                (h.pub_imu if isinstance(m, Imu) else h.pub_mag).publish(wire(m))
            assert h.spin_until(lambda h=h: h.received() >= len(sent), 10.0)
            assert h.spin_until(lambda h=h: len(h.out) >= h.est._published, 5.0)
        assert h.est._exceptions == 0, h.est._last_exception
        ref = reference_outputs(StreamAdapter(params), sent, kinds)
        sent_imu = [m for m in sent if isinstance(m, Imu)]
        assert len(h.out) == len(sent_imu) and all(r is not None for r in ref)
        for m, inp, r in zip(h.out, sent_imu, ref, strict=True):
            assert_message_is(m, inp, r)
        assert h.est.stream.counters["mag_received"] == len(sent) - len(sent_imu)
        assert len(slow) == (0 if wire is None else len(sent_imu))
        outs[ns] = [quat(m) for m in h.out]
    np.testing.assert_array_equal(outs["/le"], outs["/be"])
