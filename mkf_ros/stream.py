"""Streaming front end of the filter: stamps, gaps, an asynchronous magnetometer, input checks.

:class:`StreamAdapter` holds an :class:`~mkf_ros.core.filter.AttitudeFilter` and every rule
about time and input that a live sensor stream or a recorded bag needs. It works on arrays and
stamps in seconds and never imports ROS: the ``estimator`` node is a thin rclpy wrapper around
it, and offline bag processing drives the same class, so both give identical results.

Time rules (stamps in seconds, the IMU stream sets the filter's clock):

* ``dt`` = IMU stamp − previous accepted IMU stamp, or ``constant_dt`` when that is > 0 (the
  stamps are then ignored, as in imu_filter_madgwick). The first sample initialises.
* ``dt == 0`` (a duplicate) and ``dt < 0`` (out of order) drop the sample, counted. A stamp
  more than ``time_jump_threshold`` older than the previous one (a bag loop, a clock reset), or
  :data:`MAX_BACKWARDS` out-of-order samples in a row, reset the filter and start over from it.
* ``dt > max_dt`` (a gap): the filter re-aligns roll and pitch from this sample's accelerometer
  (heading from the next magnetometer sample with ``use_mag``, otherwise the heading held
  before the gap) instead of integrating a stale rate across the gap. Until the magnetometer
  fixes the heading (or a reset), the published yaw variance is that of an unknown angle,
  :data:`YAW_UNKNOWN_VAR`: the sensor may have turned by anything during the gap.
* Magnetometer samples are fused asynchronously, at their own stamp, never gating the IMU:
  a sample newer than the filter's time is held until the IMU stream reaches its stamp and is
  then fused there (predict to it, update, continue); a sample up to ``mag_max_delay`` older is
  fused at once, rotated forward by the estimated rate over its age; older ones are dropped.
  The filter runs on gyro + accelerometer until the first magnetometer sample and keeps running
  when they stop.

Input rules: a gyro/accelerometer/magnetometer vector that is all NaN is *missing*, one that
is partly non-finite (or a zero accelerometer/magnetometer vector) is *invalid*, an
accelerometer whose magnitude is implausible (``acc_magnitude_tolerance``) is *rejected*;
only that sensor's part of the sample is skipped, and every case is counted with its reason.
Output is never produced before initialisation and never contains NaN.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mkf_ros.core.filter import COUNTER_NAMES as FILTER_COUNTERS
from mkf_ros.core.filter import AttitudeFilter, build_cfg
from mkf_ros.core.frames import FROM_ENU
from mkf_ros.core.params import BY_NAME, PARAMS, FilterParams, Param
from mkf_ros.core.quaternion import qconj_np, qmul_np, rotmat_np

#: Out-of-order IMU samples in a row after which the stream is taken to have jumped back.
MAX_BACKWARDS = 10
#: Magnetometer samples held while waiting for the IMU stream to reach their stamps.
MAX_PENDING_MAG = 32
#: Smallest time step of an internal magnetometer-only filter step (the MUKF cannot
#: factorise its sigma points with zero process noise at dt = 0).
MIN_STEP = 1e-9
#: A magnetometer stamp this close to an IMU stamp is fused in the same filter step.
SAME_STAMP = 1e-6
#: Published yaw variance (rad²) while the heading is unknown: after a gap the filter keeps
#: the heading it had, but the sensor may have turned by any angle meanwhile (uniform on ±π).
YAW_UNKNOWN_VAR = math.pi**2 / 3.0
_K_GAPS = FILTER_COUNTERS.index("gaps")

#: Reasons a sample (or part of one) was dropped, rejected or caused a reset; see module doc.
COUNTER_REASONS: dict[str, str] = {
    "imu_received": "IMU samples received",
    "imu_duplicate": "IMU samples dropped: stamp equal to the previous one",
    "imu_out_of_order": "IMU samples dropped: stamp older than the previous one",
    "imu_bad_stamp": "IMU samples dropped: stamp zero or not finite (set constant_dt?)",
    "gyr_missing": "gyro readings missing (all NaN or covariance[0] = -1)",
    "gyr_invalid": "gyro readings skipped: partly NaN/Inf, or faster than 1000 rad/s",
    "acc_missing": "accelerometer readings missing (all NaN or covariance[0] = -1)",
    "acc_invalid": "accelerometer readings skipped: NaN/Inf or zero vector",
    "acc_implausible": "accelerometer readings skipped: magnitude far from gravity",
    "mag_received": "magnetometer samples received",
    "mag_unused": "magnetometer samples ignored: use_mag is false",
    "mag_missing": "magnetometer samples missing (all NaN)",
    "mag_invalid": "magnetometer samples skipped: partly NaN/Inf or zero vector",
    "mag_too_old": "magnetometer samples dropped: older than mag_max_delay",
    "mag_ahead": "magnetometer samples dropped: stamp ahead of the IMU stream by > max_dt",
    "mag_overflow": "magnetometer samples dropped: too many waiting for the IMU stream",
    "mag_fused": "magnetometer samples fused",
    "gaps": "gaps longer than max_dt (re-aligned)",
    "update_failed": "filter updates that failed to factorise (regularised)",
    "output_nonfinite": "non-finite estimates (filter reset, nothing published)",
    "resets": "filter resets (all causes; see last_reset_reason)",
    "resets_time_jump": "resets because the IMU stamps jumped back",
}
#: The filter's own counters that the adapter reports too (the others, samples and
#: missing/invalid vectors, the adapter counts itself before the filter sees a sample).
_FILTER_SKIP = {"samples", "gyr_missing", "gyr_invalid", "acc_missing", "acc_invalid",
                "mag_missing", "mag_invalid", "before_init", "gaps", "update_failed"}
FILTER_REPORTED = tuple(n for n in FILTER_COUNTERS if n not in _FILTER_SKIP)
_FILTER_REASONS = {
    "acc_rejected_norm": "accelerometer samples not fused: magnitude (acc_norm_tolerance)",
    "acc_rejected_chi2": "accelerometer samples not fused: innovation gate (acc_gate)",
    "mag_rejected_norm": "magnetometer samples not fused: magnitude (mag_norm_tolerance)",
    "mag_rejected_dip": "magnetometer samples not fused: dip angle (mag_dip_tolerance)",
    "mag_rejected_chi2": "magnetometer samples not fused: innovation gate (mag_gate)",
    "rest_updates": "zero-rate updates at rest (rest_detection)",
}
COUNTER_REASONS.update({n: _FILTER_REASONS.get(n, f"filter counter {n}")
                        for n in FILTER_REPORTED})
_FILTER_SYNCED = {"gaps", "update_failed", *FILTER_REPORTED}

#: Counters that mean data was lost or rejected: diagnostics warn whenever one grows.
REJECTIONS = (
    "imu_duplicate", "imu_out_of_order", "imu_bad_stamp", "gyr_invalid", "acc_invalid",
    "mag_invalid", "mag_too_old", "mag_ahead", "mag_overflow", "update_failed",
    "output_nonfinite",
)
#: Rejections that are normal in moderation (motion, magnetic disturbances): diagnostics warn
#: when they hit most samples of a period. Counter → the counter of the samples it refers to.
GATED = {"acc_implausible": "imu_received",
         **{n: ("imu_received" if n.startswith("acc_") else "mag_received")
            for n in FILTER_REPORTED if "_rejected_" in n}}


@dataclass(slots=True)
class StreamOutput:
    """The estimate after one IMU sample, ready to publish (all finite)."""

    stamp: float  #: s, the IMU sample's stamp
    quat_wxyz: np.ndarray  #: (4,) sensor → world (``world_frame``, yaw offset applied), w ≥ 0
    orientation_cov: np.ndarray  #: (3, 3) rad², about the world axes
    #: (3,) rad/s per ``angular_velocity_source``; None: the input had no valid gyro reading
    angular_velocity: np.ndarray | None
    #: (3, 3) rad²/s² replacing the input's covariance (source ``estimate``), else None
    angular_velocity_cov: np.ndarray | None
    #: (3, 3) rad²/s² to add to the input's covariance (``bias_corrected``: bias variance)
    angular_velocity_cov_add: np.ndarray | None
    #: (3,) m/s² the input specific force (gravity removed if asked); None: no valid reading
    linear_acceleration: np.ndarray | None
    omega: np.ndarray  #: (3,) estimated body rate, rad/s
    bias: np.ndarray  #: (3,) estimated gyro bias, rad/s
    bias_stddev: np.ndarray  #: (3,) rad/s
    heading_initialized: bool  #: the magnetometer has fixed the heading


def _check(p: Param, value: Any) -> Any:
    """``p.validate`` but keeping the case of free-form strings (frame ids)."""
    v = p.validate(value)
    if p.type is str and not p.choices:
        return value.strip()
    return v


def validate_param(name: str, value: Any) -> Any:
    """One parameter's value coerced to its type; ValueError (one line) if invalid/unknown."""
    p = BY_NAME.get(name)
    if p is None:
        raise ValueError(f"unknown parameter {name!r}")
    return _check(p, value)


