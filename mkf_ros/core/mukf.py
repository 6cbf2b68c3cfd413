"""MUKF — Manifold Unscented Kalman Filter (spec §6; paper §3.2).

Carried state: the chart centre ``q̄_c`` (the predicted mean of the previous step), the mean ``ē``
of the distribution in that chart (not zero in general), ``ω̄``, the gyro bias ``b̄`` (extension)
and ``P`` about ``(ē, ω̄[, b̄])`` in the ``q̄_c``-chart. The estimate is ``q̂ = q̄_c * φ⁻¹(ē)``.

The chart update is implicit (§6, "How the MUKF does the chart update"): sigma points drawn in the
old chart are re-expressed exactly in the chart of the new mean. The reset variant (step 0)
re-centres at ``q̂`` and keeps ``P``.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.charts import from_chart_at, from_chart_at_t, from_chart_t, saturate_t, to_chart_t
from mkf_ros.core.linalg import cho_solve_into, cholesky_into, congruence33_t, transpose33_t
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
)

NOISE_CONSISTENT, NOISE_PUBLISHED, NOISE_INTEGRATED = 0, 1, 2
NOISE_MODES = ("consistent", "published", "integrated")


@jit_inline
def mukf_step(
    chart: int, chart_update: bool, noise_mode: int, w0: float,
    qc: np.ndarray, ebar: np.ndarray, w: np.ndarray, b: np.ndarray, P: np.ndarray, nx: int,
    dt: float, Qw: np.ndarray, Qb: np.ndarray,
    vm: np.ndarray, vref: np.ndarray, Rv: np.ndarray, Qv: np.ndarray, use_v: np.ndarray,
    wm: np.ndarray, use_w: bool, Rw: np.ndarray,
) -> bool:
    """One MUKF prediction + update over ``dt`` (§6 steps 0–7), in place.

    Measurement arguments as in :func:`mkf_ros.core.mekf.mekf_update`. ``noise_mode`` says how
    the angular-velocity noise enters (§8 item 3):

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
    none = qc[:0]  # no heading sensor (hm, href unused), no gates (nis unused)
    return _mukf_step(chart, chart_update, noise_mode, w0, qc, ebar, w, b, P, nx, dt, Qw, Qb,
                      vm, vref, Rv, Qv, use_v, wm, use_w, Rw, none, none, False, 0.0, False, 0.0,
                      none, none, False)


# measurement rows at most: two vectors, heading, gyro, zero rate
_M_MAX = 3 + 3 + 1 + 3 + 3
# sigma-point directions propagated by mukf_step_t: attitude (3), rate (3), rate noise (3)
_NDA = 9


@jit
def mukf_scratch(nx: int) -> tuple:
    """Scratch of :func:`mukf_step_t` for ``nx`` states (see its step 2): ``L``, the sigma-point
    table ``T``, ``P_xy``, ``P_yy``, its factor, ``K P_yy``, ``P_xx`` and ``Kᵀ``, each at its
    largest size (``m`` rows or columns at most ``_M_MAX``)."""
    nd = nx + 3
    return (np.empty((nd, nd)), np.empty((2 * _NDA + 3, _Y + _M_MAX)),
            np.empty((nx, _M_MAX)), np.empty((_M_MAX, _M_MAX)), np.empty((_M_MAX, _M_MAX)),
            np.empty((nx, _M_MAX)), np.empty((nx, nx)), np.empty((_M_MAX, nx)))


# measurement blocks of mukf_step_ext, in row order; index into its `gates` / `nis` arrays
B_VEC0, B_VEC1, B_HEADING, B_GYRO = 0, 1, 2, 3
_BLOCK_SIZE = (3, 3, 1, 3)
# columns of the sigma-point table of mukf_step_ext: state part x = (e, ω, b), quaternion q⁻,
# measurement y
_X, _Q, _Y = 0, 9, 13


