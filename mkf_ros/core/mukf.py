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

from mkf_ros.core._jit import jit
from mkf_ros.core.charts import from_chart_at, from_chart_t, saturate, saturate_t, to_chart_t
from mkf_ros.core.linalg import cho_solve, cholesky, mtv, symmetrize
from mkf_ros.core.mekf import heading_residual
from mkf_ros.core.quaternion import (
    q_omega_t,
    qconj_mul_t,
    qmul_t,
    qnormalize_t,
    rotate_inv_t,
    rotmat,
    t3,
    t4,
)

NOISE_CONSISTENT, NOISE_PUBLISHED, NOISE_INTEGRATED = 0, 1, 2
NOISE_MODES = ("consistent", "published", "integrated")


@jit
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
    gates = np.full(4, np.inf)
    nis = np.zeros(4)
    return mukf_step_ext(chart, chart_update, noise_mode, w0, qc, ebar, w, b, P, nx, dt, Qw, Qb,
                         vm, vref, Rv, Qv, use_v, wm, use_w, Rw, np.zeros(3), np.zeros(3), False,
                         0.0, False, 0.0, gates, nis)


# measurement blocks of mukf_step_ext, in row order; index into its `gates` / `nis` arrays
B_VEC0, B_VEC1, B_HEADING, B_GYRO = 0, 1, 2, 3


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
    ``0 = ψ(q) + n`` of :func:`mkf_ros.core.mekf.mekf_heading_update`, its gain projected onto
    the vertical, Joseph-form covariance), the zero-rate pseudo-measurement ``0 = ω + n`` of rest
    detection, and a χ² gate per block (vector 0, vector 1, heading, gyro; a block whose
    ``rᵀ P_yy⁻¹ r`` exceeds its gate is left out; ``nis`` receives every block's value)."""
    # 0. reset variant: re-centre at the estimate, keep P
    if not chart_update:
        qc[:] = from_chart_at(chart, qc, ebar)
        ebar[:] = 0.0
    if nx == 9:  # bias random walk, added before the sigma points so that it reaches P_xy
        P[6:9, 6:9] += Qb * dt
    published = noise_mode == NOISE_PUBLISHED
    if noise_mode == NOISE_INTEGRATED:  # Brownian-bridge part of the attitude increment
        P[0:3, 0:3] += Qw * (dt * dt * dt / 12.0)
    nvec = 0
    for k in range(use_v.shape[0]):
        if use_v[k]:
            nvec += 1
    # measurement rows: vectors (3 each), heading (1), gyro (3), zero rate (3)
    m = 3 * nvec + (1 if use_h else 0) + (3 if use_w else 0) + (3 if use_z else 0)

    # 1. augment: x̄ᵃ = (ē, ω̄[, b̄], w̄_ω = 0, w̄_v = 0 …), Pᵃ = blockdiag(P, Q_ωᵃ, Q_v …), N = dim
    # 2. sigma points X_0 = x̄ᵃ, X_j, X_{N+j} = x̄ᵃ ± c L[:, j], c = √(N/(1 − W_0)),
    #    W_j = (1 − W_0)/(2N), L the lower Cholesky factor of Pᵃ (block diagonal like Pᵃ).
    #    Exact reduction: a pair along a Q_v column leaves q, ω, b equal to X_0's and moves y_k by
    #    ±R(q_0⁻)ᵀ c L_v[:, j]; summed over the pairs (2 W_j c² = 1) it adds W_j·2 to X_0's weight
    #    in every mean and covariance and R(q_0⁻)ᵀ Q_v R(q_0⁻) to the k-th block of P_yy. So only
    #    the 1 + 2(nx + 3) state and rate-noise points are propagated.
    N = nx + 3 + 3 * nvec
    L, ok = cholesky(P[:nx, :nx].copy())
    if not ok:
        return False
    if dt > 0.0 or published:
        Lw, ok = cholesky(Qw if published else Qw * dt)
        if not ok:
            return False
    else:  # a zero-length step (e.g. a magnetometer fused at the IMU's time): no rate noise,
        Lw = np.zeros((3, 3))  # those sigma points coincide with the central one
    c = np.sqrt(N / (1.0 - w0))
    wj = (1.0 - w0) / (2.0 * N)
    nd = nx + 3  # propagated directions: state and rate noise
    ns = 2 * nd + 1
    Qs = np.empty((ns, 4))
    Ws = np.empty((ns, 3))
    Bs = np.empty((ns, 3))
    Ys = np.empty((ns, m))
    wts = np.empty(ns)
    wts[:] = wj
    wts[0] = w0 + 2.0 * 3.0 * nvec * wj
    x = np.empty(nx)
    nw = np.empty(3)
    wstep = np.empty(3)
    qc_t = t4(qc)
    for s in range(ns):
        for i in range(nx):
            x[i] = ebar[i] if i < 3 else (w[i - 3] if i < 6 else b[i - 6])
        nw[:] = 0.0
        if s > 0:
            j = (s - 1) % nd
            step = c if s <= nd else -c
            if j < nx:
                for i in range(j, nx):
                    x[i] += step * L[i, j]
            else:
                for i in range(j - nx, 3):
                    nw[i] = step * Lw[i, j - nx]
        # 3. to the manifold, propagate, predict the measurement
        #    q_j = q̄_c * φ⁻¹(sat(e_j)),  ω_j⁻ = ω_j + n_ω (·Δt),  q_j⁻ = q_j * q_ω(ω_j⁻, Δt)
        for i in range(3):
            n_w = nw[i] * dt if published else nw[i]
            Ws[s, i] = x[3 + i] + n_w  # ω_j⁻, the rate at the end of the step
            wstep[i] = x[3 + i] + 0.5 * n_w if noise_mode == NOISE_INTEGRATED else Ws[s, i]
            Bs[s, i] = x[6 + i] if nx == 9 else b[i]
        qj = qmul_t(qc_t, from_chart_t(chart, saturate_t(chart, (x[0], x[1], x[2]))))
        qj = qnormalize_t(qmul_t(qnormalize_t(qj), q_omega_t(t3(wstep), dt)))
        for i in range(4):
            Qs[s, i] = qj[i]
        row = 0
        for k in range(use_v.shape[0]):
            if use_v[k]:  # y = R(q_j⁻)ᵀ v  (w̄_v = 0; its spread is added to P_yy below)
                y = rotate_inv_t(qj, t3(vref[k]))
                for i in range(3):
                    Ys[s, row + i] = y[i]
                row += 3
        if use_h:  # heading residual ψ(q_j⁻), unwrapped around the central point's
            psi, _ = heading_residual(rotmat(Qs[s]), hm, href)
            if s > 0:
                psi = Ys[0, row] + np.arctan2(np.sin(psi - Ys[0, row]), np.cos(psi - Ys[0, row]))
            Ys[s, row] = psi
            row += 1
        if use_w:  # gyro: ω_j⁻ + b_j
            for i in range(3):
                Ys[s, row + i] = Ws[s, i] + Bs[s, i]
            row += 3
        if use_z:  # rest: ω_j⁻
            for i in range(3):
                Ys[s, row + i] = Ws[s, i]
    # 4. hemisphere alignment with the propagated sigma point 0
    for s in range(1, ns):
        dot = Qs[s, 0] * Qs[0, 0] + Qs[s, 1] * Qs[0, 1] + Qs[s, 2] * Qs[0, 2] + Qs[s, 3] * Qs[0, 3]
        if dot < 0.0:
            Qs[s] = -Qs[s]
    # 5. means: normalised weighted quaternion sum, weighted rate, bias and measurement
    qm = np.zeros(4)
    wm_ = np.zeros(3)
    bm = np.zeros(3)
    ym = np.zeros(m)
    for s in range(ns):
        qm += wts[s] * Qs[s]
        wm_ += wts[s] * Ws[s]
        bm += wts[s] * Bs[s]
        ym += wts[s] * Ys[s]
    qm /= np.sqrt(qm[0] * qm[0] + qm[1] * qm[1] + qm[2] * qm[2] + qm[3] * qm[3])
    qm_t = t4(qm)
    # 6. re-express in the chart of the new mean; covariances (no subtraction of Σ W e_j, §8.7)
    Pxx = np.zeros((nx, nx))
    Pxy = np.zeros((nx, m))
    Pyy = np.zeros((m, m))
    dx = np.empty(nx)
    dy = np.empty(m)
    for s in range(ns):
        e = to_chart_t(chart, qconj_mul_t(qm_t, t4(Qs[s])))
        dx[0], dx[1], dx[2] = e[0], e[1], e[2]
        dx[3:6] = Ws[s] - wm_
        if nx == 9:
            dx[6:9] = Bs[s] - bm
        for i in range(m):
            dy[i] = Ys[s, i] - ym[i]
        ws_ = wts[s]
        for i in range(nx):
            wdx = ws_ * dx[i]
            for jj in range(i + 1):
                Pxx[i, jj] += wdx * dx[jj]
            for jj in range(m):
                Pxy[i, jj] += wdx * dy[jj]
        for i in range(m):
            wdy = ws_ * dy[i]
            for jj in range(i + 1):
                Pyy[i, jj] += wdy * dy[jj]
    for i in range(nx):  # the loops above filled the lower triangles
        for jj in range(i):
            Pxx[jj, i] = Pxx[i, jj]
    for i in range(m):
        for jj in range(i):
            Pyy[jj, i] = Pyy[i, jj]
    # measurement noise, innovations and the row range of every block
    R0 = rotmat(Qs[0])
    inn = np.empty(m)
    first = np.full(4, -1)
    size = np.zeros(4, dtype=np.int64)
    row = 0
    for k in range(use_v.shape[0]):
        if use_v[k]:  # R_v + R(q_0⁻)ᵀ Q_v R(q_0⁻): the disturbance sigma pairs, summed exactly
            for i in range(3):
                for jj in range(3):
                    qb = 0.0
                    for a in range(3):
                        for bb in range(3):
                            qb += R0[a, i] * Qv[k, a, bb] * R0[bb, jj]
                    Pyy[row + i, row + jj] += Rv[k, i, jj] + qb
                inn[row + i] = vm[k, i] - ym[row + i]
            first[B_VEC0 + k], size[B_VEC0 + k] = row, 3  # by slot: 0 = first sensor
            row += 3
    if use_h:
        Pyy[row, row] += var_h
        inn[row] = -ym[row]
        first[B_HEADING], size[B_HEADING] = row, 1
        row += 1
    if use_w:
        for i in range(3):
            for jj in range(3):
                Pyy[row + i, row + jj] += Rw[i, jj]
            inn[row + i] = wm[i] - ym[row + i]
        first[B_GYRO], size[B_GYRO] = row, 3
        row += 3
    if use_z:
        for i in range(3):
            Pyy[row + i, row + i] += var_z
            inn[row + i] = -ym[row + i]
        row += 3
    # χ² gate per block: keep the rows of the blocks that pass
    keep = np.ones(m, dtype=np.bool_)
    for blk in range(4):
        if first[blk] < 0:
            continue
        r0, nb = first[blk], size[blk]
        Lb, okb = cholesky(Pyy[r0:r0 + nb, r0:r0 + nb].copy())
        if not okb:
            return False
        z = cho_solve(Lb, inn[r0:r0 + nb].copy().reshape(nb, 1))
        v = 0.0
        for i in range(nb):
            v += inn[r0 + i] * z[i, 0]
        nis[blk] = v
        if v > gates[blk]:
            for i in range(nb):
                keep[r0 + i] = False
    idx = np.nonzero(keep)[0]
    ma = idx.size
    # 7. update with the kept rows: K = P_xy P_yy⁻¹, Δx = K (y − ȳ)
    upd = np.zeros(nx)
    if ma > 0:
        Pyy_a = np.empty((ma, ma))
        Pxy_a = np.empty((nx, ma))
        inn_a = np.empty(ma)
        for a in range(ma):
            inn_a[a] = inn[idx[a]]
            for bb in range(ma):
                Pyy_a[a, bb] = Pyy[idx[a], idx[bb]]
            for i in range(nx):
                Pxy_a[i, a] = Pxy[i, idx[a]]
        Ly, ok = cholesky(Pyy_a)
        if not ok:
            return False
        Kt = cho_solve(Ly, Pxy_a.T.copy())  # Kᵀ = P_yy⁻¹ P_xyᵀ
        Rm = rotmat(qm)
        u0, u1, u2 = Rm[2, 0], Rm[2, 1], Rm[2, 2]  # world vertical in the new chart's axes
        projected = False
        for a in range(ma):
            if use_h and idx[a] == first[B_HEADING]:
                # heading turns about the vertical only: project its attitude gain onto u
                ku = u0 * Kt[a, 0] + u1 * Kt[a, 1] + u2 * Kt[a, 2]
                Kt[a, 0], Kt[a, 1], Kt[a, 2] = u0 * ku, u1 * ku, u2 * ku
                projected = True
            elif tilt_v0 and first[B_VEC0] >= 0 and first[B_VEC0] <= idx[a] < first[B_VEC0] + 3:
                # gravity: keep every group's gain (attitude, rate, bias) off the vertical
                for g in range(nx // 3):
                    ku = u0 * Kt[a, 3 * g] + u1 * Kt[a, 3 * g + 1] + u2 * Kt[a, 3 * g + 2]
                    Kt[a, 3 * g] -= u0 * ku
                    Kt[a, 3 * g + 1] -= u1 * ku
                    Kt[a, 3 * g + 2] -= u2 * ku
                projected = True
        upd = mtv(Kt, inn_a)
        if projected:  # Joseph form, valid for any gain: P − K P_xyᵀ − P_xy Kᵀ + K P_yy Kᵀ
            KPyy = np.zeros((nx, ma))
            for i in range(nx):
                for a in range(ma):
                    s_ = 0.0
                    for bb in range(ma):
                        s_ += Kt[bb, i] * Pyy_a[bb, a]
                    KPyy[i, a] = s_
            for i in range(nx):
                for jj in range(nx):
                    s_ = 0.0
                    for a in range(ma):
                        s_ += (-Kt[a, i] * Pxy_a[jj, a] - Pxy_a[i, a] * Kt[a, jj]
                               + KPyy[i, a] * Kt[a, jj])
                    Pxx[i, jj] += s_
        else:  # P ← P_xx − K P_yy Kᵀ = P_xx − P_xy Kᵀ
            for i in range(nx):
                for jj in range(nx):
                    s_ = 0.0
                    for a in range(ma):
                        s_ += Pxy_a[i, a] * Kt[a, jj]
                    Pxx[i, jj] -= s_
    symmetrize(Pxx)
    qc[:] = qm
    ebar[:] = saturate(chart, upd[0:3])
    w[:] = wm_ + upd[3:6]
    if nx == 9:
        b[:] = bm + upd[6:9]
    P[:nx, :nx] = Pxx
    return True


@jit
def mukf_estimate(chart: int, qc: np.ndarray, ebar: np.ndarray) -> np.ndarray:
    """The point estimate ``q̂ = q̄_c * φ⁻¹(ē)`` (§2.4)."""
    return from_chart_at(chart, qc, ebar)

