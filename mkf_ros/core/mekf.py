"""MEKF — Manifold Extended Kalman Filter (docs/math.md §5; paper §3.1, App. B/C).

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

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.charts import from_chart_t, saturate_t, t_matrix_t
from mkf_ros.core.linalg import ZERO33, cross33_t, symmetrize_leading
from mkf_ros.core.quaternion import (
    q_omega_t,
    qmul_t,
    qnormalize_t,
    rotmat_t,
    t3,
    t4,
    t33,
    up_in_body_t,
)

# Speed (the arithmetic of a 6-state update is a few hundred flops): 3-vectors, quaternions and
# 3×3 matrices are tuples (``R[i][j]``), the nx×3 and 3×3 intermediates of a block live in one
# scratch array (:func:`mekf_scratch`) since numba allocates every array on the heap, and the
# per-sample kernels and their blocks are inlined (``jit_inline``) so that passing arrays costs
# no reference counting.


# Scratch layout of one block update (``work``, :func:`mekf_scratch`), by row offsets rather than
# views (every view costs reference counting): rows ``0:nx`` ``P Hᵀ``, ``nx:2nx`` the gain ``K``,
# ``2nx:2nx+3`` ``S``, then (projected updates) ``ℓ_g = (P Hᵀ)_gᵀ u`` per group ``g`` and the
# 3×3 ``c_gh = ℓ_gᵀ S⁻¹ ℓ_h``, then (``2nx+9:2nx+12``) the block's measurement noise ``R``.
@jit_inline
def mekf_scratch(nx: int) -> np.ndarray:
    """Scratch for the block updates (layout above)."""
    return np.empty((2 * nx + 12, 3))


#: Rows of :func:`mekf_scratch` for the largest state (9: attitude, rate, bias).
MEKF_SCRATCH_ROWS = 2 * 9 + 12


# How a block's H acts (for the Joseph form, which needs B Hᵀ of a full matrix B): a vector
# sensor ``[v̄]×`` on the attitude, the rate ``[0, I, 0]``, the gyro ``[0, I, I]``.
H_VECTOR, H_RATE, H_RATE_BIAS = 0, 1, 2
#: The covariance update of a block is the simple ``P − K (P Hᵀ)ᵀ`` while the smallest
#: eigenvalue of its measurement noise ``R`` (Gershgorin bound) is at least this fraction of
#: ``tr P + tr S``: then ``S`` is conditioned well enough (cond ≤ 1/τ) for its inverse to be
#: accurate to ~1e-10 and the rounding of ``P`` is far below the posterior's own spread in the
#: measured directions. Beyond it (a very precise sensor against a very wide prior: the ends of
#: the noise parameters' ranges, the paper's ``P0 = 100 I``) the Joseph form, PSD for any gain
#: (at the range ends of the noise parameters the simple form made the bias variance
#: negative, and the inverse of an ill-conditioned ``S`` made ``P`` indefinite by up to 1 % of
#: its size).
JOSEPH_TAU = 1e-6


@jit_inline
def mekf_predict_t(q: tuple, w: tuple, P: np.ndarray, nx: int, dt: float, Qw: tuple,
                   Qb: tuple) -> tuple:
    """:func:`mekf_predict` on tuples (``Qw``, ``Qb`` tuples of rows); returns ``q̄⁻``."""
    dq = q_omega_t(w, dt)
    q = qnormalize_t(qmul_t(q, dq))
    dt2 = dt * dt
    for i in range(3):  # P + Q̂
        for j in range(3):
            qw = Qw[i][j]
            P[i, j] += qw * dt2 * dt / 3.0
            P[i, 3 + j] -= 0.5 * qw * dt2
            P[3 + i, j] -= 0.5 * qw * dt2
            P[3 + i, 3 + j] += qw * dt
            if nx == 9:
                P[6 + i, 6 + j] += Qb[i][j] * dt
    # F (P + Q̂) Fᵀ by blocks: F only mixes the attitude rows, e ← A e + Δt ω, A = R(Δq)ᵀ
    R = rotmat_t(dq)  # A[i][k] = R[k][i]
    for j in range(nx):  # rows: F (P + Q̂), column by column
        p0, p1, p2 = P[0, j], P[1, j], P[2, j]
        for i in range(3):
            P[i, j] = R[0][i] * p0 + R[1][i] * p1 + R[2][i] * p2 + dt * P[3 + i, j]
    for i in range(nx):  # columns: (F (P + Q̂)) Fᵀ
        p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
        for k in range(3):
            P[i, k] = p0 * R[0][k] + p1 * R[1][k] + p2 * R[2][k] + dt * P[i, 3 + k]
    return q


@jit_inline
def mekf_predict(
    qc: np.ndarray, w: np.ndarray, P: np.ndarray, nx: int, dt: float, Qw: np.ndarray,
    Qb: np.ndarray,
) -> None:
    """Prediction over ``dt`` (§5 "Prediction"), in place.

    ``q̄⁻ = q̄ * q_ω(ω̄, Δt)``; ``P⁻ = F (P + Q̂) Fᵀ`` with ``F = [[R(Δq)ᵀ, Δt I], [0, I]]`` and
    ``Q̂ = [[Q_ω Δt³/3, −Q_ω Δt²/2], [−Q_ω Δt²/2, Q_ω Δt]]`` (the authors' form, §8 item 2). The
    bias block gets ``Q_b Δt`` (random walk, extension).
    """
    q = mekf_predict_t(t4(qc), t3(w), P, nx, dt, t33(Qw), t33(Qb))
    for i in range(4):
        qc[i] = q[i]


@jit
def inv3_spd_t(S: tuple) -> tuple[bool, tuple]:
    """Inverse of a symmetric 3×3 matrix by cofactors, as its rows; False unless positive
    definite. ``S`` is its upper triangle ``(S00, S01, S02, S11, S12, S22)``."""
    a, b, c, d, e, f = S
    c00 = d * f - e * e
    c01 = c * e - b * f
    c02 = b * e - c * d
    det = a * c00 + b * c01 + c * c02
    if not (a > 0.0 and a * d - b * b > 0.0 and det > 0.0):
        return False, ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    inv = 1.0 / det
    i01, i02, i12 = c01 * inv, c02 * inv, (b * c - a * e) * inv
    return True, ((c00 * inv, i01, i02), (i01, (a * f - c * c) * inv, i12),
                  (i02, i12, (a * d - b * b) * inv))


@jit
def _nis3(r: tuple, Si: tuple) -> float:
    """``rᵀ S⁻¹ r``."""
    nis = 0.0
    for i in range(3):
        for j in range(3):
            nis += r[i] * Si[i][j] * r[j]
    return nis


@jit_inline
def _gain_row(work: np.ndarray, i: int, Si: tuple) -> tuple:
    """Row ``i`` of ``K = P Hᵀ S⁻¹`` (``P Hᵀ`` in the rows ``0:nx`` of ``work``)."""
    p0, p1, p2 = work[i, 0], work[i, 1], work[i, 2]
    return (p0 * Si[0][0] + p1 * Si[1][0] + p2 * Si[2][0],
            p0 * Si[0][1] + p1 * Si[1][1] + p2 * Si[2][1],
            p0 * Si[0][2] + p1 * Si[1][2] + p2 * Si[2][2])


@jit_inline
def _innovation_test(work: np.ndarray, nx: int, r: tuple,
                     gate: float) -> tuple[bool, float, tuple]:
    """The gate shared by the block updates: ``S⁻¹`` of the block's ``S`` (rows ``2nx …`` of
    ``work``, layout above) and the normalised innovation squared ``rᵀ S⁻¹ r`` (``-1`` if ``S``
    is not positive definite); ``go`` is False when the update must not happen."""
    s0 = 2 * nx
    ok, Si = inv3_spd_t((work[s0, 0], work[s0, 1], work[s0, 2], work[s0 + 1, 1],
                         work[s0 + 1, 2], work[s0 + 2, 2]))
    if not ok:
        return False, -1.0, Si
    nis = _nis3(r, Si)
    return not nis > gate, nis, Si


@jit_inline
def _needs_joseph(P: np.ndarray, nx: int, work: np.ndarray) -> bool:
    """Whether a block's covariance update needs the Joseph form (:data:`JOSEPH_TAU`): ``R`` in
    rows ``2nx+9…`` of ``work``, ``S`` in rows ``2nx…``."""
    s0, r0 = 2 * nx, 2 * nx + 9
    tr = work[s0, 0] + work[s0 + 1, 1] + work[s0 + 2, 2]
    for i in range(nx):
        tr += P[i, i]
    lo = min(work[r0, 0] - abs(work[r0, 1]) - abs(work[r0, 2]),
             work[r0 + 1, 1] - abs(work[r0 + 1, 0]) - abs(work[r0 + 1, 2]),
             work[r0 + 2, 2] - abs(work[r0 + 2, 0]) - abs(work[r0 + 2, 1]))
    return not lo >= JOSEPH_TAU * tr


@jit
def _joseph(P: np.ndarray, nx: int, work: np.ndarray, hk: int, vb: tuple, Hb: tuple) -> None:
    """``P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ`` for any gain ``K`` (rows ``nx:2nx`` of ``work``),
    ``R`` in rows ``2nx+9…``, ``H`` of kind ``hk`` (``vb`` = v̄ for :data:`H_VECTOR`): PSD for
    any gain, and computed as that product, so that the rounding of the large prior terms is
    multiplied by the small ``I − K H`` rather than left in a difference: ``B = P − K (PHᵀ)ᵀ``
    (``= (I − K H) P``, in place), then ``P' = B − (B Hᵀ − K R) Kᵀ`` (the upper triangle from
    ``B``'s, mirrored). Overwrites ``P Hᵀ`` (rows ``0:nx``). Compiled on its own, not inlined:
    the rare ill-conditioned case, called from several updates."""
    r0 = 2 * nx + 9
    for i in range(nx):  # B = P − K Cᵀ, C = P Hᵀ (full: B is not symmetric)
        k0, k1, k2 = work[nx + i, 0], work[nx + i, 1], work[nx + i, 2]
        for j in range(nx):
            P[i, j] -= k0 * work[j, 0] + k1 * work[j, 1] + k2 * work[j, 2]
    for i in range(nx):  # G = B Hᵀ − K R into rows 0:nx
        if hk == H_VECTOR:  # (B Hᵀ)_i = v̄ × B[i, 0:3]
            b0, b1, b2 = P[i, 0], P[i, 1], P[i, 2]
            h0, h1, h2 = vb[1] * b2 - vb[2] * b1, vb[2] * b0 - vb[0] * b2, vb[0] * b1 - vb[1] * b0
            if nx == 9:  # + B[i, 6:9] H_bᵀ (the bias columns of H, :func:`mekf_vector_update_t`)
                c6, c7, c8 = P[i, 6], P[i, 7], P[i, 8]
                h0 += c6 * Hb[0][0] + c7 * Hb[0][1] + c8 * Hb[0][2]
                h1 += c6 * Hb[1][0] + c7 * Hb[1][1] + c8 * Hb[1][2]
                h2 += c6 * Hb[2][0] + c7 * Hb[2][1] + c8 * Hb[2][2]
        elif hk == H_RATE:
            h0, h1, h2 = P[i, 3], P[i, 4], P[i, 5]
        else:
            h0, h1, h2 = P[i, 3] + P[i, 6], P[i, 4] + P[i, 7], P[i, 5] + P[i, 8]
        k0, k1, k2 = work[nx + i, 0], work[nx + i, 1], work[nx + i, 2]
        work[i, 0] = h0 - (k0 * work[r0, 0] + k1 * work[r0 + 1, 0] + k2 * work[r0 + 2, 0])
        work[i, 1] = h1 - (k0 * work[r0, 1] + k1 * work[r0 + 1, 1] + k2 * work[r0 + 2, 1])
        work[i, 2] = h2 - (k0 * work[r0, 2] + k1 * work[r0 + 1, 2] + k2 * work[r0 + 2, 2])
    for i in range(nx):  # P' = B − G Kᵀ (upper triangle, mirrored)
        g0, g1, g2 = work[i, 0], work[i, 1], work[i, 2]
        for j in range(i, nx):
            p = P[i, j] - (g0 * work[nx + j, 0] + g1 * work[nx + j, 1] + g2 * work[nx + j, 2])
            P[i, j] = p
            P[j, i] = p


@jit_inline
def _scale_bias_gain(work: np.ndarray, nx: int, bias_gain: float) -> None:
    """The bias rows of the gain ``K`` (rows ``nx+6 … nx+8`` of ``work``) times ``bias_gain``:
    a partial update of the bias (Brink, *Partial-Update Schmidt–Kalman Filter*, J. Guid.
    Control Dyn. 40(9), 2017; docs/math.md §9.1), any gain being valid with the Joseph form."""
    if nx == 9 and bias_gain < 1.0:
        for i in range(nx + 6, nx + 9):
            for j in range(3):
                work[i, j] *= bias_gain


@jit_inline
def _block_update(P: np.ndarray, nx: int, dx: np.ndarray, work: np.ndarray, r: tuple,
                  gate: float, hk: int, vb: tuple, frozen: int, Hb: tuple,
                  bias_gain: float) -> float:
    """Kalman update for one 3-row block given ``P Hᵀ`` (nx×3), ``S`` and ``R`` in ``work``
    (layout above), ``H`` of kind ``hk`` (``vb`` for a vector sensor) and the innovation ``r``
    (already corrected for earlier blocks): ``K = P Hᵀ S⁻¹``, ``Δx += K r``,
    ``P −= K (P Hᵀ)ᵀ`` (symmetric: the upper triangle, mirrored), or the Joseph form where that
    could lose positive definiteness (:data:`JOSEPH_TAU`, :func:`_joseph`).
    Returns the normalised innovation squared ``rᵀ S⁻¹ r``; ``-1`` if ``S`` is not positive
    definite, and nothing changes when that value exceeds ``gate``.

    ``frozen`` (0 or 3): the gain of the first ``frozen`` states is set to zero, ``K = Π K₀``
    with ``Π = blockdiag(0, I)``: their estimate and their own covariance block stay, the
    rest follows the Joseph form ``(I − KH) P (I − KH)ᵀ + K R Kᵀ``, which for this ``Π`` is
    ``P − K₀ (PHᵀ)ᵀ`` everywhere but that block (valid for any gain: PSD by construction).
    ``bias_gain`` < 1 scales the bias rows of the gain (:func:`_scale_bias_gain`), Joseph form;
    ``Hb`` the bias columns of a vector sensor's ``H`` (:func:`mekf_vector_update_t`)."""
    go, nis, Si = _innovation_test(work, nx, r, gate)
    if not go:
        return nis
    if bias_gain < 1.0 or _needs_joseph(P, nx, work):
        for i in range(nx):
            k0, k1, k2 = _gain_row(work, i, Si) if i >= frozen else (0.0, 0.0, 0.0)
            work[nx + i, 0], work[nx + i, 1], work[nx + i, 2] = k0, k1, k2
        _scale_bias_gain(work, nx, bias_gain)
        for i in range(nx):
            dx[i] += work[nx + i, 0] * r[0] + work[nx + i, 1] * r[1] + work[nx + i, 2] * r[2]
        _joseph(P, nx, work, hk, vb, Hb)
        return nis
    for i in range(nx):  # row i of K, then of Δx and P (P Hᵀ is a copy: P may change)
        k0, k1, k2 = _gain_row(work, i, Si)
        if i >= frozen:
            dx[i] += k0 * r[0] + k1 * r[1] + k2 * r[2]
        for j in range(max(i, frozen), nx):
            p = P[i, j] - (k0 * work[j, 0] + k1 * work[j, 1] + k2 * work[j, 2])
            P[i, j] = p
            P[j, i] = p
    return nis