@jit_inline
def _wmeans(T: np.ndarray, ns: int, w_0: float, wj: float, c0: int, c1: int) -> None:
    """``T[ns, c] = Σ_s W_s T[s, c]`` for columns ``c0 ≤ c < c1`` over the sigma points
    ``s < ns`` (``W_0 = w_0``, else ``wj``), accumulated from 0 in point order in registers,
    four columns at a time."""
    c = c0
    while c < c1:
        n = min(4, c1 - c)
        a0 = a1 = a2 = a3 = 0.0
        for s in range(ns):
            ws_ = w_0 if s == 0 else wj
            a0 += ws_ * T[s, c]
            if n > 1:
                a1 += ws_ * T[s, c + 1]
            if n > 2:
                a2 += ws_ * T[s, c + 2]
            if n > 3:
                a3 += ws_ * T[s, c + 3]
        T[ns, c] = a0
        if n > 1:
            T[ns, c + 1] = a1
        if n > 2:
            T[ns, c + 2] = a2
        if n > 3:
            T[ns, c + 3] = a3
        c += 4


@jit_inline
def _wsums(T: np.ndarray, s0: int, ns: int, w_0: float, wj: float, a: int, b: int, n: int,
           out: np.ndarray, r: int, oc: int) -> None:
    """``out[r, oc + k] = Σ_s W_s T[s, a] T[s, b + k]`` for ``k < n``, over the rows
    ``s0 ≤ s < s0 + ns`` (``W_{s0} = w_0``, else ``wj``), accumulated in registers four columns
    at a time, a last column in four partial sums (independent sums: the additions overlap
    instead of waiting for each other)."""
    k = 0
    s1 = s0 + ns
    while k + 4 <= n:
        wa = w_0 * T[s0, a]
        c0, c1 = wa * T[s0, b + k], wa * T[s0, b + k + 1]
        c2, c3 = wa * T[s0, b + k + 2], wa * T[s0, b + k + 3]
        for s in range(s0 + 1, s1):
            wa = wj * T[s, a]
            c0 += wa * T[s, b + k]
            c1 += wa * T[s, b + k + 1]
            c2 += wa * T[s, b + k + 2]
            c3 += wa * T[s, b + k + 3]
        out[r, oc + k], out[r, oc + k + 1], out[r, oc + k + 2], out[r, oc + k + 3] = c0, c1, c2, c3
        k += 4
    while k < n:  # one column: four sums over every fourth row, independent likewise
        c0 = (w_0 * T[s0, a]) * T[s0, b + k]
        c1 = c2 = c3 = 0.0
        s = s0 + 1
        while s + 4 <= s1:
            c0 += (wj * T[s, a]) * T[s, b + k]
            c1 += (wj * T[s + 1, a]) * T[s + 1, b + k]
            c2 += (wj * T[s + 2, a]) * T[s + 2, b + k]
            c3 += (wj * T[s + 3, a]) * T[s + 3, b + k]
            s += 4
        while s < s1:
            c0 += (wj * T[s, a]) * T[s, b + k]
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


@jit
def mukf_step_ext(
    chart: int, chart_update: bool, noise_mode: int, w0: float,
    qc: np.ndarray, ebar: np.ndarray, w: np.ndarray, b: np.ndarray, P: np.ndarray, nx: int,
    dt: float, Qw: np.ndarray, Qb: np.ndarray,
    vm: np.ndarray, vref: np.ndarray, Rv: np.ndarray, Qv: np.ndarray, use_v: np.ndarray,
    wm: np.ndarray, use_w: bool, Rw: np.ndarray,
    hm: np.ndarray, href: np.ndarray, use_h: bool, var_h: float,
    use_z: bool, var_z: float, gates: np.ndarray, nis: np.ndarray, tilt_v0: bool = False,
) -> bool:
    """:func:`mukf_step` with the real-sensor extensions: with ``tilt_v0`` the first vector
    sensor (gravity) corrects tilt only — its gain is kept off the world vertical for attitude,
    rate and bias, as in :func:`mkf_ros.core.mekf.mekf_vector_update`; a magnetometer for
    heading only
    (``hm``: body field, ``href``: horizontal world reference, the pseudo-measurement
    ``0 = ψ(q) + n`` of :func:`mkf_ros.core.mekf.mekf_heading_update`, the gain of attitude,
    rate and bias each projected onto the vertical, Joseph-form covariance), the zero-rate
    pseudo-measurement ``0 = ω + n`` of rest detection, and a χ² gate per block (vector 0,
    vector 1, heading, gyro; a block whose ``rᵀ P_yy⁻¹ r`` exceeds its gate is left out;
    ``nis`` receives every block's value). At most two vector sensors (``use_v`` of length 1
    or 2)."""
    return _mukf_step(chart, chart_update, noise_mode, w0, qc, ebar, w, b, P, nx, dt, Qw, Qb,
                      vm, vref, Rv, Qv, use_v, wm, use_w, Rw, hm, href, use_h, var_h, use_z, var_z,
                      gates, nis, tilt_v0)


