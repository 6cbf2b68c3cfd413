"""Offline estimation over a bag, without DDS: what ``mkf process`` runs.

The IMU and magnetometer messages are fed, in the order they were recorded, to the same
:class:`mkf_ros.stream.adapter.StreamAdapter` the ``estimator`` node wraps, with the node's
conversions: a field whose covariance[0] is -1 is "not reported"; the output ``imu/data`` message
keeps the input's header, carries the filter's orientation and covariance, and fills the angular
velocity and linear acceleration like the node (``mkf_ros.ros.convert.fill_imu``). So a bag
processed here and the same bag replayed through the node give the same messages.

Bulk work (reading, decoding, encoding, writing) is vectorised (see :mod:`mkf_ros.bags.cdr`);
the adapter runs the whole recording in compiled code (:meth:`StreamAdapter.process`, in chunks
for the progress bar), with the results of the node's message-by-message calls.
"""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mkf_ros.bags import cdr
from mkf_ros.bags.reader import BagError, BagReader, normalize_topic
from mkf_ros.bags.writer import BagWriter
from mkf_ros.core.state import new_records
from mkf_ros.stream import rep145


@dataclass
class Outputs:
    """The estimates, one row per published ``imu/data`` message."""

    index: np.ndarray  #: (M,) index of the input IMU message
    quat: np.ndarray  #: (M, 4) [w, x, y, z], sensor → world_frame
    cov: np.ndarray  #: (M, 9) orientation covariance, rad², world axes
    angvel: np.ndarray  #: (M, 3)
    angvel_cov: np.ndarray  #: (M, 9)
    linacc: np.ndarray  #: (M, 3)
    linacc_cov: np.ndarray  #: (M, 9)
    #: (M,) bool, published with the heading lost in a gap (the node's yaw variance rule)
    yaw_lost: np.ndarray
    #: (M,) int, the smoother's slot of each output (``--smooth``; -1 otherwise)
    slot: np.ndarray


@dataclass
class Scores:
    """Orientation errors against the ground truth (BROAD metric), degrees."""

    t: np.ndarray  #: (K,) s since the first IMU message (log time)
    q_est: np.ndarray  #: (K, 4)
    q_true: np.ndarray  #: (K, 4) in the estimate's world frame
    errors: dict[str, np.ndarray]  #: total / heading / inclination (rad), (K,)
    rmse: dict[str, float]  #: degrees
    heading_aligned: bool  #: True: no magnetometer, heading aligned once at the start
    skipped: int  #: outputs without a matching ground-truth message
    windows: dict[str, dict[str, float]] = field(default_factory=dict)  #: RMSE per interval kind
    n: int = 0  #: samples scored (``t`` etc. hold every k-th of them on long recordings)
    #: per error: (bucket start times, min, max) over buckets of k samples, when decimated
    envelope: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
    intervals: dict[str, list] = field(default_factory=dict)  #: shaded, in ``t``'s time


@dataclass
class ProcessResult:
    out: Path
    imu_topic: str
    mag_topic: str | None
    n_imu: int
    n_mag: int
    n_out: int
    params: dict[str, Any]
    counters: dict[str, int]
    timings: dict[str, float]
    outputs: Outputs | None  #: every estimate (``keep_outputs``), else None
    stamps: np.ndarray | None  #: (M,) s, output stamps (``keep_outputs``)
    log_s: np.ndarray | None  #: (M,) s since the bag start, output log times (``keep_outputs``)
    scores: Scores | None
    notes: list[str]
    accel_topic: str | None = None  #: split input: the accelerometer topic (imu_topic: gyro)
    n_accel: int = 0


def _decode(raws: np.ndarray | list[bytes], layout: cdr.Layout, topic: str,
            path: Path) -> cdr.Decoded:
    try:
        return cdr.decode(raws, layout, topic)
    except cdr.CdrError as e:
        raise BagError(f"{path}: {e}") from None


