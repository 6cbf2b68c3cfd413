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
                  Rvs, Qvs, wm, Rw):
    """§6 steps 0–7 literally: full augmentation, 2N+1 sigma points, columns of L."""
    c = CHARTS[CHART_NAMES[chart]]
    if not cu:
        qc = normalize(qmul(qc, c.from_chart(ebar)))
        ebar = np.zeros(3)
    P = P.copy()
    if nx == 9:
        P[6:9, 6:9] += Qb * dt
    nv = len(vms)
    N = nx + 3 + 3 * nv
    xa = np.zeros(N)
    xa[0:3] = ebar
    xa[3:6] = w
    if nx == 9:
        xa[6:9] = b
    Pa = np.zeros((N, N))
    Pa[:nx, :nx] = P
    Pa[nx:nx + 3, nx:nx + 3] = Qw if published else Qw * dt
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
        nw = x[nx:nx + 3]
        wj = x[3:6] + (nw * dt if published else nw)
        bj = x[6:9] if nx == 9 else b
        qj = normalize(qmul(qj, q_omega(wj, dt)))
        y = [rotmat(qj).T @ (vrefs[k] + x[nx + 3 + 3 * k:nx + 6 + 3 * k]) for k in range(nv)]
        if wm is not None:
            y.append(wj + bj)
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
        Rm[m - 3:, m - 3:] = Rw
    Pyy = Pyy + Rm
    yv = np.concatenate(list(vms) + ([wm] if wm is not None else []))
    K = Pxy @ np.linalg.inv(Pyy)
    dx = K @ (yv - ymean)
    Pn = Pxx - K @ Pyy @ K.T
    e = c.saturate(dx[0:3])
    b_new = bmean + dx[6:9] if nx == 9 else b
    return qm, e, wmean + dx[3:6], b_new, 0.5 * (Pn + Pn.T)
