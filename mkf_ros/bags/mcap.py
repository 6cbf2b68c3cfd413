"""A fast path through MCAP files: bulk reading of chosen channels and batch writing.

rosbags reads and writes MCAP one message at a time in Python (~200k messages/s). For
``mkf process`` the per-message cost has to be a small fraction of a microsecond, so this module
reads the summary and the chunk records itself and builds/parses chunks with NumPy. Everything
else (metadata.yaml, connections, QoS, message definitions, the other storage plugins) stays
with rosbags; files written here are checked against rosbags' reader in the tests.

Record layouts follow the MCAP specification (https://mcap.dev/spec); all integers are little
endian, strings and byte arrays are prefixed by a ``uint32`` length.
"""

from __future__ import annotations

import struct
import sys
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_MESSAGE_INDEX, OP_CHUNK_INDEX, OP_STATISTICS, OP_METADATA = 7, 8, 11, 12
OP_METADATA_INDEX, OP_SUMMARY_OFFSET, OP_DATA_END = 13, 14, 15
CHUNK_BYTES = 1 << 20  # target uncompressed chunk size (as rosbags and rosbag2)
MSG_HEAD = 31  # opcode(1) length(8) channel(2) sequence(4) log_time(8) publish_time(8)


class McapError(ValueError):
    """The file is not a readable MCAP file (one line, names the problem)."""


# ------------------------------------------------------------------ reading


@dataclass(frozen=True)
class Channel:
    id: int
    topic: str
    schema: str  #: message type name, e.g. sensor_msgs/msg/Imu
    encoding: str  #: message encoding, "cdr" for ROS 2


@dataclass(frozen=True)
class ChunkRef:
    start_time: int
    end_time: int
    offset: int  #: file offset of the chunk record
    length: int
    compression: str
    compressed_size: int
    uncompressed_size: int
    channels: frozenset[int]  #: channels that have messages in this chunk (from the index)
    index: dict[int, int]  #: channel → file offset of its message index record


class _Buf:
    """Cursor over a bytes object for the small summary records."""

    def __init__(self, data: bytes) -> None:
        self.d = data
        self.p = 0

    def take(self, fmt: str) -> Any:
        v = struct.unpack_from(fmt, self.d, self.p)
        self.p += struct.calcsize(fmt)
        return v[0] if len(v) == 1 else v

    def string(self) -> str:
        n = self.take("<I")
        s = self.d[self.p:self.p + n]
        if len(s) != n:
            raise McapError("record ends inside a string")
        self.p += n
        return s.decode("utf-8", "replace")


def _records(data: bytes, start: int, end: int) -> Iterator[tuple[int, int, int]]:
    """(opcode, content start, content end) of the records in ``data[start:end]``."""
    p = start
    unpack = struct.unpack_from
    while p < end:
        if p + 9 > end:
            raise McapError("truncated record")
        op, ln = unpack("<BQ", data, p)
        q = p + 9 + ln
        if q > end:
            raise McapError("truncated record")
        yield op, p + 9, q
        p = q


