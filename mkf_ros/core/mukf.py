"""MUKF — Manifold Unscented Kalman Filter (docs/math.md §6; paper §3.2).

Carried state: the chart centre ``q̄_c`` (the predicted mean of the previous step), the mean ``ē``
of the distribution in that chart (not zero in general), ``ω̄``, the gyro bias ``b̄`` (extension)
and ``P`` about ``(ē, ω̄[, b̄])`` in the ``q̄_c``-chart. The estimate is ``q̂ = q̄_c * φ⁻¹(ē)``
(:func:`mkf_ros.core.charts.from_chart_at`).

The chart update is implicit (§6, "How the MUKF does the chart update"): sigma points drawn in the
old chart are re-expressed exactly in the chart of the new mean. The reset variant (step 0)
re-centres at ``q̂`` and keeps ``P``.

:func:`mukf_step_t` is the step; it calls one function per step of §6 (those are inlined into it:
a call between compiled functions costs reference counting on every array argument, more than
the arithmetic of most of these steps). The sigma points live in one table ``X`` (the spec's
``X_j``, one row per point; not to be confused with the T-matrices of §3.2, which the MUKF does
not need).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.charts import from_chart_at_t, from_chart_t, saturate_t, to_chart_t
from mkf_ros.core.linalg import (
    ZERO33,
    cho_solve_into,
    cholesky_into,
    congruence33_t,
    cross33_t,
    transpose33_t,
)
from mkf_ros.core.mekf import heading_residual_t
from mkf_ros.core.quaternion import (
    q_omega_t,
    qconj_mul_t,
    qmul_t,
    qnormalize_t,
    rotate_inv_t,
    rotmat_t,
    t3,
    t4,
    t33,
    up_in_body_t,
)

NOISE_CONSISTENT, NOISE_PUBLISHED, NOISE_INTEGRATED = 0, 1, 2
NOISE_MODES = ("consistent", "published", "integrated")


#: The measurements of one MUKF step (§6 and the real-sensor extensions): up to two vector
#: sensors (eq. 24: readings ``vm``, world references ``vref``, noise ``Rv``, external
#: disturbance ``Qv``, which are present ``use_v``), the gyro (eq. 23: ``wm``, ``use_w``,
#: ``Rw``), the field for heading only (``hm`` body, ``href`` horizontal world reference,
#: ``use_h``, variance ``var_h``), rest's zero rate (``use_z``, ``var_z``), a χ² gate per block
#: (``gates``, vector 0, vector 1, heading, gyro; only with ``gated``), gravity's tilt-only
#: gain (``tilt_v0``), its dependence on the bias and the bias's share of its gain
#: (``sens_v0``, ``bias_gain_v0``, docs/math.md §9.1) and the heading's bias share
#: (``bias_gain_h``, §9.2; default 1). Tuples for :func:`mukf_step_t` (a pair of 3-tuples, of
#: rows, of flags for the vectors), arrays for :func:`mukf_step_ext` (``(k, 3)``,
#: ``(k, 3, 3)``, ``(k,)``; ``gated`` there: ``gates`` not empty).
MukfMeasurement = namedtuple("MukfMeasurement", (
    "vm", "vref", "Rv", "Qv", "use_v", "wm", "use_w", "Rw", "hm", "href", "use_h", "var_h",
    "use_z", "var_z", "gates", "gated", "tilt_v0", "sens_v0", "bias_gain_v0", "bias_gain_h"),
    defaults=(1.0,))


@jit_inline
def mukf_step(chart: int, chart_update: bool, noise_mode: int, w0: float, x: tuple,
              P: np.ndarray, nx: int, dt: float, Qw: np.ndarray, Qb: np.ndarray, vectors: tuple,
              gyro: tuple) -> bool:
    """One MUKF prediction + update over ``dt`` (§6 steps 0–7), in place: the state
    ``x = (q̄_c, ē, ω̄, b̄)`` (arrays) and ``P``.

    The measurement as in :func:`mkf_ros.core.mekf.mekf_update`: ``vectors = (vm, vref, Rv,
    Qv, use_v)`` and ``gyro = (wm, use_w, Rw)``. ``noise_mode`` says how the angular-velocity
    noise enters (§8 item 3):

    * ``NOISE_CONSISTENT`` (0, the spec's recommendation): ``Q_ωᵃ = Q_ω Δt``, ``ω_j⁻ = ω_j + n``;
    * ``NOISE_PUBLISHED`` (1, also ``True``): the authors' ``Q_ωᵃ = Q_ω``, ``ω_j⁻ = ω_j + n Δt``
      (the rate variance grows by ``Q_ω Δt²``; reproduces the paper's figures);
    * ``NOISE_INTEGRATED`` (2, extension): as consistent, but the step rotates with the mean
      rate ``ω_j + n/2`` of a Wiener rate going from ``ω_j`` to ``ω_j + n``, and the Brownian-
      bridge remainder ``Q_ω Δt³/12`` is added to the attitude covariance. The attitude then
      receives ``Q_ω Δt³/3`` per step like the MEKF (§5) and a continuously varying rate;
      with 0 and 1 the gyro at the end of the step appears to observe the whole increment,
      which makes the covariance over-confident when the rate wanders.

    Returns False (state untouched) if a factorisation fails.
    """
    vm, vref, Rv, Qv, use_v = vectors
    wm, use_w, Rw = gyro
    none = x[0][:0]  # no heading sensor (hm, href unused), no gates (nis unused)
    return mukf_step_ext(chart, chart_update, noise_mode, w0, x, P, nx, dt, Qw, Qb,
                         MukfMeasurement(vm, vref, Rv, Qv, use_v, wm, use_w, Rw, none, none,
                                         False, 0.0, False, 0.0, none, False, False,
                                         _NO_SENSITIVITY, 1.0, 1.0), none)


#: ``sens_v0`` of a vector that does not depend on the bias (a global array: numba compiles it
#: in as a constant, no allocation per step)
_NO_SENSITIVITY = np.zeros((3, 3))

# measurement rows at most: two vectors, heading, gyro, zero rate
_M_MAX = 3 + 3 + 1 + 3 + 3
# sigma-point directions propagated by mukf_step_t: attitude (3), rate (3), rate noise (3)
_NDA = 9


@jit
def mukf_scratch(nx: int) -> tuple:
    """Scratch of :func:`mukf_step_t` for ``nx`` states (see its step 2): ``L``, the sigma-point
    table ``X``, ``P_xy``, ``P_yy``, its factor, ``K P_yy``, ``P_xx`` and ``Kᵀ``, each at its
    largest size (``m`` rows or columns at most ``_M_MAX``)."""
    nd = nx + 3
    return (np.empty((nd, nd)), np.empty((2 * _NDA + 3, _CY + _M_MAX)),
            np.empty((nx, _M_MAX)), np.empty((_M_MAX, _M_MAX)), np.empty((_M_MAX, _M_MAX)),
            np.empty((nx, _M_MAX)), np.empty((nx, nx)), np.empty((_M_MAX, nx)))


# measurement blocks of mukf_step_ext, in row order; index into its `gates` / `nis` arrays
B_VEC0, B_VEC1, B_HEADING, B_GYRO = 0, 1, 2, 3
_BLOCK_SIZE = (3, 3, 1, 3)
# columns of the sigma-point table X: the state part x = (e, ω, b) (later Δx), the quaternion q⁻,
# the measurement y (later Δy)
_CX, _CQ, _CY = 0, 9, 13

#: The same scratch as fields of a record (sized for 9 states; a filter with 6 uses the leading
#: blocks): name, type, shape, in :func:`mukf_scratch`'s order.
MUKF_SCRATCH = [
    ("L", np.float64, (12, 12)), ("X", np.float64, (2 * _NDA + 3, _CY + _M_MAX)),
    ("Pxy", np.float64, (9, _M_MAX)), ("Pyy", np.float64, (_M_MAX, _M_MAX)),
    ("Ly", np.float64, (_M_MAX, _M_MAX)), ("KPyy", np.float64, (9, _M_MAX)),
    ("Pxx", np.float64, (9, 9)), ("Kt", np.float64, (_M_MAX, 9)),
]


@jit_inline
def _wmeans(X: np.ndarray, ns: int, w_0: float, wj: float, c0: int, c1: int) -> None:
    """``X[ns, c] = Σ_s W_s X[s, c]`` for columns ``c0 ≤ c < c1`` over the sigma points
    ``s < ns`` (``W_0 = w_0``, else ``wj``), accumulated from 0 in point order in registers,
    four columns at a time."""
    c = c0
    while c < c1:
        n = min(4, c1 - c)
        a0 = a1 = a2 = a3 = 0.0
        for s in range(ns):
            ws_ = w_0 if s == 0 else wj
            a0 += ws_ * X[s, c]
            if n > 1:
                a1 += ws_ * X[s, c + 1]
            if n > 2:
                a2 += ws_ * X[s, c + 2]
            if n > 3:
                a3 += ws_ * X[s, c + 3]
        X[ns, c] = a0
        if n > 1:
            X[ns, c + 1] = a1
        if n > 2:
            X[ns, c + 2] = a2
        if n > 3:
            X[ns, c + 3] = a3
        c += 4


@jit_inline
def _wsums(X: np.ndarray, s0: int, ns: int, w_0: float, wj: float, a: int, b: int, n: int,
           out: np.ndarray, r: int, oc: int) -> None:
    """``out[r, oc + k] = Σ_s W_s X[s, a] X[s, b + k]`` for ``k < n``, over the rows
    ``s0 ≤ s < s0 + ns`` (``W_{s0} = w_0``, else ``wj``), accumulated in registers four columns
    at a time, a last column in four partial sums (independent sums: the additions overlap
    instead of waiting for each other)."""
    k = 0
    s1 = s0 + ns
    while k + 4 <= n:
        wa = w_0 * X[s0, a]
        c0, c1 = wa * X[s0, b + k], wa * X[s0, b + k + 1]
        c2, c3 = wa * X[s0, b + k + 2], wa * X[s0, b + k + 3]
        for s in range(s0 + 1, s1):
            wa = wj * X[s, a]
            c0 += wa * X[s, b + k]
            c1 += wa * X[s, b + k + 1]
            c2 += wa * X[s, b + k + 2]
            c3 += wa * X[s, b + k + 3]
        out[r, oc + k], out[r, oc + k + 1], out[r, oc + k + 2], out[r, oc + k + 3] = c0, c1, c2, c3
        k += 4
    while k < n:  # one column: four sums over every fourth row, independent likewise
        c0 = (w_0 * X[s0, a]) * X[s0, b + k]
        c1 = c2 = c3 = 0.0
        s = s0 + 1
        while s + 4 <= s1:
            c0 += (wj * X[s, a]) * X[s, b + k]
            c1 += (wj * X[s + 1, a]) * X[s + 1, b + k]
            c2 += (wj * X[s + 2, a]) * X[s + 2, b + k]
            c3 += (wj * X[s + 3, a]) * X[s + 3, b + k]
            s += 4
        while s < s1:
            c0 += (wj * X[s, a]) * X[s, b + k]
            s += 1
        out[r, oc + k] = (c0 + c1) + (c2 + c3)
        k += 1


@jit
def _row_kept(r: int, first: tuple, rejected: int) -> bool:
    """Whether measurement row ``r`` belongs to no block rejected by the χ² gate (bit mask)."""
    for blk in range(4):
        if (rejected >> blk) & 1 and first[blk] <= r < first[blk] + _BLOCK_SIZE[blk]:
            return False
    return True


@jit_inline
def mukf_step_ext(chart: int, chart_update: bool, noise_mode: int, w0: float, x: tuple,
                  P: np.ndarray, nx: int, dt: float, Qw: np.ndarray, Qb: np.ndarray,
                  z: MukfMeasurement, nis: np.ndarray) -> bool:
    """:func:`mukf_step` with the real-sensor extensions (``z``, a :data:`MukfMeasurement` of
    arrays): with ``tilt_v0`` the first vector sensor (gravity) corrects tilt only — its gain
    is kept off the world vertical for attitude, rate and bias, as in
    :func:`mkf_ros.core.mekf.mekf_vector_update`; a magnetometer for heading only (the
    pseudo-measurement ``0 = ψ(q) + n`` of :func:`mkf_ros.core.mekf.mekf_heading_update`, the
    gain of attitude, rate and bias each projected onto the vertical, Joseph-form covariance),
    the zero-rate pseudo-measurement ``0 = ω + n`` of rest detection, and a χ² gate per block
    (vector 0, vector 1, heading, gyro; a block whose ``rᵀ P_yy⁻¹ r`` exceeds its gate is left
    out; ``nis`` receives every block's value). At most two vector sensors (``use_v`` of
    length 1 or 2). With ``gates`` empty no block is gated and ``nis`` is not written.

    The arrays as tuples for :func:`mukf_step_t`."""
    z3 = (0.0, 0.0, 0.0)
    z33 = (z3, z3, z3)
    qc, ebar, w, b = x
    nv = z.use_v.shape[0]
    v0, v1 = nv > 0 and bool(z.use_v[0]), nv > 1 and bool(z.use_v[1])
    gated = z.gates.shape[0] > 0
    inf4 = (np.inf, np.inf, np.inf, np.inf)
    vm, vref, Rv, Qv = z.vm, z.vref, z.Rv, z.Qv
    zt = MukfMeasurement(
        (t3(vm[0]) if v0 else z3, t3(vm[1]) if v1 else z3),
        (t3(vref[0]) if v0 else z3, t3(vref[1]) if v1 else z3),
        (t33(Rv[0]) if v0 else z33, t33(Rv[1]) if v1 else z33),
        (t33(Qv[0]) if v0 else z33, t33(Qv[1]) if v1 else z33), (v0, v1),
        t3(z.wm) if z.use_w else z3, z.use_w, t33(z.Rw) if z.use_w else z33,
        t3(z.hm) if z.use_h else z3, t3(z.href) if z.use_h else z3, z.use_h, z.var_h,
        z.use_z, z.var_z, (z.gates[0], z.gates[1], z.gates[2], z.gates[3]) if gated else inf4,
        gated, z.tilt_v0, t33(z.sens_v0), z.bias_gain_v0, z.bias_gain_h)
    ok, q, e, w_, b_, nis_ = mukf_step_t(
        chart, chart_update, noise_mode, w0, (t4(qc), t3(ebar), t3(w), t3(b)), P, nx, dt,
        t33(Qw), t33(Qb), zt, mukf_scratch(nx))
    if gated:
        for i in range(4):
            nis[i] = nis_[i]
    for i in range(4):  # (on failure as far as changed: step 0's re-centring)
        qc[i] = q[i]
    for i in range(3):
        ebar[i] = e[i]
        w[i] = w_[i]
        b[i] = b_[i]
    return ok


@jit
def mukf_step_t(chart: int, chart_update: bool, noise_mode: int, w0: float, x: tuple,
                P: np.ndarray, nx: int, dt: float, Qw: tuple, Qb: tuple, z: MukfMeasurement,
                scratch: tuple) -> tuple:
    """:func:`mukf_step_ext` on tuples: ``x = (q̄_c, ē, ω̄, b̄)``; ``Qw``, ``Qb`` tuples of rows,
    ``z`` a :data:`MukfMeasurement` of tuples; ``scratch`` from :func:`mukf_scratch` for ``nx``
    states. ``P`` is updated in place. Returns
    ``(ok, q̄_c, ē, ω̄, b̄, nis)``; if a factorisation fails, ``ok`` is False and the rest as far
    as computed (step 0's re-centring, the bias noise added to ``P``). Speed: no allocation,
    no views; every small input a tuple (no reference counting).

    The steps of §6, in order: 0. reset (:func:`_reset`), the process noise outside the sigma
    points (:func:`_add_process_noise`), 1.–2. the augmented factor and the weights
    (:func:`_augmented_factor`, :func:`_weights`), 2. :func:`_sigma_points`, 3.
    :func:`_propagate` and :func:`_predict_measurements`, 4. :func:`_align_hemispheres`, 5.
    :func:`_means`, 6. the points in the chart of the new mean (:func:`_to_chart_of_mean`) and
    the covariances (:func:`_sigma_covariances`, :func:`_linear_covariances`,
    :func:`_noise_and_innovation`), the χ² gate (:func:`_chi2_gate`, :func:`_keep_rows`),
    7. :func:`_update` and :func:`_new_state`."""
    qc, ebar, w, b = x
    nis = (0.0, 0.0, 0.0, 0.0)
    if not chart_update:
        qc, ebar = _reset(chart, qc, ebar)
    _add_process_noise(P, nx, dt, Qw, Qb, noise_mode)
    nvec, row_h, row_g, row_z, m, first = _measurement_rows(z.use_v, z.use_h, z.use_w, z.use_z)
    L, X, Pxy, Pyy, Ly, KPyy, Pxx, _ = scratch  # (see "Scratch layout" below)
    qa = _rate_noise_scale(noise_mode, dt)
    if not _augmented_factor(P, L, nx, Qw, qa):
        return False, qc, ebar, w, b, nis
    c, wj, w_0 = _weights(w0, nx, nvec)
    _sigma_points(X, L, ebar, c, nx)
    _propagate(X, chart, qc, ebar, w, dt, noise_mode, nx)
    _predict_measurements(X, first, z.vref, z.use_h, z.hm, z.href, row_h)
    ns = 2 * _NDA + 1  # the points' rows; row ns: means, row ns + 1: update and innovation
    _align_hemispheres(X, ns)
    qm = _means(X, ns, w_0, wj, w, b, row_g, row_z, z.use_w, z.use_z)
    _to_chart_of_mean(X, ns, chart, qm, row_g)
    _sigma_covariances(X, Pxx, Pxy, Pyy, ns, w_0, wj, nx, row_g)
    Hb = cross33_t(rotate_inv_t(qm, z.vref[0]), z.sens_v0) if nx == 9 else ZERO33
    _linear_covariances(P, Pxx, Pxy, Pyy, nx, m, Qw, qa,
                        (first[0] if z.use_v[0] else -1, row_g, row_z), Hb)
    _noise_and_innovation(X, Pyy, ns, first, z, (row_h, row_g, row_z))
    ok, nis, rejected = _chi2_gate(X, Pyy, Ly, KPyy, ns, first, z.gates, z.gated)
    if not ok:
        return False, qc, ebar, w, b, nis
    ma, row_v0k, row_hk = _keep_rows(X, Pxy, Pyy, ns, nx, m, first, rejected)
    if not _update(X, scratch, ns, nx, ma, qm, (z.tilt_v0, z.bias_gain_v0, z.bias_gain_h),
                   row_v0k, row_hk):
        return False, qc, ebar, w, b, nis
    e, w, b = _new_state(X, P, Pxx, ns, nx, chart, w, b)
    return True, qm, e, w, b, nis


# Scratch layout. numba has no stack arrays, and every allocation, every view and every array
# argument of a call costs reference counting (atomic operations) that outweighs a small
# matrix's arithmetic; so: eight arrays given by the caller (mukf_scratch), used in their
# leading blocks, no views; tables by column.
# L: lower Cholesky factor of the propagated part of Pᵃ, blockdiag(P, Q_ωᵃ).
# X: row s for sigma point s: e_s in columns _CX…_CX+2 (later e_s⁻, see step 6), the offset
#    Δz_s of (ω_s⁻, b_s) in _CX+3…_CX+nx−1, q_s⁻ in _CQ…_CQ+3, y_s in _CY…; row ns: the means of
#    q⁻ and y; row ns + 1: the update Δx and the innovation y − ȳ.
# P_xy, P_yy, its factor Ly, K P_yy, Kᵀ: m ≤ _M_MAX rows or columns, the first m used.


@jit_inline
def _reset(chart: int, qc: tuple, ebar: tuple) -> tuple:
    """Step 0 (reset variant only): ``q̄_c ← q̂ = q̄_c * φ⁻¹(ē)``, ``ē ← 0``; ``P`` is kept."""
    return from_chart_at_t(chart, qc, ebar), (0.0, 0.0, 0.0)


@jit_inline
def _add_process_noise(P: np.ndarray, nx: int, dt: float, Qw: tuple, Qb: tuple,
                       noise_mode: int) -> None:
    """The process noise that does not go through the sigma points (extensions), added to ``P``
    before step 1: the bias random walk ``Q_b Δt`` (so that it reaches ``P_xy``) and, with
    ``NOISE_INTEGRATED``, the Brownian-bridge part ``Q_ω Δt³/12`` of the attitude increment."""
    if nx == 9:
        for i in range(3):
            for j in range(3):
                P[6 + i, 6 + j] += Qb[i][j] * dt
    if noise_mode == NOISE_INTEGRATED:
        k3 = dt * dt * dt / 12.0
        for i in range(3):
            for j in range(3):
                P[i, j] += Qw[i][j] * k3


@jit_inline
def _measurement_rows(use_v: tuple, use_h: bool, use_w: bool, use_z: bool) -> tuple:
    """The stacked measurement's rows, in this order: vectors (3 each), heading (1), gyro (3),
    zero rate (3). Returns ``(nvec, row_h, row_g, row_z, m, first)``: the number of vector
    sensors, the first row of the heading, gyro and zero-rate blocks, the number of rows, and
    ``first[blk]``, the first row of block ``blk`` (``B_VEC0`` … ``B_GYRO``), −1 if absent. The
    rows before ``row_g`` (vectors, heading) are the ones not linear in the state."""
    v0, v1 = use_v
    nvec = (1 if v0 else 0) + (1 if v1 else 0)
    row_h = 3 * nvec
    row_g = row_h + (1 if use_h else 0)
    row_z = row_g + (3 if use_w else 0)
    m = row_z + (3 if use_z else 0)
    first = (0 if v0 else -1, (3 if v0 else 0) if v1 else -1, row_h if use_h else -1,
             row_g if use_w else -1)
    return nvec, row_h, row_g, row_z, m, first


@jit_inline
def _rate_noise_scale(noise_mode: int, dt: float) -> float:
    """Step 1, ``Q_ωᵃ = Q_ω·qa``, the covariance of the rate increment ``n_ω = ω⁻ − ω``:
    ``qa = Δt`` (consistent, integrated) or ``Δt²`` (published: the authors' ``Q_ω`` with
    ``n Δt``, the same spread); §8 item 3."""
    return dt * dt if noise_mode == NOISE_PUBLISHED else max(dt, 0.0)


@jit_inline
def _augmented_factor(P: np.ndarray, L: np.ndarray, nx: int, Qw: tuple, qa: float) -> bool:
    """Steps 1–2: ``L``, the lower Cholesky factor of the propagated part of
    ``Pᵃ = blockdiag(P, Q_ωᵃ, Q_v …)``, ``blockdiag(P, Q_ω qa)`` (block diagonal like it; the
    ``Q_v`` pairs are summed exactly, see :func:`_weights`). False if not positive definite."""
    if not cholesky_into(P, L, 0, nx):
        return False
    if qa > 0.0:
        for i in range(3):
            for j in range(3):
                L[nx + i, nx + j] = Qw[i][j] * qa
        if not cholesky_into(L, L, nx, 3):
            return False
    else:  # a zero-length step (e.g. a magnetometer fused at the IMU's time): no rate noise,
        L[nx:, nx:] = 0.0  # those sigma points coincide with the central one
    return True


@jit_inline
def _weights(w0: float, nx: int, nvec: int) -> tuple:
    """Step 2's scale and weights for ``N = nx + 3 + 3·nvec`` (state, rate noise, ``n_v`` per
    vector sensor): ``c = √(N/(1 − W_0))``, ``W_j = (1 − W_0)/(2N)``, and the weight of ``X_0``
    with the folded pairs' ``w_0 = W_0 + 2 W_j·(3·nvec + nx − 6)``. Returns ``(c, W_j, w_0)``.

    Exact reductions (the sums of steps 5–6 are linear in the points; ``2 W_j c² = 1``):

    * a pair along a ``Q_v`` column leaves q, ω, b equal to ``X_0``'s and moves ``y_k`` by
      ``±R(q_0⁻)ᵀ c L_v[:, j]``: it adds ``2 W_j`` to ``X_0``'s weight in every sum and
      ``R(q_0⁻)ᵀ Q_v R(q_0⁻)`` to the k-th block of ``P_yy`` (:func:`_noise_and_innovation`);
    * a pair along a bias column (L is lower triangular: it moves b only) leaves ``q⁻`` and
      every non-linear y equal to ``X_0``'s: it adds ``2 W_j`` to ``X_0``'s weight, nothing to
      the sums with e or y (its two b offsets cancel) and its share of ``L Lᵀ`` to ``P_bb``;
    * ``z = (ω⁻, b)`` is linear in the points: ``z̄⁻ = (ω̄, b̄)`` and ``P_zz = P_zz + Q_ωᵃ``
      exactly, and a sum ``Σ_s W_s a_s Δz_s`` (``Δz_0 = 0``, ``Δz_{j−} = −Δz_{j+}``) is
      ``W_j Σ_j (a_{j+} − a_{j−}) Δz_{j+}``.

    So ``1 + 2·9`` points are propagated (directions: attitude, rate, rate noise)."""
    N = nx + 3 + 3 * nvec
    c = np.sqrt(N / (1.0 - w0))
    wj = (1.0 - w0) / (2.0 * N)
    w_0 = w0 + 2.0 * (3.0 * nvec + (nx - 6)) * wj
    return c, wj, w_0


@jit_inline
def _direction(s: int, nx: int) -> int:
    """The column of L that sigma point ``s > 0`` moves along (step 2): points ``1 … 9`` go
    along ``+`` the directions (L's columns 0–5, attitude and rate, then ``nx … nx + 2``, rate
    noise), points ``10 … 18`` along ``−`` the same."""
    d = s - 1 if s <= _NDA else s - 1 - _NDA
    return d if d < 6 else d + nx - 6


@jit_inline
def _sigma_points(X: np.ndarray, L: np.ndarray, ebar: tuple, c: float, nx: int) -> None:
    """Step 2: ``X_0 = x̄ᵃ``, ``X_j, X_{N+j} = x̄ᵃ ± c L[:, j]`` for the propagated directions
    (:func:`_direction`), row ``s`` of ``X`` for point ``s``: ``e_s`` and the offset ``Δz_s`` of
    ``(ω_s⁻, b_s)``, the rate noise ``n_ω`` included."""
    for s in range(2 * _NDA + 1):
        j = _direction(s, nx)
        step = c if s <= _NDA else -c
        for i in range(3):
            X[s, _CX + i] = ebar[i]
        for i in range(3, nx):
            X[s, _CX + i] = 0.0
        if s > 0:
            if j < nx:  # a state direction (L is lower triangular: rows j … nx − 1)
                for i in range(j, nx):
                    X[s, _CX + i] += step * L[i, j]
            else:  # a rate-noise direction
                X[s, _CX + 3], X[s, _CX + 4], X[s, _CX + 5] = (
                    step * L[nx, j], step * L[nx + 1, j], step * L[nx + 2, j])


@jit_inline
def _propagate(X: np.ndarray, chart: int, qc: tuple, ebar: tuple, w: tuple, dt: float,
               noise_mode: int, nx: int) -> None:
    """Step 3, to the manifold and propagated, ``q_j⁻`` into row ``j`` of ``X``:
    ``q_j = q̄_c * φ⁻¹(sat(e_j))``, ``ω_j⁻ = ω_j + n_ω``, ``q_j⁻ = q_j * q_ω(ω_j⁻, Δt)``; with
    ``NOISE_INTEGRATED`` the step rotates with the mean rate ``ω_j + n_ω/2``. Every point that
    does not move e shares ``X_0``'s ``q_j`` (normalised once, at the end: the scale factors
    out of the product)."""
    q_mid = qnormalize_t(qmul_t(qc, from_chart_t(chart, saturate_t(chart, ebar))))
    for s in range(2 * _NDA + 1):
        j = _direction(s, nx)
        dw = (X[s, _CX + 3], X[s, _CX + 4], X[s, _CX + 5])  # ω_j − ω̄ + n_ω
        if noise_mode == NOISE_INTEGRATED:
            nw = dw if s > 0 and j >= nx else (0.0, 0.0, 0.0)  # n_ω
            wstep = (w[0] + (dw[0] - 0.5 * nw[0]), w[1] + (dw[1] - 0.5 * nw[1]),
                     w[2] + (dw[2] - 0.5 * nw[2]))
        else:
            wstep = (w[0] + dw[0], w[1] + dw[1], w[2] + dw[2])
        qj = q_mid
        if s > 0 and j < 3:
            qj = qmul_t(qc, from_chart_t(chart, saturate_t(
                chart, (X[s, _CX], X[s, _CX + 1], X[s, _CX + 2]))))
        qj = qnormalize_t(qmul_t(qj, q_omega_t(wstep, dt)))
        for i in range(4):
            X[s, _CQ + i] = qj[i]


@jit_inline
def _predict_measurements(X: np.ndarray, first: tuple, vref: tuple, use_h: bool, hm: tuple,
                          href: tuple, row_h: int) -> None:
    """Step 3, the predicted measurement of every point into its row of ``X``: the vectors
    ``y = R(q_j⁻)ᵀ v`` (``w̄_v = 0``; their spread is added to ``P_yy`` in
    :func:`_noise_and_innovation`) and the heading residual ``ψ(q_j⁻)``, unwrapped around the
    central point's. The gyro, ``ω_j⁻ + b_j``, and the zero rate, ``ω_j⁻``, are linear in the
    state: see :func:`_linear_covariances`."""
    for s in range(2 * _NDA + 1):
        qj = (X[s, _CQ], X[s, _CQ + 1], X[s, _CQ + 2], X[s, _CQ + 3])
        for k in range(2):
            if first[k] >= 0:
                y = rotate_inv_t(qj, vref[k])
                for i in range(3):
                    X[s, _CY + first[k] + i] = y[i]
        if use_h:
            psi, _ = heading_residual_t(rotmat_t(qj), hm, href)
            if s > 0:  # both in [−π, π]: one turn at most brings the difference into it
                d_psi = psi - X[0, _CY + row_h]
                if d_psi > np.pi:
                    psi -= 2.0 * np.pi
                elif d_psi < -np.pi:
                    psi += 2.0 * np.pi
            X[s, _CY + row_h] = psi


@jit_inline
def _align_hemispheres(X: np.ndarray, ns: int) -> None:
    """Step 4: ``q_j⁻ ← −q_j⁻`` where ``q_j⁻ · q_0⁻ < 0``."""
    for s in range(1, ns):
        dot = (X[s, _CQ] * X[0, _CQ] + X[s, _CQ + 1] * X[0, _CQ + 1]
               + X[s, _CQ + 2] * X[0, _CQ + 2] + X[s, _CQ + 3] * X[0, _CQ + 3])
        if dot < 0.0:
            for i in range(4):
                X[s, _CQ + i] = -X[s, _CQ + i]


@jit_inline
def _means(X: np.ndarray, ns: int, w_0: float, wj: float, w: tuple, b: tuple, row_g: int,
           row_z: int, use_w: bool, use_z: bool) -> tuple:
    """Step 5 into row ``ns`` of ``X``: ``Σ_j W_j q_j⁻`` and ``ȳ = Σ_j W_j y_j`` of the
    non-linear rows, the linear rows exactly, ``H x̄`` (``x̄⁻ = (0, ω̄, b̄)``; ``b̄`` also without
    a bias state). Returns ``q̄⁻ = Σ_j W_j q_j⁻ / ‖Σ_j W_j q_j⁻‖``. (The rate and bias means are
    ``ω̄``, ``b̄`` exactly: see :func:`_weights`.)"""
    _wmeans(X, ns, w_0, wj, _CQ, _CY + row_g)
    qs = (X[ns, _CQ], X[ns, _CQ + 1], X[ns, _CQ + 2], X[ns, _CQ + 3])
    nq = np.sqrt(qs[0] * qs[0] + qs[1] * qs[1] + qs[2] * qs[2] + qs[3] * qs[3])
    for i in range(3):
        if use_w:
            X[ns, _CY + row_g + i] = w[i] + b[i]
        if use_z:
            X[ns, _CY + row_z + i] = w[i]
    return (qs[0] / nq, qs[1] / nq, qs[2] / nq, qs[3] / nq)


@jit_inline
def _to_chart_of_mean(X: np.ndarray, ns: int, chart: int, qm: tuple, m_nl: int) -> None:
    """Step 6, the points in the chart of the new mean: ``e_j⁻ = φ(q̄⁻* * q_j⁻)`` over ``e_j``
    and ``Δy_j = y_j − ȳ`` over ``y_j`` for the ``m_nl`` non-linear rows."""
    for s in range(ns):
        e = to_chart_t(chart, qconj_mul_t(qm, (X[s, _CQ], X[s, _CQ + 1], X[s, _CQ + 2],
                                               X[s, _CQ + 3])))
        X[s, _CX], X[s, _CX + 1], X[s, _CX + 2] = e[0], e[1], e[2]
        for cc in range(_CY, _CY + m_nl):
            X[s, cc] -= X[ns, cc]


@jit_inline
def _sigma_covariances(X: np.ndarray, Pxx: np.ndarray, Pxy: np.ndarray, Pyy: np.ndarray, ns: int,
                       w_0: float, wj: float, nx: int, m_nl: int) -> None:
    """Step 6, the sums over the points (no subtraction of ``Σ W e_j``, §8 item 7) with
    ``Δx_j = (e_j⁻, Δz_j)``: ``P_ee = Σ_s W_s e_s e_sᵀ`` (lower triangle), ``P_ey``, ``P_yy``
    (lower triangle) over the ``m_nl`` non-linear rows, and ``P_ez``, ``P_zy`` by pairs
    (:func:`_weights`); rows ``1 … 9`` of ``X`` become ``a_{j+} − a_{j−}`` for ``a = e, y``."""
    nda = _NDA
    for i in range(3):
        _wsums(X, 0, ns, w_0, wj, _CX + i, _CX, i + 1, Pxx, i, 0)
        _wsums(X, 0, ns, w_0, wj, _CX + i, _CY, m_nl, Pxy, i, 0)
    for i in range(m_nl):
        _wsums(X, 0, ns, w_0, wj, _CY + i, _CY, i + 1, Pyy, i, 0)
    for s in range(1, nda + 1):
        for cc in range(_CX, _CX + 3):
            X[s, cc] -= X[s + nda, cc]
        for cc in range(_CY, _CY + m_nl):
            X[s, cc] -= X[s + nda, cc]
    for i in range(3):  # P_ez (upper block)
        _wsums(X, 1, nda, wj, wj, _CX + i, _CX + 3, nx - 3, Pxx, i, 3)
    for k in range(nx - 3):  # P_zy
        _wsums(X, 1, nda, wj, wj, _CX + 3 + k, _CY, m_nl, Pxy, 3 + k, 0)


@jit_inline
def _bias_columns(Pxx: np.ndarray, Pxy: np.ndarray, Pyy: np.ndarray, r0: int, m_nl: int,
                  Hb: tuple) -> None:
    """Step 6 for a vector reading with a part linear in the bias error (a low-passed
    accelerometer, docs/math.md §9.1): ``y = h(e) + H_b δb`` on rows ``r0 … r0+2`` adds
    ``H_b P_by + P_yb H_bᵀ + H_b P_bb H_bᵀ`` to their ``P_yy`` (``P_yb H_bᵀ`` to their cross
    terms with the other non-linear rows, lower triangle) and ``P_xb H_bᵀ`` to their columns of
    ``P_xy`` (the sums of a linear term are exact; ``ȳ`` is unchanged: ``E[δb] = 0``)."""
    for a in range(3):  # P_yy, lower triangle: the block, then the rows below it
        ra = r0 + a
        for a2 in range(a + 1):
            v = 0.0
            for k in range(3):
                v += Hb[a][k] * Pxy[6 + k, r0 + a2] + Pxy[6 + k, ra] * Hb[a2][k]
                for k2 in range(3):
                    v += Hb[a][k] * Pxx[6 + k, 6 + k2] * Hb[a2][k2]
            Pyy[ra, r0 + a2] += v
        for i in range(r0 + 3, m_nl):
            Pyy[i, ra] += (Pxy[6, i] * Hb[a][0] + Pxy[7, i] * Hb[a][1]
                           + Pxy[8, i] * Hb[a][2])
    for a in range(3):  # P_xy (after P_yy: that used the columns as they were)
        for i in range(9):
            Pxy[i, r0 + a] += (Pxx[i, 6] * Hb[a][0] + Pxx[i, 7] * Hb[a][1]
                               + Pxx[i, 8] * Hb[a][2])


@jit_inline
def _linear_covariances(P: np.ndarray, Pxx: np.ndarray, Pxy: np.ndarray, Pyy: np.ndarray,
                        nx: int, m: int, Qw: tuple, qa: float, rows: tuple, Hb: tuple) -> None:
    """Step 6, the exact parts: ``P_zz = P_zz + Q_ωᵃ`` (:func:`_weights`), ``P_xx`` completed
    from its lower triangle; the first vector's linear part in the bias (``Hb``, rows
    ``rows[0] …``: :func:`_bias_columns`); the gyro and zero-rate rows are linear in the state,
    ``y_j = H x_j``, so their sums are ``P_xy = P_xx Hᵀ`` and ``P_yy = H P_xy`` (the weighted
    sums are linear); ``P_yy`` completed from its lower triangle. ``rows``: the first rows of
    the first vector (−1: none), the gyro and the zero rate."""
    row_v0, row_g, row_z = rows
    for i in range(3, nx):  # P_zz = P_zz + Q_ωᵃ (lower triangle)
        for jj in range(3, i + 1):
            Pxx[i, jj] = P[i, jj] + (Qw[i - 3][jj - 3] * qa if i < 6 else 0.0)
    for i in range(3):
        for k in range(3, nx):
            Pxx[k, i] = Pxx[i, k]
    for i in range(nx):  # the loops above filled the lower triangle
        for jj in range(i):
            Pxx[jj, i] = Pxx[i, jj]
    if nx == 9 and row_v0 >= 0:
        _bias_columns(Pxx, Pxy, Pyy, row_v0, row_g, Hb)
    for r in range(row_g, m):  # linear rows: column r of P_xy is P_xx Hᵀ, row r of P_yy H P_xy
        k = r - row_g if r < row_z else r - row_z
        bias = r < row_z and nx == 9  # the gyro measures ω + b
        for i in range(nx):
            Pxy[i, r] = Pxx[i, 3 + k] + (Pxx[i, 6 + k] if bias else 0.0)
        for jj in range(r + 1):
            Pyy[r, jj] = Pxy[3 + k, jj] + (Pxy[6 + k, jj] if bias else 0.0)
    for i in range(m):
        for jj in range(i):
            Pyy[jj, i] = Pyy[i, jj]


@jit_inline
def _noise_and_innovation(X: np.ndarray, Pyy: np.ndarray, ns: int, first: tuple,
                          z: MukfMeasurement, rows: tuple) -> None:
    """Step 6's ``+ blockdiag(R_v, R_ω)`` in ``P_yy`` (and the disturbance sigma pairs of the
    vectors, summed exactly: ``R(q_0⁻)ᵀ Q_v R(q_0⁻)``, :func:`_weights`; the heading and
    zero-rate variances), and step 7's innovation ``y − ȳ`` into row ``ns + 1`` of ``X`` (the
    heading and zero-rate pseudo-measurements are 0); ``rows``: the first rows of the heading,
    gyro and zero-rate blocks."""
    row_h, row_g, row_z = rows
    vm, Rv, Qv = z.vm, z.Rv, z.Qv
    R0 = rotmat_t((X[0, _CQ], X[0, _CQ + 1], X[0, _CQ + 2], X[0, _CQ + 3]))
    for k in range(2):
        r0 = first[k]
        if r0 >= 0:
            QB = congruence33_t(transpose33_t(R0), Qv[k])  # R(q_0⁻)ᵀ Q_v R(q_0⁻)
            for i in range(3):
                for jj in range(3):
                    Pyy[r0 + i, r0 + jj] += Rv[k][i][jj] + QB[i][jj]
                X[ns + 1, _CY + r0 + i] = vm[k][i] - X[ns, _CY + r0 + i]
    if z.use_h:
        Pyy[row_h, row_h] += z.var_h
        X[ns + 1, _CY + row_h] = -X[ns, _CY + row_h]
    if z.use_w:
        for i in range(3):
            for jj in range(3):
                Pyy[row_g + i, row_g + jj] += z.Rw[i][jj]
            X[ns + 1, _CY + row_g + i] = z.wm[i] - X[ns, _CY + row_g + i]
    if z.use_z:
        for i in range(3):
            Pyy[row_z + i, row_z + i] += z.var_z
            X[ns + 1, _CY + row_z + i] = -X[ns, _CY + row_z + i]


@jit_inline
def _chi2_gate(X: np.ndarray, Pyy: np.ndarray, Ly: np.ndarray, KPyy: np.ndarray, ns: int,
               first: tuple, gates: tuple, gated: bool) -> tuple:
    """χ² gate per block (extension): ``rᵀ P_yy⁻¹ r = ‖L⁻¹ r‖²`` of its rows alone
    (``P_yy = L Lᵀ``; ``Ly`` and the first row of ``KPyy`` are free here). Returns
    ``(ok, nis, rejected)``: False if a block's ``P_yy`` is not positive definite, every
    block's value (0 unless ``gated``), and the bit mask of the blocks above their gate."""
    nis = (0.0, 0.0, 0.0, 0.0)
    rejected = 0
    for blk in range(4 if gated else 0):
        r0 = first[blk]
        if r0 < 0:
            continue
        nb = _BLOCK_SIZE[blk]
        for i in range(nb):
            for jj in range(nb):
                Ly[i, jj] = Pyy[r0 + i, r0 + jj]
        if not cholesky_into(Ly, Ly, 0, nb):
            return False, nis, rejected
        v = 0.0
        for i in range(nb):  # z = L⁻¹ r
            z = X[ns + 1, _CY + r0 + i]
            for k in range(i):
                z -= Ly[i, k] * KPyy[0, k]
            KPyy[0, i] = z / Ly[i, i]
            v += KPyy[0, i] * KPyy[0, i]
        nis = (v if blk == 0 else nis[0], v if blk == 1 else nis[1],
               v if blk == 2 else nis[2], v if blk == 3 else nis[3])
        if v > gates[blk]:
            rejected |= 1 << blk
    return True, nis, rejected