def validate_changes(changes: Mapping[str, Any], base: FilterParams) -> dict[str, Any]:
    """Validated copy of ``changes`` (any scope); the filter's cross-parameter rules are
    checked against ``base``. ValueError (one line naming the parameter) if invalid."""
    out = {name: validate_param(name, v) for name, v in changes.items()}
    filt = {k: v for k, v in out.items() if BY_NAME[k].scope == "filter"}
    if filt:
        build_cfg(base.replace(**filt))
    return out


def covariance_out(input_cov: Any, stddev: float, add: np.ndarray | None = None) -> np.ndarray:
    """A published 3×3 covariance (9 values, row major) from the input's (REP-145).

    An unknown input covariance (all zeros) is filled with ``stddev²`` on the diagonal when
    ``stddev > 0`` and otherwise stays unknown; ``add`` (3×3) is added to a known one. A
    covariance with NaN/Inf or the "not reported" marker (-1 first) counts as unknown.
    """
    c = np.array(input_cov, dtype=float).reshape(9)
    if c[0] == -1.0 or not math.isfinite(float(c.sum())):
        c[:] = 0.0
    if not c.any():
        if stddev <= 0.0:
            return c
        c[0] = c[4] = c[8] = stddev * stddev
    if add is not None:
        c += np.asarray(add, dtype=float).reshape(9)
    return c