class McapFile:
    """Summary of an indexed MCAP file, and bulk reading of its messages."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.channels: dict[int, Channel] = {}
        self.chunks: list[ChunkRef] = []
        self.counts: dict[int, int] = {}
        try:
            with self.path.open("rb") as f:
                self._read_summary(f)
        except (OSError, struct.error) as e:
            raise McapError(f"{e}") from None

    def _read_summary(self, f: BinaryIO) -> None:
        head = f.read(8)
        if head != MAGIC:
            raise McapError("not an MCAP file (bad magic)")
        f.seek(0, 2)
        size = f.tell()
        if size < 8 + 9 + 20 + 8:
            raise McapError("file too short (truncated?)")
        f.seek(size - 8 - 29)
        tail = f.read(37)
        if tail[-8:] != MAGIC or tail[0] != OP_FOOTER:
            raise McapError("no footer (truncated or still being recorded?)")
        summary_start, _summary_offset_start, _crc = struct.unpack_from("<QQI", tail, 9)
        if summary_start == 0:
            raise McapError("no summary section (unindexed file)")
        if not 8 <= summary_start <= size - 37:
            raise McapError("corrupt footer")
        f.seek(summary_start)
        data = f.read(size - 37 - summary_start)
        schemas: dict[int, str] = {}
        chans: list[tuple[int, int, str, str]] = []
        for op, a, b in _records(data, 0, len(data)):
            r = _Buf(data[a:b])
            if op == OP_SCHEMA:
                sid = r.take("<H")
                schemas[sid] = r.string()
            elif op == OP_CHANNEL:
                cid, sid = r.take("<HH")
                chans.append((cid, sid, r.string(), r.string()))
            elif op == OP_CHUNK_INDEX:
                t0, t1, off, ln = r.take("<QQQQ")
                nmap = r.take("<I")
                index = dict(struct.unpack_from("<HQ", r.d, r.p + i)
                             for i in range(0, nmap, 10))
                ids = frozenset(index)
                r.p += nmap
                r.take("<Q")  # message index length
                comp = r.string()
                csize, usize = r.take("<QQ")
                if off + ln > size:
                    raise McapError("chunk beyond the end of the file (truncated?)")
                self.chunks.append(ChunkRef(t0, t1, off, ln, comp, csize, usize, ids, index))
            elif op == OP_STATISTICS:
                r.p = 8 + 2 + 4 * 4 + 16
                n = r.take("<I")
                for i in range(0, n, 10):
                    cid, cnt = struct.unpack_from("<HQ", r.d, r.p + i)
                    self.counts[cid] = cnt
        for cid, sid, topic, enc in chans:
            self.channels[cid] = Channel(cid, topic, schemas.get(sid, ""), enc)
        self.chunks.sort(key=lambda c: (c.start_time, c.offset))

    def _chunk_records(self, f: BinaryIO, c: ChunkRef) -> bytes:
        f.seek(c.offset)
        raw = f.read(c.length)
        if len(raw) != c.length or raw[0] != OP_CHUNK:
            raise McapError(f"no chunk at offset {c.offset} (corrupt index or truncated file)")
        r = _Buf(raw)
        r.p = 9
        _t0, _t1, usize, crc = r.take("<QQQI")
        comp = r.string()
        n = r.take("<Q")
        data = raw[r.p:r.p + n]
        if len(data) != n:
            raise McapError(f"chunk at offset {c.offset} is truncated")
        if comp == "zstd":
            if sys.version_info >= (3, 14):
                from compression import zstd
            else:
                from backports import zstd
            data = zstd.decompress(data)
        elif comp == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(data)
        elif comp:
            raise McapError(f"unsupported chunk compression {comp!r}")
        if len(data) != usize:
            raise McapError(f"chunk at offset {c.offset}: size mismatch after decompression")
        if crc and zlib.crc32(data) != crc:
            raise McapError(f"chunk at offset {c.offset}: checksum mismatch")
        return data

    def _indexed_offsets(self, f: BinaryIO, c: ChunkRef, ch: int) -> np.ndarray | None:
        """Offsets in the chunk of channel ``ch``'s messages, from its message index record
        (None if the chunk has no index for it)."""
        pos = c.index.get(ch)
        if pos is None:
            return None
        f.seek(pos)
        head = f.read(15)
        if len(head) != 15 or head[0] != OP_MESSAGE_INDEX:
            raise McapError(f"no message index at offset {pos} (corrupt index)")
        _, ln, cid, nbytes = struct.unpack("<BQHI", head)
        if cid != ch or nbytes % 16 or nbytes + 6 != ln:
            raise McapError(f"corrupt message index at offset {pos}")
        pairs = np.frombuffer(f.read(nbytes), dtype="<u8")
        if pairs.size * 8 != nbytes:
            raise McapError(f"message index at offset {pos} is truncated")
        return pairs.reshape(-1, 2)[:, 1].astype(np.int64)

    @staticmethod
    def _walk(data: bytes) -> np.ndarray:
        """Offsets of every message record in a chunk (when there is no message index)."""
        next_len = struct.Struct("<Q").unpack_from
        pos: list[int] = []
        add = pos.append
        p, end = 0, len(data) - 9
        while p <= end:
            add(p)
            p += 9 + next_len(data, p + 1)[0]
        if p != end + 9:
            raise McapError("record overruns its chunk")
        s = np.asarray(pos, np.int64)
        return s[np.frombuffer(data, np.uint8)[s] == OP_MESSAGE]

    def read_chunk(self, f: BinaryIO, c: ChunkRef, channel_ids: set[int]
                   ) -> dict[int, tuple[np.ndarray, np.ndarray | list[bytes]]]:
        """The messages of ``channel_ids`` in chunk ``c`` (``f``: this file, open): per channel
        (log times in ns, messages) in record order. Messages are an (N, L) uint8 array (views
        of the chunk) when they all have one length L, else a list of bytes."""
        from numpy.lib.stride_tricks import sliding_window_view

        got: dict[int, tuple[np.ndarray, np.ndarray | list[bytes]]] = {}
        want = channel_ids & c.channels if c.channels else channel_ids
        if not want:
            return got
        data = self._chunk_records(f, c)
        arr = np.frombuffer(data, np.uint8)
        walked = None
        for ch in sorted(want):
            offs = self._indexed_offsets(f, c, ch)
            if offs is None:
                if walked is None:
                    walked = self._walk(data)
                offs = walked
            if offs.size == 0:
                continue
            if offs.min() < 0 or offs.max() + MSG_HEAD > len(data):
                raise McapError(f"chunk at offset {c.offset}: index points outside it")
            head = arr[offs[:, None] + np.arange(MSG_HEAD)].copy()
            ln = head[:, 1:9].view("<u8")[:, 0].astype(np.int64)
            cid = head[:, 9:11].view("<u2")[:, 0]
            if walked is not None and offs is walked:
                keep = cid == ch
                offs, head, ln, cid = offs[keep], head[keep], ln[keep], cid[keep]
            if ((head[:, 0] != OP_MESSAGE).any() or (cid != ch).any() or (ln < 22).any()
                    or (offs + 9 + ln > len(data)).any()):
                raise McapError(f"chunk at offset {c.offset}: corrupt message records")
            if offs.size == 0:
                continue
            logt = head[:, 15:23].view("<u8")[:, 0].astype(np.int64)
            size = ln - 22
            if (size == size[0]).all() and size[0] > 0:
                got[ch] = (logt, sliding_window_view(arr, int(size[0]))[offs + MSG_HEAD])
            else:
                got[ch] = (logt, [data[a:a + n] for a, n in zip(
                    (offs + MSG_HEAD).tolist(), size.tolist(), strict=True)])
        return got

    def read(self, channel_ids: set[int], progress: Any = None
             ) -> dict[int, tuple[np.ndarray, np.ndarray | list[bytes]]]:
        """All messages of ``channel_ids``: per channel (log times in ns, messages), in
        log-time order (see :meth:`read_chunk`). ``progress`` (optional) is called with bytes
        done."""
        parts: dict[int, list[tuple[np.ndarray, np.ndarray | list[bytes]]]] = {
            c: [] for c in channel_ids}
        with self.path.open("rb") as f:
            for c in self.chunks:
                for ch, piece in self.read_chunk(f, c, channel_ids).items():
                    parts[ch].append(piece)
                if progress:
                    progress(c.length)
        return {ch: _concat(p) for ch, p in parts.items()}


def _concat(parts: list[tuple[np.ndarray, np.ndarray | list[bytes]]]
            ) -> tuple[np.ndarray, np.ndarray | list[bytes]]:
    """Join per-chunk pieces of one channel, in log-time order (stable)."""
    if not parts:
        return np.zeros(0, np.int64), []
    t = np.concatenate([p[0] for p in parts])
    arrays = [p[1] for p in parts if isinstance(p[1], np.ndarray)]
    uniform = len(arrays) == len(parts) and len({a.shape[1] for a in arrays}) == 1
    if uniform:
        data: np.ndarray | list[bytes] = (parts[0][1] if len(parts) == 1 else
                                          np.concatenate([p[1] for p in parts]))
    else:
        data = [x for p in parts for x in (
            p[1] if isinstance(p[1], list) else [r.tobytes() for r in p[1]])]
    if t.size > 1 and (np.diff(t) < 0).any():
        order = np.argsort(t, kind="stable")
        t = t[order]
        data = data[order] if isinstance(data, np.ndarray) else [data[i] for i in
                                                                 order.tolist()]
    return t, data


# ------------------------------------------------------------------ writing


def _u16(v: int) -> bytes:
    return v.to_bytes(2, "little")


def _u32(v: int) -> bytes:
    return v.to_bytes(4, "little")


def _u64(v: int) -> bytes:
    return v.to_bytes(8, "little")


def _str(s: str | bytes) -> bytes:
    b = s.encode("utf-8") if isinstance(s, str) else s
    return _u32(len(b)) + b


def _record(op: int, content: bytes) -> bytes:
    return bytes([op]) + _u64(len(content)) + content


def _message_records(cids: np.ndarray, ts: np.ndarray, data: np.ndarray | list[bytes]
                     ) -> tuple[bytes, np.ndarray]:
    """Message records of a batch as one bytes object, and each record's start offset."""
    n = cids.shape[0]
    if isinstance(data, np.ndarray):  # equal lengths: one structured array
        L = data.shape[1]
        dt = np.dtype([("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"),
                       ("log", "<u8"), ("pub", "<u8"), ("data", "u1", (L,))])
        rec = np.zeros(n, dtype=dt)
        rec["op"] = OP_MESSAGE
        rec["len"] = 22 + L
        rec["ch"] = cids
        rec["log"] = ts
        rec["pub"] = ts
        rec["data"] = data
        return rec.tobytes(), np.arange(n, dtype=np.int64) * dt.itemsize
    lens = np.fromiter(map(len, data), dtype=np.int64, count=n)
    head = np.zeros(n, dtype=[("op", "u1"), ("len", "<u8"), ("ch", "<u2"), ("seq", "<u4"),
                              ("log", "<u8"), ("pub", "<u8")])
    head["op"] = OP_MESSAGE
    head["len"] = 22 + lens
    head["ch"] = cids
    head["log"] = ts
    head["pub"] = ts
    hb = head.tobytes()
    parts: list[bytes] = []
    for i in range(n):
        parts.append(hb[i * MSG_HEAD:(i + 1) * MSG_HEAD])
        parts.append(data[i])
    offs = np.zeros(n, dtype=np.int64)
    np.cumsum(MSG_HEAD + lens[:-1], out=offs[1:])
    return b"".join(parts), offs