@jit_inline
def _keep_rows(X: np.ndarray, Pxy: np.ndarray, Pyy: np.ndarray, ns: int, nx: int, m: int,
               first: tuple, rejected: int) -> tuple:
    """The rows of the blocks that pass the gate, moved to the front in order (in place: a row
    or column only moves up) in the innovation, ``P_xy`` and ``P_yy``. Returns
    ``(ma, row_v0k, row_hk)``: the number of kept rows and the new first row of vector 0 and
    of the heading (−1 if absent or rejected)."""
    row_hk = first[B_HEADING] if not (rejected >> B_HEADING) & 1 else -1
    row_v0k = first[B_VEC0] if not (rejected >> B_VEC0) & 1 else -1
    ma = m
    if rejected:
        ma = 0
        for r in range(m):
            if not _row_kept(r, first, rejected):
                continue
            if r == row_hk:
                row_hk = ma
            if r == row_v0k:
                row_v0k = ma
            X[ns + 1, _CY + ma] = X[ns + 1, _CY + r]
            for i in range(nx):
                Pxy[i, ma] = Pxy[i, r]
            a = 0
            for cc in range(m):
                if _row_kept(cc, first, rejected):
                    Pyy[ma, a] = Pyy[r, cc]
                    a += 1
            ma += 1
    return ma, row_v0k, row_hk


