"""The attitude filter's public face: :class:`AttitudeFilter` (the stateful Python filter used by
the stream adapter and the ROS node), :func:`run_batch` (the loop behind
:func:`mkf_ros.estimate`) and the output in the chosen world frame with the orientation
covariance about world axes.

Compiled front ends (:mod:`mkf_ros.stream.kernel`) drive the filter through the kernels listed
in ``__all__`` below and the arrays of :meth:`AttitudeFilter.kernel_arrays`, never through the
layouts of :mod:`mkf_ros.core.state`.
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.baseline_glue import (
    baseline_estimate,
    from_canonical,
    to_canonical,
)
from mkf_ros.core.charts import from_chart_t, t_matrix_t
from mkf_ros.core.frames import FROM_ENU
from mkf_ros.core.linalg import congruence33_t
from mkf_ros.core.mekf import (
    mekf_scratch,
)
from mkf_ros.core.mukf import mukf_scratch
from mkf_ros.core.params import FilterParams
from mkf_ros.core.quaternion import (
    qmul_t,
    qnormalize_t,
    rotmat_t,
    t4,
    t33,
)
from mkf_ros.core.sensor import (
    sensor_step,
    sensor_step_t,
)
from mkf_ros.core.state import (
    ALGO_EULER_KF,
    ALGO_MADGWICK,
    ATTITUDE_VAR_UNKNOWN,
    C_ACC_ALIGN,
    C_ALGO,
    C_B0,
    C_CHART,
    C_GRAVITY,
    C_MAXDT,
    C_NX,
    C_REST_SPLIT,
    C_USE_MAG,
    COUNTER_NAMES,
    F_HEADING,
    F_INIT,
    F_SIZE,
    K_GAPS,
    K_SIZE,
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    NX_MAX,
    S_B,
    S_E,
    S_QC,
    S_SIZE,
    S_W,
    YAW_VAR_UNKNOWN,
    build_cfg,
    build_noise,
    classify_reading,
)

#: The stateful filter and its batch loop, the plausibility contract of a reading (issue 14) and
#: the kernel interface of compiled front ends.
__all__ = [
    "COUNTER_NAMES",
    "MAX_ACC_G",
    "MAX_GYRO_RATE",
    "MAX_MAG",
    "YAW_VAR_UNKNOWN",
    "AttitudeFilter",
    "BatchOutputs",
    "KernelArrays",
    "bias",
    "bias_variance",
    "build_cfg",
    "classify_reading",
    "gap_count",
    "gravity",
    "heading_fixed",
    "is_initialized",
    "max_dt",
    "rate",
    "rate_covariance",
    "run_batch",
    "sensor_step",
    "uses_mag",
    "world_output"
]


@jit_inline
def world_output_t(cfg: np.ndarray, st: np.ndarray, P: np.ndarray,
                    q_from_enu: np.ndarray) -> tuple[tuple, tuple]:
    """:func:`world_output` as tuples (the quaternion, the covariance's rows): reads ``st`` and
    ``P`` element by element, so that the per-sample output of :func:`run_batch` allocates
    nothing and creates no array views (each costs reference counting)."""
    if int(cfg[C_ALGO]) >= ALGO_EULER_KF:
        qa, Pa = baseline_estimate(cfg, st, P)
        q, Pb = t4(qa), t33(Pa)
    else:  # q̂ = q̄_c * φ⁻¹(ē), Σ_body = T P_ee Tᵀ (identity for ē = 0)
        q = (st[S_QC], st[S_QC + 1], st[S_QC + 2], st[S_QC + 3])
        Pb = ((P[0, 0], P[0, 1], P[0, 2]), (P[1, 0], P[1, 1], P[1, 2]),
              (P[2, 0], P[2, 1], P[2, 2]))
        e = (st[S_E], st[S_E + 1], st[S_E + 2])
        if not (e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0):
            chart = int(cfg[C_CHART])
            d = from_chart_t(chart, e)
            q = qnormalize_t(qmul_t(q, d))
            Pb = congruence33_t(t_matrix_t(chart, d), Pb)
    q = qmul_t(t4(q_from_enu), q)
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[0] < 0.0:
        n = -n
    q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
    C = congruence33_t(rotmat_t(q), Pb)
    f2 = cfg[C_ACC_ALIGN] ** 2 if int(cfg[C_ALGO]) != ALGO_MADGWICK else 0.0
    # the accelerometer's own misalignment: a constant no filter averages out (published only,
    # by every filter but Madgwick, whose published value is a parameter; every world frame
    # here has its z vertical, so x and y are the tilt axes). Symmetric by construction: the
    # mean of the two triangles, which the congruence's rounding makes differ by ~1e-16 of
    # the largest element (bit-identical where they agree)
    c01, c02, c12 = 0.5 * (C[0][1] + C[1][0]), 0.5 * (C[0][2] + C[2][0]), 0.5 * (C[1][2] + C[2][1])
    return q, ((C[0][0] + f2, c01, c02), (c01, C[1][1] + f2, c12), (c02, c12, C[2][2]))


@jit
def world_output(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, q_from_enu: np.ndarray,
                 q_out: np.ndarray, cov_out: np.ndarray) -> None:
    """Orientation in the world frame (``q0 ≥ 0``) and its 3×3 covariance about world axes:
    ``Σ_W = R(q_W) Σ_body R(q_W)ᵀ`` (the error is body-side, ``q = q̂ * δ(e)``)."""
    q, cov = world_output_t(cfg, st, P, q_from_enu)
    for i in range(4):
        q_out[i] = q[i]
    for i in range(3):
        for j in range(3):
            cov_out[i, j] = cov[i][j]


# --- the kernel interface of compiled front ends (mkf_ros.stream.kernel) ---------------------
# A front end that runs its own compiled loop holds the filter's arrays
# (:meth:`AttitudeFilter.kernel_arrays`) and calls :func:`sensor_step` and :func:`world_output`;
# what else it reads of the filter it reads through these, never through the layouts.


@jit_inline
def gravity(cfg: np.ndarray) -> float:
    """The ``gravity`` parameter (m/s²)."""
    return cfg[C_GRAVITY]


@jit_inline
def max_dt(cfg: np.ndarray) -> float:
    """The ``max_dt`` parameter (s): a longer step is a gap (re-alignment)."""
    return cfg[C_MAXDT]


@jit_inline
def uses_mag(cfg: np.ndarray) -> bool:
    """Whether the magnetometer is fused (``use_mag``)."""
    return cfg[C_USE_MAG] > 0


@jit_inline
def is_initialized(fl: np.ndarray) -> bool:
    """Whether the filter has an estimate (aligned, or the paper's start)."""
    return fl[F_INIT] > 0


@jit_inline
def heading_fixed(cfg: np.ndarray, fl: np.ndarray) -> bool:
    """Whether the magnetometer has fixed the heading (never without ``use_mag``)."""
    return fl[F_HEADING] > 0 and cfg[C_USE_MAG] > 0


@jit_inline
def gap_count(cnt: np.ndarray) -> int:
    """How many steps longer than ``max_dt`` the filter has re-aligned after."""
    return cnt[K_GAPS]


@jit_inline
def rate(st: np.ndarray, i: int) -> float:
    """Component ``i`` of the estimated angular velocity ``ω̄`` (body, rad/s)."""
    return st[S_W + i]


@jit_inline
def bias(st: np.ndarray, i: int) -> float:
    """Component ``i`` of the estimated gyro bias ``b̄`` (rad/s; 0 without bias estimation)."""
    return st[S_B + i]


@jit_inline
def bias_variance(cfg: np.ndarray, P: np.ndarray, i: int) -> float:
    """Variance of bias component ``i`` (rad²/s²; 0 without bias estimation)."""
    return P[6 + i, 6 + i] if int(cfg[C_NX]) == 9 else 0.0


@jit_inline
def rate_covariance(P: np.ndarray, i: int, j: int) -> float:
    """Element ``(i, j)`` of the covariance of ``ω̄`` (rad²/s²)."""
    return P[3 + i, 3 + j]


@jit
def run_batch(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray, cnt: np.ndarray,
              dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray,
              q_from_enu: np.ndarray, out_q: np.ndarray, out_cov: np.ndarray,
              out_w: np.ndarray, out_b: np.ndarray, out_bvar: np.ndarray,
              out_init: np.ndarray) -> None:
    """:func:`sensor_step` over a whole recording, writing the outputs of every sample
    (element by element: no array views in the loop)."""
    nx = int(cfg[C_NX])
    nz = build_noise(cfg)
    dx = np.empty(NX_MAX)
    work = mekf_scratch(NX_MAX)
    mwork = mukf_scratch(nx)
    for n in range(dts.shape[0]):
        sensor_step_t(cfg, nz, st, P, fl, cnt, dts[n], (gyr[n, 0], gyr[n, 1], gyr[n, 2]),
                     (acc[n, 0], acc[n, 1], acc[n, 2]), (mag[n, 0], mag[n, 1], mag[n, 2]), dx,
                     work, mwork)
        q, cov = world_output_t(cfg, st, P, q_from_enu)
        init = fl[F_INIT] > 0
        out_init[n] = init
        for i in range(4):
            out_q[n, i] = q[i]
        for i in range(3):
            for j in range(3):
                out_cov[n, i, j] = cov[i][j]
            if not init:
                out_cov[n, i, i] = ATTITUDE_VAR_UNKNOWN
            out_w[n, i] = st[S_W + i]
            out_b[n, i] = st[S_B + i]
            out_bvar[n, i] = P[6 + i, 6 + i] if nx == 9 else 0.0


class KernelArrays(NamedTuple):
    """The arrays of an :class:`AttitudeFilter`, in the order of :func:`sensor_step`'s and
    :func:`world_output`'s arguments (``counters`` is ``cnt``)."""

    cfg: np.ndarray
    nz: np.ndarray
    st: np.ndarray
    P: np.ndarray
    fl: np.ndarray
    counters: np.ndarray
    q_from_enu: np.ndarray


class BatchOutputs(NamedTuple):
    """Per-sample outputs of :meth:`AttitudeFilter.run` (the last arguments of
    :func:`run_batch`): orientation ``[w, x, y, z]`` in the world frame, its covariance about
    world axes (``π² I`` before initialisation), rate, bias, bias variance, initialised."""

    quat: np.ndarray
    cov: np.ndarray
    omega: np.ndarray
    bias: np.ndarray
    bias_var: np.ndarray
    initialized: np.ndarray


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
        self._cfg = self._build_cfg(self._params)
        self._nz = build_noise(self._cfg)
        self._q_from_enu = FROM_ENU[self._params.world_frame].copy()
        self.counters = np.zeros(K_SIZE, dtype=np.int64)
        self.reset()

    # --- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the estimate: the next accelerometer sample re-initialises (bias kept at 0)."""
        self._st = np.zeros(S_SIZE)
        self._st[S_QC] = 1.0
        self._P = np.zeros((NX_MAX, NX_MAX))
        self._fl = np.zeros(F_SIZE, dtype=np.int64)

    @property
    def params(self) -> FilterParams:
        return self._params

    def set_params(self, **changes: object) -> FilterParams:
        """Validate and apply parameter changes atomically (ValueError: nothing changes).

        Switching ``algorithm``, ``chart`` or ``chart_update`` keeps the estimate: a MUKF mean
        ``ē ≠ 0`` is first moved onto the chart origin with the T-matrix (§3.2); at the origin
        every chart agrees with the rotation vector to first order (eq. 10), so ``P`` carries
        over unchanged. A switch to or from a baseline converts the state through that form:
        quaternion ↔ Euler angles, ``P_ee = E Σ Eᵀ`` ↔ ``Σ = W P_ee Wᵀ`` (:func:`to_canonical`,
        :func:`from_canonical`). Enabling bias estimation starts the bias at 0 with
        ``gyro_bias_stddev``; disabling it freezes the current bias.
        """
        new = self._params.replace(**changes)
        cfg = self._build_cfg(new)
        switch = new.algorithm != self._params.algorithm
        if switch or int(self._cfg[C_ALGO]) < ALGO_EULER_KF:
            to_canonical(self._cfg, self._st, self._P)
        old_nx, new_nx = int(self._cfg[C_NX]), int(cfg[C_NX])
        if new_nx > old_nx and self._fl[F_INIT]:
            self._P[6:9, :] = 0.0
            self._P[:, 6:9] = 0.0
            self._P[6:9, 6:9] = cfg[C_B0] * np.eye(3)
        if new.mag_reference != self._params.mag_reference or (
            new.use_mag and not self._params.use_mag
        ):
            self._fl[F_HEADING] = 0  # re-establish heading from the next magnetometer sample
        if switch:
            from_canonical(cfg, self._st, self._P)
        self._params, self._cfg, self._nz = new, cfg, build_noise(cfg)
        self._q_from_enu = FROM_ENU[new.world_frame].copy()
        return new

    def set_split_input(self, split: bool) -> None:
        """Tell the rest test that the gyro and the accelerometer come in separate samples
        (split input, issue 15): each sensor's part of the test is then held across the steps
        without its reading. Kept across :meth:`set_params`."""
        self._split = bool(split)
        self._cfg[C_REST_SPLIT] = float(self._split)

    def _build_cfg(self, p: FilterParams) -> np.ndarray:
        cfg = build_cfg(p)
        cfg[C_REST_SPLIT] = float(self._split)
        return cfg

    def kernel_arrays(self) -> KernelArrays:
        """The filter's arrays, for a front end running its own compiled loop around
        :func:`sensor_step` and :func:`world_output` (:mod:`mkf_ros.stream.kernel`). They are
        the filter's own (updated in place) until :meth:`reset` or :meth:`set_params`; their
        layouts are not part of the interface (read them through the accessors above)."""
        return KernelArrays(self._cfg, self._nz, self._st, self._P, self._fl, self.counters,
                            self._q_from_enu)

    def run(self, dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
            mag: np.ndarray) -> BatchOutputs:
        """Every sample of a recording through the filter (:func:`run_batch`), from its
        current state: ``dts`` (N,) the steps (s, validated by the caller), readings (N, 3)
        float64, NaN rows missing. The filter's state and counters advance as by N
        :meth:`step` calls."""
        n = len(dts)
        out = BatchOutputs(np.empty((n, 4)), np.empty((n, 3, 3)), np.empty((n, 3)),
                           np.empty((n, 3)), np.empty((n, 3)), np.empty(n, dtype=np.bool_))
        run_batch(self._cfg, self._st, self._P, self._fl, self.counters, dts, gyr, acc, mag,
                  self._q_from_enu, *out)
        return out

    def step(self, dt: float, gyr: object = None, acc: object = None, mag: object = None) -> None:
        """Process one sample; ``None`` means the sensor has no reading at this time.

        ``dt`` (s) is the time since the previous sample: finite and ``≥ 0``. ``dt = 0`` is a
        sample at the same instant: no prediction, its readings are fused as further
        measurements at that instant (Madgwick's correction is a rate: it has no effect over
        no time). Readings as for :func:`mkf_ros.estimate` (all NaN: missing; partly
        non-finite, a zero vector or beyond the plausibility limits: invalid, skipped and
        counted). An invalid ``dt`` or a sample of the wrong shape raises ValueError naming
        the argument and leaves the filter exactly as it was."""
        d = _dt(dt)
        g, a, m = _vec(gyr, "gyr"), _vec(acc, "acc"), _vec(mag, "mag")
        sensor_step(self._cfg, self._nz, self._st, self._P, self._fl, self.counters, d, g, a, m)

    @property
    def initialized(self) -> bool:
        return bool(self._fl[F_INIT])

    @property
    def heading_initialized(self) -> bool:
        """True once the magnetometer has fixed the heading (always False without it)."""
        return bool(self._fl[F_HEADING]) and self._params.use_mag

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
        return self._st[S_W:S_W + 3].copy()

    @property
    def bias(self) -> np.ndarray:
        """Estimated gyro bias (rad/s); zero unless ``estimate_gyro_bias``."""
        return self._st[S_B:S_B + 3].copy()

    @property
    def bias_stddev(self) -> np.ndarray:
        return np.sqrt(np.diag(self._P)[6:9]) if self._cfg[C_NX] == 9 else np.zeros(3)

    @property
    def state_covariance(self) -> np.ndarray:
        """The filter's covariance of ``(e, ω[, b])`` in its current chart."""
        n = int(self._cfg[C_NX])
        return self._P[:n, :n].copy()

    def counter_dict(self) -> dict[str, int]:
        return dict(zip(COUNTER_NAMES, (int(c) for c in self.counters), strict=True))

    def _output(self) -> tuple[np.ndarray, np.ndarray]:
        q = np.empty(4)
        c = np.empty((3, 3))
        world_output(self._cfg, self._st, self._P, self._q_from_enu, q, c)
        if not self._fl[F_INIT]:
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
