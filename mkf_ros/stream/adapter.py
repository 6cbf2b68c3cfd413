"""Streaming front end of the filter: stamps, gaps, an asynchronous magnetometer, input checks.

:class:`StreamAdapter` holds an :class:`~mkf_ros.core.filter.AttitudeFilter` and every rule
about time and input that a live sensor stream or a recorded bag needs. It works on arrays and
stamps in seconds and never imports ROS: the ``estimator`` node is a thin rclpy wrapper around
it, and offline bag processing drives the same class, so both give identical results. The
rules below run compiled (:mod:`mkf_ros.stream.kernel`), one message at a time
(:meth:`StreamAdapter.on_imu`, :meth:`StreamAdapter.on_mag`) or over a whole recording
(:meth:`StreamAdapter.process`), with the same results either way.

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
  :data:`~mkf_ros.core.state.YAW_VAR_UNKNOWN`: the sensor may have turned by anything during
  the gap.
* Magnetometer samples are fused asynchronously, at their own stamp, never gating the IMU:
  a sample newer than the filter's time is held until the IMU stream reaches its stamp and is
  then fused there (predict to it, update, continue); a sample up to ``mag_max_delay`` older is
  fused at once, rotated forward by the estimated rate over its age; older ones are dropped.
  The filter runs on gyro + accelerometer until the first magnetometer sample and keeps running
  when they stop.
* Split input (``input_mode`` split: separate accelerometer and gyroscope streams, as the Intel
  RealSense drivers publish them): the gyro stream sets the filter's clock and is published
  (one output per gyro message, at its stamp; its accelerometer field is ignored), and each
  accelerometer sample is fused at its own stamp like a magnetometer sample: held until the
  gyro stream reaches it (with the gyro sample of the same stamp, or predicted to it with the
  rate estimate, updated, and on), fused at once when up to ``acc_max_delay`` late (rotated
  forward), dropped when older. No resampling, no unite step. The output's linear
  acceleration is "not reported" (the accelerometer is on its own topic).

Input rules: a gyro/accelerometer/magnetometer vector that is all NaN is *missing*, one that
is partly non-finite (or a zero accelerometer/magnetometer vector) is *invalid*, an
accelerometer whose magnitude is implausible (``acc_magnitude_tolerance``) is *rejected*;
only that sensor's part of the sample is skipped, and every case is counted with its reason.
Output is never produced before initialisation and never contains NaN.

Input that cannot give an orientation is named by :meth:`StreamAdapter.input_problems` (the
node logs it once and puts it in ``/diagnostics``; ``mkf process`` stops with one line and no
output when there is no accelerometer, and notes the rest): after
:data:`INPUT_CHECK_MESSAGES` messages, no angular velocity other than exactly zero (an
accelerometer-only topic?) or no usable accelerometer sample (a gyro-only topic?);
:func:`carries_orientation` names an input that carries an orientation already (an
estimator's output rather than raw data?).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from mkf_ros.core import _jit, smoother
from mkf_ros.core.filter import COUNTER_NAMES as FILTER_COUNTERS
from mkf_ros.core.filter import (
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    AttitudeFilter,
    kernel_table,
    new_records,
    record,
)
from mkf_ros.core.frames import FROM_ENU
from mkf_ros.core.params import BY_NAME, PARAMS, FilterParams, Param
from mkf_ros.core.quaternion import qconj_np, qmul_np, rotmat_np
from mkf_ros.core.state import ACC_NORM_TOLERANCE
from mkf_ros.stream import kernel as sk
from mkf_ros.stream import rep145

# constants of the rules above, defined with the rules in stream/kernel.py
from mkf_ros.stream.kernel import MAX_BACKWARDS as MAX_BACKWARDS
from mkf_ros.stream.rep145 import covariance_out as covariance_out

#: Reasons a sample (or part of one) was dropped, rejected or caused a reset; see module doc.
COUNTER_REASONS: dict[str, str] = {
    "imu_received": "IMU samples received",
    "imu_duplicate": "IMU samples dropped: stamp equal to the previous one",
    "imu_out_of_order": "IMU samples dropped: stamp older than the previous one",
    "imu_bad_stamp": "IMU samples dropped: stamp zero or not finite (set constant_dt?)",
    "gyr_missing": "gyro readings missing (all NaN or covariance[0] = -1)",
    "gyr_invalid": "gyro readings skipped: partly NaN/Inf, or faster than "
                   f"{MAX_GYRO_RATE:g} rad/s",
    "acc_missing": "accelerometer readings missing (all NaN or covariance[0] = -1)",
    "acc_invalid": "accelerometer readings skipped: NaN/Inf, zero vector, or beyond "
                   f"{MAX_ACC_G:g} g",
    "acc_implausible": "accelerometer readings skipped: magnitude far from gravity",
    "acc_received": "accelerometer samples received (split input)",
    "acc_too_old": "accelerometer samples dropped: older than acc_max_delay (split input)",
    "acc_ahead": "accelerometer samples dropped: stamp ahead of the gyro stream by > max_dt",
    "acc_overflow": "accelerometer samples dropped: too many waiting for the gyro stream",
    "acc_fused": "accelerometer samples fused (split input)",
    "mag_received": "magnetometer samples received",
    "mag_unused": "magnetometer samples ignored: use_mag is false",
    "mag_missing": "magnetometer samples missing (all NaN)",
    "mag_invalid": "magnetometer samples skipped: partly NaN/Inf, zero vector, or larger "
                   f"than {MAX_MAG:g}",
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
    "acc_rejected_norm": "accelerometer samples not fused raw: magnitude over "
                         f"{ACC_NORM_TOLERANCE:g} g off gravity (the low-pass carries gravity; "
                         "refused while it forms its first average or is itself that far off)",
    "acc_rejected_chi2": "accelerometer samples not fused: innovation gate (chi-square 16.3)",
    "mag_rejected_norm": "magnetometer samples not fused: magnitude (mag_norm_tolerance)",
    "mag_rejected_chi2": "magnetometer samples not fused: innovation gate (chi-square 10.8)",
    "rest_updates": "zero-rate updates at rest (rest_detection)",
}
COUNTER_REASONS.update({n: _FILTER_REASONS.get(n, f"filter counter {n}")
                        for n in FILTER_REPORTED})
#: Whether each counter is the adapter's own (else the filter's), in COUNTER_REASONS order
#: (which diagnostics show).
_COUNTER_OWN = {n: n in sk.ADAPTER_COUNTERS for n in COUNTER_REASONS}

#: Counters that mean data was lost or rejected: diagnostics warn whenever one grows.
REJECTIONS = (
    "imu_duplicate", "imu_out_of_order", "imu_bad_stamp", "gyr_invalid", "acc_invalid",
    "mag_invalid", "mag_too_old", "mag_ahead", "mag_overflow", "update_failed",
    "output_nonfinite", "acc_too_old", "acc_ahead", "acc_overflow",
)
#: Messages after which :meth:`StreamAdapter.input_problems` judges the input.
INPUT_CHECK_MESSAGES = 50
#: Rejections that are normal in moderation (motion, magnetic disturbances): diagnostics warn
#: when they hit most samples of a period. Counter → the counter of the samples it refers to.
GATED = {"acc_implausible": "imu_received",
         **{n: ("imu_received" if n.startswith("acc_") else "mag_received")
            for n in FILTER_REPORTED if "_rejected_" in n}}


@dataclass(slots=True)
class StreamOutput:
    """The estimate after one IMU sample, ready to publish (all finite)."""

    stamp: float  #: s, the IMU sample's stamp
    #: (4,) [w, x, y, z] sensor → world (``world_frame``, yaw offset applied), w ≥ 0
    quat: np.ndarray
    cov: np.ndarray  #: (3, 3) orientation covariance, rad², about the world axes
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
    bias_std: np.ndarray  #: (3,) its standard deviation, rad/s
    heading_initialized: bool  #: the magnetometer has fixed the heading
    #: published with the heading lost in a gap (yaw variance of an unknown angle)
    yaw_lost: bool = False
    slot: int = -1  #: the smoother's slot of this step (:meth:`StreamAdapter.record_into`)


@dataclass(slots=True)
class StreamOutputs:
    """The estimates of :meth:`StreamAdapter.process`, one row per published IMU message: the
    fields of :class:`StreamOutput` stacked, with NaN rows where that has None."""

    index: np.ndarray  #: (M,) int, the IMU message (row of the input arrays) of each output
    stamp: np.ndarray  #: (M,) s
    quat: np.ndarray  #: (M, 4)
    cov: np.ndarray  #: (M, 3, 3)
    angular_velocity: np.ndarray  #: (M, 3)
    angular_velocity_cov: np.ndarray  #: (M, 3, 3)
    angular_velocity_cov_add: np.ndarray  #: (M, 3, 3)
    linear_acceleration: np.ndarray  #: (M, 3)
    omega: np.ndarray  #: (M, 3)
    bias: np.ndarray  #: (M, 3)
    bias_std: np.ndarray  #: (M, 3)
    heading_initialized: np.ndarray  #: (M,) bool
    #: (M,) bool, published with the heading lost in a gap (yaw variance raised to
    #: :data:`~mkf_ros.core.state.YAW_VAR_UNKNOWN` until the magnetometer fixes it)
    yaw_lost: np.ndarray
    #: (M,) int, the smoother's slot of each output's filter step (:meth:`record_into`;
    #: -1 when not recording)
    slot: np.ndarray


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
        base.replace(**filt)  # the rules between filter parameters
    return out


def carries_orientation(quat_xyzw: Any, cov0: Any) -> bool:
    """True if any of these ``sensor_msgs/Imu`` messages (orientation x, y, z, w and
    ``orientation_covariance[0]``, one row each) carries an orientation: a unit quaternion
    other than the identity, its covariance not marked "not reported" (−1, REP-145). Raw IMU
    data (``imu/data_raw``) has none; an estimator's output (``imu/data``) has one."""
    q = np.asarray(quat_xyzw, dtype=float).reshape(-1, 4)
    c = np.asarray(cov0, dtype=float).reshape(-1)
    unit = np.abs(np.linalg.norm(q, axis=1) - 1.0) < 1e-3
    identity = np.abs(np.abs(q[:, 3]) - 1.0) < 1e-9
    return bool(np.any(~rep145.not_reported(c) & unit & ~identity))