@jit_inline
def _update(X: np.ndarray, scratch: tuple, ns: int, nx: int, ma: int, qm: tuple,
            v0: tuple, row_v0k: int, row_hk: int) -> bool:
    """Step 7 with the ``ma`` kept rows: ``K = P_xy P_yy⁻¹`` (:func:`_gain`), projected for the
    gravity rows and the heading row (``v0 = (tilt_v0, bias_gain_v0, bias_gain_h)``)
    (:func:`_gain_projection`), ``Δx = K (y − ȳ)`` into
    row ``ns + 1`` of ``X`` (:func:`_correction`), ``P ← P_xx − K P_yy Kᵀ`` in ``Pxx``
    (:func:`_covariance_update`); ``scratch`` as in :func:`mukf_step_t`. False if ``P_yy`` is
    not positive definite."""
    _, _, Pxy, Pyy, Ly, KPyy, Pxx, Kt = scratch
    if ma == 0:
        for i in range(nx):
            X[ns + 1, _CX + i] = 0.0  # Δx
        return True
    if not _gain(Pxy, Pyy, Ly, Kt, nx, ma):
        return False
    dK = KPyy  # (free here)
    np_, pc = _gain_projection(Kt, dK, nx, qm, v0, row_v0k, row_hk)
    _correction(X, Kt, dK, ns, nx, ma, np_, pc)
    _covariance_update(Pxx, Pxy, Pyy, Ly, Kt, dK, nx, ma, np_, pc)
    return True