class McapStorageWriter:
    """rosbags storage-writer protocol (``rosbags.rosbag2.Writer`` drives it) writing MCAP with
    NumPy-built chunks; adds :meth:`write_batch`. ``compression``: rosbags' CompressionMode
    (``STORAGE`` = zstd chunks)."""

    def __init__(self, path: Path, compression: Any) -> None:
        self.path = path / f"{path.name}.mcap"
        self.bio = self.path.open("xb")
        self.compress = getattr(compression, "name", "NONE") == "STORAGE"
        self.bio.write(MAGIC + _record(OP_HEADER, _str("ros2") + _str("mkf_ros")))
        self.schemas: dict[str, int] = {}
        self.schema_records: list[bytes] = []
        self.channel_records: list[bytes] = []
        self.chunk_indexes: list[bytes] = []
        self.stats: dict[int, int] = {}
        self.t_min = 2**63 - 1
        self.t_max = 0
        self._pend: list[tuple[np.ndarray, np.ndarray, bytes, np.ndarray]] = []
        self._pend_bytes = 0

    # -- protocol --------------------------------------------------------------------------
    def add_msgtype(self, connection: Any) -> None:
        sid = len(self.schemas) + 1
        self.schemas[connection.msgtype] = sid
        fmt = "ros2msg" if getattr(connection.msgdef.format, "name", "MSG") == "MSG" \
            else "ros2idl"
        rec = _record(OP_SCHEMA, _u16(sid) + _str(connection.msgtype) + _str(fmt)
                      + _str(connection.msgdef.data))
        self.schema_records.append(rec)
        self._flush()
        self.bio.write(rec)

    def add_connection(self, connection: Any, offered_qos_profiles: str) -> None:
        meta = _str("offered_qos_profiles") + _str(offered_qos_profiles)
        rec = _record(OP_CHANNEL, _u16(connection.id) + _u16(self.schemas[connection.msgtype])
                      + _str(connection.topic) + _str(connection.ext.serialization_format)
                      + _u32(len(meta)) + meta)
        self.channel_records.append(rec)
        self.stats[connection.id] = 0
        self._flush()
        self.bio.write(rec)

    def write(self, connection: Any, timestamp: int, data: bytes | memoryview) -> None:
        self.write_batch(np.array([connection.id]), np.array([timestamp], np.int64),
                         [bytes(data)])

    def write_batch(self, cids: np.ndarray, ts: np.ndarray,
                    data: np.ndarray | list[bytes]) -> None:
        """Append messages: channel ids (N,), log times in ns (N,), and either an (N, L)
        uint8 array of equal-length messages or a list of N bytes."""
        n = len(cids)
        if n == 0:
            return
        cids = np.asarray(cids, np.uint16)
        ts = np.asarray(ts, np.int64)
        if isinstance(data, np.ndarray):
            per = MSG_HEAD + data.shape[1]
            step = max(1, CHUNK_BYTES // per)
            for a in range(0, n, step):
                self._add(cids[a:a + step], ts[a:a + step], data[a:a + step])
        else:
            a = 0
            size = 0
            for i, d in enumerate(data):
                size += MSG_HEAD + len(d)
                if size >= CHUNK_BYTES:
                    self._add(cids[a:i + 1], ts[a:i + 1], data[a:i + 1])
                    a, size = i + 1, 0
            if a < n:
                self._add(cids[a:], ts[a:], data[a:])

    def _add(self, cids: np.ndarray, ts: np.ndarray, data: np.ndarray | list[bytes]) -> None:
        blob, offs = _message_records(cids, ts, data)
        self._pend.append((cids, ts, blob, offs))
        self._pend_bytes += len(blob)
        for cid, cnt in zip(*np.unique(cids, return_counts=True), strict=True):
            self.stats[int(cid)] = self.stats.get(int(cid), 0) + int(cnt)
        self.t_min = min(self.t_min, int(ts.min()))
        self.t_max = max(self.t_max, int(ts.max()))
        if self._pend_bytes >= CHUNK_BYTES:
            self._flush()

    def _flush(self) -> None:
        """Write the pending messages as one chunk and its message indexes."""
        if not self._pend:
            return
        base = 0
        offs_all, cids_all, ts_all, blobs = [], [], [], []
        for cids, ts, blob, offs in self._pend:
            offs_all.append(offs + base)
            cids_all.append(cids)
            ts_all.append(ts)
            blobs.append(blob)
            base += len(blob)
        self._pend, self._pend_bytes = [], 0
        records = b"".join(blobs)
        offs = np.concatenate(offs_all)
        cids = np.concatenate(cids_all)
        ts = np.concatenate(ts_all)
        t0, t1 = int(ts.min()), int(ts.max())
        if self.compress:
            if sys.version_info >= (3, 14):
                from compression import zstd
            else:
                from backports import zstd
            payload, comp = zstd.compress(records), "zstd"
        else:
            payload, comp = records, ""
        content = (_u64(t0) + _u64(t1) + _u64(len(records)) + _u32(zlib.crc32(records))
                   + _str(comp) + _u64(len(payload)))
        chunk_start = self.bio.tell()
        self.bio.write(bytes([OP_CHUNK]) + _u64(len(content) + len(payload)) + content)
        self.bio.write(payload)
        chunk_len = self.bio.tell() - chunk_start
        index_map = b""
        idx_start = self.bio.tell()
        for cid in np.unique(cids).tolist():
            sel = np.flatnonzero(cids == cid)
            order = sel[np.argsort(ts[sel], kind="stable")]
            pairs = np.empty((order.size, 2), dtype="<u8")
            pairs[:, 0] = ts[order]
            pairs[:, 1] = offs[order]
            index_map += _u16(cid) + _u64(self.bio.tell())
            self.bio.write(_record(OP_MESSAGE_INDEX, _u16(cid) + _u32(pairs.nbytes)
                                   + pairs.tobytes()))
        idx_len = self.bio.tell() - idx_start
        self.chunk_indexes.append(_record(
            OP_CHUNK_INDEX, _u64(t0) + _u64(t1) + _u64(chunk_start) + _u64(chunk_len)
            + _u32(len(index_map)) + index_map + _u64(idx_len) + _str(comp)
            + _u64(len(payload)) + _u64(len(records))))

    def close(self, version: int, metadata: str) -> None:
        self._flush()
        bio = self.bio
        meta_start = bio.tell()
        kv = _str("serialized_metadata") + _str(metadata)
        bio.write(_record(OP_METADATA, _str("rosbag2") + _u32(len(kv)) + kv))
        meta_len = bio.tell() - meta_start
        bio.write(_record(OP_DATA_END, _u32(0)))
        summary_start = bio.tell()
        groups: list[tuple[int, int, int]] = []

        def group(op: int, recs: list[bytes]) -> None:
            if recs:
                a = bio.tell()
                for r in recs:
                    bio.write(r)
                groups.append((op, a, bio.tell() - a))

        group(OP_SCHEMA, self.schema_records)
        group(OP_CHANNEL, self.channel_records)
        group(OP_CHUNK_INDEX, self.chunk_indexes)
        counts = b"".join(_u16(c) + _u64(n) for c, n in sorted(self.stats.items()))
        t0 = self.t_min if self.stats and sum(self.stats.values()) else 0
        stats = (_u64(sum(self.stats.values())) + _u16(len(self.schema_records))
                 + _u32(len(self.channel_records)) + _u32(0) + _u32(1)
                 + _u32(len(self.chunk_indexes)) + _u64(t0) + _u64(self.t_max)
                 + _u32(len(counts)) + counts)
        group(OP_STATISTICS, [_record(OP_STATISTICS, stats)])
        group(OP_METADATA_INDEX, [_record(OP_METADATA_INDEX, _u64(meta_start) + _u64(meta_len)
                                          + _str("rosbag2"))])
        offset_start = bio.tell()
        for op, a, ln in groups:
            bio.write(_record(OP_SUMMARY_OFFSET, bytes([op]) + _u64(a) + _u64(ln)))
        bio.write(_record(OP_FOOTER, _u64(summary_start) + _u64(offset_start) + _u32(0)))
        bio.write(MAGIC)
        bio.close()

    def abort(self) -> None:
        self.bio.close()