def run_stream(adapter: Any, imu: cdr.Decoded, imu_log: np.ndarray, mag: cdr.Decoded | None,
               mag_log: np.ndarray | None, node_params: Mapping[str, Any],
               progress: Callable[[int], object] | None = None, accel: cdr.Decoded | None = None,
               accel_log: np.ndarray | None = None) -> Outputs:
    """Run ``adapter`` over the messages in recording order (by log time, the magnetometer
    first at equal times, as ``mkf synth`` writes); the ``imu/data`` fields it publishes.
    Split input (``accel`` given, ``input_mode`` split): ``imu`` is the gyro stream (its
    linear acceleration ignored) and ``accel`` the accelerometer stream (its angular velocity
    ignored), each message fused at its own stamp."""
    def seconds(stamp_ns: np.ndarray) -> np.ndarray:  # as the node: sec + nanosec · 1e-9
        return stamp_ns // 1_000_000_000 + (stamp_ns % 1_000_000_000) * 1e-9

    f = imu.fields
    av_in = f["angular_velocity_covariance"]
    la_in = f["linear_acceleration_covariance"]
    gyr = rep145.input_rows(f["angular_velocity"], av_in[:, 0])
    a_st = None
    if accel is not None:
        fa = accel.fields
        acc = rep145.input_rows(fa["linear_acceleration"],
                                fa["linear_acceleration_covariance"][:, 0])
        a_st = seconds(accel.stamp_ns)
    else:
        acc = rep145.input_rows(f["linear_acceleration"], la_in[:, 0])
    m_st = m_val = None
    if mag is not None and mag_log is not None and len(mag_log):
        m_st, m_val = seconds(mag.stamp_ns), mag.fields["magnetic_field"]
    res = adapter.process(seconds(imu.stamp_ns), gyr, acc, m_st, m_val, imu_arrival=imu_log,
                          mag_arrival=mag_log, acc_stamp=a_st, acc_arrival=accel_log,
                          progress=progress)
    i = res.index
    m = len(i)
    w_ok = ~np.isnan(res.angular_velocity[:, 0])
    a_ok = ~np.isnan(res.linear_acceleration[:, 0])
    w_cov = rep145.published_covariances(w_ok, res.angular_velocity_cov, av_in[i],
                                         float(node_params["angular_velocity_stddev"]),
                                         res.angular_velocity_cov_add)
    a_cov = rep145.published_covariances(a_ok, None, la_in[i],
                                         float(node_params["linear_acceleration_stddev"]))
    return Outputs(index=i, quat=res.quat_wxyz, cov=res.orientation_cov.reshape(m, 9),
                   angvel=np.where(w_ok[:, None], res.angular_velocity, 0.0), angvel_cov=w_cov,
                   linacc=np.where(a_ok[:, None], res.linear_acceleration, 0.0),
                   linacc_cov=a_cov, yaw_lost=res.yaw_lost, slot=res.slot)


def encode_outputs(imu: cdr.Decoded, batch: Any, out: Outputs) -> np.ndarray | list[bytes]:
    """``imu/data`` messages: the input messages with the estimate written in (header kept)."""
    if len(out.index) == 0:
        return []
    q = out.quat
    values = dict(orientation=np.column_stack([q[:, 1], q[:, 2], q[:, 3], q[:, 0]]),
                  orientation_covariance=out.cov, angular_velocity=out.angvel,
                  angular_velocity_covariance=out.angvel_cov, linear_acceleration=out.linacc,
                  linear_acceleration_covariance=out.linacc_cov)
    if imu.rows is not None:
        rows = imu.rows[out.index].copy()
        cdr.set_fields(rows, cdr.IMU, **values)
        return rows
    res: list[bytes] = []  # several frame_id lengths: patch each message
    raws = batch.raws
    for j, i in enumerate(out.index.tolist()):
        row = np.frombuffer(raws[i], np.uint8)[None, :].copy()
        cdr.set_fields(row, cdr.IMU, **{k: v[j] for k, v in values.items()})
        res.append(row.tobytes())
    return res


def _match_truth(stamps_ns: np.ndarray, log_ns: np.ndarray, truth_stamp: np.ndarray,
                 truth_log: np.ndarray) -> np.ndarray:
    """Index of the ground-truth message for each output (-1: none): equal stamp, and among
    equal stamps (stamps that jump back repeat) the closest log time."""
    res = np.full(len(stamps_ns), -1, dtype=np.int64)
    if len(truth_log) == 0:
        return res
    order = np.lexsort((truth_log, truth_stamp))
    ts = truth_stamp[order]
    lo = np.searchsorted(ts, stamps_ns, "left")
    hi = np.searchsorted(ts, stamps_ns, "right")
    one = hi - lo == 1
    res[one] = order[lo[one]]
    for k in np.flatnonzero(hi - lo > 1).tolist():
        cand = order[lo[k]:hi[k]]
        res[k] = cand[np.argmin(np.abs(truth_log[cand] - log_ns[k]))]
    return res


#: IMU messages per window of the streaming pass (about 35 MB of messages in flight)
WINDOW_MESSAGES = 50_000
#: at most this many scored samples are kept for the plot (every k-th beyond), plus
#: per-bucket minimum/maximum envelopes of the errors
SERIES_MAX = 100_000


