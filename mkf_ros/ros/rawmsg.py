"""Fast path for the node: ``sensor_msgs/Imu`` and ``MagneticField`` as serialized CDR bytes.

At 1 kHz the Python message objects cost more than the filter: deserialising an Imu builds
six nested objects and three arrays, and publishing one serialises them again. The node
therefore subscribes with ``raw=True`` and reads the fixed layout with :mod:`struct`, and
publishes ``imu/data`` as bytes: the input's header bytes followed by the 37 doubles of the
estimate. Only little-endian plain CDR (encapsulation ``00 01``, what every ROS 2 RMW on
x86/ARM sends) is handled here; anything else returns None and the node falls back to
``rclpy.serialization`` and message objects.

The node's per-message path uses no numpy either (each numpy call costs microseconds when
the caches are cold, as they are between two messages): :func:`unpack_imu` reads the message
with one :mod:`struct` call, :func:`pack_imu_event` writes the readings into the adapter's
event record (:attr:`StreamAdapter.imu_event_bytes
<mkf_ros.stream.adapter.StreamAdapter.imu_event_bytes>`) and :meth:`ImuEncoder.encode_record`
builds the output from the adapter's output record with another.

The layout (header, padding, the float64 fields and their order) is the one
:mod:`mkf_ros.bags.cdr` decodes bags with: :data:`mkf_ros.bags.cdr.IMU` and
:data:`~mkf_ros.bags.cdr.MAGNETIC_FIELD`.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.stream import kernel as sk
from mkf_ros.stream import rep145
from mkf_ros.stream.adapter import StreamOutput, covariance_out

_HEAD = struct.Struct("<iII")  # header.stamp.sec, header.stamp.nanosec, frame_id length
_STAMP = struct.Struct("<iI")  # header.stamp
_NAN3 = (math.nan,) * 3
_LE = cdr.CDR_LE[:2]
IMU_DOUBLES = cdr.IMU.doubles
MAG_DOUBLES = cdr.MAGNETIC_FIELD.doubles
# offsets into the Imu doubles
Q, QC, W, WC, A, AC = (cdr.IMU.offsets()[f][0] for f in (
    "orientation", "orientation_covariance", "angular_velocity", "angular_velocity_covariance",
    "linear_acceleration", "linear_acceleration_covariance"))


class RawHeader:
    """The parsed header of a serialized message and a view of its doubles."""

    __slots__ = ("buf", "d", "frame_id", "nanosec", "off", "prefix", "sec", "stamp")

    def __init__(self, buf: bytes, n_doubles: int) -> None:
        sec, nsec, n = _HEAD.unpack_from(buf, cdr.HEADER_BYTES)
        end = cdr.HEADER_BYTES + _HEAD.size + n  # frame_id ends (NUL included)
        off = cdr.HEADER_BYTES + cdr.body_offset(n - 1)
        if n == 0 or len(buf) < off + 8 * n_doubles:
            raise ValueError(f"truncated message ({len(buf)} bytes)")
        self.sec, self.nanosec = sec, nsec
        self.stamp = sec + nsec * 1e-9
        self.frame_id = buf[end - n:end - 1].decode("utf-8", "replace")
        self.buf, self.off = buf, off
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


def _changing_fields(flags: int) -> tuple[np.ndarray, np.ndarray]:
    """The output doubles that change from sample to sample (the estimate; the rates and the
    acceleration when present; the rate covariance when it is the filter's) and where they
    are in the output record: ``(dst, src)`` for ``out[dst] = values[src]``."""
    dst = [np.arange(Q, Q + 4), np.arange(QC, QC + 9)]
    src = [_XYZW, np.arange(_OCOV.start, _OCOV.stop)]
    for flag, at, n, field in ((sk.OF_W, W, 3, _OW), (sk.OF_WCOV, WC, 9, _OWCOV),
                               (sk.OF_LIN, A, 3, _OLIN)):
        if flags & flag:
            dst.append(np.arange(at, at + n))
            src.append(np.arange(field.start, field.stop))
    return np.concatenate(dst), np.concatenate(src)


_DOUBLES = struct.Struct(f"<{IMU_DOUBLES}d")  # the Imu message after its header
_VEC4 = struct.Struct("<4d")
assert (WC, AC) == (W + 3, A + 3)  # each vector followed by its covariance
# the adapter's records as bytes: the fields read and written here, from their dtypes
_EV = sk.EVENT.fields
assert _EV is not None
assert (_EV["stamp"][1], _EV["v"][1], _EV["a"][1]) == (0, 8, 32), "EVENT layout changed"
_EVENT = struct.Struct("<7d")  # stamp, v (gyro), a (accelerometer)
_OF = sk.OUTPUT.fields
assert _OF is not None
assert all(_OF[f][0].base == np.float64 for f in ("q", "cov", "w", "wcov", "lin"))
# the output record's fields as byte ranges: q is [w, x, y, z], the message's [x, y, z, w]
_REC_W0, _REC_XYZ = slice(_OF["q"][1], _OF["q"][1] + 8), slice(_OF["q"][1] + 8, _OF["q"][1] + 32)
_REC_COV, _REC_W, _REC_WCOV, _REC_LIN = (
    slice(_OF[f][1], _OF[f][1] + _OF[f][0].itemsize) for f in ("cov", "w", "wcov", "lin"))
_ZERO3_BYTES = bytes(24)
_ANY3 = np.zeros(3)  # a value present (the covariance rules ask only whether there is one)


def unpack_imu(buf: bytes) -> tuple[int, int, int, Any, Any] | None:
    """``(sec, nanosec, offset of the doubles, gyr, acc)`` of a serialized Imu: ``gyr`` and
    ``acc`` 3 floats each, None for a field whose covariance[0] is -1
    (:func:`mkf_ros.stream.rep145.not_reported`); None for anything but little-endian plain
    CDR; ValueError when truncated. Reads only these (two :mod:`struct` calls)."""
    if not buf.startswith(_LE):
        return None
    sec, nsec, n = _HEAD.unpack_from(buf, cdr.HEADER_BYTES)
    off = _BODY.get(n)
    if off is None:
        off = _BODY[n] = cdr.HEADER_BYTES + cdr.body_offset(n - 1)
    if n == 0 or len(buf) < off + 8 * IMU_DOUBLES:
        raise ValueError(f"truncated message ({len(buf)} bytes)")
    g = _VEC4.unpack_from(buf, off + 8 * W)  # angular_velocity, then its covariance[0]
    a = _VEC4.unpack_from(buf, off + 8 * A)
    return (sec, nsec, off, None if rep145.not_reported(g[3]) else g[:3],
            None if rep145.not_reported(a[3]) else a[:3])


def doubles(buf: bytes, off: int) -> tuple[float, ...]:
    """The 37 doubles of a serialized Imu whose doubles start at ``off``."""
    return _DOUBLES.unpack_from(buf, off)


#: the offset of the doubles by frame_id length (NUL included)
_BODY: dict[int, int] = {}


def pack_imu_event(event: memoryview, stamp: float, gyr: Any, acc: Any) -> None:
    """The stamp and the readings (3 numbers each; None: not reported, NaN) into the bytes of
    the adapter's IMU event record
    (:attr:`~mkf_ros.stream.adapter.StreamAdapter.imu_event_bytes`)."""
    _EVENT.pack_into(event, 0, stamp, *(_NAN3 if gyr is None else gyr),
                     *(_NAN3 if acc is None else acc))


def frame_id(buf: bytes) -> str:
    """The header's frame_id of a serialized message."""
    n = _HEAD.unpack_from(buf, cdr.HEADER_BYTES)[2]
    at = cdr.HEADER_BYTES + _HEAD.size
    return buf[at:at + max(n - 1, 0)].decode("utf-8", "replace")


def restamped_prefix(buf: bytes, off: int, sec: int, nanosec: int) -> bytes:
    """The header bytes of ``buf`` (up to the doubles at ``off``) with another stamp."""
    at = cdr.HEADER_BYTES
    return buf[:at] + _STAMP.pack(sec, nanosec) + buf[at + 8:off]


class ImuEncoder:
    """Builds the serialized ``imu/data`` message from the input's bytes and an estimate,
    with the same rules as :func:`mkf_ros.ros.convert.fill_imu`.

    Per message (:meth:`encode_values`) only the fields that change from sample to sample
    are written: drivers send the same covariances every time, so the covariance fields of
    the output (REP-145's rules, :mod:`mkf_ros.stream.rep145`) are worked out once per input
    covariances, parameters and present fields, and kept."""

    def __init__(self) -> None:
        self._out = np.zeros(IMU_DOUBLES, dtype="<f8")
        self._cache: dict[tuple[bytes, float], np.ndarray] = {}
        self._layout: tuple[Any, ...] | None = None  # the key of the kept fields
        self._record_layout: tuple[Any, ...] | None = None  # encode_record's
        self._kept: tuple[bytes, bytes] = (b"", b"")
        self._dst = self._src = np.zeros(0, dtype=np.intp)

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
        q = est.quat
        return self._encode(h, (q[1], q[2], q[3], q[0]), est.cov.reshape(9),
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
        if flags & sk.OF_WADD:  # bias_corrected: the covariance changes with every sample
            self._layout = None
            return self._encode_all(h, values, flags, angular_velocity_stddev,
                                    linear_acceleration_stddev)
        b, at = h.buf, h.off
        key = (flags, angular_velocity_stddev, linear_acceleration_stddev,
               b[at + 8 * WC:at + 8 * WC + 72], b[at + 8 * AC:at + 8 * AC + 72])
        if key != self._layout:  # new covariances or fields: everything, and what changes
            self._layout = key
            self._dst, self._src = _changing_fields(flags)
            return self._encode_all(h, values, flags, angular_velocity_stddev,
                                    linear_acceleration_stddev)
        o = self._out
        o[self._dst] = values[self._src]
        return h.prefix + o.tobytes()

    def encode_record(self, buf: bytes, off: int, record: memoryview,
                      flags: int, angular_velocity_stddev: float,
                      linear_acceleration_stddev: float, prefix: bytes | None = None) -> bytes:
        """The bytes :meth:`encode_values` builds, from the input message ``buf`` (its
        doubles at ``off``, :func:`unpack_imu`) and the adapter's output record as bytes
        (:attr:`~mkf_ros.stream.adapter.StreamAdapter.output_bytes`): the record's float64
        fields copied as bytes (no number is converted), and the covariances that do not
        change from sample to sample (the input's, REP-145's rules) worked out once per input
        covariances and kept. Not for ``OF_WADD`` (the bias-corrected rate's covariance
        changes every sample: :meth:`encode_values`). ``prefix``: the output's header bytes,
        if not the input's."""
        wc, ac = off + 8 * WC, off + 8 * AC
        key = self._record_layout
        if (key is None or key[0] != flags or key[1] != angular_velocity_stddev
                or key[2] != linear_acceleration_stddev or not buf.startswith(key[3], wc)
                or not buf.startswith(key[4], ac)):
            self._record_layout = (flags, angular_velocity_stddev, linear_acceleration_stddev,
                                   buf[wc:wc + 72], buf[ac:ac + 72])
            self._kept = self._kept_covariances(doubles(buf, off), flags,
                                                angular_velocity_stddev,
                                                linear_acceleration_stddev)
        wcov, lincov = self._kept
        has_w = flags & sk.OF_W
        return b"".join((
            buf[:off] if prefix is None else prefix,
            record[_REC_XYZ], record[_REC_W0], record[_REC_COV],  # x, y, z, w; covariance
            record[_REC_W] if has_w else _ZERO3_BYTES,
            record[_REC_WCOV] if has_w and flags & sk.OF_WCOV else wcov,
            record[_REC_LIN] if flags & sk.OF_LIN else _ZERO3_BYTES, lincov))

    def _kept_covariances(self, d: tuple[float, ...], flags: int,
                          angular_velocity_stddev: float, linear_acceleration_stddev: float
                          ) -> tuple[bytes, bytes]:
        """The published rate and acceleration covariances from the input's (REP-145:
        :func:`mkf_ros.stream.rep145.published_covariance`), as bytes."""
        w = _ANY3 if flags & sk.OF_W else None  # present or not: the rule needs no value
        lin = _ANY3 if flags & sk.OF_LIN else None
        wcov = rep145.published_covariance(w, None, np.array(d[WC:WC + 9]),
                                           angular_velocity_stddev, fill=self._cov)
        lincov = rep145.published_covariance(lin, None, np.array(d[AC:AC + 9]),
                                             linear_acceleration_stddev, fill=self._cov)
        return (np.ascontiguousarray(wcov, dtype="<f8").tobytes(),
                np.ascontiguousarray(lincov, dtype="<f8").tobytes())

    def _encode_all(self, h: RawHeader, values: np.ndarray, flags: int,
                    angular_velocity_stddev: float, linear_acceleration_stddev: float) -> bytes:
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
