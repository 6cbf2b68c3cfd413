"""Literal NumPy transcriptions of the spec's §5 (MEKF) and §6 (MUKF) update equations.

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


def mukf_step_ref(chart, cu, published, w0, qc, ebar, w, b, P, nx, dt, Qw, Qb, vms, vrefs,
                  Rvs, Qvs, wm, Rw, z_var=None, drop=(), nis_out=None):
    """§6 steps 0–7 literally: full augmentation, 2N+1 sigma points, columns of L.

    ``published`` is the noise mode: 0 (False) consistent, 1 (True) published, 2 integrated
    (rotation with the mean rate ω + n/2, plus Q_ω Δt³/12 on the attitude). Extensions of
    ``mukf_step_ext``: ``z_var`` adds the zero-rate pseudo-measurement ``0 = ω + n``; ``drop``
    leaves out measurement blocks (indices in row order: the vectors, the gyro, the zero rate)
    after the sums, as the χ² gate does; ``nis_out`` (a list) receives ``rᵀ P_yy⁻¹ r`` of every
    block, alone."""
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
    Rm = np.zeros((m, m))
    for k in range(nv):
        Rm[3 * k:3 * k + 3, 3 * k:3 * k + 3] = Rvs[k]
    if wm is not None:
        Rm[3 * nv:3 * nv + 3, 3 * nv:3 * nv + 3] = Rw
    if z_var is not None:
        Rm[m - 3:, m - 3:] = z_var * np.eye(3)
    Pyy = Pyy + Rm
    yv = np.concatenate(list(vms) + ([wm] if wm is not None else [])
                        + ([np.zeros(3)] if z_var is not None else []))
    r = yv - ymean
    keep = np.ones(m, dtype=bool)
    for blk in range(m // 3):
        rows = slice(3 * blk, 3 * blk + 3)
        if nis_out is not None:
            nis_out.append(r[rows] @ np.linalg.solve(Pyy[rows, rows], r[rows]))
        if blk in drop:
            keep[rows] = False
    Pxy, Pyy, r = Pxy[:, keep], Pyy[np.ix_(keep, keep)], r[keep]
    K = Pxy @ np.linalg.inv(Pyy) if keep.any() else np.zeros((nx, 0))
    dx = K @ r
    Pn = Pxx - K @ Pyy @ K.T
    e = c.saturate(dx[0:3])
    b_new = bmean + dx[6:9] if nx == 9 else b
    return qm, e, wmean + dx[3:6], b_new, 0.5 * (Pn + Pn.T)