class _Series:
    """Decimated series of the scored samples (every ``step``-th) and the min/max of each
    error over each bucket of ``step`` samples: what the plot shows, in bounded memory."""

    def __init__(self, step: int) -> None:
        self.step = step
        self.n = 0
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]] = []
        self.env: list[tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]] = []

    def add(self, t: np.ndarray, q_est: np.ndarray, q_true: np.ndarray,
            err: Mapping[str, np.ndarray]) -> None:
        g = self.n + np.arange(len(t))
        self.n += len(t)
        sel = g % self.step == 0
        self.parts.append((t[sel], q_est[sel], q_true[sel], {k: v[sel] for k, v in err.items()}))
        if self.step > 1 and len(t):
            b = g // self.step
            starts = np.flatnonzero(np.r_[True, b[1:] != b[:-1]])
            self.env.append((t[starts], {k: np.minimum.reduceat(v, starts)
                                         for k, v in err.items()},
                             {k: np.maximum.reduceat(v, starts) for k, v in err.items()}))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        keys = ("total", "heading", "inclination")
        if not self.parts:
            return np.zeros(0), np.zeros((0, 4)), np.zeros((0, 4)), {k: np.zeros(0)
                                                                      for k in keys}
        return (np.concatenate([p[0] for p in self.parts]),
                np.concatenate([p[1] for p in self.parts]),
                np.concatenate([p[2] for p in self.parts]),
                {k: np.concatenate([p[3][k] for p in self.parts]) for k in keys})

    def envelope(self) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
        """Per error: (bucket start times, minimum, maximum); a bucket cut by a window
        boundary appears twice (harmless for a plot). None when nothing was decimated."""
        if not self.env:
            return None
        t = np.concatenate([e[0] for e in self.env])
        return {k: (t, np.concatenate([e[1][k] for e in self.env]),
                    np.concatenate([e[2][k] for e in self.env])) for k in self.env[0][1]}


