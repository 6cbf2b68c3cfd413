"""The attitude filter's public face: :class:`AttitudeFilter` (the stateful Python filter used by
the stream adapter and the ROS node), :func:`run_batch` (the loop behind
:func:`mkf_ros.estimate`) and the output in the chosen world frame with the orientation
covariance about world axes.

Compiled front ends (:mod:`mkf_ros.stream.kernel`) drive the filter through the kernels listed
in ``__all__`` below and the records of :meth:`AttitudeFilter.kernel_arrays`.
"""

from __future__ import annotations

import contextlib
from collections import namedtuple
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from numba import types as nt

from mkf_ros.core._jit import JIT_DISABLED, function_at, jit, tuple_type, unit
from mkf_ros.core.baseline_glue import (
    Canonical,
    baseline_estimate,
    export,
    mkf_canonical,
    restore,
)
from mkf_ros.core.charts import from_chart_t, t_matrix_t
from mkf_ros.core.linalg import cap_eigenvalues33_t, congruence33_t
from mkf_ros.core.params import FilterParams
from mkf_ros.core.quaternion import (
    qmul_t,
    qnormalize_t,
    rotmat_t,
    t3,
    t4,
    t33,
)
from mkf_ros.core.sensor import (
    UNITS_T,
    Units,
    acc_recovery,
    baseline_step,
    mag_recovery,
    mukf_update,
    no_baseline,
    no_mukf,
    start,
    step,
)
from mkf_ros.core.state import (
    ACC,
    ALGO_EULER_KF,
    ALGO_MADGWICK,
    ALGO_MEKF,
    ALGO_MUKF,
    ATTITUDE_VAR_UNKNOWN,
    CONFIG,
    CONFIG_T,
    COUNTER_NAMES,
    COUNTERS,
    F4,
    F33,
    GYR,
    MAG,
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    STATE,
    STATE_T,
    WORK,
    YAW_VAR_UNKNOWN,
    build_config,
    classify_reading,
    count_reading,
    heading_fixed,
    new_records,
    recentre,
    record,
)

#: The stateful filter and its batch loop, the plausibility contract of a reading and the
#: kernel interface of compiled front ends.
__all__ = [
    "ACC",
    "CONFIG",
    "COUNTERS",
    "COUNTER_NAMES",
    "GYR",
    "MAG",
    "MAX_ACC_G",
    "MAX_GYRO_RATE",
    "MAX_MAG",
    "STATE",
    "WORK",
    "YAW_VAR_UNKNOWN",
    "AttitudeFilter",
    "BatchOutputs",
    "KernelArrays",
    "Kernels",
    "bias",
    "bias_variance",
    "classify_reading",
    "count_reading",
    "gap_count",
    "gravity",
    "heading_fixed",
    "is_initialized",
    "kernel_table",
    "kernels_at",
    "max_dt",
    "new_batch_outputs",
    "new_records",
    "output",
    "rate",
    "rate_covariance",
    "record",
    "run_batch",
    "run_step",
    "sensor_step",
    "uses_mag",
    "world_output",
]


