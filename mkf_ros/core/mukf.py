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
from mkf_ros.core.charts import from_chart_at, saturate, to_chart_at
from mkf_ros.core.linalg import cho_solve, cholesky, mtv, symmetrize
from mkf_ros.core.quaternion import q_omega, qmul, rotmat


@jit
def mukf_step(
    chart: int, chart_update: bool, published_scaling: bool, w0: float,
    qc: np.ndarray, ebar: np.ndarray, w: np.ndarray, b: np.ndarray, P: np.ndarray, nx: int,
    dt: float, Qw: np.ndarray, Qb: np.ndarray,
    vm: np.ndarray, vref: np.ndarray, Rv: np.ndarray, Qv: np.ndarray, use_v: np.ndarray,
    wm: np.ndarray, use_w: bool, Rw: np.ndarray,
) -> bool:
    """One MUKF prediction + update over ``dt`` (§6 steps 0–7), in place.

    Measurement arguments as in :func:`mkf_ros.core.mekf.mekf_update`. ``published_scaling``
    selects the authors' ``ω + n_ω Δt`` with ``Q_ωᵃ = Q_ω`` (ω-variance grows by ``Q_ω Δt²``,
    reproduces the paper's figures) instead of the consistent ``ω + n_ω`` with
    ``Q_ωᵃ = Q_ω Δt`` (§8 item 3). Returns False (state untouched) if a factorisation fails.
    """
    # 0. reset variant: re-centre at the estimate, keep P
    if not chart_update:
        qc[:] = from_chart_at(chart, qc, ebar)
        ebar[:] = 0.0
    if nx == 9:  # bias random walk, added before the sigma points so that it reaches P_xy
        P[6:9, 6:9] += Qb * dt
    nvec = 0
    for k in range(use_v.shape[0]):
        if use_v[k]:
            nvec += 1
    m = 3 * nvec + (3 if use_w else 0)

    # 1. augment: x̄ᵃ = (ē, ω̄[, b̄], w̄_ω = 0, w̄_v = 0 …), Pᵃ = blockdiag(P, Q_ωᵃ, Q_v …)
    N = nx + 3 + 3 * nvec
    xa = np.zeros(N)
    xa[0:3] = ebar
    xa[3:6] = w
    if nx == 9:
        xa[6:9] = b
    Pa = np.zeros((N, N))
    Pa[:nx, :nx] = P[:nx, :nx]
    Pa[nx:nx + 3, nx:nx + 3] = Qw if published_scaling else Qw * dt
    col = nx + 3
    for k in range(use_v.shape[0]):
        if use_v[k]:
            Pa[col:col + 3, col:col + 3] = Qv[k]
            col += 3

    # 2. sigma points: X_0 = x̄ᵃ, X_{j}, X_{N+j} = x̄ᵃ ± c L[:, j],  c = √(N/(1 − W_0))
    L, ok = cholesky(Pa)
    if not ok:
        return False
    c = np.sqrt(N / (1.0 - w0))
    wj = (1.0 - w0) / (2.0 * N)
    ns = 2 * N + 1
    Qs = np.empty((ns, 4))
    Ws = np.empty((ns, 3))
    Bs = np.empty((ns, 3))
    Ys = np.empty((ns, m))
    wts = np.empty(ns)
    wts[:] = wj
    wts[0] = w0
    for s in range(ns):
        x = xa.copy()
        if s > 0:
            j = (s - 1) % N
            sign = 1.0 if s <= N else -1.0
            for i in range(N):
                x[i] += sign * c * L[i, j]
        # 3. to the manifold, propagate, predict the measurement
        q = from_chart_at(chart, qc, saturate(chart, x[0:3]))
        ws = x[3:6] + (x[nx:nx + 3] * dt if published_scaling else x[nx:nx + 3])
        bs = x[6:9] if nx == 9 else b
        q = qmul(q, q_omega(ws, dt))
        q = q / np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        Qs[s] = q
        Ws[s] = ws
        Bs[s] = bs
        R = rotmat(q)
        row = 0
        col = nx + 3
        for k in range(use_v.shape[0]):
            if use_v[k]:
                Ys[s, row:row + 3] = mtv(R, vref[k] + x[col:col + 3])  # R(q_j⁻)ᵀ (v + n_v,j)
                row += 3
                col += 3
        if use_w:
            Ys[s, row:row + 3] = ws + bs
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
    # 6. re-express in the chart of the new mean; covariances (no subtraction of Σ W e_j, §8.7)
    Pxx = np.zeros((nx, nx))
    Pxy = np.zeros((nx, m))
    Pyy = np.zeros((m, m))
    dx = np.empty(nx)
    dy = np.empty(m)
    for s in range(ns):
        dx[0:3] = to_chart_at(chart, qm, Qs[s])
        dx[3:6] = Ws[s] - wm_
        if nx == 9:
            dx[6:9] = Bs[s] - bm
        for i in range(m):
            dy[i] = Ys[s, i] - ym[i]
        ws_ = wts[s]
        for i in range(nx):
            for jj in range(nx):
                Pxx[i, jj] += ws_ * dx[i] * dx[jj]
            for jj in range(m):
                Pxy[i, jj] += ws_ * dx[i] * dy[jj]
        for i in range(m):
            for jj in range(m):
                Pyy[i, jj] += ws_ * dy[i] * dy[jj]
    row = 0
    for k in range(use_v.shape[0]):
        if use_v[k]:
            Pyy[row:row + 3, row:row + 3] += Rv[k]
            row += 3
    if use_w:
        Pyy[row:row + 3, row:row + 3] += Rw
    # 7. update
    upd = np.zeros(nx)
    if m > 0:
        Ly, ok = cholesky(Pyy)
        if not ok:
            return False
        Kt = cho_solve(Ly, Pxy.T.copy())  # Kᵀ = P_yy⁻¹ P_xyᵀ
        inn = np.empty(m)
        row = 0
        for k in range(use_v.shape[0]):
            if use_v[k]:
                inn[row:row + 3] = vm[k] - ym[row:row + 3]
                row += 3
        if use_w:
            inn[row:row + 3] = wm - ym[row:row + 3]
        upd = mtv(Kt, inn)
        # P ← P_xx − K P_yy Kᵀ = P_xx − P_xy Kᵀ
        for i in range(nx):
            for jj in range(nx):
                s_ = 0.0
                for p in range(m):
                    s_ += Pxy[i, p] * Kt[p, jj]
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