@jit_inline
def _joseph_projected(P: np.ndarray, nx: int, dx: np.ndarray, work: np.ndarray, r: tuple,
                      gate: float, u: tuple, vb: tuple, Hb: tuple, bias_gain: float) -> float:
    """:func:`_block_update` with the gain of every 3-row group (attitude, rate, bias) projected
    off the direction ``u`` (the world vertical in body axes), so that this measurement cannot
    change heading, vertical rate or vertical bias: ``K = Π K₀``, ``K₀ = P Hᵀ S⁻¹``,
    ``Π = blockdiag(I − u uᵀ)`` per group. ``P`` by the Joseph form, valid for any gain:
    ``(I − K H) P (I − K H)ᵀ + K R Kᵀ = P − K (PHᵀ)ᵀ − PHᵀ Kᵀ + K S Kᵀ``, which with
    ``M = K₀ (PHᵀ)ᵀ = PHᵀ S⁻¹ (PHᵀ)ᵀ`` is ``P − ΠM − MΠ + ΠMΠ = P − M + (I − Π) M (I − Π)``;
    its group block ``(g, h)`` is ``P_gh − M_gh + c_gh u uᵀ``, ``c_gh = ℓ_gᵀ S⁻¹ ℓ_h``,
    ``ℓ_g = (PHᵀ)_gᵀ u``. That expansion assumes the exact ``K₀``; where ``S`` is too
    ill-conditioned for that (:data:`JOSEPH_TAU`) the Joseph form is computed as the product
    (:func:`_joseph`, ``H = [v̄]×``); so is it with ``bias_gain`` < 1 (the bias rows of ``K``
    scaled after the projection, :func:`_scale_bias_gain`)."""
    go, nis, Si = _innovation_test(work, nx, r, gate)
    if not go:
        return nis
    ng = nx // 3
    for i in range(nx):  # K₀
        work[nx + i, 0], work[nx + i, 1], work[nx + i, 2] = _gain_row(work, i, Si)
    if bias_gain < 1.0 or _needs_joseph(P, nx, work):  # K = Π K₀, the Joseph form (product)
        for g in range(ng):
            k = nx + 3 * g
            for col in range(3):
                ku = u[0] * work[k, col] + u[1] * work[k + 1, col] + u[2] * work[k + 2, col]
                for i in range(3):
                    work[k + i, col] -= u[i] * ku
        _scale_bias_gain(work, nx, bias_gain)
        for i in range(nx):
            dx[i] += work[nx + i, 0] * r[0] + work[nx + i, 1] * r[1] + work[nx + i, 2] * r[2]
        _joseph(P, nx, work, H_VECTOR, vb, Hb)
        return nis
    _projected_correction(P, nx, dx, work, r, u, Si)
    return nis