def orientation_note(topic: str) -> str:
    """What :func:`carries_orientation` means for the user (one line)."""
    return (f"{topic} already carries an orientation (orientation_covariance[0] is not -1): "
            "an estimator's output (imu/data) rather than raw data (imu/data_raw)? Its "
            "orientation is ignored; the estimate comes from its gyro and accelerometer")


_PRESENT = struct.Struct("<q").unpack_from  # the output record's flags (its first field)
assert sk.OUTPUT.fields is not None and sk.OUTPUT.fields["present"][1] == 0
_NAN3 = np.full(3, math.nan)


#: The fields of an :data:`~mkf_ros.stream.kernel.OUTPUT` record viewed as float64 values.
_Q, _COV, _W, _WCOV, _WADD, _LIN, _OMEGA, _BIAS, _BSTD = (
    sk.float_slice(sk.OUTPUT, name)
    for name in ("q", "cov", "w", "wcov", "wadd", "lin", "omega", "bias", "bstd"))


def _vec(v: Any, kind: str) -> Any:
    """One sensor vector as 3 numbers; None (not reported) as all NaN, which the rules treat
    alike (missing). ValueError for another number of components."""
    if v is None:
        return _NAN3
    if type(v) is np.ndarray and v.shape == (3,):  # the common case, without a copy
        return v
    a = np.asarray(v, dtype=float)
    if a.size != 3:
        raise ValueError(f"{kind} sample must have 3 components, got shape {np.shape(v)}")
    return a.reshape(3)