@unit(nt.Tuple((F4, F33))(CONFIG_T, STATE_T), cost=1.3)
def output(c: np.record, s: np.record) -> tuple[tuple, tuple]:
    """Orientation in the world frame (``q0 ≥ 0``) and its 3×3 covariance about world axes
    (rows), ``Σ_W = R(q_W) Σ_body R(q_W)ᵀ`` (the error is body-side, ``q = q̂ * δ(e)``), plus
    the accelerometer's misalignment. Reads the state element by element: no allocation."""
    if c.algorithm >= ALGO_EULER_KF:
        qa, Pa = baseline_estimate(c, s)
        q, Pb = t4(qa), t33(Pa)
    else:  # q̂ = q̄_c * φ⁻¹(ē), Σ_body = T P_ee Tᵀ (identity for ē = 0)
        q = t4(s.q_c)
        P = s.P
        Pb = ((P[0, 0], P[0, 1], P[0, 2]), (P[1, 0], P[1, 1], P[1, 2]),
              (P[2, 0], P[2, 1], P[2, 2]))
        e = (s.e[0], s.e[1], s.e[2])
        if not (e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0):
            d = from_chart_t(c.chart, e)
            q = qnormalize_t(qmul_t(q, d))
            Pb = congruence33_t(t_matrix_t(c.chart, d), Pb)
    q = qmul_t(t4(c.q_from_enu), q)
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[0] < 0.0:
        n = -n
    q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
    C = congruence33_t(rotmat_t(q), Pb)
    f2 = c.acc_alignment_error ** 2 if c.algorithm != ALGO_MADGWICK else 0.0
    # the accelerometer's own misalignment: a constant no filter averages out (published only,
    # by every filter but Madgwick, whose published value is a parameter; every world frame
    # here has its z vertical, so x and y are the tilt axes). Symmetric by construction: the
    # mean of the two triangles, which the congruence's rounding makes differ by ~1e-16 of
    # the largest element (bit-identical where they agree)
    c01, c02, c12 = 0.5 * (C[0][1] + C[1][0]), 0.5 * (C[0][2] + C[2][0]), 0.5 * (C[1][2] + C[2][1])
    C = ((C[0][0] + f2, c01, c02), (c01, C[1][1] + f2, c12), (c02, c12, C[2][2]))
    # no variance beyond an angle's uniform one about any axis (the MKFs' state is capped
    # alike, sensor._cap_attitude_variance; a baseline's Euler covariance is not): the upper
    # triangle mirrored
    C = cap_eigenvalues33_t(C, YAW_VAR_UNKNOWN)
    return q, ((C[0][0], C[0][1], C[0][2]), (C[0][1], C[1][1], C[1][2]),
               (C[0][2], C[1][2], C[2][2]))


#: The compiled kernels a front end hands to the compiled loops: :func:`step` and its
#: :data:`~mkf_ros.core.sensor.Units`, and :func:`output`.
Kernels = namedtuple("Kernels", ("step", "units", "output"))
KERNELS_T = tuple_type([step.type, UNITS_T, output.type], Kernels)
#: Every unit of :data:`Kernels`, in the order of :func:`kernel_table`'s addresses.
KERNEL_TABLE_ORDER = _TABLE = (step, start, acc_recovery, mag_recovery, mukf_update,
                               baseline_step, export, restore, output)
#: What the kernel table holds in the slots of the units an algorithm never calls
#: (:func:`kernel_table`): the MUKF's update (only the MUKF calls it), the baselines' update
#: and conversions (only the baselines call them).
_STANDINS = {mukf_update: no_mukf, baseline_step: no_baseline, export: mkf_canonical,
             restore: mkf_canonical}
#: Among those, the units each kind of algorithm calls (:func:`_kind`: MEKF, MUKF, baseline).
_OWN_UNITS: tuple[tuple, ...] = ((), (mukf_update,), (baseline_step, export, restore))
_tables: dict[int, Any] = {}


def _kind(algorithm: int) -> int:
    """0 for the MEKF, 1 for the MUKF, 2 for a baseline (an index of :data:`_OWN_UNITS`)."""
    return 0 if algorithm == ALGO_MEKF else 1 if algorithm == ALGO_MUKF else 2


def table_units(algorithm: int) -> list[Any]:
    """The units of :data:`Kernels` in :func:`kernel_table` order for ``algorithm`` (an
    ``ALGO_*`` index): a stand-in (:data:`_STANDINS`) in the place of each unit it never
    calls. The install-time compile makes the units of the installed algorithms' tables
    (:func:`mkf_ros.kernels.compile_tasks`); the others are compiled on first use."""
    own = _OWN_UNITS[_kind(algorithm)]
    return [_STANDINS[u] if u in _STANDINS and u not in own else u for u in _TABLE]


def kernel_table(cfg: np.ndarray | None = None) -> Any:
    """The compiled units of :data:`Kernels` (compiled, or loaded from the kernel cache, once
    per process) as the array of their addresses that the compiled loops take
    (:func:`kernels_at` makes them :data:`Kernels` again); the :data:`Kernels` of Python
    functions with ``NUMBA_DISABLE_JIT=1``. For the configuration ``cfg`` (a :data:`CONFIG`
    record array; None: the MEKF's): :func:`table_units` of its algorithm, so that a unit is
    compiled only when an algorithm that calls it runs."""
    algo = ALGO_MEKF if cfg is None else int(cfg[0]["algorithm"])
    kind = 0 if JIT_DISABLED else _kind(algo)
    table = _tables.get(kind)
    if table is None:
        if JIT_DISABLED:
            table = Kernels(*_assemble([u.compiled for u in _TABLE]))
        else:
            table = np.array([u.compiled.address for u in table_units(algo)], dtype=np.int64)
        _tables[kind] = table
    return table


