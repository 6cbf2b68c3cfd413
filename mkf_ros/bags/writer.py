"""Writing rosbag2 bags (Jazzy's v9 layout, MCAP or sqlite3) atomically and in batches.

The bag is built in a hidden temporary directory next to the target and renamed into place only
when complete, so a failure never leaves a half-written bag under the requested name. The
storage writers add a :meth:`BagWriter.write_batch` that takes whole NumPy arrays of messages.
"""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags.cdr import split_rows
from mkf_ros.bags.reader import BagError, normalize_topic

STORAGES = ("mcap", "sqlite3")


def _writer_class() -> type:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.storage_sqlite3 import Sqlite3Writer

    from mkf_ros.bags.mcap import McapStorageWriter

    class FastSqlite3Writer(Sqlite3Writer):
        """rosbags' sqlite3 storage plus one ``executemany`` per batch. No journal and no
        fsync: the bag is built under a temporary name and only renamed when complete."""

        def __init__(self, path: Path, compression: Any) -> None:
            # rosbags' constructor (compression is only ever set for MCAP), with the pragmas
            # before the schema: otherwise each statement of it is a synced transaction of
            # its own (~0.15 s per bag)
            self.path = path / f"{path.name}.db3"
            self.conn = sqlite3.connect(f"file:{self.path}", uri=True)
            self.conn.execute("PRAGMA synchronous=OFF")
            self.conn.execute("PRAGMA journal_mode=OFF")
            self.conn.executescript(self.SQLITE_SCHEMA)
            self.cursor = self.conn.cursor()

        def write_batch(self, cids: np.ndarray, ts: np.ndarray,
                        data: np.ndarray | list[bytes]) -> None:
            raws = split_rows(data) if isinstance(data, np.ndarray) else data
            self.cursor.executemany(
                "INSERT INTO messages (topic_id, timestamp, data) VALUES(?, ?, ?)",
                zip(np.asarray(cids).tolist(), np.asarray(ts).tolist(), raws, strict=True))

    class BatchWriter(Writer):
        """rosbags' rosbag2 writer with the fast storage plugins and batch writes."""

        STORAGE_PLUGINS = {StoragePlugin.SQLITE3: FastSqlite3Writer,  # noqa: RUF012
                           StoragePlugin.MCAP: McapStorageWriter}

        def write_batch(self, cids: np.ndarray, ts: np.ndarray,
                        data: np.ndarray | list[bytes]) -> None:
            storage = self.storage  # set by open(), one of STORAGE_PLUGINS
            assert isinstance(storage, (FastSqlite3Writer, McapStorageWriter))
            storage.write_batch(cids, ts, data)
            ids, counts = np.unique(np.asarray(cids), return_counts=True)
            for cid, cnt in zip(ids.tolist(), counts.tolist(), strict=True):
                self.counts[cid] += cnt
            self.min_timestamp = min(self.min_timestamp, int(np.min(ts)))
            self.max_timestamp = max(self.max_timestamp, int(np.max(ts)))

    return BatchWriter


class BagWriter:
    """A new rosbag2 bag at ``path`` (a directory, as ``ros2 bag record`` makes).

    Use as a context manager: the bag appears under ``path`` when the block ends normally and
    not at all when it raises. ``overwrite`` replaces an existing bag at ``path``.
    """

    def __init__(self, path: str | Path, storage: str = "mcap", *, overwrite: bool = False,
                 compress: bool = False) -> None:
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin

        self.path = Path(path)
        self.check(self.path, storage, overwrite)
        parent = self.path.parent
        self.storage = storage
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.partial-", dir=parent))
        except OSError as e:
            raise BagError(f"cannot write {self.path}: {e.strerror or e}") from None
        self._overwrite = overwrite
        cls = _writer_class()
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._w = cls(self._tmp / self.path.name, version=9, storage_plugin=plugin)
        if compress and storage == "mcap":
            self._w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._w.open()
        self._ts: Any = None
        self.connections: dict[str, Any] = {}

    @staticmethod
    def check(path: Path, storage: str, overwrite: bool) -> None:
        """BagError (one line) unless a bag of ``storage`` can be written at ``path``."""
        if storage not in STORAGES:
            raise BagError(f"unknown storage {storage!r} (choose from {', '.join(STORAGES)})")
        if path.exists() and not overwrite:
            raise BagError(f"{path} already exists (use --overwrite to replace it)")
        if path.exists() and not _is_bag_dir(path):
            raise BagError(f"{path} exists and is not a bag; not replacing it")
        if not path.parent.is_dir():
            raise BagError(f"cannot write {path}: directory {path.parent} does not exist")

    def add_topic(self, topic: str, msgtype: str, typestore: Any = None) -> Any:
        """Register a topic (absolute name) and return its connection."""
        if typestore is None:
            if self._ts is None:
                from mkf_ros.bags.reader import _typestore

                self._ts = _typestore()
            typestore = self._ts
        topic = normalize_topic(topic)
        conn = self._w.add_connection(topic, msgtype, typestore=typestore)
        self.connections[topic] = conn
        return conn

    def write(self, conn: Any, log_ns: int, raw: bytes) -> None:
        self._w.write(conn, int(log_ns), raw)

    def write_batch(self, conns: Any, log_ns: np.ndarray, data: np.ndarray | list[bytes]
                    ) -> None:
        """Write many messages: ``conns`` one connection or an array of connection ids (N,),
        ``log_ns`` (N,), ``data`` an (N, L) uint8 array or N bytes objects."""
        n = len(log_ns)
        if n == 0:
            return
        cids = (np.full(n, conns.id, dtype=np.int64) if hasattr(conns, "id")
                else np.asarray(conns, dtype=np.int64))
        self._w.write_batch(cids, np.asarray(log_ns, dtype=np.int64), data)

    def close(self) -> None:
        """Finish the bag and move it into place."""
        try:
            self._w.close()
            if self.path.exists() and self._overwrite:
                shutil.rmtree(self.path)
            (self._tmp / self.path.name).rename(self.path)
        except OSError as e:
            self.abort()
            raise BagError(f"cannot write {self.path}: {e.strerror or e}") from None
        shutil.rmtree(self._tmp, ignore_errors=True)

    def abort(self) -> None:
        """Drop everything written so far."""
        with contextlib.suppress(Exception):  # cleaning up after a failure: best effort
            if self._w.storage is not None:
                self._w.abort()
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _is_bag_dir(p: Path) -> bool:
    return p.is_dir() and ((p / "metadata.yaml").is_file() or not any(p.iterdir()))
