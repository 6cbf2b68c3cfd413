"""Reading bags: ROS 2 (rosbag2 v4–v9, MCAP or sqlite3, as a directory or a bare storage file)
and ROS 1 (``.bag``, converted to ROS 2 CDR on the fly), with one error type.

Messages always come out as ROS 2 CDR bytes, exactly as recorded for ROS 2 bags (never
re-encoded), so they can be published raw or decoded with :mod:`mkf_ros.bags.cdr`.
"""

from __future__ import annotations

import contextlib
import sqlite3
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

STORAGE_SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3", ".bag": "ros1"}
#: rows fetched from sqlite3 at a time (the storage's unit of a window)
SQLITE_FETCH = 50_000


class BagError(Exception):
    """A bag cannot be used: one line naming the bag and the problem."""


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str
    count: int


class Batch:
    """All messages of one topic in log order: log (receive) times in ns and the raw ROS 2
    CDR messages, as ``rows`` (an (N, L) uint8 array, when all have one length) and/or
    ``raws`` (a list of bytes; made from ``rows`` on first use)."""

    def __init__(self, log_ns: np.ndarray, data: np.ndarray | list[bytes]) -> None:
        self.log_ns = log_ns
        self.rows: np.ndarray | None = data if isinstance(data, np.ndarray) else None
        self._raws: list[bytes] | None = None if isinstance(data, np.ndarray) else data

    @property
    def raws(self) -> list[bytes]:
        if self._raws is None:
            from mkf_ros.bags.cdr import split_rows

            assert self.rows is not None
            self._raws = split_rows(self.rows)
        return self._raws

    @property
    def data(self) -> np.ndarray | list[bytes]:
        """``rows`` if available (cheapest to decode and write), else ``raws``."""
        return self.rows if self.rows is not None else self.raws

    def __len__(self) -> int:
        return len(self.log_ns)


def _typestore() -> Any:
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def normalize_topic(name: str) -> str:
    """Bags store absolute names: ``imu/data_raw`` → ``/imu/data_raw``."""
    name = name.strip()
    return name if name.startswith("/") else "/" + name