def _rows(v: Any, n: int, kind: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != (n, 3):
        raise ValueError(f"{kind} must have shape ({n}, 3), got {a.shape}")
    return a


def _ts_value(field: str, doc: str) -> property:
    """A read-only float property of :class:`StreamAdapter` reading ``field`` of its compiled
    rules' time state (:data:`mkf_ros.stream.kernel.STREAM`)."""
    return property(lambda self: float(record(self._ts)[field]), doc=doc)


class StreamAdapter:
    """An :class:`AttitudeFilter` fed by timestamped IMU and magnetometer samples.

    >>> s = StreamAdapter(algorithm="mekf")
    >>> out = s.on_imu(0.00, [0, 0, 0], [0, 0, 9.81])   # initialises, returns the estimate
    >>> out = s.on_imu(0.01, [0, 0, 0], [0, 0, 9.81])
    >>> s.on_mag(0.012, [20e-6, 0, -40e-6])              # held until the IMU reaches 0.012 s
    >>> res = s.process(t, gyr, acc, t_mag, mag)         # a whole recording: arrays of outputs

    Parameters are every entry of :data:`mkf_ros.core.params.PARAMS` (filter and node scope).
    The state is a few records that the compiled rules (:mod:`mkf_ros.stream.kernel`) update
    in place: the filter's, the time state ``_ts`` (with the held samples), the adapter's
    counters ``_acnt`` and the node parameters ``_npar``.
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
        self.last_reset_reason = ""
        self._acnt = new_records(sk.ADAPTER_COUNTER_RECORD)
        self._ts = new_records(sk.STREAM)
        for name in ("acc_norm", "mag_norm", "mag_offset", "last_imu", "last_mag", "last_acc"):
            record(self._ts)[name] = math.nan
        self._reset_dt_stats()
        # the one-event sequences of on_imu / on_mag / on_accel
        # (the per-message path reads and writes them through field views: a numpy record's
        # attribute access costs microseconds)
        self._ev = {kind: new_records(sk.EVENT) for kind in (sk.EV_IMU, sk.EV_MAG, sk.EV_ACC)}
        for kind, ev in self._ev.items():
            ev["kind"] = kind
        self._out = new_records(sk.OUTPUT)
        # the smoother's recording (record_into): slots, [slots filled, out of room]
        self._rec = new_records(smoother.RECORD, 0)
        self._rn = np.zeros(4, dtype=np.int64)
        self._recording = False
        self._on_full: Callable[[int], tuple[np.ndarray, int, int]] | None = None
        #: while recording: the number of the first slot after each reset (the filter's chain
        #: starts anew there: a pass over the recording reversed starts anew too)
        self.reset_slots: list[int] = []
        self._bind_views()
        self._derive()

    def _bind_views(self) -> None:
        """The field views of the event and output records that the per-message path reads
        and writes (a numpy record's attribute access costs microseconds). Views, so never
        copied or pickled: :meth:`__getstate__` leaves them out and a copy binds its own."""
        self._ev_views = {kind: (ev["stamp"], ev["v"][0], ev["a"][0])
                          for kind, ev in self._ev.items()}
        self._out_present = self._out["present"]
        self._out_slot = self._out["slot"]
        self._ev_imu = self._ev_views[sk.EV_IMU]
        self._ev_imu_seq = self._ev[sk.EV_IMU]
        self._out_flat = self._out.view(np.float64)
        self._out_bytes = self._out.view(np.uint8).data.toreadonly()
        self._ev_imu_bytes = self._ev_imu_seq.view(np.uint8).data
        self._bound: dict[int, _BoundCall] = {}  # _run_event's compiled calls, by event kind

    _VIEWS = ("_ev_views", "_out_present", "_out_slot", "_ev_imu", "_ev_imu_seq", "_out_flat",
              "_out_bytes", "_ev_imu_bytes", "_bound")

    def __getstate__(self) -> dict[str, Any]:
        """The state of :func:`copy.deepcopy` and :mod:`pickle`: every record, without the
        views into them (a copy rebinds its own: copied apart from their records, the views
        would feed a twin's input to nothing). TypeError while recording for the smoother
        (:meth:`record_into`): its slots and ``on_full`` belong to the pass in progress."""
        if self._recording:
            raise TypeError("a StreamAdapter recording for the smoother cannot be copied or "
                            "pickled: call record_into(None) first")
        return {k: v for k, v in self.__dict__.items() if k not in self._VIEWS}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._bind_views()

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
            record(self._ts).n_mag = 0
        if not self.split:
            record(self._ts).n_acc = 0
        self._derive()

    @property
    def split(self) -> bool:
        """Split input (``input_mode`` split): separate accelerometer and gyro streams."""
        return self._node["input_mode"] == "split"

    @property
    def params(self) -> dict[str, Any]:
        """Current value of every parameter (filter and node scope)."""
        return {**self.filter.params, **self._node}

    def _derive(self) -> None:
        """The node parameters as the kernels read them (``npar``, :data:`~.kernel.NODE`)."""
        n, f = self._node, self.filter.params
        q_w = FROM_ENU[f.world_frame]
        psi = float(n["yaw_offset"] - n["declination"])
        qz = np.array([math.cos(psi / 2), 0.0, 0.0, math.sin(psi / 2)])
        q_off = qmul_np(qmul_np(q_w, qz), qconj_np(q_w))  # about world up, in W axes
        rec = new_records(sk.NODE)
        p = record(rec)
        for name in ("constant_dt", "time_jump_threshold", "acc_magnitude_tolerance",
                     "mag_max_delay", "acc_max_delay", "orientation_stddev",
                     "remove_gravity_vector"):
            p[name] = n[name]
        p.has_offset = abs(psi) > 0.0
        p.q_offset[:] = q_off
        p.R_offset[:] = rotmat_np(q_off)
        p.up_world[:] = rotmat_np(q_w) @ np.array([0.0, 0.0, 1.0])  # world up
        p.av_source = sk.AV_SOURCES.index(n["angular_velocity_source"])
        p.split = n["input_mode"] == "split"
        self._npar = rec
        self.filter.set_split_input(self.split)

    # --- state -----------------------------------------------------------------------------
    def reset(self, reason: str = "requested") -> None:
        """Forget the estimate; the next IMU sample re-initialises. Counters are kept."""
        self.filter.reset()
        if self._recording:
            self.reset_slots.append(int(self._rn[3] + self._rn[0]))
        for name in sk.RESET_FIELDS:
            record(self._ts)[name] = 0
        record(self._acnt).resets += 1
        self.last_reset_reason = reason

    @property
    def initialized(self) -> bool:
        return self.filter.initialized

    @property
    def time(self) -> float | None:
        """Stamp (s) of the filter's state, None before the first IMU sample."""
        t = record(self._ts)
        return float(t.t) if t.valid else None

    acc_norm = _ts_value("acc_norm", "m/s², magnitude of the latest finite accelerometer "
                                     "sample.")
    mag_norm = _ts_value("mag_norm", "T, magnitude of the latest finite magnetometer sample.")
    mag_offset = _ts_value("mag_offset", "s, latest magnetometer stamp − filter time at its "
                                         "arrival.")
    last_imu_stamp = _ts_value("last_imu", "Stamp of the latest IMU (gyro) sample.")
    last_mag_stamp = _ts_value("last_mag", "Stamp of the latest magnetometer sample.")
    last_acc_stamp = _ts_value("last_acc", "Stamp of the latest accelerometer sample of split "
                                           "input (NaN: none yet).")

    def _reset_dt_stats(self) -> None:
        t = record(self._ts)
        t.dt_n, t.dt_min, t.dt_sum, t.dt_max = 0, math.inf, 0.0, 0.0

    def pop_dt_stats(self) -> tuple[int, float, float, float]:
        """``(n, min, mean, max)`` of the IMU time steps (s) since the previous call."""
        t = record(self._ts)
        n, lo, s, hi = int(t.dt_n), float(t.dt_min), float(t.dt_sum), float(t.dt_max)
        self._reset_dt_stats()
        return (n, lo, s / n, hi) if n else (0, math.nan, math.nan, math.nan)

    @property
    def counters(self) -> dict[str, int]:
        """Every counter of :data:`COUNTER_REASONS` (the adapter's and the filter's)."""
        a, f = record(self._acnt), self.filter.counter_dict()
        return {n: int(a[n]) if own else f[n] for n, own in _COUNTER_OWN.items()}

    def all_counters(self) -> dict[str, int]:
        """Adapter counters plus the filter's own sample/gap/update counters."""
        return self.counters

    def input_problems(self, imu_topic: str = "", accel_topic: str = "") -> dict[str, str]:
        """Why the input cannot give an orientation, one line each by kind (``"gyro"``: no
        angular velocity but exactly zero, or none at all; ``"accel"``: no usable
        accelerometer sample), judged once :data:`INPUT_CHECK_MESSAGES` messages have
        arrived; empty: nothing wrong. The topic names, if given, go into the text
        (``imu_topic``: the IMU, or with split input the gyro topic)."""
        a, ts = record(self._acnt), record(self._ts)
        out = {}
        n_imu = int(a.imu_received)
        imu = f" on {imu_topic}" if imu_topic else ""
        if n_imu >= INPUT_CHECK_MESSAGES and not ts.gyr_seen:
            hint = ("is it the accelerometer topic? (split input: check the gyro topic)"
                    if self.split else "is this an accelerometer-only topic? (separate "
                    "accelerometer and gyro topics: input_mode split)")
            out["gyro"] = (f"angular velocity zero or not reported in all {n_imu} IMU messages"
                           f"{imu}: {hint}")
        n_acc = int(a.acc_received) if self.split else n_imu
        acc = f" on {accel_topic or imu_topic}" if (accel_topic or imu_topic) else ""
        if n_acc >= INPUT_CHECK_MESSAGES and not ts.acc_seen:
            hint = ("is it the gyro topic? (split input: check the accelerometer topic)"
                    if self.split else "is this a gyro-only topic? (separate accelerometer "
                    "and gyro topics: input_mode split)")
            what = "accelerometer samples" if self.split else "IMU messages"
            out["accel"] = (f"no usable accelerometer reading (zero, invalid, not reported or "
                            f"far from gravity) in all {n_acc} {what}{acc}: {hint}")
        return out

    # --- the smoother's recording ------------------------------------------------------------
    def record_into(self, rec: np.ndarray | None,
                    on_full: Callable[[int], tuple[np.ndarray, int, int]] | None = None,
                    base: int = 0) -> None:
        """Record every filter step for the smoother (docs/math.md §11.1; ``mkf process
        --smooth``) into the slots of ``rec`` (:data:`~mkf_ros.core.smoother.RECORD`), one
        per step (:func:`~mkf_ros.core.smoother.recorded_step`), the first numbered ``base``;
        each output of :meth:`process` names its step's slot by that number
        (:attr:`StreamOutputs.slot`). When the slots but
        :data:`~mkf_ros.stream.kernel.MAX_STEPS_PER_EVENT` are filled, after that event,
        ``on_full(filled)`` makes room and returns ``(rec, filled, base)`` to go on with.
        None: stop recording. ValueError for a baseline algorithm (no smoother)."""
        if rec is None:
            self._recording = False
            self._rec, self._rn[:] = new_records(smoother.RECORD, 0), 0
            self._on_full = None
            record(self.filter.kernel_arrays().cfg).record_posterior = False
            return
        if self.filter.params.algorithm not in ("mekf", "mukf"):
            raise ValueError("the smoother needs algorithm mekf or mukf, not "
                             f"{self.filter.params.algorithm!r}")
        if len(rec) <= sk.MAX_STEPS_PER_EVENT:
            raise ValueError(f"a recording needs more than {sk.MAX_STEPS_PER_EVENT} slots")
        self._set_recording(rec, 0, base)
        self._on_full = on_full
        self._recording = True
        self.reset_slots = []

    def _set_recording(self, rec: np.ndarray, filled: int, base: int) -> None:
        self._rec = rec
        self._rn[:] = (filled, 0, len(rec) - sk.MAX_STEPS_PER_EVENT, base)

    def published_orientation(self, quat: np.ndarray, cov: np.ndarray,
                              yaw_lost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Orientations ``(M, 4)`` ``[w, x, y, z]`` and covariances ``(M, 3, 3)`` about the
        world axes (the filter's or the smoother's, docs/math.md §9.6) as published, by the
        node's rules of :func:`~mkf_ros.stream.kernel.output`: the yaw offset / declination
        turn (``w ≥ 0``), the yaw variance of an unknown heading where ``yaw_lost``, a fixed
        ``orientation_stddev``. New arrays."""
        q = np.array(quat, dtype=float)
        c = np.array(cov, dtype=float)
        sk.published_batch(self._npar, q, c, np.ascontiguousarray(yaw_lost, dtype=np.bool_))
        return q, c

    @property
    def recorded(self) -> int:
        """Slots of the recording filled so far (:meth:`record_into`)."""
        return int(self._rn[0])

    # --- input -----------------------------------------------------------------------------
    def on_imu(self, stamp: float, gyr: Any, acc: Any = None) -> StreamOutput | None:
        """Process one IMU sample (rad/s, m/s²; None or all-NaN = not reported); with split
        input, one gyro sample (``acc`` is ignored).

        Returns the estimate at ``stamp``, or None when nothing is to be published (sample
        dropped, filter not initialised yet).
        """
        return self.last_output() if self.step_imu(stamp, gyr, acc) else None

    def step_imu(self, stamp: float, gyr: Any, acc: Any = None) -> int:
        """:meth:`on_imu` without building its :class:`StreamOutput` (the node's per-message
        path): the output's flags (``OF_*`` of :mod:`mkf_ros.stream.kernel`; 0 when nothing
        is to be published). The estimate is :attr:`output_values` until the next call;
        :meth:`last_output` makes it a :class:`StreamOutput`."""
        stamp_v, v, a = self._ev_imu
        v[:] = _vec(gyr, "gyr")
        a[:] = _vec(acc, "acc")
        stamp_v[0] = float(stamp)
        return self.run_imu_event()

    @property
    def imu_event_bytes(self) -> memoryview:
        """The bytes of :meth:`step_imu`'s event record (:data:`~mkf_ros.stream.kernel.EVENT`:
        ``stamp`` s, ``v`` the gyro, ``a`` the accelerometer, float64, all NaN = not
        reported), writable: a front end that has the readings as bytes writes them here and
        calls :meth:`run_imu_event` (the node's per-message path, without numpy)."""
        return self._ev_imu_bytes

    def run_imu_event(self) -> int:
        """:meth:`step_imu` of the sample already in :attr:`imu_event_bytes` (the same rules:
        the record is what :meth:`step_imu` writes)."""
        self._run_event(sk.EV_IMU)
        return _PRESENT(self._out_bytes)[0]  # the flags, without a numpy scalar

    @property
    def output_bytes(self) -> memoryview:
        """The latest IMU sample's output record (:data:`~mkf_ros.stream.kernel.OUTPUT`) as
        read-only bytes, updated in place like :attr:`output_values`."""
        return self._out_bytes

    @property
    def output_values(self) -> np.ndarray:
        """The latest IMU sample's output record viewed as float64 values (fields at
        :func:`mkf_ros.stream.kernel.float_slice`), updated in place by :meth:`step_imu`:
        read it before the next sample."""
        return self._out_flat

    def last_output(self) -> StreamOutput:
        """The estimate of the latest :meth:`step_imu` that returned non-zero flags, as
        :meth:`on_imu` returns it (new arrays)."""
        stamp = float(self._ev_imu[0][0])
        o = self._out_flat.copy()  # the fields below are views of this copy
        flags = int(self._out_present[0])
        return StreamOutput(
            stamp=stamp, quat=o[_Q], cov=o[_COV].reshape(3, 3),
            angular_velocity=o[_W] if flags & sk.OF_W else None,
            angular_velocity_cov=o[_WCOV].reshape(3, 3) if flags & sk.OF_WCOV else None,
            angular_velocity_cov_add=np.diag(o[_WADD]) if flags & sk.OF_WADD else None,
            linear_acceleration=o[_LIN] if flags & sk.OF_LIN else None,
            omega=o[_OMEGA], bias=o[_BIAS], bias_std=o[_BSTD],
            heading_initialized=bool(flags & sk.OF_HEADING),
            yaw_lost=bool(flags & sk.OF_YAW_LOST), slot=int(self._out_slot[0]))

    def on_gyro(self, stamp: float, gyr: Any) -> StreamOutput | None:
        """Split input: one gyro sample (rad/s); the estimate at ``stamp`` as :meth:`on_imu`."""
        return self.on_imu(stamp, gyr, None)

    def on_accel(self, stamp: float, acc: Any) -> None:
        """Split input: one accelerometer sample (m/s², +g up at rest; all NaN = none), fused
        at its stamp (see the module docstring). ValueError unless ``input_mode`` is split."""
        if not self.split:
            raise ValueError("on_accel needs input_mode split (with input_mode imu the "
                             "accelerometer comes with the gyro in on_imu)")
        stamp_v, v, _ = self._ev_views[sk.EV_ACC]
        v[:] = _vec(acc, "acc")
        stamp_v[0] = stamp
        self._run_event(sk.EV_ACC)

    def on_mag(self, stamp: float, mag: Any) -> None:
        """Process one magnetometer sample (any unit, tesla by REP-145; all NaN = none)."""
        stamp_v, v, _ = self._ev_views[sk.EV_MAG]
        v[:] = _vec(mag, "mag")
        stamp_v[0] = stamp
        self._run_event(sk.EV_MAG)

    def process(self, imu_stamp: Any, gyr: Any, acc: Any, mag_stamp: Any = None,
                mag: Any = None, *, imu_arrival: Any = None, mag_arrival: Any = None,
                acc_stamp: Any = None, acc_arrival: Any = None,
                progress: Callable[[int], object] | None = None,
                chunk: int = 4096) -> StreamOutputs:
        """A whole recording, with the results of :meth:`on_imu` / :meth:`on_mag` (and
        :meth:`on_accel`) called message by message in arrival order (bit for bit), in
        compiled code.

        ``imu_stamp`` (N,) s, ``gyr``/``acc`` (N, 3) (a NaN row: not reported);
        ``mag_stamp`` (K,) s and ``mag`` (K, 3), or None. Split input (``input_mode``
        split): ``imu_stamp`` and ``gyr`` are the gyro stream, and ``acc`` (J, 3) the
        accelerometer samples at their own stamps ``acc_stamp`` (J,), required. The streams
        are merged by arrival time, ``imu_arrival`` (N,), ``mag_arrival`` (K,) and
        ``acc_arrival`` (J,) in any one unit (e.g. a bag's log times; default: the stamps),
        at equal times the magnetometer first, then the accelerometer, each stream in its own
        order among equal times. ``progress(n)`` is called after every ``chunk`` events. The
        adapter's state carries over from and to per-message calls.
        """
        ts = np.asarray(imu_stamp, dtype=float).reshape(-1)
        n = len(ts)
        if self.split != (acc_stamp is not None):
            raise ValueError("split input (input_mode split) takes the accelerometer samples "
                             "at their own stamps: pass acc_stamp" if self.split else
                             "acc_stamp is for split input (input_mode split)")
        k = 0 if mag_stamp is None else len(mag_stamp)
        j = 0 if acc_stamp is None else len(acc_stamp)
        ev = new_records(sk.EVENT, n + k + j)
        ev["stamp"][:n] = ts
        ev["v"][:n] = _rows(gyr, n, "gyr")
        ev["a"][:] = math.nan
        if acc_stamp is None:
            ev["a"][:n] = _rows(acc, n, "acc")
        ev["row"][:n] = np.arange(n)
        ev["kind"][n:n + k] = sk.EV_MAG
        ev["kind"][n + k:] = sk.EV_ACC
        if k:
            ev["stamp"][n:n + k] = mag_stamp
            ev["v"][n:n + k] = _rows(mag, k, "mag")
        if j:
            ev["stamp"][n + k:] = acc_stamp
            ev["v"][n + k:] = _rows(acc, j, "acc")
        if k or j:
            parts = [ts if imu_arrival is None else imu_arrival]  # one dtype: ns stay exact
            if k:
                parts.append(mag_stamp if mag_arrival is None else mag_arrival)
            if j:
                parts.append(acc_stamp if acc_arrival is None else acc_arrival)
            when = np.concatenate(parts)
            # at equal times: magnetometer, accelerometer, IMU; stable: each stream's order
            rank = np.array([2, 0, 1])[ev["kind"]]
            ev = ev[np.lexsort((rank, when))]
        elif imu_arrival is not None:
            ev = ev[np.argsort(imu_arrival, kind="stable")]
        out = new_records(sk.OUTPUT, n)
        total = n + k + j
        for k0 in range(0, total, chunk):
            k1 = min(k0 + chunk, total)
            self._run(ev, out, k0, k1)
            if progress is not None:
                progress(k1 - k0)
        return _outputs(out, ts)

    def _args(self, ev: np.ndarray, out: np.ndarray, k0: int, k1: int) -> tuple:
        """The arguments of :func:`~mkf_ros.stream.kernel.run_events` for these events."""
        arrays = self.filter.kernel_arrays()
        return (kernel_table(arrays.cfg), tuple(arrays), self._npar, self._ts,
                self._acnt, self._rec, self._rn, ev, out, k0, k1)

    def _run(self, ev: np.ndarray, out: np.ndarray, k0: int, k1: int) -> None:
        """Events ``k0 … k1-1`` through the compiled rules. Only resets come back here: the
        filter gets new state, then the loop resumes."""
        if self._recording:  # (set_params builds a new configuration)
            record(self.filter.kernel_arrays().cfg).record_posterior = True
        while True:
            k0 = self._resume(*sk.run_events(*self._args(ev, out, k0, k1)))
            if k0 < 0:
                return

    def _resume(self, k: int, why: int) -> int:
        """What :func:`~mkf_ros.stream.kernel.run_events` returned, ``(k, why)``: the event
        to resume from, once the filter is reset or the recording has room; -1 when done."""
        if self._recording and self._rn[1]:
            raise RuntimeError("smoother recording out of room (record_into: leave a slot "
                               "per event)")
        if why == sk.R_DONE:
            return -1
        if why == sk.R_FULL:
            if self._on_full is None:
                raise RuntimeError("smoother recording full (record_into: no on_full)")
            self._set_recording(*self._on_full(int(self._rn[0])))
            return k
        if why == sk.R_TIME_JUMP:  # the same sample again, re-initialising from it
            self.reset("time jump")
            record(self._ts).resume = True
            return k
        # R_NONFINITE: nothing published for that sample
        if self._recording:  # its step leaves the smoother's chain
            smoother.cut(self._rec, int(self._rn[0]) - 1)
        self.reset("non-finite estimate")
        return k + 1

    def _run_event(self, kind: int) -> None:
        """:meth:`_run` of the one-event sequence of ``kind`` (``EV_*``; on_imu, on_mag,
        on_accel), the per-message path: the compiled loop called through its entry point
        for exactly these arguments, bound once (numba's dispatcher otherwise works out the
        types of its eleven arguments at every call) and bound again whenever the filter's
        or the adapter's records are replaced (reset, set_params, recording)."""
        ev = self._ev[kind]
        b = self._bound.get(kind)
        if (b is None or b.arrays is not self.filter.kernel_arrays() or b.npar is not self._npar
                or b.rec is not self._rec or self._recording):
            self._run(ev, self._out, 0, 1)
            self._bind(kind)
            return
        k0 = self._resume(*b.call(*b.args))
        if k0 >= 0:
            self._run(ev, self._out, k0, 1)

    def _bind(self, kind: int) -> None:
        """The compiled entry point of :func:`~mkf_ros.stream.kernel.run_events` for the
        one-event sequence of ``kind`` and the current records (:meth:`_run_event`): the
        version numba compiled for exactly these argument types, looked up after a call
        through the dispatcher; none while recording or without JIT."""
        self._bound.pop(kind, None)
        if self._recording or _jit.JIT_DISABLED:
            return
        args = self._args(self._ev[kind], self._out, 0, 1)
        disp: Any = sk.run_events  # a numba dispatcher (overloads, typeof_pyval)
        cres = disp.overloads.get(tuple(disp.typeof_pyval(a) for a in args))
        if cres is not None:
            self._bound[kind] = _BoundCall(self.filter.kernel_arrays(), self._npar, self._rec,
                                           cres.entry_point, args)


class _BoundCall(NamedTuple):
    """:meth:`StreamAdapter._run_event`'s compiled call for one event kind, with the records it
    was bound to (it is bound again when any of them is replaced)."""

    arrays: Any  #: the filter's kernel arrays
    npar: np.ndarray
    rec: np.ndarray
    call: Any  #: the compiled entry point of run_events for these argument types
    args: tuple


def _outputs(out: np.ndarray, stamps: np.ndarray) -> StreamOutputs:
    """The published rows of a table of :data:`~mkf_ros.stream.kernel.OUTPUT` records (one
    per IMU message) as arrays (views of the table, absent optional fields NaN)."""
    flags = out["present"]
    if flags.all():
        idx = np.arange(len(out))
    else:
        idx = np.flatnonzero(flags)
        out, flags = out[idx], flags[idx]
    m = len(idx)
    wadd = np.zeros((m, 3, 3))
    wadd[:, (0, 1, 2), (0, 1, 2)] = out["wadd"]
    wadd[(flags & sk.OF_WADD) == 0] = math.nan
    return StreamOutputs(
        index=idx, stamp=stamps[idx], quat=out["q"], cov=out["cov"],
        angular_velocity=out["w"], angular_velocity_cov=out["wcov"],
        angular_velocity_cov_add=wadd, linear_acceleration=out["lin"],
        omega=out["omega"], bias=out["bias"], bias_std=out["bstd"],
        heading_initialized=(flags & sk.OF_HEADING) > 0,
        yaw_lost=(flags & sk.OF_YAW_LOST) > 0, slot=out["slot"])
