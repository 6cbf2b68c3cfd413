"""Scoring ``mkf process``'s output against a ground-truth topic, one window of the bag at a
time: BROAD's errors (:func:`mkf_ros.evaluation.metrics.orientation_errors`) as sums over the
windows, per interval kind of the bag's description, and a decimated series for the plot, in
bounded memory."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mkf_ros.bags import cdr


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


class Scorer:
    """BROAD errors against the ground truth, one window at a time: each window's outputs are
    matched to the truth of the previous, the same and the next window (by stamp; among equal
    stamps the nearest log time), sums of squares accumulate, and the plot series are
    decimated (:class:`_Series`)."""

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
