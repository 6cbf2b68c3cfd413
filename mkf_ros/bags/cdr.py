"""Vectorised CDR codecs for the few stamped messages mkf_ros reads and writes in bulk.

A ROS 2 message in a bag is CDR: a 4-byte encapsulation header (``00 01 00 00`` = little
endian) and the payload, aligned relative to the payload start. The messages used here share a
layout: ``header.stamp`` (``int32 sec``, ``uint32 nanosec``), ``header.frame_id`` (``uint32``
length including the NUL, the characters, the NUL), padding to 8, then only ``float64`` fields.
So within one topic all messages with the same ``frame_id`` length have the same byte length and
the same field offsets, and a batch of them is a 2-D ``uint8`` array whose fields are NumPy views:
no per-message Python work. ``test/bags/test_cdr.py`` checks every codec against rosbags'
own (de)serialisation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

CDR_LE = b"\x00\x01\x00\x00"
HEADER_BYTES = 4  # encapsulation header


class CdrError(ValueError):
    """A message is not what its topic's type says (wrong length, bad string, ...)."""


@dataclass(frozen=True)
class Layout:
    """``float64`` fields after the header: name → (offset in doubles, count)."""

    msgtype: str
    fields: tuple[tuple[str, int], ...]

    @property
    def doubles(self) -> int:
        return sum(n for _, n in self.fields)

    def offsets(self) -> dict[str, tuple[int, int]]:
        out, o = {}, 0
        for name, n in self.fields:
            out[name] = (o, n)
            o += n
        return out


IMU = Layout("sensor_msgs/msg/Imu", (
    ("orientation", 4), ("orientation_covariance", 9),
    ("angular_velocity", 3), ("angular_velocity_covariance", 9),
    ("linear_acceleration", 3), ("linear_acceleration_covariance", 9),
))
MAGNETIC_FIELD = Layout("sensor_msgs/msg/MagneticField", (
    ("magnetic_field", 3), ("magnetic_field_covariance", 9),
))
QUATERNION_STAMPED = Layout("geometry_msgs/msg/QuaternionStamped", (("quaternion", 4),))
LAYOUTS = {x.msgtype: x for x in (IMU, MAGNETIC_FIELD, QUATERNION_STAMPED)}


def _align8(n: np.ndarray | int) -> np.ndarray | int:
    return (n + 7) // 8 * 8


def body_offset(frame_len: int) -> int:
    """Payload offset of the first float64 for a ``frame_id`` of ``frame_len`` characters."""
    return int(_align8(12 + frame_len + 1))


@dataclass
class Decoded:
    """Fields of a batch of messages of one layout, in input order."""

    stamp_ns: np.ndarray  #: (N,) int64, header.stamp in ns
    frame_ids: list[str]  #: distinct frame ids seen (usually one)
    fields: dict[str, np.ndarray]  #: name → (N, count) float64 (copies)
    rows: np.ndarray | None  #: (N, L) uint8 message bytes if all have one length L, else None


def _stamp_ns(sec: np.ndarray, nsec: np.ndarray) -> np.ndarray:
    return sec.astype(np.int64) * 1_000_000_000 + nsec.astype(np.int64)


def _decode_rows(rows: np.ndarray, layout: Layout, topic: str) -> tuple[np.ndarray, str, dict]:
    """Decode an (n, L) uint8 block of equal-length little-endian messages."""
    L = rows.shape[1]
    first = bytes(rows[0, :HEADER_BYTES])
    if first[:2] not in (b"\x00\x01",):
        raise CdrError(f"{topic}: unsupported CDR encapsulation {first.hex()}")
    if (rows[:, 1] != 1).any() or (rows[:, 0] != 0).any():
        raise CdrError(f"{topic}: mixed CDR encapsulations")
    body = layout.doubles * 8
    off = L - HEADER_BYTES - body
    if off < 16 or off % 8:
        raise CdrError(f"{topic}: message of {L} bytes does not match {layout.msgtype}")
    p = rows[:, HEADER_BYTES:]
    sec = np.ascontiguousarray(p[:, 0:4]).view("<i4")[:, 0]
    nsec = np.ascontiguousarray(p[:, 4:8]).view("<u4")[:, 0]
    slen = np.ascontiguousarray(p[:, 8:12]).view("<u4")[:, 0].astype(np.int64)
    if (_align8(12 + slen) != off).any() or (slen < 1).any():
        raise CdrError(f"{topic}: corrupt {layout.msgtype} (frame_id length does not match "
                       "the message length)")
    vals = np.ascontiguousarray(p[:, off:off + body]).view("<f8")
    fields = {name: vals[:, o:o + c].copy() for name, (o, c) in layout.offsets().items()}
    s = int(slen[0])
    frame = bytes(p[0, 12:12 + s - 1]).decode("utf-8", "replace")
    return _stamp_ns(sec, nsec), frame, fields