class BagReader:
    """An open bag. Use as a context manager; every failure raises :class:`BagError`.

    ``path`` is a rosbag2 directory (with ``metadata.yaml``), a bare ``.mcap`` or ``.db3`` file,
    or a ROS 1 ``.bag`` file.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader: Any = None
        self._ros1 = False
        self._files: list[Path] = []
        self._ts: Any = None
        self._conv: dict[str, Callable[[bytes], bytes] | None] = {}
        self._compressed = False
        try:
            self._open()
        except BagError:
            raise
        except Exception as e:  # rosbags, sqlite3, yaml and OS errors on a broken bag
            self.close()
            raise BagError(f"cannot read bag {self.path}: {_reason(e)}") from None

    # -- opening ---------------------------------------------------------------------------
    def _open(self) -> None:
        p = self.path
        if not p.exists():
            raise BagError(f"no such bag: {p}")
        if p.is_dir():
            if not (p / "metadata.yaml").is_file():
                files = [f for f in sorted(p.iterdir()) if f.suffix in (".mcap", ".db3")]
                if len(files) != 1:
                    raise BagError(f"{p} is not a bag: no metadata.yaml and "
                                   f"{'no' if not files else 'several'} .mcap/.db3 files")
                p = files[0]
        elif p.suffix not in STORAGE_SUFFIXES:
            raise BagError(f"unknown storage format of {p}: expected a rosbag2 directory, an "
                           ".mcap or .db3 file, or a ROS 1 .bag file")
        if p.is_file() and p.stat().st_size == 0:
            raise BagError(f"cannot read bag {self.path}: the file is empty")
        if p.is_file():
            _check_content(p)
        if p.suffix == ".bag":
            from rosbags.rosbag1 import Reader as Reader1

            self._ros1 = True
            self._reader = Reader1(p)
            self._reader.open()
            self.storage = "ros1"
            self._files = [p]
        else:
            from rosbags.rosbag2 import Reader as Reader2

            self._reader = Reader2(p)
            self._reader.open()
            if p.is_dir():
                import yaml

                info = yaml.safe_load((p / "metadata.yaml").read_text())
                info = info["rosbag2_bagfile_information"]
                self._files = [p / Path(x).name for x in info.get("relative_file_paths", [])]
                self.storage = str(info.get("storage_identifier", ""))
                self._compressed = bool(info.get("compression_format"))
            else:
                self._files = [p]
                self.storage = STORAGE_SUFFIXES[p.suffix]
                self._compressed = False
        self.topics: dict[str, TopicInfo] = {}
        for c in self._reader.connections:
            old = self.topics.get(c.topic)
            cnt = c.msgcount + (old.count if old else 0)
            self.topics[c.topic] = TopicInfo(c.topic, c.msgtype, cnt)
        if self._reader.message_count == 0 and not self.topics:
            raise BagError(f"bag {self.path} contains no topics")

    def close(self) -> None:
        if self._reader is not None and getattr(self._reader, "is_open", True):
            with contextlib.suppress(Exception):  # closing a half-open reader: best effort
                self._reader.close()
        self._reader = None

    def __enter__(self) -> BagReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- metadata --------------------------------------------------------------------------
    @property
    def start_ns(self) -> int:
        return int(self._reader.start_time)

    @property
    def end_ns(self) -> int:
        return int(self._reader.end_time)

    @property
    def message_count(self) -> int:
        return int(self._reader.message_count)

    def resolve(self, topic: str, msgtype: str | None = None, *, role: str = "") -> str:
        """The bag's name for ``topic`` (leading slash optional); BagError if it is missing or
        has another type than ``msgtype``."""
        for name in (topic, normalize_topic(topic)):
            if name in self.topics:
                info = self.topics[name]
                if msgtype and info.msgtype != msgtype:
                    what = f"{role} topic" if role else "topic"
                    raise BagError(f"{what} {name} in {self.path} is {info.msgtype}, expected "
                                   f"{msgtype}")
                return name
        what = f"{role} topic" if role else "topic"
        if msgtype:
            have = self.listing(msgtype)
        else:
            have = "topics: " + (", ".join(sorted(self.topics)) or "none")
        raise BagError(f"{what} {normalize_topic(topic)} not in {self.path} ({have})")

    def of_type(self, msgtype: str) -> list[str]:
        """The topics of type ``msgtype``, sorted."""
        return sorted(t for t, i in self.topics.items() if i.msgtype == msgtype)

    def listing(self, msgtype: str) -> str:
        """``msgtype`` topics: each with its message count (for error messages)."""
        names = self.of_type(msgtype)
        short = msgtype.replace("/msg/", "/")
        if not names:
            return f"no {short} topic in the bag"
        return f"{short} topics: " + ", ".join(
            f"{t} ({self.topics[t].count:,} messages)" for t in names)

    def discover(self, msgtype: str, *, role: str, flag: str,
                 preferred: str | None = None) -> str:
        """The bag's only ``msgtype`` topic, or ``preferred`` if it is one of several; BagError
        naming the candidates (with message counts) and ``flag`` to choose otherwise."""
        names = self.of_type(msgtype)
        if len(names) == 1:
            return names[0]
        if preferred and normalize_topic(preferred) in names:
            return normalize_topic(preferred)
        if not names:
            raise BagError(f"no {role} topic in {self.path}: "
                           f"{self.listing(msgtype)}")
        raise BagError(f"{len(names)} {role} topics in {self.path}, choose one with {flag}: "
                       f"{self.listing(msgtype)}")

    # -- messages --------------------------------------------------------------------------
    def _converter(self, conn: Any) -> Callable[[bytes], bytes] | None:
        """ROS 1 → ROS 2 CDR for a connection's type (None: type unknown, skip)."""
        if not self._ros1:
            return bytes
        if conn.msgtype not in self._conv:
            if self._ts is None:
                self._ts = _typestore()
            ts = self._ts
            if conn.msgtype not in ts.fielddefs:
                try:
                    from rosbags.typesys import get_types_from_msg

                    types = get_types_from_msg(conn.msgdef.data, conn.msgtype)
                    types.pop("std_msgs/msg/Header", None)
                    ts.register(types)
                except Exception:
                    self._conv[conn.msgtype] = None
                    return None
            typename = conn.msgtype
            self._conv[typename] = lambda raw: bytes(ts.ros1_to_cdr(raw, typename))
        return self._conv[conn.msgtype]

    def messages(self, topics: Iterable[str] | None = None, start_ns: int | None = None,
                 stop_ns: int | None = None) -> Iterator[tuple[str, int, bytes]]:
        """``(topic, log time ns, ROS 2 CDR bytes)`` in log-time order (streaming)."""
        want = None if topics is None else set(topics)
        conns = [c for c in self._reader.connections if want is None or c.topic in want]
        convs = {id(c): conv for c in conns if (conv := self._converter(c)) is not None}
        conns = [c for c in conns if id(c) in convs]
        if not conns:
            return
        try:
            for c, t, raw in self._reader.messages(connections=conns, start=start_ns,
                                                   stop=stop_ns):
                yield c.topic, t, convs[id(c)](raw)
        except BagError:
            raise
        except Exception as e:
            raise BagError(f"cannot read bag {self.path}: {_reason(e)}") from None

    def read(self, topics: Iterable[str], progress: Callable[[int], object] | None = None
             ) -> dict[str, Batch]:
        """Every message of ``topics`` at once: :meth:`read_windows` as one window.

        ``progress``, if given, is called with increments of work done; the total is
        :meth:`work_total`.
        """
        return next(iter(self.read_windows(topics, None, progress)))

    def read_windows(self, topics: Iterable[str], size: int | None,
                     progress: Callable[[int], object] | None = None
                     ) -> Iterator[dict[str, Batch]]:
        """The messages of ``topics`` in consecutive windows of log time: each window holds,
        per topic, every message whose log time lies in it, in log-time order (equal times
        in recording order), and the windows follow each other in time; messages of equal log
        time are never split between windows. A window is closed once it has at least
        ``size`` messages (over all topics) and the storage chunk that completes it is read
        (``None``: one window, the whole bag). At least one window (perhaps empty) is
        yielded. Memory: about one window and one storage chunk.

        Fast bulk paths for MCAP (chunk by chunk, in the order of the chunk index) and sqlite3
        files (through the timestamp index); other storages go through rosbags' iterator.
        ``progress`` as in :meth:`read`.
        """
        topics = list(topics)
        if self.storage == "mcap" and not self._compressed:
            pieces = self._pieces_mcap(topics, progress)
        elif self.storage == "sqlite3" and not self._compressed:
            pieces = self._pieces_sqlite(topics, progress)
        else:
            pieces = self._pieces_generic(topics, progress)
        win = _Windows(topics, size)
        try:
            for bound, piece in pieces:
                for topic, (t, d) in piece.items():
                    win.add(topic, t, d)
                if win.full() and bound is not None:
                    got = win.take(bound)
                    if got is not None:
                        yield got
        except BagError:
            raise
        except Exception as e:  # the storage backends' errors on a broken bag
            raise BagError(f"cannot read bag {self.path}: {_reason(e)}") from None
        last = win.take(None)
        if last is not None or not win.yielded:
            yield last if last is not None else win.empty()

    def work_total(self, topics: Iterable[str]) -> int:
        """Units :meth:`read` reports to ``progress`` (bytes for MCAP, messages otherwise)."""
        if self.storage == "mcap" and not self._compressed:
            return sum(f.stat().st_size for f in self._files)
        return sum(self.topics[t].count for t in topics if t in self.topics)

    def _pieces_mcap(self, topics: list[str], progress: Callable[[int], object] | None
                     ) -> Iterator[tuple[int | None, dict[str, tuple[np.ndarray, Any]]]]:
        """(bound, messages per topic) chunk by chunk, over every file in the order of the
        chunks' first log times; every later chunk has log times >= bound (None: last)."""
        from mkf_ros.bags.mcap import McapError, McapFile, _concat

        files = []
        for f in self._files:
            try:
                files.append(McapFile(f))
            except McapError as e:
                raise BagError(f"cannot read bag {self.path}: {f.name}: {e}") from None
        refs = sorted(((c.start_time, i, c.offset), i, c)
                      for i, mf in enumerate(files) for c in mf.chunks)
        handles: dict[int, Any] = {}
        try:
            for k, (_, i, c) in enumerate(refs):
                mf = files[i]
                ids = {cid for cid, ch in mf.channels.items() if ch.topic in topics}
                if i not in handles:
                    handles[i] = mf.path.open("rb")
                try:
                    got = mf.read_chunk(handles[i], c, ids)
                except McapError as e:
                    raise BagError(f"cannot read bag {self.path}: {mf.path.name}: {e}") \
                        from None
                piece: dict[str, tuple[np.ndarray, Any]] = {}
                for cid, (t, d) in got.items():
                    topic = mf.channels[cid].topic
                    piece[topic] = _concat([piece[topic], (t, d)]) if topic in piece else (t, d)
                if progress:
                    progress(c.length)
                yield (refs[k + 1][2].start_time if k + 1 < len(refs) else None), piece
        finally:
            for h in handles.values():
                h.close()

    def _pieces_sqlite(self, topics: list[str], progress: Callable[[int], object] | None
                       ) -> Iterator[tuple[int | None, dict[str, tuple[np.ndarray, Any]]]]:
        """(bound, messages per topic) in batches of rows, file by file, in (timestamp, id)
        order: the rows of a topic as rosbag2 inserted them, sorted stably by log time."""
        for f in self._files:
            db = sqlite3.connect(f"file:{f}?mode=ro&immutable=1", uri=True)
            try:
                names = {row[0]: row[1] for row in db.execute("SELECT id, name FROM topics")
                         if row[1] in topics}
                if not names:
                    continue
                marks = ",".join("?" * len(names))
                cur = db.execute("SELECT topic_id, timestamp, data FROM messages WHERE "
                                 f"topic_id IN ({marks}) ORDER BY timestamp, id",
                                 list(names))
                while rows := cur.fetchmany(SQLITE_FETCH):
                    tid = np.fromiter((r[0] for r in rows), np.int64, len(rows))
                    t = np.fromiter((r[1] for r in rows), np.int64, len(rows))
                    piece: dict[str, tuple[np.ndarray, Any]] = {}
                    for i, name in names.items():
                        sel = np.flatnonzero(tid == i)
                        if sel.size:
                            piece[name] = (t[sel], [rows[j][2] for j in sel.tolist()])
                    if progress:
                        progress(len(rows))
                    yield int(t[-1]), piece
            finally:
                db.close()

    def _pieces_generic(self, topics: list[str], progress: Callable[[int], object] | None
                        ) -> Iterator[tuple[int | None, dict[str, tuple[np.ndarray, Any]]]]:
        """(bound, messages per topic) in batches of 10 000 from rosbags' iterator."""
        ts: dict[str, list[int]] = {t: [] for t in topics}
        ds: dict[str, list[bytes]] = {t: [] for t in topics}
        n = 0
        for topic, t, raw in self.messages(topics):
            ts[topic].append(t)
            ds[topic].append(raw)
            n += 1
            if n % 10000 == 0:
                if progress:
                    progress(10000)
                yield t, {k: (np.asarray(ts[k], np.int64), ds[k]) for k in topics if ts[k]}
                ts = {k: [] for k in topics}
                ds = {k: [] for k in topics}
        if progress:
            progress(n % 10000)
        yield None, {k: (np.asarray(ts[k], np.int64), ds[k]) for k in topics if ts[k]}