def _assemble(u: list) -> tuple:
    """``(step, units, output)`` of :data:`Kernels` from the units in :data:`_TABLE` order."""
    return u[0], Units(Canonical(u[6], u[7]), u[1], u[2], u[3], u[4], u[5]), u[8]


def _kernels_at(a: np.ndarray) -> Kernels:
    """The :data:`Kernels` at the addresses of :func:`kernel_table` (compiled code)."""
    return Kernels(function_at(a[0], _STEP_T),
                   Units(Canonical(function_at(a[6], _EXPORT_T), function_at(a[7], _RESTORE_T)),
                         function_at(a[1], _START_T), function_at(a[2], _ACC_RECOVERY_T),
                         function_at(a[3], _MAG_RECOVERY_T), function_at(a[4], _MUKF_T),
                         function_at(a[5], _BASELINE_T)),
                   function_at(a[8], _OUTPUT_T))


#: :func:`kernel_table`'s :data:`Kernels` in compiled code (the table itself without JIT).
kernels_at: Callable[[Any], Kernels] = (
    (lambda table: table) if JIT_DISABLED else jit(_kernels_at))


(_STEP_T, _START_T, _ACC_RECOVERY_T, _MAG_RECOVERY_T, _MUKF_T, _BASELINE_T, _EXPORT_T,
 _RESTORE_T, _OUTPUT_T) = (u.type for u in _TABLE)


@jit
def run_step(kern: Kernels, c: np.record, s: np.record, k: np.record, w: np.record, dt: float,
             gyr: tuple, acc: tuple, mag: tuple) -> None:
    """One sample through the compiled :func:`~mkf_ros.core.sensor.step`."""
    kern.step(c, s, k, w, kern.units, dt, gyr, acc, mag)


@jit
def sensor_step(table: np.ndarray, cfg: np.ndarray, st: np.ndarray, cnt: np.ndarray,
                work: np.ndarray, dt: float, gyr: np.ndarray, acc: np.ndarray,
                mag: np.ndarray) -> None:
    """One sample on the filter's record arrays (:class:`AttitudeFilter`), readings as arrays
    of 3; ``table``: :func:`kernel_table`."""
    run_step(kernels_at(table), cfg[0], st[0], cnt[0], work[0], dt, t3(gyr), t3(acc), t3(mag))


@jit
def world_output(table: np.ndarray, cfg: np.ndarray, st: np.ndarray, q_out: np.ndarray,
                 cov_out: np.ndarray) -> None:
    """:func:`output` of the filter's record arrays, into ``q_out`` (4) and ``cov_out``
    (3×3); ``table``: :func:`kernel_table`."""
    q, cov = kernels_at(table).output(cfg[0], st[0])
    for i in range(4):
        q_out[i] = q[i]
    for i in range(3):
        for j in range(3):
            cov_out[i, j] = cov[i][j]


# --- the kernel interface of compiled front ends (mkf_ros.stream.kernel) ---------------------
# A front end that runs its own compiled loop holds the filter's records
# (:meth:`AttitudeFilter.kernel_arrays`) and the compiled :data:`Kernels` (:func:`kernel_table`,
# :func:`kernels_at`), calls :func:`run_step` and ``Kernels.output``; what else it reads of the
# filter it reads through these.


@jit
def gravity(c: np.record) -> float:
    """The ``gravity`` parameter (m/s²)."""
    return c.gravity


@jit
def max_dt(c: np.record) -> float:
    """The ``max_dt`` parameter (s): a longer step is a gap (re-alignment)."""
    return c.max_dt


@jit
def uses_mag(c: np.record) -> bool:
    """Whether the magnetometer is fused (``use_mag``)."""
    return c.use_mag


@jit
def is_initialized(s: np.record) -> bool:
    """Whether the filter has an estimate (aligned, or the paper's start)."""
    return s.initialized


@jit
def gap_count(k: np.record) -> int:
    """How many steps longer than ``max_dt`` the filter has re-aligned after."""
    return k.gaps


@jit
def rate(s: np.record, i: int) -> float:
    """Component ``i`` of the estimated angular velocity ``ω̄`` (body, rad/s)."""
    return s.w[i]


