"""``mkf process --smooth`` (docs/bags.md): the bag's output windows wait, encoded, until
the fixed-interval smoother (docs/math.md §11) has smoothed every filter step of theirs, then get
the smoothed orientation and covariance written in; ``--smooth two-way``'s spilled readings, the
reversed smoother's rows and the pass that captures them. Memory is bounded by one smoothing
window + overlap plus the bag windows it spans."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.bags.messages import Chunk
from mkf_ros.bags.reader import BagError
from mkf_ros.core.state import new_records


class Smoothing:
    """``--smooth``: the adapter records every filter step (:meth:`StreamAdapter.record_into`)
    into a :class:`~mkf_ros.core.smoother.Windows` of one smoothing window + overlap (the
    event loop stops when it is full, :meth:`_full` smooths a window and makes room); the
    windows of the bag wait (encoded, as :class:`Chunk`) until every output of theirs is
    smoothed, then get the smoothed orientation and covariance written in (the node's
    conventions, :meth:`StreamAdapter.published_orientation`) and go out in order. Held: the
    slots of one smoothing window + overlap, the smoothed rows and the bag windows they span
    (docs/bags.md)."""

    #: What a waiting chunk's outputs hold in place of the fields already encoded.
    _DROPPED = np.zeros((0, 0))

    def __init__(self, adapter: Any, window: int, overlap: int,
                 two_way: TwoWay | None = None, keep_outputs: bool = False) -> None:
        from mkf_ros.core.smoother import Windows
        from mkf_ros.stream.kernel import MAX_STEPS_PER_EVENT

        self.adapter = adapter
        self.two_way = two_way  #: the reversed smoother's rows to fuse with (two-way)
        self.keep_outputs = keep_outputs  #: the caller keeps every output field
        self.wins = Windows(adapter.filter.kernel_arrays().cfg, window, overlap,
                            window + overlap + MAX_STEPS_PER_EVENT)
        adapter.record_into(self.wins.rec, self._full)
        self.pending: list[Chunk] = []
        self.base = 0  #: global slot of the first row of the smoothed rows held
        self.quat = np.zeros((0, 4))
        self.cov = np.zeros((0, 3, 3))
        self.valid = np.zeros(0, dtype=bool)
        self.seconds = 0.0  #: spent smoothing
        self.paused = 0.0  #: of which inside the event loop (it paused for room)

    def _full(self, filled: int) -> tuple[np.ndarray, int, int]:
        """The recording is full: smooth what can be; where it goes on."""
        t0 = self.seconds
        self.wins.held = filled
        self._smooth(False)
        self.paused += self.seconds - t0
        return self.wins.rec, self.wins.held, self.wins.done

    def _smooth(self, final: bool) -> None:
        t0 = time.perf_counter()
        first = self.wins.done
        got = self.wins.smooth(final)
        if self.two_way is not None:
            for g in got:
                first = self.two_way.fuse(g, first)
        if got:
            self.quat = np.concatenate([self.quat, *(g.quat for g in got)])
            self.cov = np.concatenate([self.cov, *(g.cov for g in got)])
            self.valid = np.concatenate([self.valid, *(g.initialized for g in got)])
        self.seconds += time.perf_counter() - t0

    def ready(self, chunk: Chunk | None, final: bool) -> list[Chunk]:
        """Queue ``chunk`` (``final``: the bag has ended, smooth every step); the chunks now
        complete, smoothed, in order."""
        if chunk is not None:
            if not self.keep_outputs:  # encoded: while it waits, only what _apply needs
                o = chunk.outs
                o.angular_velocity = o.angular_velocity_covariance = self._DROPPED
                o.linear_acceleration = o.linear_acceleration_covariance = self._DROPPED
            self.pending.append(chunk)
        if final:
            self.wins.held = self.adapter.recorded
            self._smooth(True)
            self.adapter.record_into(None)
        done: list[Chunk] = []
        while self.pending:
            c = self.pending[0]
            slot = c.outs.slot
            if len(slot) and slot[-1] >= self.wins.done:
                break
            self.pending.pop(0)
            if len(slot):
                self._apply(c)
            done.append(c)
        first = self.wins.done  # drop the smoothed rows no waiting output needs
        for c in self.pending:
            if len(c.outs.slot):
                first = int(c.outs.slot[0])
                break
        k = max(0, first - self.base)
        if k:
            self.quat, self.cov, self.valid = self.quat[k:], self.cov[k:], self.valid[k:]
            self.base += k
        return done

    def _apply(self, c: Chunk) -> None:
        o = c.outs
        i = o.slot - self.base
        ok = self.valid[i]
        q, cov = self.adapter.published_orientation(self.quat[i[ok]], self.cov[i[ok]],
                                                    o.yaw_lost[ok])
        o.quat = o.quat.copy()
        o.cov = o.cov.copy()
        o.quat[ok] = q
        o.cov[ok] = cov
        values = dict(orientation=np.column_stack([o.quat[:, 1], o.quat[:, 2], o.quat[:, 3],
                                                   o.quat[:, 0]]),
                      orientation_covariance=o.cov.reshape(-1, 9))
        if isinstance(c.encoded, np.ndarray):
            cdr.set_fields(c.encoded, cdr.IMU, **values)
            return
        res = []
        for j, raw in enumerate(c.encoded):
            row = np.frombuffer(raw, np.uint8)[None, :].copy()
            cdr.set_fields(row, cdr.IMU, **{k: v[j] for k, v in values.items()})
            res.append(row.tobytes())
        c.encoded = res


#: A step's readings ``(Δt, ω_g, a, m)`` in ``--smooth two-way``'s first file (a
#: :data:`~mkf_ros.core.smoother.RECORD`'s ``u``), and its row of the reversed smoother in the
#: second (docs/bags.md).
_STEP_ROW = np.dtype(("<f8", 10))
_REVERSED_ROW = np.dtype([("q", "<f8", 4), ("P", "<f8", (3, 3)), ("ok", "?")])


def temp_files_error(folder: Path, e: OSError) -> BagError:
    """The one line for ``--smooth two-way``'s temporary files that cannot be written."""
    return BagError(f"--smooth two-way: cannot write its temporary files in {folder} (about "
                    f"0.2 KB per IMU step): {e.strerror or e}")