class _Windows:
    """Messages collected per topic (in arrival order) and handed out by log time."""

    def __init__(self, topics: list[str], size: int | None) -> None:
        self.parts: dict[str, list[tuple[np.ndarray, Any]]] = {t: [] for t in topics}
        self.size = size
        self.count = 0
        self.yielded = False
        self.emitted: int | None = None  #: every later message must have log time >= this

    def add(self, topic: str, t: np.ndarray, data: Any) -> None:
        if len(t) == 0:
            return
        if self.emitted is not None and int(t.min()) < self.emitted:
            raise BagError("messages out of the order the storage's index promises "
                           "(corrupt chunk index)")
        self.parts[topic].append((t, data))
        self.count += len(t)

    def full(self) -> bool:
        return self.size is not None and self.count >= self.size

    def empty(self) -> dict[str, Batch]:
        return {t: Batch(np.zeros(0, np.int64), []) for t in self.parts}

    def take(self, bound: int | None) -> dict[str, Batch] | None:
        """Every message with log time < ``bound`` (None: all), or None if there is none."""
        from mkf_ros.bags.mcap import _concat

        out: dict[str, Batch] = {}
        n = 0
        for topic, parts in self.parts.items():
            t, d = _concat(parts) if parts else (np.zeros(0, np.int64), [])
            cut = len(t) if bound is None else int(np.searchsorted(t, bound, "left"))
            out[topic] = Batch(t[:cut], d[:cut])
            self.parts[topic] = [(t[cut:], d[cut:])] if cut < len(t) else []
            n += cut
        self.count -= n
        if bound is not None:
            self.emitted = bound
        if n == 0:
            return None
        self.yielded = True
        return out


