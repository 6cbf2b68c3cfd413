"""MEKF — Manifold Extended Kalman Filter (spec §5; paper §3.1, App. B/C).

State: the chart centre ``q̄`` (which is also the estimate), the body rate ``ω̄`` and, as an
extension, the gyro bias ``b̄``; covariance ``P`` of the error state ``(e, ω[, b])`` in the chart
centred at ``q̄``, with mean zero. ``nx`` is 6 (paper) or 9 (with gyro bias).

Measurements are stacked (§8 item 15): any number of vector sensors
``v_m = R(q)ᵀ (v + w_v) + r_v`` (eq. 24) plus, optionally, the gyro ``ω_m = ω + b + r_ω`` (eq. 23).
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit
from mkf_ros.core.charts import from_chart, saturate, t_matrix
from mkf_ros.core.linalg import cho_solve, cholesky, congruence, mm, mmt, mtv, mv, symmetrize
from mkf_ros.core.quaternion import q_omega, qmul, qnormalize, rotmat, skew


@jit
def mekf_predict(
    qc: np.ndarray, w: np.ndarray, P: np.ndarray, nx: int, dt: float, Qw: np.ndarray,
    Qb: np.ndarray,
) -> None:
    """Prediction over ``dt`` (§5 "Prediction"), in place.

    ``q̄⁻ = q̄ * q_ω(ω̄, Δt)``; ``P⁻ = F (P + Q̂) Fᵀ`` with ``F = [[R(Δq)ᵀ, Δt I], [0, I]]`` and
    ``Q̂ = [[Q_ω Δt³/3, −Q_ω Δt²/2], [−Q_ω Δt²/2, Q_ω Δt]]`` (the authors' form, §8 item 2). The bias
    block gets ``Q_b Δt`` (random walk, extension).
    """
    dq = q_omega(w, dt)
    qc[:] = qnormalize(qmul(qc, dq))
    dt2 = dt * dt
    Pn = np.empty((nx, nx))
    Pn[:, :] = P[:nx, :nx]
    for i in range(3):  # P + Q̂
        for j in range(3):
            qw = Qw[i, j]
            Pn[i, j] += qw * dt2 * dt / 3.0
            Pn[i, 3 + j] -= 0.5 * qw * dt2
            Pn[3 + i, j] -= 0.5 * qw * dt2
            Pn[3 + i, 3 + j] += qw * dt
            if nx == 9:
                Pn[6 + i, 6 + j] += Qb[i, j] * dt
    # F (P + Q̂) Fᵀ by blocks: F only mixes the attitude rows, e ← A e + Δt ω with A = R(Δq)ᵀ
    A = rotmat(dq).T.copy()
    M = np.empty((3, nx))  # rows 0:3 of F (P + Q̂)
    for i in range(3):
        for j in range(nx):
            M[i, j] = (A[i, 0] * Pn[0, j] + A[i, 1] * Pn[1, j] + A[i, 2] * Pn[2, j]
                       + dt * Pn[3 + i, j])
    Pn[0:3, :] = M
    for i in range(nx):  # columns 0:3 of (F (P + Q̂)) Fᵀ
        c0 = Pn[i, 0] * A[0, 0] + Pn[i, 1] * A[0, 1] + Pn[i, 2] * A[0, 2] + dt * Pn[i, 3]
        c1 = Pn[i, 0] * A[1, 0] + Pn[i, 1] * A[1, 1] + Pn[i, 2] * A[1, 2] + dt * Pn[i, 4]
        c2 = Pn[i, 0] * A[2, 0] + Pn[i, 1] * A[2, 1] + Pn[i, 2] * A[2, 2] + dt * Pn[i, 5]
        Pn[i, 0], Pn[i, 1], Pn[i, 2] = c0, c1, c2
    P[:nx, :nx] = Pn


@jit
def mekf_update(
    chart: int, chart_update: bool, qc: np.ndarray, w: np.ndarray, b: np.ndarray, P: np.ndarray,
    nx: int, vm: np.ndarray, vref: np.ndarray, Rv: np.ndarray, Qv: np.ndarray, use_v: np.ndarray,
    wm: np.ndarray, use_w: bool, Rw: np.ndarray,
) -> bool:
    """Kalman update in the chart centred at ``q̄⁻`` and the move back to the manifold (§5).

    Vector sensor ``k`` (used when ``use_v[k]``) has reading ``vm[k]`` (body), reference
    ``vref[k]`` (world), noise ``Rv[k]`` and external disturbance ``Qv[k]`` (world frame, §8
    item 4). Returns False (state untouched) if the innovation covariance is not positive
    definite.
    """
    nvec = 0
    for k in range(use_v.shape[0]):
        if use_v[k]:
            nvec += 1
    m = 3 * nvec + (3 if use_w else 0)
    if m == 0:
        return True
    Rt = rotmat(qc).T.copy()
    H = np.zeros((m, nx))
    r = np.empty(m)  # innovation y − ȳ
    S = np.zeros((m, m))
    row = 0
    for k in range(use_v.shape[0]):
        if not use_v[k]:
            continue
        vbar = mv(Rt, vref[k])  # v̄ = R(q̄⁻)ᵀ v
        H[row:row + 3, 0:3] = skew(vbar)  # ∂v_m/∂e = [v̄]×  (§4.3)
        for i in range(3):
            r[row + i] = vm[k, i] - vbar[i]
        # R(q̄⁻)ᵀ Q_v R(q̄⁻) + R_v
        S[row:row + 3, row:row + 3] = congruence(Rt, Qv[k]) + Rv[k]
        row += 3
    if use_w:
        for i in range(3):
            H[row + i, 3 + i] = 1.0
            if nx == 9:
                H[row + i, 6 + i] = 1.0
            r[row + i] = wm[i] - w[i] - b[i]
        S[row:row + 3, row:row + 3] = Rw
    Pn = np.empty((nx, nx))
    Pn[:, :] = P[:nx, :nx]
    HP = mm(H, Pn)  # H P⁻ = (P⁻ Hᵀ)ᵀ; mm skips H's many zeros
    S += mmt(HP, H)  # S = H P⁻ Hᵀ + R
    L, ok = cholesky(S)
    if not ok:
        return False
    Kt = cho_solve(L, HP)  # Kᵀ = S⁻¹ H P⁻  (K = P⁻ Hᵀ S⁻¹)
    dx = mtv(Kt, r)  # Δx = K (y − ȳ)
    Pn -= mtm(Kt, HP)  # P' = (I − K H) P⁻ = P⁻ − K (H P⁻)
    # multiplicative update (§5): ē ← sat(ē), δ̄ = φ⁻¹(ē), q̄⁺ = q̄⁻ * δ̄
    e = saturate(chart, dx[0:3])
    d = from_chart(chart, e)
    qc[:] = qnormalize(qmul(qc, d))
    for i in range(3):
        w[i] += dx[3 + i]
        if nx == 9:
            b[i] += dx[6 + i]
    if chart_update:  # P⁺ = T̃ P' T̃ᵀ, T̃ = blockdiag(T(δ̄), I)  (eq. 47b)
        transport_covariance(Pn, t_matrix(chart, d))
    symmetrize(Pn)
    P[:nx, :nx] = Pn
    return True


@jit
def mtm(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``aᵀ @ b`` for small dense matrices."""
    k, n = a.shape
    m = b.shape[1]
    c = np.zeros((n, m))
    for p in range(k):
        for i in range(n):
            api = a[p, i]
            for j in range(m):
                c[i, j] += api * b[p, j]
    return c


@jit
def transport_covariance(P: np.ndarray, T: np.ndarray) -> None:
    """Move ``P`` to a new chart centre (§3.2): ``P_ee ← T P_ee Tᵀ``, ``P_e* ← T P_e*``."""
    P[0:3, :] = mm(T, P[0:3, :])
    P[:, 0:3] = mmt(P[:, 0:3], T)