def decode(raws: Sequence[bytes] | np.ndarray, layout: Layout, topic: str = "") -> Decoded:
    """Decode raw CDR messages (as stored in a bag) of one of :data:`LAYOUTS`: a sequence of
    bytes, or an (N, L) uint8 array of equal-length messages.

    Raises :class:`CdrError` for anything that does not fit the layout (a different message
    type, a truncated message, big-endian data).
    """
    if isinstance(raws, np.ndarray):
        if raws.ndim != 2 or raws.dtype != np.uint8:
            raise TypeError("decode: expected an (N, L) uint8 array")
        if raws.shape[0] == 0:
            return decode([], layout, topic)
        stamp, frame, fields = _decode_rows(raws, layout, topic)
        return Decoded(stamp, [frame], fields, raws)
    n = len(raws)
    names = [name for name, _ in layout.fields]
    if n == 0:
        return Decoded(np.zeros(0, np.int64), [], {k: np.zeros((0, c)) for k, c in
                                                  layout.fields}, np.zeros((0, 0), np.uint8))
    lens = np.fromiter(map(len, raws), dtype=np.int64, count=n)
    uniq = np.unique(lens)
    if len(uniq) == 1:
        rows = np.frombuffer(b"".join(raws), dtype=np.uint8).reshape(n, int(uniq[0]))
        stamp, frame, fields = _decode_rows(rows, layout, topic)
        return Decoded(stamp, [frame], fields, rows)
    stamp = np.empty(n, np.int64)
    fields = {k: np.empty((n, c)) for k, c in layout.fields}
    frames: list[str] = []
    for L in uniq:
        idx = np.flatnonzero(lens == L)
        rows = np.frombuffer(b"".join([raws[i] for i in idx.tolist()]), dtype=np.uint8).reshape(
            len(idx), int(L))
        st, fr, fs = _decode_rows(rows, layout, topic)
        stamp[idx] = st
        for k in names:
            fields[k][idx] = fs[k]
        if fr not in frames:
            frames.append(fr)
    return Decoded(stamp, frames, fields, None)


def encode(layout: Layout, stamp_ns: np.ndarray, frame_id: str,
           **values: np.ndarray | float) -> np.ndarray:
    """(N, L) uint8 rows of little-endian CDR messages; fields not given are zero.

    ``values`` are (N, count) arrays or scalars broadcast to them, by field name.
    """
    stamp_ns = np.asarray(stamp_ns, dtype=np.int64)
    n = stamp_ns.shape[0]
    fb = frame_id.encode("utf-8")
    off = body_offset(len(fb))
    body = layout.doubles * 8
    L = HEADER_BYTES + off + body
    rows = np.zeros((n, L), dtype=np.uint8)
    rows[:, 1] = 1
    p = rows[:, HEADER_BYTES:]
    sec, nsec = np.divmod(stamp_ns, 1_000_000_000)
    if (sec < -(2**31)).any() or (sec >= 2**31).any():
        raise ValueError("stamp out of the int32 seconds range")
    p[:, 0:4] = sec.astype("<i4").view(np.uint8).reshape(n, 4)
    p[:, 4:8] = nsec.astype("<u4").view(np.uint8).reshape(n, 4)
    p[:, 8:12] = np.frombuffer(np.uint32(len(fb) + 1).astype("<u4").tobytes(), np.uint8)
    p[:, 12:12 + len(fb)] = np.frombuffer(fb, np.uint8)
    vals = np.zeros((n, layout.doubles), dtype="<f8")
    offs = layout.offsets()
    for name, v in values.items():
        if name not in offs:
            raise KeyError(f"{layout.msgtype} has no float field {name!r}")
        o, c = offs[name]
        vals[:, o:o + c] = v
    p[:, off:off + body] = vals.view(np.uint8).reshape(n, body)
    return rows


def set_fields(rows: np.ndarray, layout: Layout, **values: np.ndarray | float) -> None:
    """Overwrite float fields of equal-length message rows in place (same frame_id length)."""
    L = rows.shape[1]
    body = layout.doubles * 8
    off = L - HEADER_BYTES - body
    vals = np.ascontiguousarray(rows[:, HEADER_BYTES + off:]).view("<f8")
    offs = layout.offsets()
    for name, v in values.items():
        o, c = offs[name]
        vals[:, o:o + c] = v
    rows[:, HEADER_BYTES + off:] = vals.view(np.uint8)


def split_rows(rows: np.ndarray) -> list[bytes]:
    """One ``bytes`` per row (what a bag writer or a raw publisher takes)."""
    n, L = rows.shape
    buf = np.ascontiguousarray(rows).tobytes()
    return [buf[i:i + L] for i in range(0, n * L, L)]


def clock_message(t_ns: int) -> bytes:
    """rosgraph_msgs/msg/Clock CDR for ``t_ns``."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return CDR_LE + int(sec).to_bytes(4, "little", signed=True) + int(nsec).to_bytes(4, "little")