@jit_inline
def _projected_correction(P: np.ndarray, nx: int, dx: np.ndarray, work: np.ndarray, r: tuple,
                          u: tuple, Si: tuple) -> None:
    """:func:`_joseph_projected`'s correction and covariance by the expansion (the exact
    ``K₀`` in ``work``): ``Δx_g += (I − u uᵀ) K₀_g r`` and
    ``P_gh ← P_gh − M_gh + c_gh u uᵀ``."""
    s0 = 2 * nx
    ng = nx // 3
    for g in range(ng):
        # Δx_g += (I − u uᵀ) K₀_g r
        k = nx + 3 * g
        a0 = work[k, 0] * r[0] + work[k, 1] * r[1] + work[k, 2] * r[2]
        a1 = work[k + 1, 0] * r[0] + work[k + 1, 1] * r[1] + work[k + 1, 2] * r[2]
        a2 = work[k + 2, 0] * r[0] + work[k + 2, 1] * r[1] + work[k + 2, 2] * r[2]
        au = u[0] * a0 + u[1] * a1 + u[2] * a2
        dx[3 * g] += a0 - u[0] * au
        dx[3 * g + 1] += a1 - u[1] * au
        dx[3 * g + 2] += a2 - u[2] * au
        for j in range(3):  # ℓ_g = (P Hᵀ)_gᵀ u
            work[s0 + 3 + g, j] = (u[0] * work[3 * g, j] + u[1] * work[3 * g + 1, j]
                                   + u[2] * work[3 * g + 2, j])
    for g in range(ng):  # c_gh = ℓ_gᵀ S⁻¹ ℓ_h
        lg = (work[s0 + 3 + g, 0], work[s0 + 3 + g, 1], work[s0 + 3 + g, 2])
        for h in range(g, ng):
            c = 0.0
            for i in range(3):
                for j in range(3):
                    c += lg[i] * Si[i][j] * work[s0 + 3 + h, j]
            work[s0 + 6 + g, h] = c
            work[s0 + 6 + h, g] = c
    for i in range(nx):  # P ← P − K₀ (P Hᵀ)ᵀ + c_gh u uᵀ (upper triangle, mirrored)
        k0, k1, k2 = work[nx + i, 0], work[nx + i, 1], work[nx + i, 2]
        cu = u[i % 3]
        for j in range(i, nx):
            p = (P[i, j] - (k0 * work[j, 0] + k1 * work[j, 1] + k2 * work[j, 2])
                 + work[s0 + 6 + i // 3, j // 3] * cu * u[j % 3])
            P[i, j] = p
            P[j, i] = p


@jit_inline
def mekf_vector_update_t(
    P: np.ndarray, nx: int, dx: np.ndarray, R: tuple, vm: tuple, vref: tuple, noise: tuple,
    gate: float, tilt_only: bool, work: np.ndarray, Sb: tuple, bias_gain: float,
) -> float:
    """:func:`mekf_vector_update` on tuples (``R`` and the noise ``(R_v, Q_v)``, tuples of
    rows) with scratch ``work``; with a bias state, ``Sb`` (3×3, rows) the reading's rotation
    per unit bias error, ``H = [[v̄]×, 0, [v̄]× S_b]`` (a low-passed accelerometer turned by
    the bias-corrected gyro, docs/math.md §9.1; zeros otherwise), and ``bias_gain`` the share
    of the gain the bias takes (:func:`_scale_bias_gain`; 1: the Kalman gain)."""
    Rv, Qv = noise
    vb = (R[0][0] * vref[0] + R[1][0] * vref[1] + R[2][0] * vref[2],  # v̄ = R(q̄⁻)ᵀ v
          R[0][1] * vref[0] + R[1][1] * vref[1] + R[2][1] * vref[2],
          R[0][2] * vref[0] + R[1][2] * vref[1] + R[2][2] * vref[2])
    Hb = cross33_t(vb, Sb) if nx == 9 else ZERO33  # H_b = [v̄]× S_b
    # innovation y − ȳ − H Δx, with H Δx = [v̄]× Δe + H_b Δb = v̄ × Δe + H_b Δb
    r = (vm[0] - vb[0] - (vb[1] * dx[2] - vb[2] * dx[1]),
         vm[1] - vb[1] - (vb[2] * dx[0] - vb[0] * dx[2]),
         vm[2] - vb[2] - (vb[0] * dx[1] - vb[1] * dx[0]))
    if nx == 9:
        r = (r[0] - (Hb[0][0] * dx[6] + Hb[0][1] * dx[7] + Hb[0][2] * dx[8]),
             r[1] - (Hb[1][0] * dx[6] + Hb[1][1] * dx[7] + Hb[1][2] * dx[8]),
             r[2] - (Hb[2][0] * dx[6] + Hb[2][1] * dx[7] + Hb[2][2] * dx[8]))
    # P Hᵀ = P[:, 0:3] [v̄]×ᵀ + P[:, 6:9] H_bᵀ = −P[:, 0:3] [v̄]× + …   (rows 0:nx of work)
    for i in range(nx):
        p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
        work[i, 0] = -(p1 * vb[2] - p2 * vb[1])
        work[i, 1] = -(p2 * vb[0] - p0 * vb[2])
        work[i, 2] = -(p0 * vb[1] - p1 * vb[0])
        if nx == 9:
            c6, c7, c8 = P[i, 6], P[i, 7], P[i, 8]
            for j in range(3):
                work[i, j] += c6 * Hb[j][0] + c7 * Hb[j][1] + c8 * Hb[j][2]
    # S = [v̄]× (P Hᵀ)[0:3] + H_b (P Hᵀ)[6:9] + R(q̄⁻)ᵀ Q_v R(q̄⁻) + R_v   (rows 2nx:2nx+3)
    isotropic = (Qv[0][1] == 0.0 and Qv[0][2] == 0.0 and Qv[1][2] == 0.0
                 and Qv[0][0] == Qv[1][1] and Qv[1][1] == Qv[2][2])
    s0 = 2 * nx
    for j in range(3):
        work[s0, j] = vb[1] * work[2, j] - vb[2] * work[1, j]
        work[s0 + 1, j] = vb[2] * work[0, j] - vb[0] * work[2, j]
        work[s0 + 2, j] = vb[0] * work[1, j] - vb[1] * work[0, j]
        if nx == 9:
            for i in range(3):
                work[s0 + i, j] += (Hb[i][0] * work[6, j] + Hb[i][1] * work[7, j]
                                    + Hb[i][2] * work[8, j])
    for i in range(3):
        for j in range(3):
            if isotropic:  # Rᵀ (σ² I) R = σ² I
                qb = Qv[i][j]
            else:
                qb = 0.0
                for k in range(3):
                    for m in range(3):
                        qb += R[k][i] * Qv[k][m] * R[m][j]
            rn = qb + Rv[i][j]
            work[s0 + i, j] += rn
            work[s0 + 9 + i, j] = rn  # the block's R (for the Joseph form)
    if tilt_only:
        return _joseph_projected(P, nx, dx, work, r, gate, R[2], vb, Hb,
                                 bias_gain)  # u = R(q̄)ᵀ ẑ
    return _block_update(P, nx, dx, work, r, gate, H_VECTOR, vb, 0, Hb, bias_gain)


@jit
def mekf_vector_update(
    P: np.ndarray, nx: int, dx: np.ndarray, R: np.ndarray, vm: np.ndarray, vref: np.ndarray,
    Rv: np.ndarray, Qv: np.ndarray, gate: float, tilt_only: bool = False,
) -> float:
    """One vector sensor (§5 "Measurement prediction", §4.3): ``v̄ = R(q̄⁻)ᵀ v``,
    ``H = [[v̄]×, 0]``, noise ``R(q̄⁻)ᵀ Q_v R(q̄⁻) + R_v``. ``R`` is ``R(q̄⁻)``. With
    ``tilt_only`` (extension, for gravity) the gain is kept off the world vertical
    (:func:`_joseph_projected`). Returns the NIS (see :func:`_block_update`)."""
    return mekf_vector_update_t(P, nx, dx, t33(R), t3(vm), t3(vref), (t33(Rv), t33(Qv)), gate,
                                tilt_only, mekf_scratch(nx), ZERO33, 1.0)


@jit_inline
def mekf_rate_update_t(
    P: np.ndarray, nx: int, dx: np.ndarray, w: tuple, b: tuple, wm: tuple, Rw: tuple,
    with_bias: bool, gate: float, work: np.ndarray, frozen: int = 0,
) -> float:
    """A rate measurement (``Rw`` a tuple of rows, scratch ``work``): the gyro (eq. 23,
    ``ȳ = ω̄⁻ + b̄``, ``H = [0, I, I]``, or ``[0, I]`` without bias) or, with
    ``with_bias=False``, the zero-rate pseudo-measurement of rest detection (``ȳ = ω̄⁻``,
    ``H = [0, I, 0]``)."""
    bias = with_bias and nx == 9
    r0 = wm[0] - w[0] - dx[3] - ((b[0] + dx[6]) if bias else (b[0] if with_bias else 0.0))
    r1 = wm[1] - w[1] - dx[4] - ((b[1] + dx[7]) if bias else (b[1] if with_bias else 0.0))
    r2 = wm[2] - w[2] - dx[5] - ((b[2] + dx[8]) if bias else (b[2] if with_bias else 0.0))
    for i in range(nx):  # P Hᵀ, H = [0, I, I] (or [0, I, 0])
        for j in range(3):
            work[i, j] = P[i, 3 + j] + (P[i, 6 + j] if bias else 0.0)
    s0 = 2 * nx
    for i in range(3):  # S = H P Hᵀ + R_ω
        for j in range(3):
            work[s0 + i, j] = work[3 + i, j] + (work[6 + i, j] if bias else 0.0) + Rw[i][j]
            work[s0 + 9 + i, j] = Rw[i][j]
    return _block_update(P, nx, dx, work, (r0, r1, r2), gate,
                         H_RATE_BIAS if bias else H_RATE, (0.0, 0.0, 0.0), frozen, ZERO33, 1.0)


@jit
def mekf_gyro_update(
    P: np.ndarray, nx: int, dx: np.ndarray, w: np.ndarray, b: np.ndarray, wm: np.ndarray,
    Rw: np.ndarray, gate: float,
) -> float:
    """The gyro (eq. 23): ``ȳ = ω̄⁻ + b̄``, ``H = [0, I, I]`` (``[0, I]`` without bias)."""
    return mekf_rate_update_t(P, nx, dx, t3(w), t3(b), t3(wm), t33(Rw), True, gate,
                              mekf_scratch(nx))


@jit
def heading_residual_t(R: tuple, m_body: tuple, ref: tuple) -> tuple[float, float]:
    """The rotation ψ about the world's vertical that brings the horizontal part of the measured
    field ``R(q) m`` onto the horizontal reference, and the horizontal share ``h`` of the field
    (extension: magnetometer for heading only). ``R`` is a tuple of rows, the vectors 3-tuples."""
    mx = R[0][0] * m_body[0] + R[0][1] * m_body[1] + R[0][2] * m_body[2]
    my = R[1][0] * m_body[0] + R[1][1] * m_body[1] + R[1][2] * m_body[2]
    psi = np.arctan2(mx * ref[1] - my * ref[0], mx * ref[0] + my * ref[1])
    return psi, np.sqrt(mx * mx + my * my)


@jit
def heading_residual(R: np.ndarray, m_body: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """Array form of :func:`heading_residual_t`."""
    return heading_residual_t(t33(R), t3(m_body), t3(ref))


@jit_inline
def mekf_heading_update_t(
    P: np.ndarray, nx: int, dx: np.ndarray, R: tuple, m_body: tuple, ref: tuple, var: float,
    gate: float, bias_gain: float,
) -> float:
    """:func:`mekf_heading_update` on tuples (``R`` a tuple of rows)."""
    psi, _ = heading_residual_t(R, m_body, ref)
    ok, He = _heading_jacobian(R, m_body)
    if not ok:
        return -1.0
    r = -psi - (He[0] * dx[0] + He[1] * dx[1] + He[2] * dx[2])  # 0 − h(x̄ + Δx)
    # v = P Hᵀ (attitude columns only); S = H P Hᵀ + var
    v = np.empty(NX_MAX_HEADING)
    for i in range(nx):
        v[i] = P[i, 0] * He[0] + P[i, 1] * He[1] + P[i, 2] * He[2]
    S = He[0] * v[0] + He[1] * v[1] + He[2] * v[2] + var
    if not S > 0.0:
        return -1.0
    nis = r * r / S
    if nis > gate:
        return nis
    u = (R[2][0], R[2][1], R[2][2])  # R(q̄)ᵀ ẑ: the world vertical in body axes
    k = np.empty(NX_MAX_HEADING)
    for i in range(nx):
        k[i] = v[i] / S
    for o in range(0, nx, 3):  # every group's gain (attitude, rate, bias) onto the vertical
        ku = u[0] * k[o] + u[1] * k[o + 1] + u[2] * k[o + 2]
        if o == 6:  # the bias's share (mag_bias_gain, docs/math.md §9.2)
            ku *= bias_gain
        k[o], k[o + 1], k[o + 2] = u[0] * ku, u[1] * ku, u[2] * ku
    for i in range(nx):
        dx[i] += k[i] * r
    _heading_covariance(P, nx, He, k, v, S, var)
    return nis


@jit_inline
def _heading_jacobian(R: tuple, m_body: tuple) -> tuple[bool, tuple]:
    """``H_e = −(d × m)``, ``d = R(q̄)ᵀ (m_y, −m_x, 0)/|m_h|²`` (``m_x, m_y`` the horizontal
    part of the field in world axes): ``∂ψ/∂e`` of ``ψ(q̄ * δ(e))``,
    ``R(q̄ δ) m ≈ R(q̄)(m + e × m)``. False when the field has no horizontal part."""
    mx = R[0][0] * m_body[0] + R[0][1] * m_body[1] + R[0][2] * m_body[2]
    my = R[1][0] * m_body[0] + R[1][1] * m_body[1] + R[1][2] * m_body[2]
    h2 = mx * mx + my * my
    if not h2 > 0.0:
        return False, (0.0, 0.0, 0.0)
    c0, c1 = my / h2, -mx / h2
    d = (R[0][0] * c0 + R[1][0] * c1, R[0][1] * c0 + R[1][1] * c1, R[0][2] * c0 + R[1][2] * c1)
    return True, (-(d[1] * m_body[2] - d[2] * m_body[1]), -(d[2] * m_body[0] - d[0] * m_body[2]),
                  -(d[0] * m_body[1] - d[1] * m_body[0]))


@jit_inline
def _heading_covariance(P: np.ndarray, nx: int, He: tuple, k: np.ndarray, v: np.ndarray,
                        S: float, var: float) -> None:
    """The heading update's covariance for its (projected) gain ``k`` (``v = P Hᵀ``), the
    Joseph form, valid for any gain: ``P − k vᵀ − v kᵀ + S k kᵀ``; as the product (see
    :func:`_joseph`) where ``var`` is too small against the prior (:data:`JOSEPH_TAU`).
    Overwrites ``v`` then."""
    tr = S
    for i in range(nx):
        tr += P[i, i]
    if not var >= JOSEPH_TAU * tr:  # the Joseph form as the product (see _joseph)
        for i in range(nx):  # B = P − k vᵀ = (I − k H) P
            for j in range(nx):
                P[i, j] -= k[i] * v[j]
        for i in range(nx):  # g = B Hᵀ − k var (over v: no longer needed)
            v[i] = P[i, 0] * He[0] + P[i, 1] * He[1] + P[i, 2] * He[2] - k[i] * var
        for i in range(nx):  # P' = B − g kᵀ
            for j in range(i, nx):
                p = P[i, j] - v[i] * k[j]
                P[i, j] = p
                P[j, i] = p
        return
    for i in range(nx):
        for j in range(i, nx):
            p = P[i, j] - k[i] * v[j] - v[i] * k[j] + S * k[i] * k[j]
            P[i, j] = p
            P[j, i] = p


NX_MAX_HEADING = 9


@jit
def mekf_heading_update(
    P: np.ndarray, nx: int, dx: np.ndarray, R: np.ndarray, m_body: np.ndarray, ref: np.ndarray,
    var: float, gate: float, bias_gain: float = 1.0,
) -> float:
    """Magnetometer for heading only (extension). Measurement ``0 = ψ(q) + n``: ``ψ`` is the
    rotation about the world vertical that brings the horizontal part of ``R(q) m`` onto the
    horizontal reference (:func:`heading_residual_t`). Linearised at ``q = q̄ * δ(e)`` with
    ``R(q̄ δ) m ≈ R(q̄)(m + e × m)``: ``H_e = −(d × m)``, ``d = R(q̄)ᵀ (m_y, −m_x, 0)/|m_h|²``
    (``m_x, m_y`` the world-horizontal components of ``R(q̄) m``). Along the vertical
    ``u = R(q̄)ᵀ ẑ`` this is ``H u = −1``; the tilt components, of size ≈ tan(dip), say how a
    tilt error moves the apparent heading, so that ``S = H P Hᵀ + var`` counts it. The gain of
    each group (attitude, rate, bias) is projected onto ``u``: the magnetometer turns the
    estimate about the vertical only and can never tilt it, not even later through the rate
    or the bias (a wrong dip, a disturbed field); the bias's times ``bias_gain``
    (``mag_bias_gain``, docs/math.md §9.2); the covariance uses
    the Joseph form, valid for any gain: ``P ← (I − K H) P (I − K H)ᵀ + K var Kᵀ``. Returns
    the NIS (−1 if ``S ≤ 0``)."""
    return mekf_heading_update_t(P, nx, dx, t33(R), t3(m_body), t3(ref), var, gate, bias_gain)


@jit_inline
def mekf_apply_t(chart: int, chart_update: bool, q: tuple, w: tuple, b: tuple, P: np.ndarray,
                 nx: int, dx: np.ndarray, free_heading: bool) -> tuple[tuple, tuple, tuple]:
    """:func:`mekf_apply` on tuples: returns ``(q̄⁺, ω̄⁺, b̄⁺)``. ``free_heading``: nothing
    observes the heading, and the chart update carries the world vertical of ``q̄⁻`` to that
    of ``q̄⁺`` (:func:`free_heading_transport_t`)."""
    d = from_chart_t(chart, saturate_t(chart, (dx[0], dx[1], dx[2])))
    qp = q
    q = qnormalize_t(qmul_t(q, d))
    w = (w[0] + dx[3], w[1] + dx[4], w[2] + dx[5])
    if nx == 9:
        b = (b[0] + dx[6], b[1] + dx[7], b[2] + dx[8])
    if chart_update:
        T = t_matrix_t(chart, d)
        if free_heading:  # the world vertical in the body, before and after
            T = free_heading_transport_t(T, up_in_body_t(qp), up_in_body_t(q))
        transport_covariance_t(P, nx, T)
    symmetrize_leading(P, nx)
    return q, w, b


@jit_inline
def free_heading_transport_t(T: tuple, u: tuple, un: tuple) -> tuple:
    """The chart update's map with the heading unobserved: ``M = T + (u⁺ − T u) uᵀ``, which
    acts as the chart's ``T(δ̄)`` across the vertical and carries the vertical ``u`` (world up
    in the body before the update) to the new one ``u⁺ = R(δ̄)ᵀ u`` exactly (docs/math.md
    §9.3). An error about the vertical by any angle θ leaves the tilt as it is: the reset's
    error ``δ̄* ⊗ exp(θ u) = exp(θ u⁺) ⊗ δ̄*`` has the same tilt for every θ. ``T`` is right
    to first order in the error; for a heading spread over ±180° its ``½ [δ̄]×`` turns the
    heading's variance by half the correction only, and what is left across the new vertical
    is taken for tilt (tyrex running trials: 0.5–1.5° of inclination)."""
    Tu = (T[0][0] * u[0] + T[0][1] * u[1] + T[0][2] * u[2],
          T[1][0] * u[0] + T[1][1] * u[1] + T[1][2] * u[2],
          T[2][0] * u[0] + T[2][1] * u[1] + T[2][2] * u[2])
    r = (un[0] - Tu[0], un[1] - Tu[1], un[2] - Tu[2])
    return ((T[0][0] + r[0] * u[0], T[0][1] + r[0] * u[1], T[0][2] + r[0] * u[2]),
            (T[1][0] + r[1] * u[0], T[1][1] + r[1] * u[1], T[1][2] + r[1] * u[2]),
            (T[2][0] + r[2] * u[0], T[2][1] + r[2] * u[1], T[2][2] + r[2] * u[2]))


@jit_inline
def mekf_apply(chart: int, chart_update: bool, qc: np.ndarray, w: np.ndarray, b: np.ndarray,
               P: np.ndarray, nx: int, dx: np.ndarray) -> None:
    """Multiplicative update and chart update (§5): ``ē = sat(Δx_e)``, ``δ̄ = φ⁻¹(ē)``,
    ``q̄⁺ = q̄⁻ * δ̄``, ``ω̄⁺ = ω̄⁻ + Δω``; with the chart update ``P⁺ = T̃ P' T̃ᵀ``,
    ``T̃ = blockdiag(T(δ̄), I)`` (eq. 47b), otherwise ``P⁺ = P'`` (reset). ``P`` symmetrised."""
    q, w1, b1 = mekf_apply_t(chart, chart_update, t4(qc), t3(w), t3(b), P, nx, dx, False)
    for i in range(4):
        qc[i] = q[i]
    for i in range(3):
        w[i] = w1[i]
        b[i] = b1[i]


@jit_inline
def transport_covariance_t(P: np.ndarray, nx: int, T: tuple) -> None:
    """Move ``P`` to a new chart centre (§3.2): ``P_ee ← T P_ee Tᵀ``, ``P_e* ← T P_e*``; ``T`` a
    tuple of rows."""
    for j in range(nx):  # rows: T P[0:3, :], column by column
        p0, p1, p2 = P[0, j], P[1, j], P[2, j]
        for i in range(3):
            P[i, j] = T[i][0] * p0 + T[i][1] * p1 + T[i][2] * p2
    for i in range(nx):  # columns: P[:, 0:3] Tᵀ, row by row
        p0, p1, p2 = P[i, 0], P[i, 1], P[i, 2]
        for k in range(3):
            P[i, k] = p0 * T[k][0] + p1 * T[k][1] + p2 * T[k][2]


@jit
def transport_covariance(P: np.ndarray, nx: int, T: np.ndarray) -> None:
    """Move ``P`` to a new chart centre (§3.2): ``P_ee ← T P_ee Tᵀ``, ``P_e* ← T P_e*``."""
    transport_covariance_t(P, nx, t33(T))


@jit_inline
def mekf_update(chart: int, chart_update: bool, x: tuple, P: np.ndarray, nx: int,
                vectors: tuple, gyro: tuple) -> bool:
    """Kalman update in the chart centred at ``q̄⁻`` and the move back to the manifold (§5), in
    place: the state ``x = (q̄, ω̄, b̄)`` (arrays) and ``P``.

    ``vectors = (vm, vref, Rv, Qv, use_v)``: vector sensor ``k`` (used when ``use_v[k]``) has
    reading ``vm[k]`` (body), reference ``vref[k]`` (world), noise ``Rv[k]`` and external
    disturbance ``Qv[k]`` (world frame, §8 item 4); ``gyro = (wm, use_w, Rw)``. Returns False if
    an innovation covariance was not positive definite (that block is skipped).
    """
    qc, w, b = x
    vm, vref, Rv, Qv, use_v = vectors
    wm, use_w, Rw = gyro
    q, wt, bt = t4(qc), t3(w), t3(b)
    R = rotmat_t(q)
    dx = np.zeros(nx)
    work = mekf_scratch(nx)
    ok = True
    for k in range(use_v.shape[0]):
        if use_v[k]:
            ok &= mekf_vector_update_t(P, nx, dx, R, t3(vm[k]), t3(vref[k]),
                                       (t33(Rv[k]), t33(Qv[k])), np.inf, False, work, ZERO33,
                                       1.0) >= 0
    if use_w:
        ok &= mekf_rate_update_t(P, nx, dx, wt, bt, t3(wm), t33(Rw), True, np.inf, work) >= 0
    mekf_apply(chart, chart_update, qc, w, b, P, nx, dx)
    return ok
