"""MEKF — Manifold Extended Kalman Filter (spec §5; paper §3.1, App. B/C).

State: the chart centre ``q̄`` (which is also the estimate), the body rate ``ω̄`` and, as an
extension, the gyro bias ``b̄``; covariance ``P`` of the error state ``(e, ω[, b])`` in the chart
centred at ``q̄``, with mean zero. ``nx`` is 6 (paper) or 9 (with gyro bias); ``P`` is a 9×9 array
of which the leading ``nx × nx`` block is used.

Measurements are stacked (§8 item 15): any number of vector sensors
``v_m = R(q)ᵀ (v + w_v) + r_v`` (eq. 24) plus, optionally, the gyro ``ω_m = ω + b + r_ω`` (eq. 23).

Implementation note (equivalent to the spec, faster): the measurement noise of the stacked
vector is block diagonal, so the joint Kalman update ``K = P⁻Hᵀ S⁻¹`` of §5 equals processing the
3-row blocks one after another — all linearised at the same ``q̄⁻``, the later innovations
corrected by ``H_k Δx`` of the earlier blocks, and a single move back to the manifold at the end.
This needs only 3×3 inverses and yields each sensor's own innovation covariance, which the
χ² gate uses. The known-answer test of §5 checks the equivalence to 1e-6.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit
from mkf_ros.core.charts import from_chart, saturate, t_matrix
from mkf_ros.core.quaternion import q_omega, qmul, rotmat


@jit
def _normalize_into(q: np.ndarray, out: np.ndarray) -> None:
    n = 1.0 / np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    for i in range(4):
        out[i] = q[i] * n


@jit
def mekf_predict(
    qc: np.ndarray, w: np.ndarray, P: np.ndarray, nx: int, dt: float, Qw: np.ndarray,
    Qb: np.ndarray,
) -> None:
    """Prediction over ``dt`` (§5 "Prediction"), in place.

    ``q̄⁻ = q̄ * q_ω(ω̄, Δt)``; ``P⁻ = F (P + Q̂) Fᵀ`` with ``F = [[R(Δq)ᵀ, Δt I], [0, I]]`` and
    ``Q̂ = [[Q_ω Δt³/3, −Q_ω Δt²/2], [−Q_ω Δt²/2, Q_ω Δt]]`` (the authors' form, §8 item 2). The
    bias block gets ``Q_b Δt`` (random walk, extension).
    """
    dq = q_omega(w, dt)
    _normalize_into(qmul(qc, dq), qc)
    dt2 = dt * dt
    for i in range(3):  # P + Q̂
        for j in range(3):
            qw = Qw[i, j]
            P[i, j] += qw * dt2 * dt / 3.0
            P[i, 3 + j] -= 0.5 * qw * dt2
            P[3 + i, j] -= 0.5 * qw * dt2
            P[3 + i, 3 + j] += qw * dt
            if nx == 9:
                P[6 + i, 6 + j] += Qb[i, j] * dt
    # F (P + Q̂) Fᵀ by blocks: F only mixes the attitude rows, e ← A e + Δt ω, A = R(Δq)ᵀ
    R = rotmat(dq)  # A[i, k] = R[k, i]
    M = np.empty((3, nx))
    for i in range(3):
        for j in range(nx):
            M[i, j] = (R[0, i] * P[0, j] + R[1, i] * P[1, j] + R[2, i] * P[2, j]
                       + dt * P[3 + i, j])
    for i in range(3):
        for j in range(nx):
            P[i, j] = M[i, j]
    for i in range(nx):
        c0 = P[i, 0] * R[0, 0] + P[i, 1] * R[1, 0] + P[i, 2] * R[2, 0] + dt * P[i, 3]
        c1 = P[i, 0] * R[0, 1] + P[i, 1] * R[1, 1] + P[i, 2] * R[2, 1] + dt * P[i, 4]
        c2 = P[i, 0] * R[0, 2] + P[i, 1] * R[1, 2] + P[i, 2] * R[2, 2] + dt * P[i, 5]
        P[i, 0] = c0
        P[i, 1] = c1
        P[i, 2] = c2


@jit
def inv3_spd(S: np.ndarray, out: np.ndarray) -> bool:
    """Inverse of a symmetric 3×3 matrix by cofactors; False unless positive definite."""
    a, b, c = S[0, 0], S[0, 1], S[0, 2]
    d, e, f = S[1, 1], S[1, 2], S[2, 2]
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    det = a * c00 + b * c01 + c * c02
    if not (a > 0.0 and a * d - b * b > 0.0 and det > 0.0):
        return False
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[0, 1] = out[1, 0] = c01 * inv
    out[0, 2] = out[2, 0] = c02 * inv
    out[1, 1] = (a * f - c * c) * inv
    out[1, 2] = out[2, 1] = (b * c - a * e) * inv
    out[2, 2] = (a * d - b * b) * inv
    return True


@jit
def _block_update(P: np.ndarray, nx: int, dx: np.ndarray, PHt: np.ndarray, S: np.ndarray,
                  r: np.ndarray, gate: float) -> float:
    """Kalman update for one 3-row block given ``P Hᵀ`` (nx×3), ``S`` and the innovation ``r``
    (already corrected for earlier blocks): ``K = P Hᵀ S⁻¹``, ``Δx += K r``, ``P −= K (P Hᵀ)ᵀ``.
    Returns the normalised innovation squared ``rᵀ S⁻¹ r``; ``-1`` if ``S`` is not positive
    definite, and nothing changes when that value exceeds ``gate``."""
    Si = np.empty((3, 3))
    if not inv3_spd(S, Si):
        return -1.0
    nis = 0.0
    for i in range(3):
        for j in range(3):
            nis += r[i] * Si[i, j] * r[j]
    if nis > gate:
        return nis
    K = np.empty((nx, 3))
    for i in range(nx):
        for j in range(3):
            K[i, j] = PHt[i, 0] * Si[0, j] + PHt[i, 1] * Si[1, j] + PHt[i, 2] * Si[2, j]
        dx[i] += K[i, 0] * r[0] + K[i, 1] * r[1] + K[i, 2] * r[2]
    for i in range(nx):
        for j in range(nx):
            P[i, j] -= K[i, 0] * PHt[j, 0] + K[i, 1] * PHt[j, 1] + K[i, 2] * PHt[j, 2]
    return nis


@jit
def _joseph_projected(P: np.ndarray, nx: int, dx: np.ndarray, PHt: np.ndarray, S: np.ndarray,
                      r: np.ndarray, gate: float, u: np.ndarray) -> float:
    """:func:`_block_update` with the gain of every 3-row group (attitude, rate, bias) projected
    off the direction ``u`` (the world vertical in body axes), so that this measurement cannot
    change heading, vertical rate or vertical bias; ``P`` by the Joseph form, valid for any
    gain: ``(I − K H) P (I − K H)ᵀ + K R Kᵀ = P − K (PHᵀ)ᵀ − PHᵀ Kᵀ + K S Kᵀ``."""
    Si = np.empty((3, 3))
    if not inv3_spd(S, Si):
        return -1.0
    nis = 0.0
    for i in range(3):
        for j in range(3):
            nis += r[i] * Si[i, j] * r[j]
    if nis > gate:
        return nis
    K = np.empty((nx, 3))
    for i in range(nx):
        for j in range(3):
            K[i, j] = PHt[i, 0] * Si[0, j] + PHt[i, 1] * Si[1, j] + PHt[i, 2] * Si[2, j]
    for g in range(nx // 3):  # K_g ← (I − u uᵀ) K_g
        for j in range(3):
            ku = u[0] * K[3 * g, j] + u[1] * K[3 * g + 1, j] + u[2] * K[3 * g + 2, j]
            for i in range(3):
                K[3 * g + i, j] -= u[i] * ku
    for i in range(nx):
        dx[i] += K[i, 0] * r[0] + K[i, 1] * r[1] + K[i, 2] * r[2]
    # Joseph form: P' = P − K PHtᵀ − PHt Kᵀ + K S Kᵀ  (S = H P Hᵀ + R; equals the Joseph form)
    KS = np.empty((nx, 3))
    for i in range(nx):
        for j in range(3):
            KS[i, j] = K[i, 0] * S[0, j] + K[i, 1] * S[1, j] + K[i, 2] * S[2, j]
    for i in range(nx):
        for j in range(nx):
            s_ = 0.0
            for k in range(3):
                s_ += -K[i, k] * PHt[j, k] - PHt[i, k] * K[j, k] + KS[i, k] * K[j, k]
            P[i, j] += s_
    return nis


@jit
def mekf_vector_update(
    P: np.ndarray, nx: int, dx: np.ndarray, R: np.ndarray, vm: np.ndarray, vref: np.ndarray,
    Rv: np.ndarray, Qv: np.ndarray, gate: float, tilt_only: bool = False,
) -> float:
    """One vector sensor (§5 "Measurement prediction", §4.3): ``v̄ = R(q̄⁻)ᵀ v``,
    ``H = [[v̄]×, 0]``, noise ``R(q̄⁻)ᵀ Q_v R(q̄⁻) + R_v``. ``R`` is ``R(q̄⁻)``. With
    ``tilt_only`` (extension, for gravity) the gain is kept off the world vertical
    (:func:`_joseph_projected`). Returns the NIS (see :func:`_block_update`)."""
    vb = np.empty(3)
    for i in range(3):
        vb[i] = R[0, i] * vref[0] + R[1, i] * vref[1] + R[2, i] * vref[2]
    # innovation y − ȳ − H Δx, with H Δx = [v̄]× Δe = v̄ × Δe
    r = np.empty(3)
    r[0] = vm[0] - vb[0] - (vb[1] * dx[2] - vb[2] * dx[1])
    r[1] = vm[1] - vb[1] - (vb[2] * dx[0] - vb[0] * dx[2])
    r[2] = vm[2] - vb[2] - (vb[0] * dx[1] - vb[1] * dx[0])
    # P Hᵀ = P[:, 0:3] [v̄]×ᵀ = −P[:, 0:3] [v̄]×
    PHt = np.empty((nx, 3))
    for i in range(nx):
        p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
        PHt[i, 0] = -(p1 * vb[2] - p2 * vb[1])
        PHt[i, 1] = -(p2 * vb[0] - p0 * vb[2])
        PHt[i, 2] = -(p0 * vb[1] - p1 * vb[0])
    # S = [v̄]× (P Hᵀ)[0:3] + R(q̄⁻)ᵀ Q_v R(q̄⁻) + R_v
    S = np.empty((3, 3))
    for j in range(3):
        S[0, j] = vb[1] * PHt[2, j] - vb[2] * PHt[1, j]
        S[1, j] = vb[2] * PHt[0, j] - vb[0] * PHt[2, j]
        S[2, j] = vb[0] * PHt[1, j] - vb[1] * PHt[0, j]
    isotropic = (Qv[0, 1] == 0.0 and Qv[0, 2] == 0.0 and Qv[1, 2] == 0.0
                 and Qv[0, 0] == Qv[1, 1] and Qv[1, 1] == Qv[2, 2])
    for i in range(3):
        for j in range(3):
            if isotropic:  # Rᵀ (σ² I) R = σ² I
                qb = Qv[i, j]
            else:
                qb = 0.0
                for k in range(3):
                    for m in range(3):
                        qb += R[k, i] * Qv[k, m] * R[m, j]
            S[i, j] += qb + Rv[i, j]
    if tilt_only:
        u = np.array((R[2, 0], R[2, 1], R[2, 2]))  # R(q̄)ᵀ ẑ
        return _joseph_projected(P, nx, dx, PHt, S, r, gate, u)
    return _block_update(P, nx, dx, PHt, S, r, gate)


@jit
def mekf_rate_update(
    P: np.ndarray, nx: int, dx: np.ndarray, w: np.ndarray, b: np.ndarray, wm: np.ndarray,
    Rw: np.ndarray, with_bias: bool, gate: float,
) -> float:
    """A rate measurement: the gyro (eq. 23, ``ȳ = ω̄⁻ + b̄``, ``H = [0, I, I]``, or ``[0, I]``
    without bias) or, with ``with_bias=False``, the zero-rate pseudo-measurement of rest
    detection (``ȳ = ω̄⁻``, ``H = [0, I, 0]``)."""
    bias = with_bias and nx == 9
    r = np.empty(3)
    PHt = np.empty((nx, 3))
    for i in range(3):
        r[i] = wm[i] - w[i] - dx[3 + i] - ((b[i] + dx[6 + i]) if bias else
                                            (b[i] if with_bias else 0.0))
    for i in range(nx):
        for j in range(3):
            PHt[i, j] = P[i, 3 + j] + (P[i, 6 + j] if bias else 0.0)
    S = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            S[i, j] = PHt[3 + i, j] + (PHt[6 + i, j] if bias else 0.0) + Rw[i, j]
    return _block_update(P, nx, dx, PHt, S, r, gate)


@jit
def mekf_gyro_update(
    P: np.ndarray, nx: int, dx: np.ndarray, w: np.ndarray, b: np.ndarray, wm: np.ndarray,
    Rw: np.ndarray, gate: float,
) -> float:
    """The gyro (eq. 23): ``ȳ = ω̄⁻ + b̄``, ``H = [0, I, I]`` (``[0, I]`` without bias)."""
    return mekf_rate_update(P, nx, dx, w, b, wm, Rw, True, gate)


@jit
def heading_residual(R: np.ndarray, m_body: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """The rotation ψ about the world's vertical that brings the horizontal part of the measured
    field ``R(q) m`` onto the horizontal reference, and the horizontal share ``h`` of the field
    (extension: magnetometer for heading only)."""
    mx = R[0, 0] * m_body[0] + R[0, 1] * m_body[1] + R[0, 2] * m_body[2]
    my = R[1, 0] * m_body[0] + R[1, 1] * m_body[1] + R[1, 2] * m_body[2]
    psi = np.arctan2(mx * ref[1] - my * ref[0], mx * ref[0] + my * ref[1])
    return psi, np.sqrt(mx * mx + my * my)


@jit
def mekf_heading_update(
    P: np.ndarray, nx: int, dx: np.ndarray, R: np.ndarray, m_body: np.ndarray, ref: np.ndarray,
    var: float, gate: float,
) -> float:
    """Magnetometer for heading only (extension). Measurement ``0 = ψ(q) + n`` with
    ``ψ(q̄ * δ(e)) ≈ ψ(q̄) − uᵀe``, ``u = R(q̄)ᵀ ẑ`` (the world vertical in body axes), so
    ``H = −uᵀ``, ``S = uᵀ P_ee u + var``. The attitude part of the gain is projected onto ``u``:
    the magnetometer turns the estimate about the vertical only and can never tilt it (a wrong
    dip, a disturbed field); the covariance uses the Joseph form, valid for any gain:
    ``P ← (I − K H) P (I − K H)ᵀ + K var Kᵀ``. Returns the NIS (−1 if ``S ≤ 0``)."""
    psi, _ = heading_residual(R, m_body, ref)
    u0, u1, u2 = R[2, 0], R[2, 1], R[2, 2]  # R(q̄)ᵀ ẑ
    r = -psi + (u0 * dx[0] + u1 * dx[1] + u2 * dx[2])  # 0 − h(x̄ + Δx), h = ψ̄ − uᵀ Δe
    Pu = np.empty(nx)
    for i in range(nx):
        Pu[i] = P[i, 0] * u0 + P[i, 1] * u1 + P[i, 2] * u2  # P Hᵀ = −P u
    S = u0 * Pu[0] + u1 * Pu[1] + u2 * Pu[2] + var
    if not S > 0.0:
        return -1.0
    nis = r * r / S
    if nis > gate:
        return nis
    K = np.empty(nx)
    for i in range(nx):
        K[i] = -Pu[i] / S
    ku = u0 * K[0] + u1 * K[1] + u2 * K[2]
    K[0], K[1], K[2] = u0 * ku, u1 * ku, u2 * ku  # projection onto the vertical
    for i in range(nx):
        dx[i] += K[i] * r
    # Joseph form with A = I − K H = I + K uᵀ (on the attitude columns)
    A = np.eye(nx)
    for i in range(nx):
        A[i, 0] += K[i] * u0
        A[i, 1] += K[i] * u1
        A[i, 2] += K[i] * u2
    AP = np.zeros((nx, nx))
    for i in range(nx):
        for k in range(nx):
            a = A[i, k]
            if a != 0.0:
                for j in range(nx):
                    AP[i, j] += a * P[k, j]
    for i in range(nx):
        for j in range(nx):
            s_ = K[i] * var * K[j]
            for k in range(nx):
                s_ += AP[i, k] * A[j, k]
            P[i, j] = s_
    return nis


@jit
def mekf_apply(chart: int, chart_update: bool, qc: np.ndarray, w: np.ndarray, b: np.ndarray,
               P: np.ndarray, nx: int, dx: np.ndarray) -> None:
    """Multiplicative update and chart update (§5): ``ē = sat(Δx_e)``, ``δ̄ = φ⁻¹(ē)``,
    ``q̄⁺ = q̄⁻ * δ̄``, ``ω̄⁺ = ω̄⁻ + Δω``; with the chart update ``P⁺ = T̃ P' T̃ᵀ``,
    ``T̃ = blockdiag(T(δ̄), I)`` (eq. 47b), otherwise ``P⁺ = P'`` (reset). ``P`` symmetrised."""
    d = from_chart(chart, saturate(chart, dx[0:3]))
    _normalize_into(qmul(qc, d), qc)
    for i in range(3):
        w[i] += dx[3 + i]
        if nx == 9:
            b[i] += dx[6 + i]
    if chart_update:
        transport_covariance(P, nx, t_matrix(chart, d))
    for i in range(nx):
        for j in range(i + 1, nx):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s


@jit
def transport_covariance(P: np.ndarray, nx: int, T: np.ndarray) -> None:
    """Move ``P`` to a new chart centre (§3.2): ``P_ee ← T P_ee Tᵀ``, ``P_e* ← T P_e*``."""
    M = np.empty((3, nx))
    for i in range(3):
        for j in range(nx):
            M[i, j] = T[i, 0] * P[0, j] + T[i, 1] * P[1, j] + T[i, 2] * P[2, j]
    for i in range(3):
        for j in range(nx):
            P[i, j] = M[i, j]
    for i in range(nx):
        c0 = P[i, 0] * T[0, 0] + P[i, 1] * T[0, 1] + P[i, 2] * T[0, 2]
        c1 = P[i, 0] * T[1, 0] + P[i, 1] * T[1, 1] + P[i, 2] * T[1, 2]
        c2 = P[i, 0] * T[2, 0] + P[i, 1] * T[2, 1] + P[i, 2] * T[2, 2]
        P[i, 0] = c0
        P[i, 1] = c1
        P[i, 2] = c2


@jit
def mekf_update(
    chart: int, chart_update: bool, qc: np.ndarray, w: np.ndarray, b: np.ndarray, P: np.ndarray,
    nx: int, vm: np.ndarray, vref: np.ndarray, Rv: np.ndarray, Qv: np.ndarray, use_v: np.ndarray,
    wm: np.ndarray, use_w: bool, Rw: np.ndarray,
) -> bool:
    """Kalman update in the chart centred at ``q̄⁻`` and the move back to the manifold (§5).

    Vector sensor ``k`` (used when ``use_v[k]``) has reading ``vm[k]`` (body), reference
    ``vref[k]`` (world), noise ``Rv[k]`` and external disturbance ``Qv[k]`` (world frame, §8
    item 4). Returns False if an innovation covariance was not positive definite (that block is
    skipped).
    """
    R = rotmat(qc)
    dx = np.zeros(nx)
    ok = True
    for k in range(use_v.shape[0]):
        if use_v[k]:
            ok &= mekf_vector_update(P, nx, dx, R, vm[k], vref[k], Rv[k], Qv[k], np.inf) >= 0
    if use_w:
        ok &= mekf_gyro_update(P, nx, dx, w, b, wm, Rw, np.inf) >= 0
    mekf_apply(chart, chart_update, qc, w, b, P, nx, dx)
    return ok