#: the first bytes of each storage format → (its suffix, what it is)
_MAGIC = {
    ".mcap": (b"\x89MCAP", "an MCAP file (rosbag2 .mcap)"),
    ".db3": (b"SQLite format 3\x00", "an sqlite3 database (rosbag2 .db3)"),
    ".bag": (b"#ROSBAG V2.0", "a ROS 1 bag (.bag)"),
}


def _check_content(p: Path) -> None:
    """BagError unless the file's first bytes are those of the format its suffix names,
    saying what the file is instead (a .db3 renamed .bag, a text file, ...)."""
    with p.open("rb") as f:
        head = f.read(512)
    magic, what = _MAGIC[p.suffix]
    if head.startswith(magic):
        return
    for suffix, (m, other) in _MAGIC.items():
        if head.startswith(m):
            raise BagError(f"cannot read bag {p}: it is {other}, not {what} as its name "
                           f"says (rename it to {p.stem}{suffix})")
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        text = ""
    if text and "\x00" not in text:
        first = text.strip().splitlines()[0][:40] if text.strip() else ""
        raise BagError(f"cannot read bag {p}: it is a text file (starting {first!r}), not "
                       f"{what}")
    raise BagError(f"cannot read bag {p}: it is not {what} (its first bytes {head[:16]!r} are "
                   "those of no bag format: MCAP, sqlite3, ROS 1)")