@jit_inline
def _gain(Pxy: np.ndarray, Pyy: np.ndarray, Ly: np.ndarray, Kt: np.ndarray, nx: int,
          ma: int) -> bool:
    """Step 7: ``Kᵀ = P_yy⁻¹ P_xyᵀ`` (the optimal gain ``K₀``, transposed) by the Cholesky
    factor ``Ly`` of ``P_yy``. False if ``P_yy`` is not positive definite."""
    if not cholesky_into(Pyy, Ly, 0, ma):
        return False
    for a in range(ma):
        for i in range(nx):
            Kt[a, i] = Pxy[i, a]
    cho_solve_into(Ly, ma, Kt, nx)
    return True


@jit_inline
def _gain_projection(Kt: np.ndarray, dK: np.ndarray, nx: int, qm: tuple, v0: tuple,
                     row_v0k: int, row_hk: int) -> tuple:
    """Gain projections (extensions): ``K = K₀ + ΔK`` with ``K₀ = P_xy P_yy⁻¹``. ``ΔK`` has
    ``np_`` non-zero columns, kept dense in ``dK``; column ``t`` belongs to row ``pc[t]`` of the
    stacked measurement: the gravity rows (``v0 = (tilt_v0, bias_gain_v0, bias_gain_h)``: with
    ``tilt_v0`` every group's gain — attitude, rate, bias — kept off the world vertical; the
    bias's times ``bias_gain_v0``, the partial update of docs/math.md §9.1), then the heading
    row (every group's gain onto the vertical, the bias's times ``bias_gain_h``, §9.2).
    Returns ``(np_, pc)``."""
    tilt_v0, bias_gain, bias_gain_h = v0
    if nx < 9:
        bias_gain = 1.0
    u = up_in_body_t(qm)  # world vertical in the new chart's axes
    u0, u1, u2 = u
    pv = 1.0 if tilt_v0 else 0.0  # gravity: the vertical's share removed, or kept
    g0 = row_v0k if (tilt_v0 or bias_gain < 1.0) else -1
    ng = 3 if g0 >= 0 else 0
    np_ = ng + (1 if row_hk >= 0 else 0)
    pc = (g0, g0 + 1, g0 + 2, row_hk) if ng else (row_hk, row_hk, row_hk, row_hk)
    for t in range(np_):
        a = pc[t]
        if t < ng:  # gravity: every group's gain (attitude, rate, bias) off the vertical
            for g in range(nx // 3):  # K_g = γ_g (I − u uᵀ) K₀_g, γ = bias_gain for the bias
                ku = pv * (u0 * Kt[a, 3 * g] + u1 * Kt[a, 3 * g + 1] + u2 * Kt[a, 3 * g + 2])
                gm = bias_gain if g == 2 else 1.0
                for i in range(3):
                    dK[3 * g + i, t] = (gm - 1.0) * Kt[a, 3 * g + i] - gm * u[i] * ku
        else:  # heading: every group's gain (attitude, rate, bias) onto the vertical u, the
            for g in range(nx // 3):  # bias's times bias_gain_h (mag_bias_gain, docs/math.md §9.2)
                ku = u0 * Kt[a, 3 * g] + u1 * Kt[a, 3 * g + 1] + u2 * Kt[a, 3 * g + 2]
                if g == 2:
                    ku *= bias_gain_h
                dK[3 * g, t], dK[3 * g + 1, t], dK[3 * g + 2, t] = (
                    u0 * ku - Kt[a, 3 * g], u1 * ku - Kt[a, 3 * g + 1],
                    u2 * ku - Kt[a, 3 * g + 2])
    return np_, pc


@jit_inline
def _correction(X: np.ndarray, Kt: np.ndarray, dK: np.ndarray, ns: int, nx: int, ma: int,
                np_: int, pc: tuple) -> None:
    """Step 7: ``Δx = K (y − ȳ) = K₀ (y − ȳ) + ΔK (y − ȳ)`` into row ``ns + 1`` of ``X``."""
    for i in range(nx):
        s_ = 0.0
        for a in range(ma):
            s_ += Kt[a, i] * X[ns + 1, _CY + a]
        for t in range(np_):
            s_ += dK[i, t] * X[ns + 1, _CY + pc[t]]
        X[ns + 1, _CX + i] = s_


@jit_inline
def _covariance_update(Pxx: np.ndarray, Pxy: np.ndarray, Pyy: np.ndarray, Ly: np.ndarray,
                       Kt: np.ndarray, dK: np.ndarray, nx: int, ma: int, np_: int,
                       pc: tuple) -> None:
    """Step 7: ``P ← P_xx − K₀ P_yy K₀ᵀ = P_xx − P_xy K₀ᵀ`` in ``Pxx``; with projected columns
    the Joseph form for the gain ``K₀ + ΔK``, valid for any gain:
    ``P − K P_xyᵀ − P_xy Kᵀ + K P_yy Kᵀ = P − K₀ P_yy K₀ᵀ + ΔK P_yy ΔKᵀ`` (``K₀ P_yy = P_xy``).
    Exactly symmetric: every update writes the upper triangle, mirrored at the end."""
    for i in range(nx):
        for jj in range(i, nx):
            s_ = 0.0
            for a in range(ma):
                s_ += Pxy[i, a] * Kt[a, jj]
            Pxx[i, jj] -= s_
    if np_ > 0:
        for t in range(np_):  # Ly ← P_yy ΔKᵀ over the non-zero columns (Ly is free here)
            for i in range(nx):
                s_ = 0.0
                for t2 in range(np_):
                    s_ += Pyy[pc[t], pc[t2]] * dK[i, t2]
                Ly[t, i] = s_
        for i in range(nx):
            for jj in range(i, nx):
                s_ = 0.0
                for t in range(np_):
                    s_ += dK[i, t] * Ly[t, jj]
                Pxx[i, jj] += s_
    for i in range(nx):
        for jj in range(i + 1, nx):
            Pxx[jj, i] = Pxx[i, jj]


@jit_inline
def _new_state(X: np.ndarray, P: np.ndarray, Pxx: np.ndarray, ns: int, nx: int, chart: int,
               w: tuple, b: tuple) -> tuple:
    """Step 7, the new state in the chart of ``q̄⁻`` (which becomes ``q̄_c``: the chart update of
    §6): ``ē ← sat(ē⁺)``, ``ω̄ ← ω̄⁻ + Δω``, ``b̄ ← b̄ + Δb``, ``P ← P_xx``. Returns
    ``(ē, ω̄, b̄)``."""
    e = saturate_t(chart, (X[ns + 1, _CX], X[ns + 1, _CX + 1], X[ns + 1, _CX + 2]))
    w = (w[0] + X[ns + 1, _CX + 3], w[1] + X[ns + 1, _CX + 4], w[2] + X[ns + 1, _CX + 5])
    if nx == 9:
        b = (b[0] + X[ns + 1, _CX + 6], b[1] + X[ns + 1, _CX + 7], b[2] + X[ns + 1, _CX + 8])
    for i in range(nx):
        for jj in range(nx):
            P[i, jj] = Pxx[i, jj]
    return e, w, b