#: A gyro reading faster than this (rad/s, ~9500 rpm) is beyond any MEMS range: invalid.
MAX_RATE = 1000.0


def _classify(v: np.ndarray, vector: bool) -> int:
    """0 valid, 1 missing (all NaN), 2 invalid (partly non-finite, or a zero vector)."""
    if math.isfinite(float(v[0] + v[1] + v[2])):  # NaN and ±Inf propagate through the sum
        return 2 if vector and v[0] == 0.0 and v[1] == 0.0 and v[2] == 0.0 else 0
    return 1 if math.isnan(v[0]) and math.isnan(v[1]) and math.isnan(v[2]) else 2


def _rotate_back(v: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """``Exp(−θ) v`` (Rodrigues): a world-fixed vector seen after the body turned by ``θ``."""
    th = math.hypot(*rotvec)
    if not 1e-12 < th < 1e3:  # no rotation, or a diverged rate: leave the vector as it is
        return v
    k = -rotvec / th
    c, s = math.cos(th), math.sin(th)
    return v * c + np.cross(k, v) * s + k * (float(k @ v) * (1.0 - c))


class StreamAdapter:
    """An :class:`AttitudeFilter` fed by timestamped IMU and magnetometer samples.

    >>> s = StreamAdapter(algorithm="mekf")
    >>> out = s.on_imu(0.00, [0, 0, 0], [0, 0, 9.81])   # initialises, returns the estimate
    >>> out = s.on_imu(0.01, [0, 0, 0], [0, 0, 9.81])
    >>> s.on_mag(0.012, [20e-6, 0, -40e-6])              # held until the IMU reaches 0.012 s

    Parameters are every entry of :data:`mkf_ros.core.params.PARAMS` (filter and node scope).
    """

    def __init__(self, params: Mapping[str, Any] | None = None, **overrides: Any) -> None:
        merged = dict(params or {}, **overrides)
        vals = validate_changes(merged, FilterParams())
        fp = FilterParams({k: v for k, v in vals.items() if BY_NAME[k].scope == "filter"})
        self.filter = AttitudeFilter(fp)
        self._node: dict[str, Any] = {
            p.name: _check(p, p.default) for p in PARAMS if p.scope == "node"
        }
        self._node.update({k: v for k, v in vals.items() if BY_NAME[k].scope == "node"})
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_REASONS, 0)
        self.last_reset_reason = ""
        self.acc_norm = math.nan  #: m/s², magnitude of the latest finite accelerometer sample
        self.mag_norm = math.nan  #: T, magnitude of the latest finite magnetometer sample
        self.mag_offset = math.nan  #: s, latest magnetometer stamp − filter time at its arrival
        self.last_imu_stamp = math.nan
        self.last_mag_stamp = math.nan
        self._filter_seen = np.zeros(len(self.filter.counters), dtype=np.int64)
        self._dt_stats = [0, math.inf, 0.0, 0.0]  # n, min, sum, max since pop_dt_stats()
        self._derive()
        self._clear_time()

    # --- parameters ------------------------------------------------------------------------
    def validate(self, changes: Mapping[str, Any]) -> dict[str, Any]:
        """Validated copy of ``changes`` against the current values, without side effects;
        ValueError (one line naming the parameter) if any is invalid."""
        return validate_changes(changes, self.filter.params)

    def set_params(self, **changes: Any) -> None:
        """Validate and apply ``changes`` atomically (ValueError: nothing changed)."""
        vals = self.validate(changes)
        filt = {k: v for k, v in vals.items() if BY_NAME[k].scope == "filter"}
        if filt:
            self.filter.set_params(**filt)
        self._node.update({k: v for k, v in vals.items() if BY_NAME[k].scope == "node"})
        if not self.filter.params.use_mag:
            self._pending.clear()
        self._derive()

    @property
    def params(self) -> dict[str, Any]:
        """Current value of every parameter (filter and node scope)."""
        return {**self.filter.params.values, **self._node}

    def _derive(self) -> None:
        n, f = self._node, self.filter.params
        self._const_dt = float(n["constant_dt"])
        q_w = FROM_ENU[f.world_frame]
        psi = float(n["yaw_offset"] - n["declination"])
        qz = np.array([math.cos(psi / 2), 0.0, 0.0, math.sin(psi / 2)])
        self._q_off = qmul_np(qmul_np(q_w, qz), qconj_np(q_w))  # about world up, in W axes
        self._r_off = rotmat_np(self._q_off)
        self._has_off = abs(psi) > 0.0
        self._up_w = rotmat_np(q_w) @ np.array([0.0, 0.0, 1.0])  # world up in W axes

    # --- state -----------------------------------------------------------------------------
    def _clear_time(self) -> None:
        self._t: float | None = None  # stamp of the filter state (= last accepted IMU stamp)
        self._yaw_lost = False  # a gap: heading unknown until the magnetometer fixes it
        self._backwards = 0
        self._pending: list[tuple[float, int, np.ndarray]] = []  # (stamp, seq, mag) sorted
        self._seq = 0

    def reset(self, reason: str = "requested") -> None:
        """Forget the estimate; the next IMU sample re-initialises. Counters are kept."""
        self.filter.reset()
        self._clear_time()
        self.counters["resets"] += 1
        self.last_reset_reason = reason

    @property
    def initialized(self) -> bool:
        return self.filter.initialized

    @property
    def time(self) -> float | None:
        """Stamp (s) of the filter's state, None before the first IMU sample."""
        return self._t

    def pop_dt_stats(self) -> tuple[int, float, float, float]:
        """``(n, min, mean, max)`` of the IMU time steps (s) since the previous call."""
        n, lo, s, hi = self._dt_stats
        self._dt_stats = [0, math.inf, 0.0, 0.0]
        return (n, lo, s / n, hi) if n else (0, math.nan, math.nan, math.nan)

    def all_counters(self) -> dict[str, int]:
        """Adapter counters plus the filter's own sample/gap/update counters."""
        self._sync_filter_counters()
        return dict(self.counters)

    def _sync_filter_counters(self) -> None:
        fc = self.filter.counters
        d = fc - self._filter_seen
        for i, name in enumerate(FILTER_COUNTERS):
            if d[i] > 0 and name in _FILTER_SYNCED:
                self.counters[name] += int(d[i])
        self._filter_seen = fc.copy()

    # --- input -----------------------------------------------------------------------------
    def _vec(self, v: Any, kind: str) -> np.ndarray | None:
        """Classify one sensor vector; None if it is to be skipped (counted)."""
        if v is None:
            self.counters[kind + "_missing"] += 1
            return None
        # a fresh C-contiguous writable copy: a read-only or strided view would make numba
        # compile another variant of the kernels in the middle of the stream
        a = np.array(v, dtype=float).reshape(-1)
        if a.shape != (3,):
            raise ValueError(f"{kind} sample must have 3 components, got shape {np.shape(v)}")
        c = _classify(a, kind != "gyr")
        if c == 0 and kind == "gyr" and math.hypot(*a) > MAX_RATE:
            c = 2
        if c:
            self.counters[kind + ("_missing" if c == 1 else "_invalid")] += 1
            return None
        return a

    def on_imu(self, stamp: float, gyr: Any, acc: Any) -> StreamOutput | None:
        """Process one IMU sample (rad/s, m/s²; None or all-NaN = not reported).

        Returns the estimate at ``stamp``, or None when nothing is to be published (sample
        dropped, filter not initialised yet).
        """
        self.counters["imu_received"] += 1
        stamp = float(stamp)
        if self._const_dt > 0.0:
            dt = self._const_dt if self._t is not None else 0.0
            t_new = (self._t + dt) if self._t is not None else 0.0
        else:
            if not math.isfinite(stamp) or stamp == 0.0:
                self.counters["imu_bad_stamp"] += 1
                return None
            t_new = stamp
            if self._t is not None:
                dt = stamp - self._t
                if dt <= 0.0:
                    if dt == 0.0:
                        self.counters["imu_duplicate"] += 1
                        return None
                    self._backwards += 1
                    thr = float(self._node["time_jump_threshold"])
                    if -dt <= thr and self._backwards < MAX_BACKWARDS:
                        self.counters["imu_out_of_order"] += 1
                        return None
                    self.counters["resets_time_jump"] += 1
                    self.reset("time jump")
                    dt = 0.0
            else:
                dt = 0.0
        self._backwards = 0
        self.last_imu_stamp = stamp
        g = self._vec(gyr, "gyr")
        a_in = a = self._vec(acc, "acc")
        if a is not None:
            norm = math.hypot(*a)
            self.acc_norm = norm
            grav = self.filter.params.gravity
            if abs(norm / grav - 1.0) > self._node["acc_magnitude_tolerance"]:
                self.counters["acc_implausible"] += 1
                a = None
        if self._t is not None and dt > 0.0:
            n = self._dt_stats
            n[0] += 1
            n[1] = min(n[1], dt)
            n[2] += dt
            n[3] = max(n[3], dt)

        mag = self._take_pending(t_new, dt)
        f = self.filter
        gaps = f.counters[_K_GAPS]
        if self._t is None or self._const_dt > 0.0:
            f.step(dt, g, a, mag)
        else:
            f.step(t_new - self._t, g, a, mag)
        if f.counters[_K_GAPS] != gaps:
            self._yaw_lost = True
        if mag is not None:
            self.counters["mag_fused"] += 1
        self._t = t_new
        return self._output(stamp, g, a_in)

    def _take_pending(self, t_new: float, dt: float) -> np.ndarray | None:
        """Fuse held magnetometer samples stamped before ``t_new``; return one stamped at
        ``t_new`` (or, on the first sample, the latest recent one) to fuse with the IMU."""
        pend = self._pending
        if not pend:
            return None
        if self._t is None:  # first sample: initialise with the latest recent magnetometer
            delay = self._node["mag_max_delay"]
            keep = [p for p in pend if p[0] > t_new + SAME_STAMP]
            near = [p for p in pend if abs(t_new - p[0]) <= max(delay, SAME_STAMP)
                    and p[0] <= t_new + SAME_STAMP]
            self.counters["mag_too_old"] += len(pend) - len(keep) - min(len(near), 1)
            self._pending = keep
            return near[-1][2] if near else None
        if dt > self.filter.params.max_dt:  # a gap: the held samples cannot be placed
            old = bisect.bisect_right(pend, (t_new - self._node["mag_max_delay"], -1))
            self.counters["mag_too_old"] += old
            del pend[:old]
        same = None
        while pend and pend[0][0] <= t_new + SAME_STAMP:
            tm, _, m = pend.pop(0)
            if abs(tm - t_new) <= SAME_STAMP:
                if same is not None:
                    self._fuse_mag_now(same, 0.0)
                same = m
            elif tm <= self._t:  # held before a reset moved the time: treat as late
                self._fuse_late(tm, m)
            else:
                self.filter.step(max(tm - self._t, MIN_STEP), None, None, m)
                self.counters["mag_fused"] += 1
                self._t = tm
        return same

    def on_mag(self, stamp: float, mag: Any) -> None:
        """Process one magnetometer sample (any unit, tesla by REP-145; all NaN = none)."""
        self.counters["mag_received"] += 1
        stamp = float(stamp)
        if not self.filter.params.use_mag:
            self.counters["mag_unused"] += 1
            return
        m = self._vec(mag, "mag")
        if m is None:
            return
        # hard/soft-iron calibration (mag_bias_*, mag_soft_iron) is applied by the core filter
        norm = math.hypot(*m)
        self.mag_norm = norm
        if not 0.0 < norm < math.inf:
            self.counters["mag_invalid"] += 1
            return
        # the raw field goes to the filter: it calibrates it and checks magnitude and dip
        self.last_mag_stamp = stamp
        if self._const_dt > 0.0:  # stamps are not trusted: fuse at the current time
            if self._t is None:
                self._pending = [(0.0, 0, m)]
            else:
                self._fuse_mag_now(m, 0.0)
            return
        if not math.isfinite(stamp):
            self.counters["mag_invalid"] += 1
            return
        if self._t is None:  # before the first IMU sample: keep the latest few
            self._hold(stamp, m)
            return
        d = stamp - self._t
        self.mag_offset = d
        if d > self.filter.params.max_dt:
            self.counters["mag_ahead"] += 1
        elif d > SAME_STAMP:
            self._hold(stamp, m)
        else:
            self._fuse_late(stamp, m)

    def _hold(self, stamp: float, m: np.ndarray) -> None:
        self._seq += 1
        bisect.insort(self._pending, (stamp, self._seq, m))
        if len(self._pending) > MAX_PENDING_MAG:
            self._pending.pop(0)
            self.counters["mag_overflow"] += 1

    def _fuse_late(self, stamp: float, m: np.ndarray) -> None:
        assert self._t is not None
        age = self._t - stamp
        if age > self._node["mag_max_delay"] + SAME_STAMP:
            self.counters["mag_too_old"] += 1
            return
        self._fuse_mag_now(m, max(age, 0.0))

    def _fuse_mag_now(self, m: np.ndarray, age: float) -> None:
        """Fuse at the filter's current time, ``m`` rotated forward over its ``age`` (s)."""
        if age > 0.0 and self.filter.initialized:
            m = _rotate_back(m, self.filter.omega * age)
        self.filter.step(MIN_STEP, None, None, m)
        self.counters["mag_fused"] += 1

    # --- output ----------------------------------------------------------------------------
    def _output(self, stamp: float, g: np.ndarray | None,
                a: np.ndarray | None) -> StreamOutput | None:
        f = self.filter
        if not f.initialized:
            return None
        n = self._node
        q = f.quaternion
        cov = f.covariance
        omega = f.omega
        bias = f.bias
        bstd = f.bias_stddev
        if not math.isfinite(float(q.sum() + cov.sum() + omega.sum() + bias.sum())):
            self.counters["output_nonfinite"] += 1
            self.reset("non-finite estimate")
            return None
        if self._has_off:
            q = qmul_np(self._q_off, q)
            cov = self._r_off @ cov @ self._r_off.T
            if q[0] < 0.0:
                q = -q
        if self._yaw_lost:
            if f.heading_initialized:
                self._yaw_lost = False
            elif cov[2, 2] < YAW_UNKNOWN_VAR:
                cov = cov.copy()
                cov[2, 2] = YAW_UNKNOWN_VAR  # world z is vertical in ENU, NED and NWU
        sd = n["orientation_stddev"]
        if sd > 0.0:
            cov = np.diag([sd * sd] * 3)
        src = n["angular_velocity_source"]
        w_cov = w_add = None
        if src == "estimate":
            w = omega
            w_cov = f.state_covariance[3:6, 3:6]
        elif g is None:
            w = None
        elif src == "bias_corrected":
            w = g - bias
            w_add = np.diag(bstd * bstd)
        else:
            w = g
        lin = a
        if lin is not None and n["remove_gravity_vector"]:
            up_b = rotmat_np(q).T @ self._up_w
            lin = lin - f.params.gravity * up_b
        return StreamOutput(stamp=stamp, quat_wxyz=q, orientation_cov=cov, angular_velocity=w,
                            angular_velocity_cov=w_cov, angular_velocity_cov_add=w_add,
                            linear_acceleration=lin, omega=omega,
                            bias=bias, bias_stddev=bstd,
                            heading_initialized=f.heading_initialized)