@jit
def bias(s: np.record, i: int) -> float:
    """Component ``i`` of the estimated gyro bias ``b̄`` (rad/s; 0 without bias estimation)."""
    return s.b[i]


@jit
def bias_variance(c: np.record, s: np.record, i: int) -> float:
    """Variance of bias component ``i`` (rad²/s²; 0 without bias estimation)."""
    return s.P[6 + i, 6 + i] if c.nx == 9 else 0.0


@jit
def rate_covariance(s: np.record, i: int, j: int) -> float:
    """Element ``(i, j)`` of the covariance of ``ω̄`` (rad²/s²)."""
    return s.P[3 + i, 3 + j]


class BatchOutputs(NamedTuple):
    """Per-sample outputs of a batch: of :meth:`AttitudeFilter.run` (:func:`run_batch`) and of
    the smoother (:mod:`mkf_ros.core.smoother`): orientation ``[w, x, y, z]`` in the world
    frame, its covariance about world axes (``π² I`` before initialisation), rate, bias, bias
    variance (the kernels' quantity; :func:`mkf_ros.estimate` publishes its square root as
    ``bias_std``), and whether the row holds an estimate (the filter initialised)."""

    quat: np.ndarray
    cov: np.ndarray
    omega: np.ndarray
    bias: np.ndarray
    bias_var: np.ndarray
    initialized: np.ndarray


def new_batch_outputs(n: int) -> BatchOutputs:
    """Empty :class:`BatchOutputs` of ``n`` rows."""
    return BatchOutputs(np.empty((n, 4)), np.empty((n, 3, 3)), np.empty((n, 3)),
                        np.empty((n, 3)), np.empty((n, 3)), np.empty(n, dtype=np.bool_))


@jit
def _write_output(kern: Kernels, c: np.record, s: np.record, out: BatchOutputs, n: int) -> None:
    """Row ``n`` of the outputs (element by element: no array views)."""
    q, cov = kern.output(c, s)
    init = s.initialized
    out.initialized[n] = init
    for i in range(4):
        out.quat[n, i] = q[i]
    for i in range(3):
        for j in range(3):
            out.cov[n, i, j] = cov[i][j]
        if not init:
            out.cov[n, i, i] = ATTITUDE_VAR_UNKNOWN
        out.omega[n, i] = s.w[i]
        out.bias[n, i] = s.b[i]
        out.bias_var[n, i] = bias_variance(c, s, i)


@jit
def run_batch(table: np.ndarray, cfg: np.ndarray, st: np.ndarray, cnt: np.ndarray,
              work: np.ndarray, dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
              mag: np.ndarray, out: BatchOutputs) -> None:
    """:func:`step` over a whole recording, writing the outputs of every sample; ``table``:
    :func:`kernel_table`."""
    kern = kernels_at(table)
    c, s, k, w = cfg[0], st[0], cnt[0], work[0]
    for n in range(dts.shape[0]):
        run_step(kern, c, s, k, w, dts[n], (gyr[n, 0], gyr[n, 1], gyr[n, 2]),
                 (acc[n, 0], acc[n, 1], acc[n, 2]), (mag[n, 0], mag[n, 1], mag[n, 2]))
        _write_output(kern, c, s, out, n)


@jit
def to_canonical_entry(table: Any, cfg: np.ndarray, st: np.ndarray) -> None:
    """Any algorithm's state in the canonical form, in the filter's record arrays: the MKFs'
    :func:`~mkf_ros.core.state.recentre`, a baseline's
    :func:`~mkf_ros.core.baseline_glue.baseline_export` through its table (:func:`kernel_table`
    of ``cfg``)."""
    c, s = cfg[0], st[0]
    if c.algorithm < ALGO_EULER_KF:
        recentre(c, s)
    else:
        kernels_at(table).units.canonical.export(c, s)


@jit
def from_canonical_entry(table: Any, cfg: np.ndarray, st: np.ndarray) -> None:
    """:func:`~mkf_ros.core.baseline_glue.from_canonical` of the filter's record arrays, through
    the table of ``cfg`` (:func:`kernel_table`; a no-op for the MKFs)."""
    kernels_at(table).units.canonical.restore(cfg[0], st[0])