class _Scorer:
    """BROAD errors against the ground truth, one window at a time (see :func:`score`): each
    window's outputs are matched to the truth of the previous, the same and the next window
    (by stamp; among equal stamps the nearest log time), sums of squares accumulate, and the
    plot series are decimated (:class:`_Series`)."""

    def __init__(self, world_frame: str, use_mag: bool, skip: float, intervals: Any,
                 expected: int) -> None:
        self.world_frame, self.use_mag, self.skip = world_frame, use_mag, skip
        self.raw_intervals = intervals  #: simulation time; shifted at the first IMU message
        self.intervals: dict[str, list] | None = None
        self.truth: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # stamp, log, wxyz
        self.pending: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.align: np.ndarray | None = None
        self.t_first: float | None = None
        self.sums: dict[str, float] = {}
        self.count = 0
        self.win_sums: dict[str, dict[str, float]] = {}
        self.win_count: dict[str, int] = {}
        self.skipped = 0
        self.series = _Series(max(1, -(-expected // SERIES_MAX)))

    def shift(self, first_log_s: float) -> None:
        if self.intervals is None:
            self.intervals = {k: [(a + first_log_s, b + first_log_s) for a, b in v]
                              for k, v in (self.raw_intervals or {}).items()}

    def add(self, truth: cdr.Decoded | None, truth_log: np.ndarray, q_est: np.ndarray,
            stamp_ns: np.ndarray, log_ns: np.ndarray, log_s: np.ndarray) -> None:
        """One window: its truth messages and its outputs (scored once the next window's
        truth is in)."""
        if truth is not None and len(truth_log):
            qt = truth.fields["quaternion"]
            self.truth.append((truth.stamp_ns, truth_log,
                               np.column_stack([qt[:, 3], qt[:, 0], qt[:, 1], qt[:, 2]])))
        if self.pending is not None:
            self._score(*self.pending)
        self.truth = self.truth[-3:]
        self.pending = (q_est, stamp_ns, log_ns, log_s)

    def finish(self) -> None:
        if self.pending is not None:
            self._score(*self.pending)
            self.pending = None

    def _score(self, q_est: np.ndarray, stamp_ns: np.ndarray, log_ns: np.ndarray,
               log_s: np.ndarray) -> None:
        from mkf_ros.core.frames import FROM_ENU
        from mkf_ros.core.quaternion import qconj_np, qmul_np
        from mkf_ros.evaluation.metrics import orientation_errors

        if not len(q_est):
            return
        if self.truth:
            ts = np.concatenate([x[0] for x in self.truth])
            tl = np.concatenate([x[1] for x in self.truth])
            m = _match_truth(stamp_ns, log_ns, ts, tl)
        else:
            m = np.full(len(q_est), -1)
        ok = m >= 0
        self.skipped += int((~ok).sum())
        if not ok.any():
            return
        q_true = np.concatenate([x[2] for x in self.truth])[m[ok]]
        q_true /= np.linalg.norm(q_true, axis=1, keepdims=True)
        q_true = qmul_np(FROM_ENU[self.world_frame], q_true)
        q = np.asarray(q_est[ok], float)
        t = log_s[ok]
        if not self.use_mag:
            if self.align is None:
                e = qmul_np(q_true[0], qconj_np(q[0]))  # world-frame error at the start
                ang = 2.0 * math.atan2(e[3], e[0])  # its twist about the world z axis
                self.align = np.array([math.cos(ang / 2), 0.0, 0.0, math.sin(ang / 2)])
            q = qmul_np(self.align, q)
        if self.t_first is None:
            self.t_first = float(t[0])
        err = orientation_errors(q, q_true)
        keep = t >= self.t_first + self.skip
        n = int(keep.sum())
        self.count += n
        for k, v in err.items():
            self.sums[k] = self.sums.get(k, 0.0) + float(np.sum(np.square(v[keep])))
        for kind, ivs in (self.intervals or {}).items():
            inside = np.zeros(len(t), dtype=bool)
            for a, b in ivs:
                inside |= (t >= a) & (t <= b)
            inside &= keep
            if inside.any():
                self.win_count[kind] = self.win_count.get(kind, 0) + int(inside.sum())
                d = self.win_sums.setdefault(kind, {})
                for k, v in err.items():
                    d[k] = d.get(k, 0.0) + float(np.sum(np.square(v[inside])))
        self.series.add(t, q, q_true, err)

    def result(self) -> Scores | None:
        if self.series.n == 0:
            return None

        def rmse(s: float, n: int) -> float:
            return float(np.degrees(math.sqrt(s / n))) if n else math.nan

        keys = ("total", "heading", "inclination")
        t, qe, qt, err = self.series.arrays()
        return Scores(t=t, q_est=qe, q_true=qt, errors=err,
                      rmse={k: rmse(self.sums.get(k, 0.0), self.count) for k in keys},
                      heading_aligned=not self.use_mag, skipped=self.skipped,
                      windows={kind: {k: rmse(d[k], self.win_count[kind]) for k in keys}
                               for kind, d in self.win_sums.items()},
                      n=self.series.n, envelope=self.series.envelope(),
                      intervals=self.intervals or {})


@dataclass
class _Chunk:
    """One window of the bag whose messages wait for their smoothed orientation."""

    outs: Outputs  #: the filter's outputs (published form); ``slot``: global slots
    encoded: np.ndarray | list[bytes]  #: the output messages with the filter's orientation
    out_log: np.ndarray
    out_stamp: np.ndarray
    log_s: np.ndarray
    truth: Any  #: the window's ground truth (decoded) or None
    truth_log: np.ndarray | None
    copies: list[tuple[Any, np.ndarray, Any]]  #: (connection, log times, messages)


class _Smoothing:
    """``--smooth``: the adapter records every filter step (:meth:`StreamAdapter.record_into`)
    into a :class:`~mkf_ros.core.smoother.Windows` of one smoothing window + overlap (the
    event loop stops when it is full, :meth:`_full` smooths a window and makes room); the
    windows of the bag wait (encoded, as :class:`_Chunk`) until every output of theirs is
    smoothed, then get the smoothed orientation and covariance written in (the node's
    conventions, :meth:`StreamAdapter.published_orientation`) and go out in order. Held: the
    slots of one smoothing window + overlap, the smoothed rows and the bag windows they span
    (docs/bags.md)."""

    #: What a waiting chunk's outputs hold in place of the fields already encoded.
    _DROPPED = np.zeros((0, 0))

    def __init__(self, adapter: Any, window: int, overlap: int,
                 two_way: _TwoWay | None = None, keep_outputs: bool = False) -> None:
        from mkf_ros.core.smoother import Windows
        from mkf_ros.stream.kernel import MAX_STEPS_PER_EVENT

        self.adapter = adapter
        self.two_way = two_way  #: the reversed smoother's rows to fuse with (two-way)
        self.keep_outputs = keep_outputs  #: the caller keeps every output field
        self.wins = Windows(adapter.filter.kernel_arrays().cfg, window, overlap,
                            window + overlap + MAX_STEPS_PER_EVENT)
        adapter.record_into(self.wins.rec, self._full)
        self.pending: list[_Chunk] = []
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
            self.valid = np.concatenate([self.valid, *(g.valid for g in got)])
        self.seconds += time.perf_counter() - t0

    def ready(self, chunk: _Chunk | None, final: bool) -> list[_Chunk]:
        """Queue ``chunk`` (``final``: the bag has ended, smooth every step); the chunks now
        complete, smoothed, in order."""
        if chunk is not None:
            if not self.keep_outputs:  # encoded: while it waits, only what _apply needs
                o = chunk.outs
                o.angvel = o.angvel_cov = o.linacc = o.linacc_cov = self._DROPPED
            self.pending.append(chunk)
        if final:
            self.wins.held = self.adapter.recorded
            self._smooth(True)
            self.adapter.record_into(None)
        done: list[_Chunk] = []
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

    def _apply(self, c: _Chunk) -> None:
        o = c.outs
        i = o.slot - self.base
        ok = self.valid[i]
        q, cov = self.adapter.published_orientation(self.quat[i[ok]], self.cov[i[ok]],
                                                    o.yaw_lost[ok])
        o.quat = o.quat.copy()
        o.cov = o.cov.copy()
        o.quat[ok] = q
        o.cov[ok] = cov.reshape(-1, 9)
        values = dict(orientation=np.column_stack([o.quat[:, 1], o.quat[:, 2], o.quat[:, 3],
                                                   o.quat[:, 0]]),
                      orientation_covariance=o.cov)
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


def _temp_files_error(folder: Path, e: OSError) -> BagError:
    """The one line for ``--smooth two-way``'s temporary files that cannot be written."""
    return BagError(f"--smooth two-way: cannot write its temporary files in {folder} (about "
                    f"0.2 KB per IMU step): {e.strerror or e}")


@dataclass
class _TwoWay:
    """``--smooth two-way``'s files (docs/bags.md): ``steps``, every filter step's readings
    ``(Δt, ω_g, a, m)`` as the first pass spilled them (:class:`_Capture`, ``n`` steps, the
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
        :class:`~mkf_ros.core.smoother.SmoothOutputs`, in place) with the reversed ones; the
        step after them."""
        from mkf_ros.core.smoother import fuse_two_way

        assert self.rows is not None
        end = first + len(rows.valid)
        if end > self.n:
            raise RuntimeError(f"two-way smoothing: step {end - 1} of the last pass, but the "
                               f"first captured {self.n} (the two passes over the bag differ)")
        b = np.fromfile(self.rows, _REVERSED_ROW, end - first,
                        offset=first * _REVERSED_ROW.itemsize)
        rows.quat[:], rows.cov[:] = fuse_two_way(rows.quat, rows.cov, rows.valid, b["q"],
                                                 b["P"], b["ok"])
        self.fused = end
        return end


class _Capture:
    """``--smooth two-way``'s first pass: the adapter records every filter step into a few
    slots (:meth:`StreamAdapter.record_into`), whose readings ``u`` go to
    ``two_way.steps`` whenever they fill (the last slot kept: the next step links to it)."""

    SLOTS = 1 << 15

    def __init__(self, adapter: Any, two_way: _TwoWay) -> None:
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
            raise _temp_files_error(self.two_way.steps.parent.parent, e) from None
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


class _NullWriter:
    """The first pass of ``--smooth two-way`` writes nothing."""

    def __enter__(self) -> _NullWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def add_topic(self, topic: str, msgtype: str) -> None:
        return None

    def write_batch(self, conn: Any, log_ns: np.ndarray, data: Any) -> None:
        return None


def stream_param_names() -> list[str]:
    """Parameters that matter offline: the filter's and the node's input/time/output ones."""
    from mkf_ros.core.params import PARAMS

    return [p.name for p in PARAMS
            if p.scope == "filter" or (p.group in ("node: input and time", "node: output")
                                       and p.name != "publish_debug_topics")]


def process_bag(bag: str | Path, out: str | Path, params: Mapping[str, Any] | None = None, *,
                imu_topic: str | None = None, mag_topic: str | None = None,
                accel_topic: str | None = None, gyro_topic: str | None = None,
                truth_topic: str | None = "imu/ground_truth", output_topic: str = "imu/data",
                storage: str = "mcap", overwrite: bool = False, copy_input: bool = False,
                skip: float = 0.0, progress: Any = None,
                window: int | None = WINDOW_MESSAGES, keep_outputs: bool = False,
                smooth: bool | str = False, smooth_window: int | None = None,
                smooth_overlap: int | None = None) -> ProcessResult:
    """Run the estimator over ``bag`` and write ``out`` (see the module docstring).

    ``params``: filter and node parameters by name (ValueError if invalid). ``progress``: a
    factory ``(description, total) -> callable(increment)`` or None. Raises :class:`BagError`
    for unusable input; the output bag is written only if everything succeeded.

    Topics: ``imu_topic`` None finds the IMU: the bag's only ``sensor_msgs/Imu`` topic, or
    ``imu/data_raw`` among several (otherwise an error lists them with their message counts);
    with ``use_mag``, ``mag_topic`` None likewise takes the only ``MagneticField`` topic (or
    ``imu/mag``). ``accel_topic`` and ``gyro_topic`` (both, and no ``imu_topic``) select split
    input (``input_mode`` split): separate accelerometer and gyro ``Imu`` streams, the output
    one message per gyro message.

    Streaming: the bag is read, filtered, written and scored in windows of log time of about
    ``window`` messages (:meth:`BagReader.read_windows`; None: the whole bag as one window),
    the adapter's state carried from one to the next, so memory does not grow with the
    recording and the output does not depend on ``window``. ``keep_outputs``: also return
    every estimate (:class:`Outputs`, ``stamps``, ``log_s``; memory grows with the bag).

    ``smooth``: the output carries the fixed-interval smoother's orientation and covariance
    (docs/math.md §11; MEKF or MUKF) instead of the filter's: every filter step of the stream
    is recorded, smoothed in windows of ``smooth_window`` steps with ``smooth_overlap`` more
    (defaults as :func:`~mkf_ros.core.smoother.window_sizes`, at the IMU topic's mean rate:
    its messages over the bag's duration)
    and the messages are written once smoothed: memory and the output's delay are bounded by
    one smoothing window + overlap plus the bag windows they span. The other fields are the
    filter's as without it. ``smooth="two-way"``: that smoother's tilt fused with the same
    smoother's over the recording reversed (docs/math.md §11.5, as ``mkf_ros.estimate(...,
    smooth="two-way")``), in three passes: the bag read once to spill every filter step's
    readings to a file beside ``out`` (80 bytes per step), the reversed smoother over that
    file (its rows to a second file, 113 bytes per step), the bag read again and smoothed as
    above with each window's rows fused with the reversed ones; the files are removed at the
    end. Memory as above; disk about 0.2 KB per step.
    """
    from mkf_ros.core import smoother as sm_core

    try:
        mode = sm_core.smooth_mode(smooth)
    except ValueError as e:
        raise BagError(str(e)) from None
    kw = dict(imu_topic=imu_topic, mag_topic=mag_topic, accel_topic=accel_topic,
              gyro_topic=gyro_topic, truth_topic=truth_topic, output_topic=output_topic,
              storage=storage, overwrite=overwrite, copy_input=copy_input, skip=skip,
              progress=progress, window=window, keep_outputs=keep_outputs,
              smooth=mode is not None, smooth_window=smooth_window,
              smooth_overlap=smooth_overlap)
    if mode != "two-way":
        return _run_bag(bag, out, params, **kw)
    out = Path(out)
    BagWriter.check(out, storage, overwrite)
    try:
        tmp_dir = tempfile.TemporaryDirectory(prefix=f".{out.name}.two-way-", dir=out.parent)
    except OSError as e:
        raise _temp_files_error(out.parent, e) from None
    with tmp_dir as tmp:
        two = _TwoWay(Path(tmp) / "steps")
        t0 = time.perf_counter()
        _run_bag(bag, out, params, **{**kw, "truth_topic": None, "copy_input": False,
                                      "keep_outputs": False}, two_way=two)
        try:
            two.reverse(Path(tmp) / "reversed", progress)
        except OSError as e:
            raise _temp_files_error(out.parent, e) from None
        seconds = time.perf_counter() - t0
        res = _run_bag(bag, out, params, **kw, two_way=two)
    res.timings["two-way"] = seconds
    return res


def _run_bag(bag: str | Path, out: str | Path, params: Mapping[str, Any] | None, *,
             imu_topic: str | None, mag_topic: str | None, accel_topic: str | None,
             gyro_topic: str | None, truth_topic: str | None, output_topic: str, storage: str,
             overwrite: bool, copy_input: bool, skip: float, progress: Any,
             window: int | None, keep_outputs: bool, smooth: bool, smooth_window: int | None,
             smooth_overlap: int | None, two_way: _TwoWay | None = None) -> ProcessResult:
    """:func:`process_bag`'s pass over the bag; ``two_way`` (with ``smooth``): the first pass
    of ``--smooth two-way`` (nothing written: every filter step's readings spilled,
    :class:`_Capture`) while it has no reversed rows, else the last (smoothed rows fused)."""
    capture = two_way is not None and two_way.rows is None
    from mkf_ros.bags.synth import read_description
    from mkf_ros.core import smoother as sm_core
    from mkf_ros.stream.adapter import (
        REJECTIONS,
        StreamAdapter,
        carries_orientation,
        orientation_note,
    )

    bag, out = Path(bag), Path(out)
    notes: list[str] = []
    tm = {"read": 0.0, "filter": 0.0, "write": 0.0}
    params = dict(params or {})
    if (accel_topic is None) != (gyro_topic is None):
        raise BagError("split input needs both --accel-topic and --gyro-topic (separate "
                       "accelerometer and gyroscope sensor_msgs/Imu topics)")
    split = accel_topic is not None
    if split:
        if imu_topic is not None:
            raise BagError("--imu-topic (one combined IMU topic) and --accel-topic/--gyro-topic "
                           "(split input) exclude each other")
        if params.get("input_mode", "split") != "split":
            raise BagError("--accel-topic/--gyro-topic are split input: input_mode must be "
                           "split")
        params["input_mode"] = "split"
    elif params.get("input_mode") == "split":
        raise BagError("input_mode split needs --accel-topic and --gyro-topic")
    if smooth:
        params = sm_core.forward_params(params)
    adapter = StreamAdapter(params)
    p = adapter.params
    smoothing = capturing = None
    if smooth:
        if p["algorithm"] not in ("mekf", "mukf"):
            raise BagError(f"--smooth needs algorithm mekf or mukf (the smoother is the MKFs'), "
                           f"not {p['algorithm']}")
        try:  # before the bag is opened (the default overlap needs its rate: below)
            sm_core.check_window(smooth_window, smooth_overlap)
        except ValueError as e:
            raise BagError(str(e)) from None
    use_mag = bool(p["use_mag"])
    t0 = time.perf_counter()
    acc_name = None
    with BagReader(bag) as br:
        if split:
            imu_name = br.resolve(gyro_topic or "", cdr.IMU.msgtype, role="gyroscope")
            acc_name = br.resolve(accel_topic or "", cdr.IMU.msgtype, role="accelerometer")
            if acc_name == imu_name:
                raise BagError(f"--accel-topic and --gyro-topic are the same topic {imu_name}; "
                               "for one combined IMU topic use --imu-topic")
        elif imu_topic is not None:
            imu_name = br.resolve(imu_topic, cdr.IMU.msgtype, role="IMU")
        else:
            imu_name = br.discover(cdr.IMU.msgtype, role="IMU", flag="--imu-topic",
                                   preferred="imu/data_raw")
        mag_name = None
        if use_mag:
            mag_name = (br.resolve(mag_topic, cdr.MAGNETIC_FIELD.msgtype, role="magnetometer")
                        if mag_topic is not None else
                        br.discover(cdr.MAGNETIC_FIELD.msgtype, role="magnetometer",
                                    flag="--mag-topic", preferred="imu/mag"))
        elif br.of_type(cdr.MAGNETIC_FIELD.msgtype):
            notes.append(f"{', '.join(br.of_type(cdr.MAGNETIC_FIELD.msgtype))} in the bag but "
                         "use_mag is false (pass --use-mag to fuse it)")
        truth_name = None
        if truth_topic and normalize_topic(truth_topic) in br.topics:
            truth_name = br.resolve(truth_topic, cdr.QUATERNION_STAMPED.msgtype,
                                    role="ground-truth")
        if smooth:
            steps = br.topics[imu_name].count  # the gyro's in split input: one step each
            sizes = sm_core.window_sizes(smooth_window, smooth_overlap, sm_core.mean_period(
                (br.end_ns - br.start_ns) * 1e-9, steps))
            if two_way is not None and capture:
                two_way.sizes = sizes
                capturing = _Capture(adapter, two_way)
            else:
                smoothing = _Smoothing(adapter, *sizes, two_way, keep_outputs)
        want = [t for t in (imu_name, acc_name, mag_name, truth_name) if t]
        extra = list(br.topics) if copy_input else []
        read = list(dict.fromkeys(want + extra))
        in_types = {t: br.topics[t].msgtype for t in extra}
        out_name = normalize_topic(output_topic)
        if copy_input and out_name in br.topics:
            raise BagError(f"output topic {out_name} is also in the input bag; choose another "
                           "--output-topic or drop --copy-input")
        bag_start = br.start_ns
        desc = (read_description(bag) or {}) if truth_name else {}
        scorer = (_Scorer(p["world_frame"], use_mag, skip, desc.get("intervals"),
                          br.topics[imu_name].count) if truth_name else None)
        tick = (progress("forward pass" if capture else "process", br.work_total(read))
                if progress else None)
        n_imu = n_acc = n_mag = n_out = 0
        orientation = False
        kept: list[tuple[Outputs, np.ndarray, np.ndarray]] = []
        tm["read"] += time.perf_counter() - t0
        with _NullWriter() if capture else BagWriter(out, storage, overwrite=overwrite) as w:
            conn = w.add_topic(out_name, cdr.IMU.msgtype)
            copies = {t: w.add_topic(t, in_types[t]) for t in extra}
            windows = br.read_windows(read, window, tick)

            def emit(c: _Chunk) -> None:
                """A window's messages out (written, scored, kept)."""
                t0 = time.perf_counter()
                w.write_batch(conn, c.out_log, c.encoded)
                for cn, log_ns, data in c.copies:
                    w.write_batch(cn, log_ns, data)
                tm["write"] += time.perf_counter() - t0
                if scorer is not None and c.truth is not None and c.truth_log is not None:
                    scorer.add(c.truth, c.truth_log, c.outs.quat, c.out_stamp, c.out_log,
                               c.log_s)
                if keep_outputs:
                    kept.append((c.outs, c.out_stamp * 1e-9, c.log_s))

            while True:
                t0 = time.perf_counter()
                win = next(windows, None)
                if win is None:
                    break
                imu_b = win[imu_name]
                imu = _decode(imu_b.data, cdr.IMU, imu_name, bag)
                acc = acc_b = None
                if acc_name:
                    acc_b = win[acc_name]
                    acc = _decode(acc_b.data, cdr.IMU, acc_name, bag)
                mag = mag_b = None
                if mag_name:
                    mag_b = win[mag_name]
                    mag = _decode(mag_b.data, cdr.MAGNETIC_FIELD, mag_name, bag)
                truth = (_decode(win[truth_name].data, cdr.QUATERNION_STAMPED, truth_name, bag)
                         if truth_name else None)
                t1 = time.perf_counter()
                tm["read"] += t1 - t0
                outs = run_stream(adapter, imu, imu_b.log_ns, mag,
                                  mag_b.log_ns if mag_b else None, p, None, acc,
                                  acc_b.log_ns if acc_b else None)
                if len(imu_b):
                    orientation = orientation or carries_orientation(
                        imu.fields["orientation"], imu.fields["orientation_covariance"][:, 0])
                t2 = time.perf_counter()
                tm["filter"] += t2 - t1
                out_log = imu_b.log_ns[outs.index]
                if scorer is not None and truth is not None and len(imu_b):
                    scorer.shift((int(imu_b.log_ns[0]) - bag_start) * 1e-9)
                chunk = _Chunk(outs, [] if capture else encode_outputs(imu, imu_b, outs), out_log,
                               imu.stamp_ns[outs.index], (out_log - bag_start) * 1e-9, truth,
                               win[truth_name].log_ns if truth_name else None,
                               [(c, win[t].log_ns, win[t].data) for t, c in copies.items()])
                outs.index = outs.index + n_imu
                n_imu += len(imu_b)
                n_acc += len(acc_b) if acc_b else 0
                n_mag += len(mag_b) if mag_b else 0
                n_out += len(outs.index)
                t3 = time.perf_counter()
                tm["write"] += t3 - t2
                if smoothing is None:
                    emit(chunk)
                    continue
                for c in smoothing.ready(chunk, False):
                    emit(c)
            if capturing is not None:
                capturing.finish()
            if smoothing is not None:
                for c in smoothing.ready(None, True):
                    emit(c)
                tw = smoothing.two_way
                if tw is not None and tw.fused != tw.n:  # (the output is dropped)
                    raise RuntimeError(f"two-way smoothing: {tw.fused} steps fused of {tw.n} "
                                       "captured (the two passes over the bag differ)")
                tm["smooth"] = smoothing.seconds
                tm["filter"] -= smoothing.paused  # (the event loop's pauses to smooth)
            if n_imu == 0:
                raise BagError(f"IMU topic {imu_name} in {bag} has no messages")
            found = adapter.input_problems(imu_name, acc_name or "")
            if "gyro" in found:  # an estimate of the tilt alone; said, not refused
                notes.append(found.pop("gyro"))
            problems = list(found.values())
            if not problems and n_out == 0:
                why = ", ".join(f"{v} {k}" for k, v in adapter.counters.items()
                                if v and k in (*REJECTIONS, "acc_missing", "acc_implausible"))
                problems = [f"no estimate from the {n_imu} messages of {imu_name}"
                            + (f" ({why})" if why else "")]
            if problems:  # the output bag is dropped (BagWriter: never half-written)
                raise BagError("; ".join(problems) + "; no output written")
            t0 = time.perf_counter()
        tm["write"] += time.perf_counter() - t0
    if orientation:
        notes.append(orientation_note(imu_name))
    scores = None
    if scorer is not None:
        scorer.finish()
        scores = scorer.result()
        if scores is None:
            notes.append(f"no {truth_name} message has the stamp of an output; not scored")
    outputs, stamps, log_s_all = _join(kept) if keep_outputs else (None, None, None)
    counters = adapter.all_counters()
    return ProcessResult(out=out, imu_topic=imu_name, mag_topic=mag_name, n_imu=n_imu,
                         accel_topic=acc_name, n_accel=n_acc, n_mag=n_mag, n_out=n_out,
                         params=p, counters=counters, timings=tm, outputs=outputs,
                         stamps=stamps, log_s=log_s_all, scores=scores, notes=notes)


def _join(kept: list[tuple[Outputs, np.ndarray, np.ndarray]]
          ) -> tuple[Outputs, np.ndarray, np.ndarray]:
    """The estimates of every window as one :class:`Outputs` (``keep_outputs``)."""
    fields = [f for f in Outputs.__dataclass_fields__]
    outs = Outputs(**{f: np.concatenate([getattr(k[0], f) for k in kept]) for f in fields})
    return outs, np.concatenate([k[1] for k in kept]), np.concatenate([k[2] for k in kept])
