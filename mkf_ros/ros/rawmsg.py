"""Fast path for the node: ``sensor_msgs/Imu`` and ``MagneticField`` as serialized CDR bytes.

At 1 kHz the Python message objects cost more than the filter: deserialising an Imu builds
six nested objects and three arrays, and publishing one serialises them again. The node
therefore subscribes with ``raw=True`` and reads the fixed layout with :mod:`struct`, and
publishes ``imu/data`` as bytes: the input's header bytes followed by the 37 doubles of the
estimate. Only little-endian plain CDR (encapsulation ``00 01``, what every ROS 2 RMW on
x86/ARM sends) is handled here; anything else returns None and the node falls back to
``rclpy.serialization`` and message objects.

The layout (header, padding, the float64 fields and their order) is the one
:mod:`mkf_ros.bags.cdr` decodes bags with: :data:`mkf_ros.bags.cdr.IMU` and
:data:`~mkf_ros.bags.cdr.MAGNETIC_FIELD`.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.stream import kernel as sk
from mkf_ros.stream import rep145
from mkf_ros.stream.adapter import StreamOutput, covariance_out

_HEAD = struct.Struct("<iII")  # header.stamp.sec, header.stamp.nanosec, frame_id length
_STAMP = struct.Struct("<iI")  # header.stamp
_LE = cdr.CDR_LE[:2]
IMU_DOUBLES = cdr.IMU.doubles
MAG_DOUBLES = cdr.MAGNETIC_FIELD.doubles
# offsets into the Imu doubles
Q, QC, W, WC, A, AC = (cdr.IMU.offsets()[f][0] for f in (
    "orientation", "orientation_covariance", "angular_velocity", "angular_velocity_covariance",
    "linear_acceleration", "linear_acceleration_covariance"))


class RawHeader:
    """The parsed header of a serialized message and a view of its doubles."""

    __slots__ = ("d", "frame_id", "nanosec", "prefix", "sec", "stamp")

    def __init__(self, buf: bytes, n_doubles: int) -> None:
        sec, nsec, n = _HEAD.unpack_from(buf, cdr.HEADER_BYTES)
        end = cdr.HEADER_BYTES + _HEAD.size + n  # frame_id ends (NUL included)
        off = cdr.HEADER_BYTES + cdr.body_offset(n - 1)
        if n == 0 or len(buf) < off + 8 * n_doubles:
            raise ValueError(f"truncated message ({len(buf)} bytes)")
        self.sec, self.nanosec = sec, nsec
        self.stamp = sec + nsec * 1e-9
        self.frame_id = buf[end - n:end - 1].decode("utf-8", "replace")
        self.prefix = buf[:off]  # encapsulation + header + padding, reused for the output
        self.d = np.frombuffer(buf, "<f8", n_doubles, off)

    def restamp(self, sec: int, nanosec: int) -> None:
        """Replace the header stamp (here and in :attr:`prefix`, the output's header)."""
        self.sec, self.nanosec = sec, nanosec
        self.stamp = sec + nanosec * 1e-9
        at = cdr.HEADER_BYTES
        self.prefix = self.prefix[:at] + _STAMP.pack(sec, nanosec) + self.prefix[at + 8:]


def parse(buf: bytes, n_doubles: int) -> RawHeader | None:
    """Parse little-endian plain CDR; None for any other encapsulation."""
    if buf[:2] != _LE:
        return None
    return RawHeader(buf, n_doubles)


def imu_arrays(h: RawHeader) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(gyr, acc)`` of a parsed Imu; a field whose covariance[0] is -1 is None."""
    d = h.d  # a read-only view of the message: copy, or numba compiles a read-only variant
    return rep145.input_vector(d[W:W + 3], d[WC]), rep145.input_vector(d[A:A + 3], d[AC])


# fields of the stream kernel's output record viewed as float64 values (StreamAdapter.step_imu)
_OQ, _OCOV, _OW, _OWCOV, _OWADD, _OLIN = (sk.float_slice(sk.OUTPUT, name) for name in (
    "q", "cov", "w", "wcov", "wadd", "lin"))
#: output quaternion [x, y, z, w] from the record's [w, x, y, z]
_XYZW = np.arange(_OQ.start, _OQ.stop)[[1, 2, 3, 0]]


def imu_views(h: RawHeader) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(gyr, acc)`` of a parsed Imu as read-only views of the message (no copies), for
    :meth:`StreamAdapter.step_imu <mkf_ros.stream.adapter.StreamAdapter.step_imu>`, which
    copies them into its event record; a field whose covariance[0] is -1 is None."""
    d = h.d
    return (rep145.input_vector(d[W:W + 3], d[WC], copy=False),
            rep145.input_vector(d[A:A + 3], d[AC], copy=False))


class ImuEncoder:
    """Builds the serialized ``imu/data`` message from the input's bytes and an estimate,
    with the same rules as :func:`mkf_ros.ros.convert.fill_imu`."""

    def __init__(self) -> None:
        self._out = np.zeros(IMU_DOUBLES, dtype="<f8")
        self._cache: dict[tuple[bytes, float], np.ndarray] = {}

    def _cov(self, cov_in: np.ndarray, stddev: float, add: np.ndarray | None) -> np.ndarray:
        if add is not None:
            return covariance_out(cov_in, stddev, add)
        key = (cov_in.tobytes(), stddev)  # drivers send the same covariance every time
        c = self._cache.get(key)
        if c is None:
            if len(self._cache) > 64:
                self._cache.clear()
            c = self._cache[key] = covariance_out(cov_in, stddev)
        return c

    def encode(self, h: RawHeader, est: StreamOutput, angular_velocity_stddev: float,
               linear_acceleration_stddev: float) -> bytes:
        q = est.quat_wxyz
        return self._encode(h, (q[1], q[2], q[3], q[0]), est.orientation_cov.reshape(9),
                            est.angular_velocity, est.angular_velocity_cov,
                            est.angular_velocity_cov_add, est.linear_acceleration,
                            angular_velocity_stddev, linear_acceleration_stddev)

    def encode_values(self, h: RawHeader, values: np.ndarray, flags: int,
                      angular_velocity_stddev: float,
                      linear_acceleration_stddev: float) -> bytes:
        """The same bytes as :meth:`encode` from the output record of
        :meth:`StreamAdapter.step_imu <mkf_ros.stream.adapter.StreamAdapter.step_imu>`
        (``values``: :attr:`~mkf_ros.stream.adapter.StreamAdapter.output_values`, ``flags``
        its return), without a :class:`StreamOutput`: the node's per-message path."""
        return self._encode(
            h, values[_XYZW], values[_OCOV], values[_OW] if flags & sk.OF_W else None,
            values[_OWCOV] if flags & sk.OF_WCOV else None,
            np.diag(values[_OWADD]) if flags & sk.OF_WADD else None,
            values[_OLIN] if flags & sk.OF_LIN else None, angular_velocity_stddev,
            linear_acceleration_stddev)

    def _encode(self, h: RawHeader, q_xyzw: Any, cov9: Any, w: Any, w_cov: Any, w_add: Any,
                a: Any, angular_velocity_stddev: float,
                linear_acceleration_stddev: float) -> bytes:
        """The message: the input's header, then the estimate with REP-145's covariances."""
        d, o = h.d, self._out
        o[Q:Q + 4] = q_xyzw
        o[QC:QC + 9] = cov9
        o[W:W + 3] = 0.0 if w is None else w
        o[WC:WC + 9] = rep145.published_covariance(
            w, w_cov, d[WC:WC + 9], angular_velocity_stddev, w_add, fill=self._cov)
        o[A:A + 3] = 0.0 if a is None else a
        o[AC:AC + 9] = rep145.published_covariance(
            a, None, d[AC:AC + 9], linear_acceleration_stddev, fill=self._cov)
        return h.prefix + o.tobytes()
