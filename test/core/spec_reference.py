"""Literal NumPy transcriptions of docs/math.md §5 (MEKF) and §6 (MUKF) update equations.

Slow and independent of the kernels (no shared code except chart maps, which have their own
known-answer tests): the kernels are checked against these on random inputs.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core.charts import CHART_NAMES, CHARTS
from mkf_ros.core.quaternion import q_omega, qconj, qmul, rotmat, skew


def normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q)


def mekf_predict_ref(q, w, P, nx, dt, Qw, Qb):
    dq = q_omega(w, dt)
    q = normalize(qmul(q, dq))
    F = np.eye(nx)
    F[0:3, 0:3] = rotmat(dq).T
    F[0:3, 3:6] = dt * np.eye(3)
    Qh = np.zeros((nx, nx))
    Qh[0:3, 0:3] = Qw * dt**3 / 3
    Qh[0:3, 3:6] = -Qw * dt**2 / 2
    Qh[3:6, 0:3] = -Qw * dt**2 / 2
    Qh[3:6, 3:6] = Qw * dt
    if nx == 9:
        Qh[6:9, 6:9] = Qb * dt
    return q, F @ (P + Qh) @ F.T


def mekf_update_ref(chart, cu, q, w, b, P, nx, vms, vrefs, Rvs, Qvs, wm, Rw):
    """Joint update with the full stacked H and S (§5), one move to the manifold."""
    R = rotmat(q)
    Hs, ys, ybars, blocks = [], [], [], []
    for vm, v, Rv, Qv in zip(vms, vrefs, Rvs, Qvs, strict=True):
        vbar = R.T @ v
        H = np.zeros((3, nx))
        H[:, 0:3] = skew(vbar)
        Hs.append(H)
        ys.append(vm)
        ybars.append(vbar)
        blocks.append(R.T @ Qv @ R + Rv)
    if wm is not None:
        H = np.zeros((3, nx))
        H[:, 3:6] = np.eye(3)
        if nx == 9:
            H[:, 6:9] = np.eye(3)
        Hs.append(H)
        ys.append(wm)
        ybars.append(w + b)
        blocks.append(Rw)
    H = np.vstack(Hs)
    Rm = np.zeros((len(blocks) * 3,) * 2)
    for k, B in enumerate(blocks):
        Rm[3 * k:3 * k + 3, 3 * k:3 * k + 3] = B
    S = H @ P @ H.T + Rm
    K = P @ H.T @ np.linalg.inv(S)
    dx = K @ (np.concatenate(ys) - np.concatenate(ybars))
    P = (np.eye(nx) - K @ H) @ P
    c = CHARTS[CHART_NAMES[chart]]
    d = c.from_chart(c.saturate(dx[0:3]))
    q = normalize(qmul(q, d))
    w = w + dx[3:6]
    b = b + dx[6:9] if nx == 9 else b
    if cu:
        T = np.eye(nx)
        T[0:3, 0:3] = c.t_matrix(d)
        P = T @ P @ T.T
    return q, w, b, 0.5 * (P + P.T)


def heading_psi_ref(q, m_body, ref):
    """The heading residual ψ(q) of the magnetometer-for-heading extension, from the rotation
    matrix: the angle about the world vertical that brings the horizontal part of ``R(q) m``
    onto the horizontal reference ``ref``."""
    mw = rotmat(q) @ m_body
    return float(np.arctan2(mw[0] * ref[1] - mw[1] * ref[0], mw[0] * ref[0] + mw[1] * ref[1]))


def group_projector(u, nx, onto):
    """``blockdiag(u uᵀ)`` (``onto``) or ``blockdiag(I − u uᵀ)`` over the 3-state groups
    (attitude, rate[, bias]): the projection of each group's gain onto / off the vertical."""
    p = np.outer(u, u) if onto else np.eye(3) - np.outer(u, u)
    return np.kron(np.eye(nx // 3), p)


def mekf_vector_update_ref(P, nx, dx, q, vm, vref, Rv, Qv, tilt_only):
    """One vector sensor of §5 as a Kalman update in the chart at ``q̄⁻``, literally:
    ``v̄ = R(q̄⁻)ᵀ v``, ``H = [[v̄]×, 0]``, noise ``R(q̄⁻)ᵀ Q_v R(q̄⁻) + R_v``, innovation
    ``v_m − v̄ − H Δx`` (``Δx`` from the earlier blocks), ``K₀ = P Hᵀ S⁻¹``. With ``tilt_only``
    (extension, gravity) the gain of each group (attitude, rate[, bias]) is projected off the
    world vertical ``u = R(q̄⁻)ᵀ ẑ``, ``K = blockdiag(I − u uᵀ) K₀``, and P follows the Joseph
    form ``(I − K H) P (I − K H)ᵀ + K R Kᵀ``. Returns ``(P, Δx, NIS)``."""
    R = rotmat(q)
    vbar = R.T @ vref
    H = np.zeros((3, nx))
    H[:, 0:3] = skew(vbar)
    Rn = R.T @ Qv @ R + Rv
    S = H @ P @ H.T + Rn
    K = P @ H.T @ np.linalg.inv(S)
    r = vm - vbar - H @ dx
    if tilt_only:
        K = group_projector(R.T @ np.array([0.0, 0.0, 1.0]), nx, onto=False) @ K
    A = np.eye(nx) - K @ H
    return A @ P @ A.T + K @ Rn @ K.T, dx + K @ r, float(r @ np.linalg.solve(S, r))


def mekf_heading_update_ref(P, nx, dx, q, m_body, ref, var, bias_gain=1.0):
    """The magnetometer for heading only (extension), literally: measurement ``0 = ψ(q) + n``
    linearised at ``q = q̄ * δ(e)`` with ``R(q̄ δ) m ≈ R(q̄)(m + e × m)``:
    ``H = [−(d × m), 0]``, ``d = R(q̄)ᵀ (m_y, −m_x, 0)/(m_x² + m_y²)`` with ``(m_x, m_y)`` the
    horizontal part of ``R(q̄) m``; ``S = H P Hᵀ + var``, ``K₀ = P Hᵀ/S``, the gain of each
    group projected onto the vertical, ``K = blockdiag(u uᵀ) K₀``, ``u = R(q̄)ᵀ ẑ``; the
    innovation ``−ψ(q̄) − H Δx``; the bias rows of ``K`` times ``bias_gain`` (docs/math.md
    §9.2, ``mag_bias_gain``); P in Joseph form. Returns ``(P, Δx, NIS)``."""
    R = rotmat(q)
    mw = R @ m_body
    d = R.T @ np.array([mw[1], -mw[0], 0.0]) / (mw[0] ** 2 + mw[1] ** 2)
    H = np.zeros((1, nx))
    H[0, 0:3] = -np.cross(d, m_body)
    S = float((H @ P @ H.T)[0, 0]) + var
    K = P @ H.T / S
    K = group_projector(R.T @ np.array([0.0, 0.0, 1.0]), nx, onto=True) @ K
    K[6:nx] *= bias_gain
    r = -heading_psi_ref(q, m_body, ref) - float((H @ dx)[0])
    A = np.eye(nx) - K @ H
    return A @ P @ A.T + var * K @ K.T, dx + K[:, 0] * r, r * r / S


def mukf_step_ref(chart, cu, published, w0, qc, ebar, w, b, P, nx, dt, Qw, Qb, vms, vrefs,
                  Rvs, Qvs, wm, Rw, z_var=None, drop=(), nis_out=None, heading=None,
                  tilt_v0=False, internals=None, heading_bias_gain=1.0):
    """§6 steps 0–7 literally: full augmentation, 2N+1 sigma points, columns of L.

    ``published`` is the noise mode: 0 (False) consistent, 1 (True) published, 2 integrated
    (rotation with the mean rate ω + n/2, plus Q_ω Δt³/12 on the attitude). Extensions of
    ``mukf_step_ext``: ``heading = (m_body, ref, var)`` adds the magnetometer-for-heading row
    ``0 = ψ(q) + n`` after the vectors (ψ of every sigma point unwrapped around the central
    point's), its gain, for each group, projected onto the world vertical u = R(q̄⁻)ᵀ ẑ of the
    new mean; ``tilt_v0`` projects the first vector's gain off u; with either, P is the Joseph
    form ``P_xx − K P_xyᵀ − P_xy Kᵀ + K P_yy Kᵀ`` for the projected gain K. ``z_var`` adds the
    zero-rate pseudo-measurement ``0 = ω + n``; ``heading_bias_gain`` scales the bias rows of
    the heading's projected gain (docs/math.md §9.2); ``drop`` leaves out measurement blocks
    (indices in row order: the vectors, the heading, the gyro, the zero rate) after the sums,
    as the χ² gate does; ``nis_out`` (a list) receives ``rᵀ P_yy⁻¹ r`` of every block, alone;
    ``internals`` (a dict) receives the optimal gain ``K0``, ``Pyy``, ``Pxy``, ``Pxx`` and the
    gain ``K`` used (over the kept rows)."""
    mode = int(published)
    c = CHARTS[CHART_NAMES[chart]]
    if not cu:
        qc = normalize(qmul(qc, c.from_chart(ebar)))
        ebar = np.zeros(3)
    P = P.copy()
    if nx == 9:
        P[6:9, 6:9] += Qb * dt
    if mode == 2:
        P[0:3, 0:3] += Qw * dt**3 / 12
    nv = len(vms)
    N = nx + 3 + 3 * nv
    xa = np.zeros(N)
    xa[0:3] = ebar
    xa[3:6] = w
    if nx == 9:
        xa[6:9] = b
    Pa = np.zeros((N, N))
    Pa[:nx, :nx] = P
    Pa[nx:nx + 3, nx:nx + 3] = Qw if mode == 1 else Qw * dt
    for k in range(nv):
        i = nx + 3 + 3 * k
        Pa[i:i + 3, i:i + 3] = Qvs[k]
    L = np.linalg.cholesky(Pa)
    cc = np.sqrt(N / (1 - w0))
    W = np.full(2 * N + 1, (1 - w0) / (2 * N))
    W[0] = w0
    X = [xa] + [xa + cc * L[:, j] for j in range(N)] + [xa - cc * L[:, j] for j in range(N)]
    qs, ws, bs, ys = [], [], [], []
    for x in X:
        qj = normalize(qmul(qc, c.from_chart(c.saturate(x[0:3]))))
        nw = x[nx:nx + 3] * (dt if mode == 1 else 1.0)
        wj = x[3:6] + nw
        bj = x[6:9] if nx == 9 else b
        qj = normalize(qmul(qj, q_omega(x[3:6] + nw / 2 if mode == 2 else wj, dt)))
        y = [rotmat(qj).T @ (vrefs[k] + x[nx + 3 + 3 * k:nx + 6 + 3 * k]) for k in range(nv)]
        if heading is not None:
            psi = heading_psi_ref(qj, heading[0], heading[1])
            if ys:  # unwrapped around the central point's
                psi0 = ys[0][3 * nv]
                psi = psi0 + float(np.angle(np.exp(1j * (psi - psi0))))
            y.append(np.array([psi]))
        if wm is not None:
            y.append(wj + bj)
        if z_var is not None:
            y.append(wj)
        qs.append(qj)
        ws.append(wj)
        bs.append(bj)
        ys.append(np.concatenate(y) if y else np.zeros(0))
    qs = [q if q @ qs[0] >= 0 else -q for q in qs]
    qm = normalize(sum(Wi * q for Wi, q in zip(W, qs, strict=True)))
    wmean = sum(Wi * x for Wi, x in zip(W, ws, strict=True))
    bmean = sum(Wi * x for Wi, x in zip(W, bs, strict=True))
    ymean = sum(Wi * y for Wi, y in zip(W, ys, strict=True))
    dX = []
    for q, wj, bj in zip(qs, ws, bs, strict=True):
        e = c.to_chart(qmul(qconj(qm), q))
        dX.append(np.concatenate([e, wj - wmean, bj - bmean][: 3 if nx == 9 else 2]))
    dY = [y - ymean for y in ys]
    Pxx = sum(Wi * np.outer(a, a) for Wi, a in zip(W, dX, strict=True))
    Pxy = sum(Wi * np.outer(a, d) for Wi, a, d in zip(W, dX, dY, strict=True))
    Pyy = sum(Wi * np.outer(d, d) for Wi, d in zip(W, dY, strict=True))
    m = ymean.size
    # measurement blocks in row order: (rows, noise, measured value)
    blocks, r0 = [], 0
    for k in range(nv):
        blocks.append((slice(r0, r0 + 3), Rvs[k], vms[k]))
        r0 += 3
    if heading is not None:
        blocks.append((slice(r0, r0 + 1), np.array([[heading[2]]]), np.zeros(1)))
        r0 += 1
    if wm is not None:
        blocks.append((slice(r0, r0 + 3), Rw, wm))
        r0 += 3
    if z_var is not None:
        blocks.append((slice(r0, r0 + 3), z_var * np.eye(3), np.zeros(3)))
        r0 += 3
    assert r0 == m
    Rm = np.zeros((m, m))
    for rows, Rb, _ in blocks:
        Rm[rows, rows] = Rb
    Pyy = Pyy + Rm
    yv = np.concatenate([yb for _, _, yb in blocks]) if blocks else np.zeros(0)
    r = yv - ymean
    keep = np.ones(m, dtype=bool)
    for blk, (rows, _, _) in enumerate(blocks):
        if nis_out is not None:
            nis_out.append(r[rows] @ np.linalg.solve(Pyy[rows, rows], r[rows]))
        if blk in drop:
            keep[rows] = False
    # gain projections (extensions), per kept row
    u = rotmat(qm).T @ np.array([0.0, 0.0, 1.0])
    proj = [None] * m
    if tilt_v0 and nv > 0:
        for i in range(3):
            proj[i] = group_projector(u, nx, onto=False)
    if heading is not None:
        proj[3 * nv] = group_projector(u, nx, onto=True)
        proj[3 * nv][6:nx] *= heading_bias_gain
    Pxy, Pyy, r = Pxy[:, keep], Pyy[np.ix_(keep, keep)], r[keep]
    proj = [p for p, k in zip(proj, keep, strict=True) if k]
    K0 = Pxy @ np.linalg.inv(Pyy) if keep.any() else np.zeros((nx, 0))
    K = K0.copy()
    for j, p in enumerate(proj):
        if p is not None:
            K[:, j] = p @ K0[:, j]
    dx = K @ r
    if any(p is not None for p in proj):  # Joseph form, valid for any gain
        Pn = Pxx - K @ Pxy.T - Pxy @ K.T + K @ Pyy @ K.T
    else:
        Pn = Pxx - K @ Pyy @ K.T
    if internals is not None:
        internals.update(K0=K0, K=K, Pyy=Pyy, Pxy=Pxy, Pxx=Pxx, u=u)
    e = c.saturate(dx[0:3])
    b_new = bmean + dx[6:9] if nx == 9 else b
    return qm, e, wmean + dx[3:6], b_new, 0.5 * (Pn + Pn.T)
