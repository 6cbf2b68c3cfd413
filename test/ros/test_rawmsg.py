"""The node's CDR fast path (mkf_ros/ros/rawmsg.py) against rclpy's own serialisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from rosharness import imu_msg
from sensor_msgs.msg import Imu, MagneticField

from mkf_ros.ros import convert, rawmsg
from mkf_ros.stream.adapter import StreamAdapter

pytestmark = pytest.mark.ros


def random_imu(rng: np.random.Generator, frame: str) -> Imu:
    acc = rng.normal(size=3) + np.array([0, 0, 9.8])
    m = imu_msg(float(rng.uniform(1, 2e9)), rng.normal(size=3), acc, frame)
    m.orientation_covariance = rng.normal(size=9)
    m.angular_velocity_covariance = rng.normal(size=9)
    m.linear_acceleration_covariance = rng.normal(size=9)
    return m


@pytest.mark.parametrize("frame", ["", "a", "imu", "imu_link", "imu_link_x", "ünï/côdé"])
def test_parse_matches_rclpy(frame: str) -> None:
    rng = np.random.default_rng(len(frame))
    m = random_imu(rng, frame)
    h = rawmsg.parse(serialize_message(m), rawmsg.IMU_DOUBLES)
    assert h is not None
    assert (h.sec, h.nanosec, h.frame_id) == (m.header.stamp.sec, m.header.stamp.nanosec, frame)
    assert h.stamp == convert.stamp_to_sec(m.header.stamp)
    gyr, acc = rawmsg.imu_arrays(h)
    np.testing.assert_array_equal(gyr, convert.vec(m.angular_velocity))
    np.testing.assert_array_equal(acc, convert.vec(m.linear_acceleration))
    np.testing.assert_array_equal(h.d[rawmsg.WC:rawmsg.WC + 9], m.angular_velocity_covariance)
    mag = MagneticField(header=m.header)
    mag.magnetic_field.x, mag.magnetic_field.y, mag.magnetic_field.z = 1e-5, -2e-5, 3e-5
    hm = rawmsg.parse(serialize_message(mag), rawmsg.MAG_DOUBLES)
    np.testing.assert_array_equal(hm.d[:3], [1e-5, -2e-5, 3e-5])
    assert hm.frame_id == frame


def test_not_reported_fields_and_other_encodings() -> None:
    m = imu_msg(5.0, None, None)
    h = rawmsg.parse(serialize_message(m), rawmsg.IMU_DOUBLES)
    assert rawmsg.imu_arrays(h) == (None, None)
    data = bytearray(serialize_message(m))
    data[1] = 0  # big-endian CDR: not for the fast path
    assert rawmsg.parse(bytes(data), rawmsg.IMU_DOUBLES) is None
    with pytest.raises(ValueError, match="truncated"):
        rawmsg.parse(serialize_message(m)[:100], rawmsg.IMU_DOUBLES)


@pytest.mark.parametrize("source", ["input", "bias_corrected", "estimate"])
@pytest.mark.parametrize("missing", [None, "gyr", "acc"])
def test_encode_equals_the_message_path(source: str, missing: str | None) -> None:
    """Bytes built by ImuEncoder deserialise to exactly what fill_imu writes."""
    rng = np.random.default_rng(3)
    enc = rawmsg.ImuEncoder()
    s = StreamAdapter(angular_velocity_source=source, estimate_gyro_bias=True)
    for k, frame in enumerate(["imu_link", "x", "imu_link", "sensor/imu_0"]):
        m = random_imu(rng, frame)
        m.header.stamp = convert.sec_to_stamp(100.0 + 0.01 * k)
        m.angular_velocity_covariance = [0.0] * 9 if k % 2 else np.diag([1e-4] * 3).reshape(9)
        if missing == "gyr" and k > 0:
            m.angular_velocity_covariance[0] = -1.0
        if missing == "acc" and k > 0:
            m.linear_acceleration_covariance[0] = -1.0
        h = rawmsg.parse(serialize_message(m), rawmsg.IMU_DOUBLES)
        out = s.on_imu(h.stamp, *rawmsg.imu_arrays(h))
        assert out is not None
        got = deserialize_message(enc.encode(h, out, 0.02, 0.3), Imu)
        want = convert.fill_imu(Imu(), m, out, 0.02, 0.3)
        assert got.header == want.header
        for f in ("orientation", "angular_velocity", "linear_acceleration"):
            assert getattr(got, f) == getattr(want, f), f
        for f in ("orientation_covariance", "angular_velocity_covariance",
                  "linear_acceleration_covariance"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f), f)
        assert all(math.isfinite(x) for x in got.orientation_covariance)


def changing_imu_messages(rng: np.random.Generator, missing: str | None, n: int = 12) -> list:
    """``n`` IMU messages 10 ms apart whose covariances change from one to the next (known,
    unknown, and with ``missing`` the gyro's, the accelerometer's or both marked "not
    reported" now and then)."""
    out = []
    for k in range(n):
        m = random_imu(rng, "imu_link")
        m.header.stamp = convert.sec_to_stamp(100.0 + 0.01 * k)
        m.angular_velocity_covariance = [0.0] * 9 if k % 2 else np.diag([1e-4] * 3).reshape(9)
        m.linear_acceleration_covariance = [0.0] * 9 if k % 3 else np.diag([1e-2] * 3).reshape(9)
        if missing in ("gyr", "both") and k % 4 == 3:
            m.angular_velocity_covariance[0] = -1.0
        if missing in ("acc", "both") and k % 4 == 2:
            m.linear_acceleration_covariance[0] = -1.0
        out.append(m)
    return out


@pytest.mark.parametrize("source", ["input", "bias_corrected", "estimate"])
@pytest.mark.parametrize("missing", [None, "gyr", "acc", "both"])
def test_encode_values_equals_encode(source: str, missing: str | None) -> None:
    """The node's per-message path (step_imu + encode_values, no StreamOutput) builds the
    same bytes as on_imu + encode, and step_imu leaves the adapter as on_imu does."""
    rng = np.random.default_rng(5)
    enc, enc_values = rawmsg.ImuEncoder(), rawmsg.ImuEncoder()
    kw: dict = dict(angular_velocity_source=source, estimate_gyro_bias=True,
                    remove_gravity_vector=source == "estimate")
    s, s_values = StreamAdapter(**kw), StreamAdapter(**kw)
    for k, m in enumerate(changing_imu_messages(rng, missing)):
        h = rawmsg.parse(serialize_message(m), rawmsg.IMU_DOUBLES)
        out = s.on_imu(h.stamp, *rawmsg.imu_arrays(h))
        flags = s_values.step_imu(h.stamp, *rawmsg.imu_views(h))
        assert (out is None) == (flags == 0)
        if out is None:
            continue
        want = enc.encode(h, out, 0.02, 0.3 * (k % 2))
        assert enc_values.encode_values(h, s_values.output_values, flags, 0.02,
                                        0.3 * (k % 2)) == want
        last = s_values.last_output()
        for f in ("quat", "cov", "angular_velocity", "angular_velocity_cov",
                  "angular_velocity_cov_add", "linear_acceleration", "bias", "omega"):
            np.testing.assert_array_equal(getattr(last, f), getattr(out, f), f)
        assert (last.stamp, last.yaw_lost, last.slot) == (out.stamp, out.yaw_lost, out.slot)


@pytest.mark.parametrize("source", ["input", "estimate"])
@pytest.mark.parametrize("missing", [None, "gyr", "acc", "both"])
def test_the_node_byte_path_equals_encode(source: str, missing: str | None) -> None:
    """The node's per-message path without numpy (unpack_imu, pack_imu_event,
    run_imu_event, encode_record; the not-reported fields None as imu_arrays has them) builds
    the same bytes as on_imu + encode, message after message, as the input covariances and
    the present fields change."""
    rng = np.random.default_rng(7)
    enc, enc_record = rawmsg.ImuEncoder(), rawmsg.ImuEncoder()
    kw: dict = dict(angular_velocity_source=source, estimate_gyro_bias=True,
                    remove_gravity_vector=source == "estimate")
    s, s_bytes = StreamAdapter(**kw), StreamAdapter(**kw)
    for k, m in enumerate(changing_imu_messages(rng, missing)):
        data = serialize_message(m)
        h = rawmsg.parse(data, rawmsg.IMU_DOUBLES)
        out = s.on_imu(h.stamp, *rawmsg.imu_arrays(h))
        sec, nsec, off, gyr, acc = rawmsg.unpack_imu(data)
        np.testing.assert_array_equal(rawmsg.doubles(data, off), h.d)
        assert (sec, nsec) == (m.header.stamp.sec, m.header.stamp.nanosec)
        rawmsg.pack_imu_event(s_bytes.imu_event_bytes, sec + nsec * 1e-9, gyr, acc)
        assert (gyr is None, acc is None) == tuple(x is None for x in rawmsg.imu_arrays(h))
        flags = s_bytes.run_imu_event()
        assert (out is None) == (flags == 0)
        if out is None:
            continue
        want = enc.encode(h, out, 0.02, 0.3 * (k % 2))
        got = enc_record.encode_record(data, off, s_bytes.output_bytes, flags, 0.02,
                                       0.3 * (k % 2))
        assert got == want
    assert rawmsg.frame_id(data) == "imu_link"
    restamped = rawmsg.restamped_prefix(data, off, 7, 8) + data[off:]
    assert deserialize_message(restamped, Imu).header.stamp.sec == 7