@jit_inline
def _mukf_step(
    chart: int, chart_update: bool, noise_mode: int, w0: float,
    qc: np.ndarray, ebar: np.ndarray, w: np.ndarray, b: np.ndarray, P: np.ndarray, nx: int,
    dt: float, Qw: np.ndarray, Qb: np.ndarray,
    vm: np.ndarray, vref: np.ndarray, Rv: np.ndarray, Qv: np.ndarray, use_v: np.ndarray,
    wm: np.ndarray, use_w: bool, Rw: np.ndarray,
    hm: np.ndarray, href: np.ndarray, use_h: bool, var_h: float,
    use_z: bool, var_z: float, gates: np.ndarray, nis: np.ndarray, tilt_v0: bool,
) -> bool:
    """The body of :func:`mukf_step_ext` (inlined into it and into :func:`mukf_step`): the
    arrays as tuples for :func:`mukf_step_t`. With ``gates`` empty no block is gated and ``nis``
    is not written. (At most 30 arguments: numba cannot inline a call with more.)"""
    z3 = (0.0, 0.0, 0.0)
    z33 = (z3, z3, z3)
    nv = use_v.shape[0]
    v0, v1 = nv > 0 and bool(use_v[0]), nv > 1 and bool(use_v[1])
    gated = gates.shape[0] > 0
    inf4 = (np.inf, np.inf, np.inf, np.inf)
    ok, q, e, w_, b_, nis_ = mukf_step_t(
        chart, chart_update, noise_mode, w0, (t4(qc), t3(ebar), t3(w), t3(b)), P, nx, dt,
        t33(Qw), t33(Qb),
        (t3(vm[0]) if v0 else z3, t3(vm[1]) if v1 else z3),
        (t3(vref[0]) if v0 else z3, t3(vref[1]) if v1 else z3),
        (t33(Rv[0]) if v0 else z33, t33(Rv[1]) if v1 else z33),
        (t33(Qv[0]) if v0 else z33, t33(Qv[1]) if v1 else z33), (v0, v1),
        t3(wm) if use_w else z3, use_w, t33(Rw) if use_w else z33,
        t3(hm) if use_h else z3, t3(href) if use_h else z3, use_h, var_h, use_z, var_z,
        (gates[0], gates[1], gates[2], gates[3]) if gated else inf4, gated, tilt_v0,
        mukf_scratch(nx))
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
def mukf_step_t(
    chart: int, chart_update: bool, noise_mode: int, w0: float, x: tuple, P: np.ndarray,
    nx: int, dt: float, Qw: tuple, Qb: tuple,
    vm: tuple, vref: tuple, Rv: tuple, Qv: tuple, use_v: tuple,
    wm: tuple, use_w: bool, Rw: tuple,
    hm: tuple, href: tuple, use_h: bool, var_h: float,
    use_z: bool, var_z: float, gates: tuple, gated: bool, tilt_v0: bool, scratch: tuple,
) -> tuple:
    """:func:`mukf_step_ext` on tuples: ``x = (q̄_c, ē, ω̄, b̄)``; ``Qw``, ``Qb``, ``Rw`` and the
    two vector sensors' ``Rv[k]``, ``Qv[k]`` tuples of rows, ``vm``, ``vref`` pairs of 3-tuples,
    ``use_v`` a pair of flags; ``gates`` one per block, used only if ``gated``; ``scratch`` from
    :func:`mukf_scratch` for ``nx`` states. ``P`` is updated in place. Returns
    ``(ok, q̄_c, ē, ω̄, b̄, nis)``; if a factorisation fails, ``ok`` is False and the rest as far
    as computed (step 0's re-centring, the bias noise added to ``P``). Speed: no allocation,
    no views; every small input a tuple (no reference counting)."""
    qc_t, ebar, w, b = x
    nis = (0.0, 0.0, 0.0, 0.0)
    # 0. reset variant: re-centre at the estimate, keep P
    if not chart_update:
        qc_t = from_chart_at_t(chart, qc_t, ebar)
        ebar = (0.0, 0.0, 0.0)
    if nx == 9:  # bias random walk, added before the sigma points so that it reaches P_xy
        for i in range(3):
            for j in range(3):
                P[6 + i, 6 + j] += Qb[i][j] * dt
    published = noise_mode == NOISE_PUBLISHED
    if noise_mode == NOISE_INTEGRATED:  # Brownian-bridge part of the attitude increment
        k3 = dt * dt * dt / 12.0
        for i in range(3):
            for j in range(3):
                P[i, j] += Qw[i][j] * k3
    # measurement rows, in this order: vectors (3 each), heading (1), gyro (3), zero rate (3);
    # first[blk] is the first row of block blk (B_VEC0 … B_GYRO), −1 if absent
    v0, v1 = use_v
    nvec = (1 if v0 else 0) + (1 if v1 else 0)
    row_h = 3 * nvec
    row_g = row_h + (1 if use_h else 0)
    row_z = row_g + (3 if use_w else 0)
    m = row_z + (3 if use_z else 0)
    m_nl = row_g  # the rows that are not linear in the state: vectors and heading
    first = (0 if v0 else -1, (3 if v0 else 0) if v1 else -1, row_h if use_h else -1,
             row_g if use_w else -1)

    # 1. augment: x̄ᵃ = (ē, ω̄[, b̄], w̄_ω = 0, w̄_v = 0 …), Pᵃ = blockdiag(P, Q_ωᵃ, Q_v …), N = dim
    # 2. sigma points X_0 = x̄ᵃ, X_j, X_{N+j} = x̄ᵃ ± c L[:, j], c = √(N/(1 − W_0)),
    #    W_j = (1 − W_0)/(2N), L the lower Cholesky factor of Pᵃ (block diagonal like Pᵃ).
    #    Exact reductions (the sums of steps 5–6 are linear in the points; 2 W_j c² = 1):
    #    * a pair along a Q_v column leaves q, ω, b equal to X_0's and moves y_k by
    #      ±R(q_0⁻)ᵀ c L_v[:, j]: it adds 2 W_j to X_0's weight in every sum and
    #      R(q_0⁻)ᵀ Q_v R(q_0⁻) to the k-th block of P_yy;
    #    * a pair along a bias column (L is lower triangular: it moves b only) leaves q⁻ and
    #      every non-linear y equal to X_0's: it adds 2 W_j to X_0's weight, nothing to the sums
    #      with e or y (its two b offsets cancel) and its share of L Lᵀ to P_bb (below);
    #    * z = (ω⁻, b) is linear in the points: z̄⁻ = (ω̄, b̄) and P_zz = P_zz + Q_ωᵃ exactly,
    #      and a sum Σ_s W_s a_s Δz_s (Δz_0 = 0, Δz_{j−} = −Δz_{j+}) is
    #      W_j Σ_j (a_{j+} − a_{j−}) Δz_{j+}.
    #    So 1 + 2·9 points are propagated (directions: attitude, rate, rate noise).
    N = nx + 3 + 3 * nvec
    nda = _NDA  # propagated directions: L's columns 0–5 (attitude, rate), nx … nx + 2 (noise)
    ns = 2 * nda + 1
    # Scratch. numba has no stack arrays, and every allocation, every view and every array
    # argument of a call costs reference counting (atomic operations) that outweighs a small
    # matrix's arithmetic; so: eight arrays given by the caller (mukf_scratch), used in their
    # leading blocks, no views; tables by column.
    # L: lower Cholesky factor of the propagated part of Pᵃ, blockdiag(P, Q_ωᵃ).
    # T: row s for sigma point s: e_s in columns _X…_X+2 (later e_s⁻, see step 6), the offset
    #    Δz_s of (ω_s⁻, b_s) in _X+3…_X+nx−1, q_s⁻ in _Q…_Q+3, y_s in _Y…; row ns: the means of
    #    q⁻ and y; row ns + 1: the update Δx and the innovation y − ȳ.
    # P_xy, P_yy, its factor Ly, K P_yy, Kᵀ: m ≤ _M_MAX rows or columns, the first m used.
    L, T, Pxy, Pyy, Ly, KPyy, Pxx, Kt = scratch
    if not cholesky_into(P, L, 0, nx):
        return False, qc_t, ebar, w, b, nis
    # Q_ωᵃ = Q_ω·qa, the covariance of the rate increment n_ω = ω⁻ − ω: Q_ω Δt (consistent,
    # integrated) or Q_ω Δt² (published: the authors' Q_ω with n Δt, the same spread)
    qa = dt * dt if published else max(dt, 0.0)
    if qa > 0.0:
        for i in range(3):
            for j in range(3):
                L[nx + i, nx + j] = Qw[i][j] * qa
        if not cholesky_into(L, L, nx, 3):
            return False, qc_t, ebar, w, b, nis
    else:  # a zero-length step (e.g. a magnetometer fused at the IMU's time): no rate noise,
        L[nx:, nx:] = 0.0  # those sigma points coincide with the central one
    c = np.sqrt(N / (1.0 - w0))
    wj = (1.0 - w0) / (2.0 * N)
    w_0 = w0 + 2.0 * (3.0 * nvec + (nx - 6)) * wj  # X_0's weight, with the folded pairs'
    # X_0 on the manifold; also every point that does not move e
    q_mid = qnormalize_t(qmul_t(qc_t, from_chart_t(chart, saturate_t(chart, ebar))))
    for s in range(ns):
        d = s - 1 if s <= nda else s - 1 - nda
        j = d if d < 6 else d + nx - 6  # direction: column of L
        step = c if s <= nda else -c
        for i in range(3):
            T[s, _X + i] = ebar[i]
        for i in range(3, nx):
            T[s, _X + i] = 0.0
        nw0 = nw1 = nw2 = 0.0
        if s > 0:
            if j < nx:  # a state direction (L is lower triangular: rows j … nx − 1)
                for i in range(j, nx):
                    T[s, _X + i] += step * L[i, j]
            else:  # a rate-noise direction
                nw0, nw1, nw2 = step * L[nx, j], step * L[nx + 1, j], step * L[nx + 2, j]
                T[s, _X + 3], T[s, _X + 4], T[s, _X + 5] = nw0, nw1, nw2
        # 3. to the manifold, propagate, predict the measurement
        #    q_j = q̄_c * φ⁻¹(sat(e_j)),  ω_j⁻ = ω_j + n_ω,  q_j⁻ = q_j * q_ω(ω_j⁻, Δt)
        if noise_mode == NOISE_INTEGRATED:  # rotate with the mean rate ω_j + n_ω/2 over the step
            wstep = (w[0] + (T[s, _X + 3] - 0.5 * nw0), w[1] + (T[s, _X + 4] - 0.5 * nw1),
                     w[2] + (T[s, _X + 5] - 0.5 * nw2))
        else:
            wstep = (w[0] + T[s, _X + 3], w[1] + T[s, _X + 4], w[2] + T[s, _X + 5])
        qj = q_mid
        if s > 0 and j < 3:  # (normalised once, below: the scale factors out of the product)
            qj = qmul_t(qc_t, from_chart_t(chart, saturate_t(
                chart, (T[s, _X], T[s, _X + 1], T[s, _X + 2]))))
        qj = qnormalize_t(qmul_t(qj, q_omega_t(wstep, dt)))
        for i in range(4):
            T[s, _Q + i] = qj[i]
        for k in range(2):
            if first[k] >= 0:  # y = R(q_j⁻)ᵀ v  (w̄_v = 0; its spread is added to P_yy below)
                y = rotate_inv_t(qj, vref[k])
                for i in range(3):
                    T[s, _Y + first[k] + i] = y[i]
        if use_h:  # heading residual ψ(q_j⁻), unwrapped around the central point's
            psi, _ = heading_residual_t(rotmat_t(qj), hm, href)
            if s > 0:  # both in [−π, π]: one turn at most brings the difference into it
                d_psi = psi - T[0, _Y + row_h]
                if d_psi > np.pi:
                    psi -= 2.0 * np.pi
                elif d_psi < -np.pi:
                    psi += 2.0 * np.pi
            T[s, _Y + row_h] = psi
        # (the gyro, ω_j⁻ + b_j, and the zero rate, ω_j⁻, are linear: see step 6)
    # 4. hemisphere alignment with the propagated sigma point 0
    for s in range(1, ns):
        dot = (T[s, _Q] * T[0, _Q] + T[s, _Q + 1] * T[0, _Q + 1] + T[s, _Q + 2] * T[0, _Q + 2]
               + T[s, _Q + 3] * T[0, _Q + 3])
        if dot < 0.0:
            for i in range(4):
                T[s, _Q + i] = -T[s, _Q + i]
    # 5. means: normalised weighted quaternion sum and measurement; the rate and bias exactly
    _wmeans(T, ns, w_0, wj, _Q, _Y + m_nl)  # q, the non-linear rows of y
    qs = (T[ns, _Q], T[ns, _Q + 1], T[ns, _Q + 2], T[ns, _Q + 3])
    nq = np.sqrt(qs[0] * qs[0] + qs[1] * qs[1] + qs[2] * qs[2] + qs[3] * qs[3])
    qm = (qs[0] / nq, qs[1] / nq, qs[2] / nq, qs[3] / nq)
    for i in range(3):  # the linear rows: H x̄ (x̄⁻ = (0, ω̄, b̄); b̄ also without bias state)
        if use_w:
            T[ns, _Y + row_g + i] = w[i] + b[i]
        if use_z:
            T[ns, _Y + row_z + i] = w[i]
    # 6. re-express in the chart of the new mean; covariances (no subtraction of Σ W e_j, §8.7)
    #    Δx_j = (e_j⁻, Δz_j), Δy_j = y_j − ȳ, e_j⁻ written over e_j, Δy_j over y_j.
    #    Exact reduction: the gyro and zero-rate rows are linear in the state, y_j = H x_j, so
    #    their sums are P_xy = P_xx Hᵀ and P_yy = H P_xy (the weighted sums are linear); only
    #    the vector and heading rows (the first m_nl) are summed over the points.
    for s in range(ns):
        e = to_chart_t(chart, qconj_mul_t(qm, (T[s, _Q], T[s, _Q + 1], T[s, _Q + 2],
                                               T[s, _Q + 3])))
        T[s, _X], T[s, _X + 1], T[s, _X + 2] = e[0], e[1], e[2]
        for cc in range(_Y, _Y + m_nl):
            T[s, cc] -= T[ns, cc]
    # P_ee = Σ_s W_s e_s e_sᵀ (lower triangle), P_ey = Σ_s W_s e_s Δy_sᵀ, P_yy likewise
    for i in range(3):
        _wsums(T, 0, ns, w_0, wj, _X + i, _X, i + 1, Pxx, i, 0)
        _wsums(T, 0, ns, w_0, wj, _X + i, _Y, m_nl, Pxy, i, 0)
    for i in range(m_nl):
        _wsums(T, 0, ns, w_0, wj, _Y + i, _Y, i + 1, Pyy, i, 0)
    # the sums with Δz by pairs: rows 1 … nda ← a_{j+} − a_{j−} for a = e, y
    for s in range(1, nda + 1):
        for cc in range(_X, _X + 3):
            T[s, cc] -= T[s + nda, cc]
        for cc in range(_Y, _Y + m_nl):
            T[s, cc] -= T[s + nda, cc]
    for i in range(3):  # P_ez (upper block)
        _wsums(T, 1, nda, wj, wj, _X + i, _X + 3, nx - 3, Pxx, i, 3)
    for k in range(nx - 3):  # P_zy
        _wsums(T, 1, nda, wj, wj, _X + 3 + k, _Y, m_nl, Pxy, 3 + k, 0)
    for i in range(3, nx):  # P_zz = P_zz + Q_ωᵃ (lower triangle)
        for jj in range(3, i + 1):
            Pxx[i, jj] = P[i, jj] + (Qw[i - 3][jj - 3] * qa if i < 6 else 0.0)
    for i in range(3):
        for k in range(3, nx):
            Pxx[k, i] = Pxx[i, k]
    for i in range(nx):  # the loops above filled the lower triangle
        for jj in range(i):
            Pxx[jj, i] = Pxx[i, jj]
    for r in range(m_nl, m):  # linear rows: column r of P_xy is P_xx Hᵀ, row r of P_yy H P_xy
        k = r - row_g if r < row_z else r - row_z
        bias = r < row_z and nx == 9  # the gyro measures ω + b
        for i in range(nx):
            Pxy[i, r] = Pxx[i, 3 + k] + (Pxx[i, 6 + k] if bias else 0.0)
        for jj in range(r + 1):
            Pyy[r, jj] = Pxy[3 + k, jj] + (Pxy[6 + k, jj] if bias else 0.0)
    for i in range(m):
        for jj in range(i):
            Pyy[jj, i] = Pyy[i, jj]
    # measurement noise and innovations
    R0 = rotmat_t((T[0, _Q], T[0, _Q + 1], T[0, _Q + 2], T[0, _Q + 3]))
    for k in range(2):
        r0 = first[k]
        if r0 >= 0:  # R_v + R(q_0⁻)ᵀ Q_v R(q_0⁻): the disturbance sigma pairs, summed exactly
            QB = congruence33_t(transpose33_t(R0), Qv[k])  # R(q_0⁻)ᵀ Q_v R(q_0⁻)
            for i in range(3):
                for jj in range(3):
                    Pyy[r0 + i, r0 + jj] += Rv[k][i][jj] + QB[i][jj]
                T[ns + 1, _Y + r0 + i] = vm[k][i] - T[ns, _Y + r0 + i]
    if use_h:
        Pyy[row_h, row_h] += var_h
        T[ns + 1, _Y + row_h] = -T[ns, _Y + row_h]
    if use_w:
        for i in range(3):
            for jj in range(3):
                Pyy[row_g + i, row_g + jj] += Rw[i][jj]
            T[ns + 1, _Y + row_g + i] = wm[i] - T[ns, _Y + row_g + i]
    if use_z:
        for i in range(3):
            Pyy[row_z + i, row_z + i] += var_z
            T[ns + 1, _Y + row_z + i] = -T[ns, _Y + row_z + i]
    # χ² gate per block: rᵀ P_yy⁻¹ r = ‖L⁻¹ r‖² of its rows alone (P_yy = L Lᵀ; Ly and the
    # first row of KPyy are free here)
    rejected = 0  # bit mask of blocks
    for blk in range(4 if gated else 0):
        r0 = first[blk]
        if r0 < 0:
            continue
        nb = _BLOCK_SIZE[blk]
        for i in range(nb):
            for jj in range(nb):
                Ly[i, jj] = Pyy[r0 + i, r0 + jj]
        if not cholesky_into(Ly, Ly, 0, nb):
            return False, qc_t, ebar, w, b, nis
        v = 0.0
        for i in range(nb):  # z = L⁻¹ r
            z = T[ns + 1, _Y + r0 + i]
            for k in range(i):
                z -= Ly[i, k] * KPyy[0, k]
            KPyy[0, i] = z / Ly[i, i]
            v += KPyy[0, i] * KPyy[0, i]
        nis = (v if blk == 0 else nis[0], v if blk == 1 else nis[1],
               v if blk == 2 else nis[2], v if blk == 3 else nis[3])
        if v > gates[blk]:
            rejected |= 1 << blk
    # the rows that pass, moved to the front in order (in place: a row or column only moves up)
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
            T[ns + 1, _Y + ma] = T[ns + 1, _Y + r]
            for i in range(nx):
                Pxy[i, ma] = Pxy[i, r]
            a = 0
            for cc in range(m):
                if _row_kept(cc, first, rejected):
                    Pyy[ma, a] = Pyy[r, cc]
                    a += 1
            ma += 1
    # 7. update with the kept rows: K = P_xy P_yy⁻¹, Δx = K (y − ȳ)
    for i in range(nx):
        T[ns + 1, _X + i] = 0.0  # Δx
    if ma > 0:
        if not cholesky_into(Pyy, Ly, 0, ma):
            return False, qc_t, ebar, w, b, nis
        for a in range(ma):
            for i in range(nx):
                Kt[a, i] = Pxy[i, a]
        cho_solve_into(Ly, ma, Kt)  # Kᵀ = P_yy⁻¹ P_xyᵀ
        Rm = rotmat_t(qm)
        u0, u1, u2 = Rm[2][0], Rm[2][1], Rm[2][2]  # world vertical in the new chart's axes
        dK = KPyy
        # gain projections: K = K₀ + ΔK with K₀ = P_xy P_yy⁻¹ the optimal gain. ΔK has np_
        # non-zero columns, kept dense in dK (KPyy's rows, free here); column t belongs to row
        # pc[t] of the stacked measurement: the gravity rows (tilt only), then the heading row
        g0 = row_v0k if tilt_v0 else -1
        ng = 3 if g0 >= 0 else 0
        np_ = ng + (1 if row_hk >= 0 else 0)
        pc = (g0, g0 + 1, g0 + 2, row_hk) if ng else (row_hk, row_hk, row_hk, row_hk)
        for t in range(np_):
            a = pc[t]
            if t < ng:  # gravity: keep every group's gain (attitude, rate, bias) off the vertical
                for g in range(nx // 3):
                    ku = u0 * Kt[a, 3 * g] + u1 * Kt[a, 3 * g + 1] + u2 * Kt[a, 3 * g + 2]
                    dK[3 * g, t], dK[3 * g + 1, t], dK[3 * g + 2, t] = -u0 * ku, -u1 * ku, -u2 * ku
            else:  # heading: every group's gain (attitude, rate, bias) onto the vertical u
                for g in range(nx // 3):
                    ku = u0 * Kt[a, 3 * g] + u1 * Kt[a, 3 * g + 1] + u2 * Kt[a, 3 * g + 2]
                    dK[3 * g, t], dK[3 * g + 1, t], dK[3 * g + 2, t] = (
                        u0 * ku - Kt[a, 3 * g], u1 * ku - Kt[a, 3 * g + 1],
                        u2 * ku - Kt[a, 3 * g + 2])
        for i in range(nx):  # Δx = K (y − ȳ) = K₀ (y − ȳ) + ΔK (y − ȳ)
            s_ = 0.0
            for a in range(ma):
                s_ += Kt[a, i] * T[ns + 1, _Y + a]
            for t in range(np_):
                s_ += dK[i, t] * T[ns + 1, _Y + pc[t]]
            T[ns + 1, _X + i] = s_
        # P ← P_xx − K₀ P_yy K₀ᵀ = P_xx − P_xy K₀ᵀ (symmetric: the upper triangle, mirrored)
        for i in range(nx):
            for jj in range(i, nx):
                s_ = 0.0
                for a in range(ma):
                    s_ += Pxy[i, a] * Kt[a, jj]
                Pxx[i, jj] -= s_
        if np_ > 0:  # Joseph form for the gain K₀ + ΔK, valid for any gain:
            # P − K P_xyᵀ − P_xy Kᵀ + K P_yy Kᵀ = P − K₀ P_yy K₀ᵀ + ΔK P_yy ΔKᵀ  (K₀ P_yy = P_xy)
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
    # (P_xx is exactly symmetric: every update above wrote one triangle and mirrored it)
    e = saturate_t(chart, (T[ns + 1, _X], T[ns + 1, _X + 1], T[ns + 1, _X + 2]))
    w = (w[0] + T[ns + 1, _X + 3], w[1] + T[ns + 1, _X + 4], w[2] + T[ns + 1, _X + 5])
    if nx == 9:
        b = (b[0] + T[ns + 1, _X + 6], b[1] + T[ns + 1, _X + 7], b[2] + T[ns + 1, _X + 8])
    for i in range(nx):
        for jj in range(nx):
            P[i, jj] = Pxx[i, jj]
    return True, qm, e, w, b, nis


@jit
def mukf_estimate(chart: int, qc: np.ndarray, ebar: np.ndarray) -> np.ndarray:
    """The point estimate ``q̂ = q̄_c * φ⁻¹(ē)`` (§2.4)."""
    return from_chart_at(chart, qc, ebar)

