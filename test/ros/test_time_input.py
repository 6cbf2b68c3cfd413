"""Time and bad input through the node: every case is dropped or skipped and counted, the
node never publishes NaN and never dies on a message."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rosgraph_msgs.msg import Clock
from rosharness import finite, imu_msg, mag_msg, quat

from mkf_ros.ros import convert

pytestmark = pytest.mark.ros
T0 = 100.0
G = (0.0, 0.0, 9.80665)


def yaw(m) -> float:
    q = quat(m)
    return 2 * math.atan2(q[3], q[0])


def test_not_published_before_initialisation(harness) -> None:
    h = harness()
    h.send([imu_msg(T0, (0, 0, 0), None), imu_msg(T0 + 0.01, (0, 0, 0), (0, 0, 0))])
    assert h.out == [] and not h.est.stream.initialized
    h.send_imu([T0 + 0.02])
    assert len(h.out) == 1
    assert any(h.out[0].orientation_covariance), "orientation_covariance never all zero"


def test_duplicate_and_out_of_order_dropped(harness) -> None:
    h = harness()
    h.send_imu([T0, T0 + 0.01, T0 + 0.02, T0 + 0.02, T0 + 0.015, T0 + 0.03])
    stamps = [convert.stamp_to_sec(m.header.stamp) for m in h.out]
    np.testing.assert_allclose(stamps, [T0, T0 + 0.01, T0 + 0.02, T0 + 0.03])
    c = h.est.stream.counters
    assert (c["imu_duplicate"], c["imu_out_of_order"], c["resets"]) == (1, 1, 0)


def test_bag_loop_resets(harness) -> None:
    h = harness()
    h.send_imu([T0 + 0.01 * k for k in range(50)], gyr=(0.0, 0.0, 1.0))
    assert yaw(h.out[-1]) > 0.4
    h.send_imu([T0 - 10.0 + 0.01 * k for k in range(5)])  # the bag starts again
    assert h.est.stream.counters["resets_time_jump"] == 1
    assert len(h.out) == 55
    assert abs(yaw(h.out[50])) < 1e-9  # re-initialised from the first sample after the loop


def test_sim_time_jump_back_resets(harness) -> None:
    h = harness({"use_sim_time": True})
    clock = h.cli.create_publisher(Clock, "/clock", 10)
    assert h.spin_until(lambda: clock.get_subscription_count() > 0)

    def tick(t: float) -> None:
        clock.publish(Clock(clock=convert.sec_to_stamp(t)))
        assert h.spin_until(lambda: abs(h.est.get_clock().now().nanoseconds * 1e-9 - t) < 1e-6)

    tick(T0)
    h.send_imu([T0 + 0.01 * k for k in range(10)])
    assert h.est.stream.counters["resets"] == 0
    tick(T0 + 1.0)
    assert h.est.stream.counters["resets"] == 0
    tick(T0 - 50.0)  # `ros2 bag play --loop` with /clock
    assert h.est.stream.counters["resets"] == 1
    assert "ROS time jumped back by 51.000 s" in h.est.stream.last_reset_reason
    assert not h.est.stream.initialized
    h.send_imu([T0 - 50.0 + 0.01 * k for k in range(3)])
    assert len(h.out) == 13


def test_gap_realigns(harness) -> None:
    h = harness({"max_dt": 0.5})
    h.send_imu([T0 + 0.01 * k for k in range(10)])
    rolled = (0.0, 9.80665 * math.sin(0.4), 9.80665 * math.cos(0.4))
    h.send_imu([T0 + 5.0], acc=rolled)
    q = quat(h.out[-1])
    assert 2 * math.atan2(q[1], q[0]) == pytest.approx(0.4, abs=1e-6)
    assert h.est.stream.all_counters()["gaps"] == 1


def test_bad_vectors_skipped_counted_never_nan(harness) -> None:
    h = harness({"use_mag": True})
    nan, inf = math.nan, math.inf
    h.send_imu([T0 + 0.01 * k for k in range(5)])
    t = T0 + 0.05
    msgs = [
        imu_msg(t, (nan, nan, nan), G),  # gyro missing: published, angular velocity -1
        imu_msg(t + 0.01, (nan, 0.0, 0.0), G),  # gyro invalid
        imu_msg(t + 0.02, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),  # zero accelerometer
        imu_msg(t + 0.03, (0.0, 0.0, 0.0), (inf, 0.0, 9.8)),  # Inf accelerometer
        imu_msg(t + 0.04, (0.0, 0.0, 0.0), (0.0, 0.0, 0.9)),  # in g, or gravity removed
        imu_msg(t + 0.05, None, None),  # both not reported (covariance[0] = -1)
        mag_msg(t + 0.05, (nan, nan, nan)),  # phidgets-style empty magnetometer sample
        mag_msg(t + 0.05, (inf, 0.0, 1e-5)),
        mag_msg(t + 0.05, (0.0, 0.0, 0.0)),
        imu_msg(t + 0.06, (0.0, 0.0, 0.0), G),
    ]
    h.send(msgs)
    assert all(finite(m) for m in h.out)
    c = h.est.stream.counters
    assert (c["gyr_missing"], c["gyr_invalid"]) == (2, 1)
    assert (c["acc_missing"], c["acc_invalid"], c["acc_implausible"]) == (1, 2, 1)
    assert (c["mag_missing"], c["mag_invalid"]) == (1, 2)
    assert len(h.out) == 5 + 7
    assert h.out[5].angular_velocity_covariance[0] == -1.0  # "not reported", REP-145
    assert h.out[10].linear_acceleration_covariance[0] == -1.0
    assert h.out[9].linear_acceleration.z == pytest.approx(0.9)  # passed through
    assert h.est._exceptions == 0


def test_zero_stamps_take_the_receive_time(harness, capfd) -> None:
    """A driver that does not stamp (header stamps zero, as imu_filter_madgwick accepts them):
    each message takes its receive time (the node's clock) as its stamp, in the filter and in
    the header of what is published for it, with one warning per input; constant_dt still
    sets the step."""
    h = harness({"use_mag": True})
    before = h.est.get_clock().now().nanoseconds
    h.send([imu_msg(0.0, (0, 0, 0), G), mag_msg(0.0, (20e-6, 0.0, -40e-6)),
            imu_msg(0.0, (0, 0, 0), G), imu_msg(0.0, (0, 0, 0), G)])
    after = h.est.get_clock().now().nanoseconds
    stamps = [m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in h.out]
    assert len(stamps) == 3 and before <= stamps[0] < stamps[1] < stamps[2] <= after
    assert all(finite(m) for m in h.out)
    c = h.est.stream.counters
    assert (c["imu_bad_stamp"], c["mag_fused"]) == (0, 1)
    assert h.est.stamped_on_receipt == {"imu": 3, "acc": 0, "mag": 1}
    err = capfd.readouterr().err
    assert err.count("/imu/data_raw have a zero header stamp") == 1
    assert err.count("/imu/mag have a zero header stamp") == 1
    assert h.set(constant_dt=0.01)[0].successful
    h.send([imu_msg(0.0, (0.0, 0.0, 1.0), G) for _ in range(101)])
    assert len(h.out) == 104
    assert h.out[-1].header.stamp.sec > 0
    turned = yaw(h.out[-1]) - yaw(h.out[2])
    assert turned == pytest.approx(1.01, abs=0.02)  # 101 × 0.01 s × 1 rad/s


def test_magnetometer_never_gates_the_imu(harness) -> None:
    h = harness({"use_mag": True})
    h.send_imu([T0 + 0.01 * k for k in range(20)])
    assert len(h.out) == 20 and not h.est.stream.filter.heading_initialized
    msgs = []
    for k in range(20, 40):
        msgs.append(imu_msg(T0 + 0.01 * k, (0, 0, 0), G))
        if k % 5 == 0:
            msgs.append(mag_msg(T0 + 0.01 * k - 0.003, (20e-6, 20e-6, -40e-6)))
    h.send(msgs)
    assert len(h.out) == 40 and h.est.stream.filter.heading_initialized
    assert abs(math.degrees(yaw(h.out[-1]))) == pytest.approx(45.0, abs=0.5)
    h.send_imu([T0 + 0.01 * k for k in range(40, 60)])  # the magnetometer stops
    assert len(h.out) == 60


def test_never_dies_on_a_message(harness) -> None:
    """An exception inside the processing is counted and reported; the node goes on."""
    h = harness({"diagnostics_period": 0.2})
    real = h.est.stream.run_imu_event  # the node's per-message path
    calls = {"n": 0}

    def flaky(*a):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("boom")
        return real(*a)

    h.est.stream.run_imu_event = flaky
    h.send_imu([T0 + 0.01 * k for k in range(6)])
    assert len(h.out) == 5 and h.est._exceptions == 1
    assert h.spin_until(lambda: any(s.level == b"\x02" for d in h.diag for s in d.status), 3.0)
    st = next(s for d in h.diag for s in d.status if s.level == b"\x02")
    assert "RuntimeError: boom" in st.message


def test_never_nan_at_valid_range_ends_or_with_huge_finite_readings(harness) -> None:
    """Valid settings must give valid output: at these the bias variance went negative at the first
    rest update and every angular_velocity_covariance was NaN; a gyro of 1e150 or a field of 1e155
    was a reading."""
    from mkf_ros.sim import simulate

    h = harness({"use_mag": True, "gyro_noise": 1e-6, "rate_process_noise": 1e9,
                 "rest_rate_stddev": 1e-6, "angular_velocity_source": "bias_corrected"})
    rec = simulate("static", duration=3, rate=100, seed=1)
    h.send_recording(rec)
    assert len(h.out) == rec.t.size
    t = T0 + 3.01
    h.send([imu_msg(t, (1e150, 0.0, 0.0), G), imu_msg(t + 0.01, (0.0, 0.0, 0.0), (1e200, 0, 0)),
            mag_msg(t + 0.01, (1e155, 0.0, 1e155)), imu_msg(t + 0.02, (0.0, 0.0, 0.0), G)])
    assert len(h.out) == rec.t.size + 3
    assert all(finite(m) for m in h.out)
    c = h.est.stream.counters
    assert (c["gyr_invalid"], c["acc_invalid"], c["mag_invalid"]) == (1, 1, 1)
    assert h.est._exceptions == 0


def test_magnetometer_messages_keep_rest(harness) -> None:
    """At rest for 3 s (rest_time 1 s) with the magnetometer on its own topic: each field
    message, an event of its own after the IMU message of its stamp, used to reset the rest
    test (0 rest updates in the node, 200 in StreamAdapter.process, which merges the field into
    the IMU sample). Now the node makes as many as the merged recording."""
    from mkf_ros.sim import simulate
    from mkf_ros.stream.adapter import StreamAdapter

    h = harness({"use_mag": True})
    rec = simulate("static", duration=3, rate=100, seed=1)
    h.send_recording(rec)
    merged = StreamAdapter(use_mag=True)
    merged.process(T0 + rec.t, rec.gyr, rec.acc, T0 + rec.t, rec.mag)
    n = merged.counters["rest_updates"]
    assert n >= 190
    assert abs(h.est.stream.counters["rest_updates"] - n) <= 1
