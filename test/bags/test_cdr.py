"""The vectorised CDR codecs agree with rosbags' (de)serialisation, byte for byte."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore  # a hard dependency (install_requires)

from mkf_ros.bags import cdr

ts = get_typestore(Stores.ROS2_JAZZY)


def _rosbags_imu(i: int, frame: str) -> object:
    T = ts.types
    v = lambda a: T["geometry_msgs/msg/Vector3"](x=a[0], y=a[1], z=a[2])  # noqa: E731
    r = np.random.default_rng(i)
    return T["sensor_msgs/msg/Imu"](
        header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=1_700_000_000 + i, nanosec=123 * i),
            frame_id=frame),
        orientation=T["geometry_msgs/msg/Quaternion"](x=r.normal(), y=r.normal(),
                                                      z=r.normal(), w=r.normal()),
        orientation_covariance=r.normal(size=9),
        angular_velocity=v(r.normal(size=3)), angular_velocity_covariance=r.normal(size=9),
        linear_acceleration=v(r.normal(size=3)),
        linear_acceleration_covariance=r.normal(size=9))


@pytest.mark.parametrize("frame", ["", "a", "imu_link", "a_rather_long_frame_id_0123"])
def test_decode_matches_rosbags(frame: str) -> None:
    msgs = [_rosbags_imu(i, frame) for i in range(5)]
    raws = [bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu")) for m in msgs]
    d = cdr.decode(raws, cdr.IMU)
    assert d.frame_ids == [frame]
    for i, m in enumerate(msgs):
        assert d.stamp_ns[i] == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
        o = m.orientation
        np.testing.assert_array_equal(d.fields["orientation"][i], [o.x, o.y, o.z, o.w])
        av, la = m.angular_velocity, m.linear_acceleration
        np.testing.assert_array_equal(d.fields["angular_velocity"][i], [av.x, av.y, av.z])
        np.testing.assert_array_equal(d.fields["linear_acceleration"][i], [la.x, la.y, la.z])
        for name in ("orientation_covariance", "angular_velocity_covariance",
                     "linear_acceleration_covariance"):
            np.testing.assert_array_equal(d.fields[name][i], getattr(m, name))
    assert d.rows is not None and bytes(d.rows[2]) == raws[2]


def test_mixed_frame_lengths_keep_the_input_order() -> None:
    frames = ["a", "imu_link", "a", "xy_long_frame_name", "imu_link"]
    msgs = [_rosbags_imu(i, f) for i, f in enumerate(frames)]
    raws = [bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Imu")) for m in msgs]
    d = cdr.decode(raws, cdr.IMU)
    assert d.rows is None and set(d.frame_ids) == set(frames)
    assert list(d.stamp_ns) == [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                                for m in msgs]
    np.testing.assert_array_equal(d.fields["angular_velocity"][3],
                                  [msgs[3].angular_velocity.x, msgs[3].angular_velocity.y,
                                   msgs[3].angular_velocity.z])


@pytest.mark.parametrize("layout", [cdr.IMU, cdr.MAGNETIC_FIELD, cdr.QUATERNION_STAMPED])
def test_encode_is_what_rosbags_reads_and_writes(layout: cdr.Layout) -> None:
    r = np.random.default_rng(3)
    n = 4
    stamps = np.array([0, 1, 1_704_067_200_123_456_789, 2**31 * 10**9 - 1], dtype=np.int64)
    values = {name: r.normal(size=(n, c)) for name, c in layout.fields}
    rows = cdr.encode(layout, stamps, "imu_link", **values)
    for i in range(n):
        m = ts.deserialize_cdr(bytes(rows[i]), layout.msgtype)
        assert m.header.frame_id == "imu_link"
        assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == stamps[i]
        assert bytes(ts.serialize_cdr(m, layout.msgtype)) == bytes(rows[i])
    back = cdr.decode(cdr.split_rows(rows), layout)
    for name in values:
        np.testing.assert_array_equal(back.fields[name], values[name])


def test_set_fields_patches_in_place() -> None:
    rows = cdr.encode(cdr.IMU, np.arange(3), "imu", angular_velocity=[1.0, 2.0, 3.0])
    cdr.set_fields(rows, cdr.IMU, orientation=np.tile([0.0, 0.0, 0.6, 0.8], (3, 1)))
    m = ts.deserialize_cdr(bytes(rows[1]), "sensor_msgs/msg/Imu")
    assert (m.orientation.z, m.orientation.w) == (0.6, 0.8)
    assert (m.angular_velocity.x, m.angular_velocity.z) == (1.0, 3.0)


def test_wrong_or_corrupt_messages_are_rejected() -> None:
    mag = cdr.split_rows(cdr.encode(cdr.MAGNETIC_FIELD, np.arange(2), "imu"))
    with pytest.raises(cdr.CdrError, match="does not match sensor_msgs/msg/Imu"):
        cdr.decode(mag, cdr.IMU, "/imu")
    imu = cdr.split_rows(cdr.encode(cdr.IMU, np.arange(2), "imu"))
    with pytest.raises(cdr.CdrError):
        cdr.decode([r[:-8] for r in imu], cdr.IMU)
    bad = bytearray(imu[0])
    bad[12] = 40  # frame_id length no longer matches the message length
    with pytest.raises(cdr.CdrError, match="corrupt"):
        cdr.decode([bytes(bad)], cdr.IMU)
    big_endian = b"\x00\x00\x00\x00" + imu[0][4:]
    with pytest.raises(cdr.CdrError, match="encapsulation"):
        cdr.decode([big_endian], cdr.IMU)


def test_clock_message() -> None:
    raw = cdr.clock_message(5 * 10**9 + 7)
    m = ts.deserialize_cdr(raw, "rosgraph_msgs/msg/Clock")
    assert (m.clock.sec, m.clock.nanosec) == (5, 7)