class KernelArrays(NamedTuple):
    """The record arrays of an :class:`AttitudeFilter` (one element each: the record), in the
    order of :func:`step`'s arguments."""

    cfg: np.ndarray
    st: np.ndarray
    counters: np.ndarray
    work: np.ndarray


class AttitudeFilter:
    """Stateful single-step attitude filter (MEKF or MUKF, any chart, or a baseline of
    :mod:`mkf_ros.core.baselines`) for streaming use.

    >>> f = AttitudeFilter(algorithm="mekf", chart="rp")
    >>> f.step(0.01, gyr=[0, 0, 0], acc=[0, 0, 9.81])
    >>> f.quaternion  # [w, x, y, z], sensor → world
    array([1., 0., 0., 0.])
    """

    def __init__(self, params: FilterParams | None = None, **overrides: object) -> None:
        self._params = (params or FilterParams()).replace(**overrides)
        self._split = False
        self._cfg = build_config(self._params, self._split)
        self._counters = new_records(COUNTERS)
        self._work = new_records(WORK)
        self.reset()

    # --- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the estimate: the next accelerometer sample re-initialises (bias kept at 0)."""
        self._st = new_records(STATE)
        record(self._st).q_c[0] = 1.0
        self._arrays = KernelArrays(self._cfg, self._st, self._counters, self._work)

    @property
    def counters(self) -> np.ndarray:
        """The counters as an int64 array in :data:`COUNTER_NAMES` order."""
        return self._counters.view(np.int64)

    @property
    def params(self) -> FilterParams:
        return self._params

    def set_params(self, **changes: object) -> FilterParams:
        """Validate and apply parameter changes atomically (ValueError: nothing changes).

        Switching ``algorithm``, ``chart`` or ``chart_update`` keeps the estimate: a MUKF mean
        ``ē ≠ 0`` is first moved onto the chart origin with the T-matrix (§3.2); at the origin
        every chart agrees with the rotation vector to first order (eq. 10), so ``P`` carries
        over unchanged. A switch to or from a baseline converts the state through that form:
        quaternion ↔ Euler angles, ``P_ee = E Σ Eᵀ`` ↔ ``Σ = W P_ee Wᵀ``
        (:func:`to_canonical_entry`, :func:`from_canonical_entry`). Enabling bias estimation
        starts the bias at 0 with ``gyro_bias_stddev``; disabling it freezes the current bias.
        """
        new = self._params.replace(**changes)
        cfg = build_config(new, self._split)
        old_c, c, s = record(self._cfg), record(cfg), record(self._st)
        switch = new.algorithm != self._params.algorithm
        if switch or old_c.algorithm < ALGO_EULER_KF:
            to_canonical_entry(kernel_table(self._cfg), self._cfg, self._st)
        if c.nx > old_c.nx and s.initialized:
            s.P[6:9, :] = 0.0
            s.P[:, 6:9] = 0.0
            s.P[6:9, 6:9] = c.bias_var0 * np.eye(3)
        if new.mag_reference != self._params.mag_reference or (
            new.use_mag and not self._params.use_mag
        ):
            s.heading_fixed = False  # re-establish heading from the next magnetometer sample
        if switch:
            from_canonical_entry(kernel_table(cfg), cfg, self._st)
        self._params, self._cfg = new, cfg
        self._arrays = KernelArrays(self._cfg, self._st, self._counters, self._work)
        return new

    def set_split_input(self, split: bool) -> None:
        """Tell the rest test that the gyro and the accelerometer come in separate samples
        (split input): each sensor's part of the test is then held across the steps without
        its reading. Kept across :meth:`set_params`."""
        self._split = bool(split)
        record(self._cfg).split_input = self._split

    def kernel_arrays(self) -> KernelArrays:
        """The filter's record arrays, for a front end running its own compiled loop around
        :func:`run_step` and ``Kernels.output`` (:mod:`mkf_ros.stream.kernel`). They are the
        filter's own (updated in place) until :meth:`reset` or :meth:`set_params`; read them
        through the accessors above."""
        return self._arrays  # built when they change (a front end calls this per message)

    def run(self, dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
            mag: np.ndarray) -> BatchOutputs:
        """Every sample of a recording through the filter (:func:`run_batch`), from its
        current state: ``dts`` (N,) the steps (s, validated by the caller), readings (N, 3)
        float64, NaN rows missing. The filter's state and counters advance as by N
        :meth:`step` calls."""
        n = len(dts)
        out = new_batch_outputs(n)
        run_batch(kernel_table(self._cfg), self._cfg, self._st, self._counters, self._work, dts,
                  gyr, acc, mag, out)
        return out

    def step(self, dt: float, gyr: object = None, acc: object = None, mag: object = None) -> None:
        """Process one sample; ``None`` means the sensor has no reading at this time.

        ``dt`` (s) is the time since the previous sample: finite and ``≥ 0``. ``dt = 0`` is a
        sample at the same instant: no prediction, its readings are fused as further
        measurements at that instant (Madgwick's correction is a rate: it has no effect over
        no time); so is a ``dt`` below :data:`~mkf_ros.core.state.DT_MIN` (1 ns); one above
        ``max_dt`` is a gap (docs/math.md §9.5). Readings as for :func:`mkf_ros.estimate`
        (all NaN: missing; partly non-finite, a zero vector or beyond the plausibility
        limits: invalid, skipped and counted). An invalid ``dt`` or a sample of the wrong
        shape raises ValueError naming the argument and leaves the filter exactly as it was."""
        d = _dt(dt)
        g, a, m = _vec(gyr, "gyr"), _vec(acc, "acc"), _vec(mag, "mag")
        sensor_step(kernel_table(self._cfg), self._cfg, self._st, self._counters, self._work, d,
                    g, a, m)

    @property
    def initialized(self) -> bool:
        return bool(record(self._st).initialized)

    @property
    def heading_initialized(self) -> bool:
        """True once the magnetometer has fixed the heading (always False without it)."""
        return bool(record(self._st).heading_fixed) and self._params.use_mag

    @property
    def quaternion(self) -> np.ndarray:
        """Orientation ``[w, x, y, z]`` of the sensor in the world frame."""
        q, _ = self._output()
        return q

    @property
    def covariance(self) -> np.ndarray:
        """3×3 orientation covariance about the world frame's x, y, z axes (rad²)."""
        _, c = self._output()
        return c

    @property
    def omega(self) -> np.ndarray:
        """Estimated angular velocity, body frame (rad/s)."""
        return record(self._st).w.copy()

    @property
    def bias(self) -> np.ndarray:
        """Estimated gyro bias (rad/s); zero unless ``estimate_gyro_bias``."""
        return record(self._st).b.copy()

    @property
    def bias_std(self) -> np.ndarray:
        return (np.sqrt(np.diag(record(self._st).P)[6:9]) if record(self._cfg).nx == 9
                else np.zeros(3))

    @property
    def state_covariance(self) -> np.ndarray:
        """The filter's covariance of ``(e, ω[, b])`` in its current chart."""
        n = int(record(self._cfg).nx)
        return record(self._st).P[:n, :n].copy()

    def counter_dict(self) -> dict[str, int]:
        c = record(self._counters)
        return {name: int(c[name]) for name in COUNTER_NAMES}

    def _output(self) -> tuple[np.ndarray, np.ndarray]:
        q = np.empty(4)
        c = np.empty((3, 3))
        world_output(kernel_table(self._cfg), self._cfg, self._st, q, c)
        if not record(self._st).initialized:
            c = ATTITUDE_VAR_UNKNOWN * np.eye(3)
        return q, c


_NAN3 = np.full(3, np.nan)


def _dt(dt: object) -> float:
    """``dt`` of :meth:`AttitudeFilter.step` as a float; ValueError unless finite and ≥ 0."""
    d = np.nan
    if not isinstance(dt, (str, bytes, bool, np.bool_)):
        with contextlib.suppress(TypeError, ValueError):
            d = float(dt)  # type: ignore[arg-type]
    if not (np.isfinite(d) and d >= 0.0):
        raise ValueError(f"dt must be a finite number of seconds >= 0 (the time since the "
                         f"previous sample), got {dt!r}")
    return d


def _vec(v: object, name: str) -> np.ndarray:
    if v is None:
        return _NAN3
    # a fresh C-contiguous, writable float64 array: anything else would make numba compile a
    # new specialisation of the kernels in the middle of a stream
    try:
        a = np.array(v, dtype=np.float64, copy=True)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 3 numbers or None, got {v!r}") from None
    if a.size != 3:
        raise ValueError(f"{name} must have 3 components, got shape {a.shape}")
    return a.reshape(-1)