@dataclass
class TwoWay:
    """``--smooth two-way``'s files (docs/bags.md): ``steps``, every filter step's readings
    ``(Δt, ω_g, a, m)`` as the first pass spilled them (:class:`Capture`, ``n`` steps, the
    filter started anew at ``starts``, its parameters ``params``); after :meth:`reverse`,
    ``rows``: the reversed smoother's rows of the same steps (:data:`_REVERSED_ROW`), which
    the last pass fuses with its own (:meth:`fuse`). Both are read and written a block at a
    time with plain file I/O (memory maps would count every page touched as resident)."""

    steps: Path
    n: int = 0
    starts: list[int] = field(default_factory=list)
    params: Any = None
    rows: Path | None = None
    fused: int = 0  #: steps of the last pass fused so far
    sizes: tuple[int, int] = (1, 0)  #: the smoothing window and overlap (the first pass's)

    def _read(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        u = np.fromfile(self.steps, _STEP_ROW, b - a, offset=a * _STEP_ROW.itemsize)
        return u[:, 0], u[:, 1:4], u[:, 4:7], u[:, 7:10]

    def reverse(self, rows: Path, progress: Any) -> None:
        """The reversed smoother over the spilled steps (streamed: one smoothing window and
        overlap, :attr:`sizes`, in memory) into the file ``rows``."""
        from mkf_ros.core.smoother import smooth_reversed_into

        self.rows = rows
        tick = progress("reversed pass", self.n) if progress else None
        with open(rows, "wb") as f:
            def write(first: int, q: np.ndarray, P: np.ndarray, ok: np.ndarray) -> None:
                block = np.empty(len(ok), _REVERSED_ROW)
                block["q"], block["P"], block["ok"] = q, P, ok
                f.seek(first * _REVERSED_ROW.itemsize)
                f.write(block.tobytes())

            smooth_reversed_into(self.params, self.n, self._read, self.starts, *self.sizes,
                                 write, tick)

    def fuse(self, rows: Any, first: int) -> int:
        """Fuse the smoothed rows of the steps ``first …`` (a
        :class:`~mkf_ros.core.filter.BatchOutputs`, in place) with the reversed ones; the
        step after them."""
        from mkf_ros.core.smoother import fuse_two_way

        assert self.rows is not None
        end = first + len(rows.initialized)
        if end > self.n:
            raise RuntimeError(f"two-way smoothing: step {end - 1} of the last pass, but the "
                               f"first captured {self.n} (the two passes over the bag differ)")
        b = np.fromfile(self.rows, _REVERSED_ROW, end - first,
                        offset=first * _REVERSED_ROW.itemsize)
        rows.quat[:], rows.cov[:] = fuse_two_way(rows.quat, rows.cov, rows.initialized, b["q"],
                                                 b["P"], b["ok"])
        self.fused = end
        return end


class Capture:
    """``--smooth two-way``'s first pass: the adapter records every filter step into a few
    slots (:meth:`StreamAdapter.record_into`), whose readings ``u`` go to
    ``two_way.steps`` whenever they fill (the last slot kept: the next step links to it)."""

    SLOTS = 1 << 15

    def __init__(self, adapter: Any, two_way: TwoWay) -> None:
        from mkf_ros.core.smoother import RECORD
        from mkf_ros.stream.kernel import MAX_STEPS_PER_EVENT

        self.adapter = adapter
        self.two_way = two_way
        self.file = open(two_way.steps, "wb")  # noqa: SIM115 (closed by finish)
        self.n = 0
        self.rec = new_records(RECORD, self.SLOTS + MAX_STEPS_PER_EVENT)
        adapter.record_into(self.rec, self._full)

    def _spill(self, k: int) -> None:
        try:
            self.file.write(self.rec["u"][:k].astype(_STEP_ROW.base).tobytes())
        except OSError as e:
            raise temp_files_error(self.two_way.steps.parent.parent, e) from None
        self.n += k

    def _full(self, filled: int) -> tuple[np.ndarray, int, int]:
        self._spill(filled - 1)
        self.rec[0] = self.rec[filled - 1]
        return self.rec, 1, self.n

    def finish(self) -> None:
        """Every step spilled; the file closed, the count, resets and parameters noted."""
        self._spill(self.adapter.recorded)
        self.file.close()
        tw = self.two_way
        tw.n, tw.starts = self.n, list(self.adapter.reset_slots)
        tw.params = self.adapter.filter.params
        self.adapter.record_into(None)


class NullWriter:
    """The first pass of ``--smooth two-way`` writes nothing."""

    def __enter__(self) -> NullWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def add_topic(self, topic: str, msgtype: str) -> None:
        return None

    def write_batch(self, conn: Any, log_ns: np.ndarray, data: Any) -> None:
        return None