#: storage backend messages → what they mean for the user
_HINTS = (
    ("end magic", "truncated or incomplete MCAP file"),
    ("file magic", "not an MCAP file"),
    ("malformed", "corrupt or truncated sqlite3 database"),
    ("not a database", "not an sqlite3 database"),
    ("no such table", "not a rosbag2 sqlite3 database"),
    ("a metadata key is missing", "metadata.yaml is incomplete or not rosbag2 metadata"),
    ("invalid bag metadata", "metadata.yaml is not rosbag2 metadata"),
)


def _reason(e: BaseException) -> str:
    """One line for an exception from a storage backend."""
    text = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    text = text.rstrip(".")
    low = text.lower()
    for key, hint in _HINTS:
        if key in low:
            return f"{hint} ({text})"
    if isinstance(e, EOFError) or "truncat" in low:
        return f"truncated ({text})"
    # the backends' internals on a damaged file (seen on truncated and corrupted bags: "'rss2msg'",
    # "KeyError('version')", "ord() expected a character…", "'int' object is not subscriptable", a
    # MemoryError): say what that means for the file, keep the internal text only as a detail
    if isinstance(e, MemoryError):
        return ("damaged: a length field asks for more memory than is available "
                "(corrupt record header)")
    if isinstance(e, KeyError):
        key = e.args[0] if e.args else text
        return f"damaged or incomplete: a required entry is missing ({key!r})"
    if type(e).__name__ == "ReaderError" and not any(k in low for k, _ in _HINTS):
        return f"damaged or not a bag ({text})"
    if isinstance(e, (TypeError, AttributeError, IndexError, UnicodeError, ValueError)):
        return f"damaged or not a bag: unexpected content ({type(e).__name__}: {text})"
    return text
