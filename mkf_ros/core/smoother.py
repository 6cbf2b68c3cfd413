"""The fixed-interval manifold smoother (docs/math.md §11): the causal filter forward, recording
each step's posterior before its prediction, then a Rauch–Tung–Striebel pass backward over the
error state, in windows of bounded memory.

Forward (:func:`forward_recorded`): the filter's own per-sample step
(:func:`~mkf_ros.core.sensor.step`) with ``CONFIG.record_posterior`` set, so that every
decision of the sensor layer (gates, rest, the magnetometer's checks, re-alignments) is made
causally, once, and reused. Each sample ``n`` leaves in its :data:`RECORD` slot either the
posterior at ``t_n`` just before step ``n + 1``'s prediction (after that step's gyro and rest
rate updates, which observe the rate at ``t_n``: :data:`TRANS`, with ``Δt_{n+1}``), or, until
that step has run or when it re-aligned, the filter's final state at ``t_n`` (:data:`END`).

Backward (:func:`backward`): from the last slot of a window, each :data:`TRANS` slot is
combined with the smoothed estimate of the next sample through the prediction it preceded
(re-done by :func:`~mkf_ros.core.mekf.mekf_predict_t`, hence the filter's own ``P⁻`` and
``Φ``); an :data:`END` slot starts a new segment at the filtered estimate.

Windows (:func:`smooth_run`): the forward pass is continuous; the records of ``window +
overlap`` samples are kept; each backward pass starts at the last of them with the filtered
estimate there and publishes the first ``window``; the next window starts ``window`` samples
later. Memory: :data:`RECORD` (529 bytes) per kept sample.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.charts import from_chart_t, saturate_t, t_matrix_t, to_chart_t
from mkf_ros.core.filter import (
    AttitudeFilter,
    BatchOutputs,
    Kernels,
    _write_output,
    kernel_table,
    kernels_at,
    new_batch_outputs,
    run_step,
)
from mkf_ros.core.frames import swing_rotvec
from mkf_ros.core.linalg import cap_eigenvalues33_t, cho_solve_into, cholesky_into, congruence33_t
from mkf_ros.core.mekf import mekf_predict_t, transport_covariance_t
from mkf_ros.core.params import SMOOTH_MODES
from mkf_ros.core.quaternion import (
    q_omega_t,
    qconj_mul_t,
    qconj_np,
    qmul_np,
    qmul_t,
    qnormalize_t,
    rotmat_t,
    t3,
    t4,
    t33,
)
from mkf_ros.core.state import (
    ALGO_MUKF,
    NX_MAX,
    YAW_VAR_UNKNOWN,
    iso33,
    new_records,
    record,
    record_posterior,
    step_dt,
)

#: Kinds of a :data:`RECORD` slot: no estimate at this sample (before the first alignment);
#: the filter's final estimate (a segment's end: the last sample so far, or the sample before a
#: re-alignment); the posterior before the next sample's prediction (a link to the next sample).
NONE, END, TRANS = 0, 1, 2
#: Packed upper triangle of a 9×9 covariance.
NP_PACKED = NX_MAX * (NX_MAX + 1) // 2

#: One sample of the forward pass as the backward pass needs it (docs/math.md §11.1): the
#: estimate ``(q̂, ω̄, b̄)`` (chart centre at ``q̂``), the packed upper triangle of ``P`` of
#: ``(e, ω[, b])``, the kind, and for :data:`TRANS` the step ``Δt`` to the next sample; and
#: the step's own readings ``u = (Δt, ω_g, a, m)`` as the filter took them (what a pass over
#: the recording reversed needs: ``mkf process --smooth two-way``, docs/math.md §11.5).
RECORD = np.dtype([("kind", np.int8), ("dt", np.float64), ("q", np.float64, 4),
                   ("w", np.float64, 3), ("b", np.float64, 3), ("P", np.float64, NP_PACKED),
                   ("ws2", np.float64), ("u", np.float64, 10)])

#: Parameters whose default differs in the smoother's forward pass (docs/math.md §11.1): the
#: heading's partial update of the gyro bias (``mag_bias_gain``, §9.2) protects a causal
#: filter, which has no later evidence to undo a bias learned from a passing disturbance; the
#: smoother's backward pass brings that evidence, and the information the partial update leaves
#: out is lost to it (tyrex 9D smoothed 11.76° with the full gain, 13.24° with 0.3:
#: docs/real_data.md).
FORWARD_DEFAULTS = {"mag_bias_gain": 1.0}


def forward_params(params: dict) -> dict:
    """``params`` for the smoother's forward pass: :data:`FORWARD_DEFAULTS` where not given."""
    return {**FORWARD_DEFAULTS, **params}


#: Samples per window of :func:`smooth_run` (docs/math.md §11.4): the memory bound.
DEFAULT_WINDOW = 1 << 17
#: The default overlap as a duration (docs/math.md §11.4): what a cut costs decays with the time
#: the measurements need to correct the state (the 9D heading's is the slowest: a minute on
#: BROAD), not with a count of samples. Measured in docs/real_data.md: 57 s of overlap left
#: ≤ 0.11° on BROAD's 9D recordings (their RMSE: 1.9°), 115 s 0.004° but twice the memory and
#: backward work at 1 kHz (docs/bags.md), 7 s 2°.
DEFAULT_OVERLAP_S = 60.0
#: ... in samples at the recording's mean rate, at most one default window (the backward pass
#: then does at most twice the work it publishes; above 2.2 kHz the default overlap is shorter
#: than :data:`DEFAULT_OVERLAP_S`).
MAX_DEFAULT_OVERLAP = DEFAULT_WINDOW


def window_sizes(window: int | None, overlap: int | None, period: float) -> tuple[int, int]:
    """The smoother's window and overlap in samples (docs/math.md §11.4) for a recording of
    mean sample ``period`` (s): ``window`` None → :data:`DEFAULT_WINDOW`; ``overlap`` None →
    :data:`DEFAULT_OVERLAP_S` at that period (:data:`MAX_DEFAULT_OVERLAP` at most, one window
    where the period is unknown, i.e. not positive and finite). ValueError for a window < 1 or an
    overlap < 0."""
    check_window(window, overlap)
    w = DEFAULT_WINDOW if window is None else int(window)
    if overlap is not None:
        return w, int(overlap)
    if period > 0 and np.isfinite(period):
        return w, min(MAX_DEFAULT_OVERLAP, int(np.ceil(DEFAULT_OVERLAP_S / period)))
    return w, w


def check_window(window: int | None, overlap: int | None) -> None:
    """ValueError for a window < 1 or an overlap < 0 (None: the default, always valid)."""
    if (window is not None and window < 1) or (overlap is not None and overlap < 0):
        raise ValueError(f"smoother window must be >= 1 and overlap >= 0, got {window}, "
                         f"{overlap}")


def mean_period(duration: float, steps: int) -> float:
    """The mean sample period (s) of ``steps`` samples spanning ``duration`` s (0 for fewer than
    two): what :func:`window_sizes` converts the default overlap with."""
    return duration / (steps - 1) if steps > 1 else 0.0


def steps_period(dts: np.ndarray) -> float:
    """:func:`mean_period` of the steps ``dts`` (the first step's is not an interval of the
    recording)."""
    return mean_period(float(np.sum(dts[1:])), len(dts))


def new_smooth_outputs(n: int) -> BatchOutputs:
    """``n`` rows of smoothed outputs, zeros: the filter's
    :class:`~mkf_ros.core.filter.BatchOutputs` (the smoother publishes its estimate as the
    filter does, docs/math.md §9.6; ``initialized`` False where a sample has no estimate,
    before the first alignment: the caller keeps the filter's rows there)."""
    return BatchOutputs(np.zeros((n, 4)), np.zeros((n, 3, 3)), np.zeros((n, 3)),
                        np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n, dtype=np.bool_))


# --- records ---------------------------------------------------------------------------------
@jit_inline
def _store(r: np.record, nx: int, w: np.record, kind: int, dt: float) -> None:
    """Write the recorded estimate of ``w`` (``rec_*``), the upper triangle of its ``P`` and
    the gyro's scale noise of the step into the slot ``r``."""
    q, wr, b, P = w.rec_q, w.rec_w, w.rec_b, w.rec_P
    r.kind = kind
    r.dt = dt
    r.ws2 = w.rec_ws2
    for i in range(4):
        r.q[i] = q[i]
    for i in range(3):
        r.w[i] = wr[i]
        r.b[i] = b[i]
    m = 0
    for i in range(nx):
        for j in range(i, nx):
            r.P[m] = P[i, j]
            m += 1


@jit_inline
def _load_cov(r: np.record, nx: int, P: np.ndarray) -> None:
    """``P`` (leading ``nx × nx``) from the slot's packed upper triangle."""
    m = 0
    for i in range(nx):
        for j in range(i, nx):
            P[i, j] = r.P[m]
            P[j, i] = r.P[m]
            m += 1


@jit  # compiled once and called (inlined into each event of the stream loop it doubled the
# install-time compile of that loop, 12 → 28 s; the call costs nothing next to a recorded step)
def recorded_step(kern: Kernels, c: np.record, s: np.record, k: np.record, w: np.record,
                  dt: float, gyr: tuple, acc: tuple, mag: tuple, rec: np.ndarray,
                  m: int) -> None:
    """One filter step (:func:`~mkf_ros.core.filter.run_step`, ``c.record_posterior`` set)
    recorded into the slot ``rec[m]`` (docs/math.md §11.1): its final state (:data:`END`,
    :data:`NONE` without an estimate), the previous slot ``rec[m − 1]`` (if ``m > 0``)
    overwritten by this step's recorded posterior (:data:`TRANS`, with ``dt``) unless this step
    re-aligned (a gap) or started the estimate. The one recording rule of every forward pass
    (:func:`forward_recorded`, the stream adapter's event loop)."""
    nx = c.nx
    w.rec_set = False
    gaps = k.gaps
    u = rec[m].u
    u[0] = dt
    for i in range(3):
        u[1 + i] = gyr[i]
        u[4 + i] = acc[i]
        u[7 + i] = mag[i]
    run_step(kern, c, s, k, w, dt, gyr, acc, mag)
    if w.rec_set and k.gaps == gaps and m >= 1 and rec[m - 1].kind != NONE:
        _store(rec[m - 1], nx, w, TRANS, step_dt(dt))
    if s.initialized:
        record_posterior(c, s, w)  # the final state (moved onto q̂ for the MUKF)
        _store(rec[m], nx, w, END, 0.0)
    else:
        rec[m].kind = NONE


@jit
def forward_recorded(table: np.ndarray, cfg: np.ndarray, st: np.ndarray, cnt: np.ndarray,
                     work: np.ndarray, dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
                     mag: np.ndarray, out: BatchOutputs, rec: np.ndarray, r0: int) -> None:
    """The filter's step over ``dts`` (:func:`~mkf_ros.core.filter.run_batch`, the filtered
    outputs into ``out``), sample ``n`` recorded into the slot ``rec[r0 + n]``
    (:func:`recorded_step`). ``cfg`` must have ``record_posterior`` set; ``rec[r0 − 1]`` (if
    ``r0 > 0``) is the previous sample's."""
    kern: Kernels = kernels_at(table)
    c, s, k, w = cfg[0], st[0], cnt[0], work[0]
    for n in range(dts.shape[0]):
        recorded_step(kern, c, s, k, w, dts[n], (gyr[n, 0], gyr[n, 1], gyr[n, 2]),
                      (acc[n, 0], acc[n, 1], acc[n, 2]), (mag[n, 0], mag[n, 1], mag[n, 2]),
                      rec, r0 + n)
        _write_output(kern, c, s, out, n)


def cut(rec: np.ndarray, m: int) -> None:
    """Drop the slot ``rec[m]`` from the chain (an estimate that went non-finite and was
    reset): it becomes :data:`NONE`, and a :data:`TRANS` link into it from ``rec[m − 1]``
    becomes that segment's end (:data:`END`, its recorded posterior; :data:`NONE` if that is
    not finite either)."""
    rec[m]["kind"] = NONE
    if m >= 1 and rec[m - 1]["kind"] == TRANS:
        r = rec[m - 1]
        finite = all(np.isfinite(r[f]).all() for f in ("q", "w", "b", "P"))
        r["kind"] = END if finite else NONE


# --- the backward pass -----------------------------------------------------------------------
@jit_inline
def rts_linear(nx: int, Pa: np.ndarray, Pp: np.ndarray, A: tuple, dt: float, Qp: np.ndarray,
               Ps: np.ndarray, dx: np.ndarray, C: np.ndarray, scratch: tuple, Pout: np.ndarray,
               dxo: np.ndarray) -> bool:
    """One Rauch–Tung–Striebel step of a linear-Gaussian model (docs/math.md §11.2), on the
    leading ``nx × nx`` blocks, for the transition of the filter's prediction
    ``Φ = [[A, Δt I, 0], [0, I, 0], [0, 0, I]]`` (``A`` a 3×3 tuple of rows; §5): the posterior
    ``Pa`` at ``t_k``, its prediction ``Pp = Φ (Pa + Q) Φᵀ = Φ Pa Φᵀ + Qp`` at ``t_{k+1}``
    (``Qp = Φ Q Φᵀ``), the smoothed covariance ``Ps`` at ``t_{k+1}`` and the
    smoothed-minus-predicted mean ``dx``. Writes the gain ``C = Pa Φᵀ Pp⁻¹``, the correction
    ``dxo = C dx`` and the smoothed covariance

        ``Pout = (I − CΦ) Pa (I − CΦ)ᵀ + C (Qp + Ps) Cᵀ``

    (equal to ``Pa + C (Ps − Pp) Cᵀ``; a sum of congruences of PSD matrices, computed as such:
    symmetric PSD by construction). ``scratch``: two ``nx × nx`` arrays ``(G, X)``; ``Pp`` is
    overwritten (its Cholesky factor), ``Qp`` too (by ``Qp + Ps``). False if ``Pp`` is not
    positive definite."""
    G, X = scratch
    for j in range(nx):  # X = Φ Pa (Φ's structure), then Pp⁻¹ Φ Pa = Cᵀ
        p0, p1, p2 = Pa[0, j], Pa[1, j], Pa[2, j]
        for i in range(3):
            X[i, j] = A[i][0] * p0 + A[i][1] * p1 + A[i][2] * p2 + dt * Pa[3 + i, j]
        for i in range(3, nx):
            X[i, j] = Pa[i, j]
    if not cholesky_into(Pp, Pp, 0, nx):
        return False
    cho_solve_into(Pp, nx, X, nx)
    for i in range(nx):
        for j in range(nx):
            C[i, j] = X[j, i]
    for i in range(nx):  # dxo = C dx;  G = I − C Φ (Φ's structure)
        a = 0.0
        for m in range(nx):
            a += C[i, m] * dx[m]
        dxo[i] = a
        c0, c1, c2 = C[i, 0], C[i, 1], C[i, 2]
        for j in range(3):
            G[i, j] = -(c0 * A[0][j] + c1 * A[1][j] + c2 * A[2][j])
            G[i, 3 + j] = -(C[i, 3 + j] + dt * C[i, j])
        for j in range(6, nx):
            G[i, j] = -C[i, j]
        G[i, i] += 1.0
    for i in range(nx):  # X = G Pa
        for j in range(nx):
            a = 0.0
            for m in range(nx):
                a += G[i, m] * Pa[m, j]
            X[i, j] = a
    for i in range(nx):  # Pout = X Gᵀ (upper triangle)
        for j in range(i, nx):
            a = 0.0
            for m in range(nx):
                a += X[i, m] * G[j, m]
            Pout[i, j] = a
    for i in range(nx):  # Qp + Ps, once (not inside the product: −10 % of the backward step)
        for j in range(nx):
            Qp[i, j] += Ps[i, j]
    for i in range(nx):  # X = C (Qp + Ps)
        for j in range(nx):
            a = 0.0
            for m in range(nx):
                a += C[i, m] * Qp[m, j]
            X[i, j] = a
    for i in range(nx):  # Pout += X Cᵀ, mirrored
        for j in range(i, nx):
            a = Pout[i, j]
            for m in range(nx):
                a += X[i, m] * C[j, m]
            Pout[i, j] = a
            Pout[j, i] = a
    return True


# rts_linear with nx a literal, on the scratch of rts_manifold, each compiled once: the compiler
# unrolls its 9×9 (6×6) loops (inlined at both call sites instead, the backward pass took half
# as long again to compile, and a third more memory)
@jit
def _rts_linear9(S: np.ndarray, A: tuple, dt: float) -> bool:
    return rts_linear(9, S[0], S[1], A, dt, S[2], S[4], S[9][0], S[5], (S[6], S[7]), S[8],
                      S[9][1])


@jit
def _rts_linear6(S: np.ndarray, A: tuple, dt: float) -> bool:
    return rts_linear(6, S[0], S[1], A, dt, S[2], S[4], S[9][0], S[5], (S[6], S[7]), S[8],
                      S[9][1])


@jit_inline
def transition_matrix(w: tuple, dt: float, nx: int, Phi: np.ndarray) -> None:
    """The error-state transition of :func:`~mkf_ros.core.mekf.mekf_predict_t` (docs/math.md
    §5): ``Φ = [[R(Δq)ᵀ, Δt I, 0], [0, I, 0], [0, 0, I]]``, ``Δq = q_ω(ω̄, Δt)``."""
    R = rotmat_t(q_omega_t(w, dt))
    for i in range(nx):
        for j in range(nx):
            Phi[i, j] = 1.0 if i == j else 0.0
    for i in range(3):
        for j in range(3):
            Phi[i, j] = R[j][i]
        Phi[i, 3 + i] = dt


@jit_inline
def _inv33_t(A: tuple) -> tuple:
    """Inverse of a general invertible 3×3 matrix (rows) by cofactors."""
    c00 = A[1][1] * A[2][2] - A[1][2] * A[2][1]
    c01 = A[1][2] * A[2][0] - A[1][0] * A[2][2]
    c02 = A[1][0] * A[2][1] - A[1][1] * A[2][0]
    d = 1.0 / (A[0][0] * c00 + A[0][1] * c01 + A[0][2] * c02)
    return ((c00 * d, (A[0][2] * A[2][1] - A[0][1] * A[2][2]) * d,
             (A[0][1] * A[1][2] - A[0][2] * A[1][1]) * d),
            (c01 * d, (A[0][0] * A[2][2] - A[0][2] * A[2][0]) * d,
             (A[0][2] * A[1][0] - A[0][0] * A[1][2]) * d),
            (c02 * d, (A[0][1] * A[2][0] - A[0][0] * A[2][1]) * d,
             (A[0][0] * A[1][1] - A[0][1] * A[1][0]) * d))


@jit_inline
def rts_manifold(c: np.record, r: np.record, qs: np.ndarray, ws: np.ndarray, bs: np.ndarray,
                 Ps: np.ndarray, S: np.ndarray, nx: int) -> bool:
    """One backward step on the manifold (docs/math.md §11.3), in place: the smoothed estimate
    ``(qs, ws, bs, Ps)`` at ``t_{k+1}`` (``Ps`` in the chart at ``qs``) becomes that at ``t_k``
    from the :data:`TRANS` slot ``r`` (the posterior at ``t_k``). ``S``: scratch
    ``(10, 9, 9)``. False (nothing changed) if the prediction's covariance is not positive
    definite."""
    Pa, Pp, Qp, Pn, Po = S[0], S[1], S[2], S[4], S[8]  # (S[5:8]: rts_linear's C, G, X)
    _load_cov(r, nx, Pa)
    qa, wa, ba = t4(r.q), t3(r.w), t3(r.b)
    for i in range(nx):
        for j in range(nx):
            Pp[i, j] = Pa[i, j]
            Qp[i, j] = 0.0
            Pn[i, j] = Ps[i, j]
    Qw, Qb = iso33(c.rate_process_noise), iso33(c.bias_process_var)
    qm = mekf_predict_t(qa, wa, Pp, nx, r.dt, Qw, Qb)  # the filter's prediction: q̄⁻, P⁻
    # the gyro's scale noise W_s (§9.1), added by the filter before the rate updates, is noise
    # of this transition: out of the posterior, into Q (it leaves the rate updates' gains alone)
    ws2 = r.ws2
    for i in range(3):
        Pa[i, i] -= ws2
        Qp[i, i] = ws2
    mekf_predict_t(qa, wa, Qp, nx, r.dt, Qw, Qb)  # Φ (W_s + Q̂) Φᵀ
    R = rotmat_t(q_omega_t(wa, r.dt))
    Am = ((R[0][0], R[1][0], R[2][0]), (R[0][1], R[1][1], R[2][1]),
          (R[0][2], R[1][2], R[2][2]))  # R(Δq)ᵀ
    # the smoothed estimate at t_{k+1} in the chart at q̄⁻: the mean φ(q̄⁻* qˢ), the covariance
    # carried by the inverse T-matrix of the reverse move (§3.2)
    d = qconj_mul_t(qm, (qs[0], qs[1], qs[2], qs[3]))
    e = to_chart_t(c.chart, d)
    transport_covariance_t(Pn, nx, _inv33_t(t_matrix_t(c.chart, d)))
    dx, dxo = S[9][0], S[9][1]
    for i in range(3):
        dx[i] = e[i]
        dx[3 + i] = ws[i] - wa[i]
        if nx == 9:
            dx[6 + i] = bs[i] - ba[i]
    if not (_rts_linear9(S, Am, r.dt) if nx == 9 else _rts_linear6(S, Am, r.dt)):
        return False
    # back to the manifold at the posterior's centre, as the filter's update (§5)
    de = saturate_t(c.chart, (dxo[0], dxo[1], dxo[2]))
    dd = from_chart_t(c.chart, de)
    q = qnormalize_t(qmul_t(qa, dd))
    for i in range(4):
        qs[i] = q[i]
    for i in range(3):
        ws[i] = wa[i] + dxo[3 + i]
        bs[i] = ba[i] + (dxo[6 + i] if nx == 9 else 0.0)
    for i in range(nx):
        for j in range(nx):
            Ps[i, j] = Po[i, j]
    if c.chart_update:
        transport_covariance_t(Ps, nx, t_matrix_t(c.chart, dd))
    return True


@jit_inline
def _load(r: np.record, nx: int, qs: np.ndarray, ws: np.ndarray, bs: np.ndarray,
          Ps: np.ndarray) -> None:
    """The slot's estimate as the smoothed one (a segment's last sample)."""
    for i in range(4):
        qs[i] = r.q[i]
    for i in range(3):
        ws[i] = r.w[i]
        bs[i] = r.b[i]
    _load_cov(r, nx, Ps)


@jit_inline
def _write_smoothed(c: np.record, qs: np.ndarray, ws: np.ndarray, bs: np.ndarray,
                    Ps: np.ndarray, out: BatchOutputs, j: int) -> None:
    """Row ``j`` of the outputs, published as the filter's (docs/math.md §9.6): ``q_W`` with
    ``q0 ≥ 0`` and ``Σ_W = R(q_W) Pˢ_ee R(q_W)ᵀ + diag(σ_a², σ_a², 0)``, capped at ``π²/3``
    about any axis."""
    q = qmul_t(t4(c.q_from_enu), (qs[0], qs[1], qs[2], qs[3]))
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[0] < 0.0:
        n = -n
    q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
    Pb = ((Ps[0, 0], Ps[0, 1], Ps[0, 2]), (Ps[1, 0], Ps[1, 1], Ps[1, 2]),
          (Ps[2, 0], Ps[2, 1], Ps[2, 2]))
    Cw = congruence33_t(rotmat_t(q), Pb)
    f2 = c.acc_alignment_error ** 2
    c01, c02 = 0.5 * (Cw[0][1] + Cw[1][0]), 0.5 * (Cw[0][2] + Cw[2][0])
    c12 = 0.5 * (Cw[1][2] + Cw[2][1])
    Cw = cap_eigenvalues33_t(((Cw[0][0] + f2, c01, c02), (c01, Cw[1][1] + f2, c12),
                              (c02, c12, Cw[2][2])), YAW_VAR_UNKNOWN)
    for i in range(4):
        out.quat[j, i] = q[i]
    for i in range(3):
        for k in range(3):
            out.cov[j, i, k] = Cw[min(i, k)][max(i, k)]
        out.omega[j, i] = ws[i]
        out.bias[j, i] = bs[i]
        out.bias_var[j, i] = Ps[6 + i, 6 + i] if c.nx == 9 else 0.0
    out.initialized[j] = True


@jit
def backward(cfg: np.ndarray, rec: np.ndarray, n: int, out: BatchOutputs) -> int:
    """The backward pass over the slots ``rec[0:n]`` (docs/math.md §11.3), from ``rec[n − 1]``
    (its estimate taken as the smoothed one) down to ``rec[0]``, into rows ``0 … n − 1`` of
    ``out``. Returns how many links fell back to the filtered estimate (a prediction whose
    covariance was not positive definite)."""
    c = cfg[0]
    nx = c.nx
    S = np.zeros((10, NX_MAX, NX_MAX))
    Ps = np.zeros((NX_MAX, NX_MAX))
    qs, ws, bs = np.zeros(4), np.zeros(3), np.zeros(3)
    have = False
    failed = 0
    for j in range(n - 1, -1, -1):
        r = rec[j]
        if r.kind == NONE:
            out.initialized[j] = False
            have = False
            continue
        if r.kind == TRANS and have:
            if not rts_manifold(c, r, qs, ws, bs, Ps, S, nx):
                failed += 1
                _load(r, nx, qs, ws, bs, Ps)
        else:
            _load(r, nx, qs, ws, bs, Ps)
        have = True
        _write_smoothed(c, qs, ws, bs, Ps, out, j)
    return failed


# --- the driver ------------------------------------------------------------------------------
class Windows:
    """The records of a continuous forward pass, smoothed in windows (docs/math.md §11.4): a
    forward pass appends slots to ``rec[held:]`` (and adds them to ``held``); :meth:`smooth`
    runs the backward pass over the first ``window + overlap`` held slots whenever that many
    are held (all of them at the end) and hands out the smoothed rows of the first ``window``
    (all at the end), which leave the buffer. So the windows depend only on the slots'
    sequence, not on how the forward pass was cut, and memory is that of ``capacity`` slots
    (``window + overlap`` and what a forward pass may append beyond that before it stops)."""

    def __init__(self, cfg: np.ndarray, window: int, overlap: int, capacity: int) -> None:
        check_window(window, overlap)
        self.cfg = cfg
        self.window, self.overlap = window, overlap
        self.span = window + overlap
        self.rec = new_records(RECORD, max(capacity, 1))
        self.held = 0  #: slots held: ``rec[0:held]``
        self.done = 0  #: slots smoothed and handed out before ``rec[0]``
        self.failed = 0  #: links that fell back to the filtered estimate
        self._local = new_smooth_outputs(min(self.span, max(capacity, 1)))

    def smooth(self, final: bool) -> list[BatchOutputs]:
        """The smoothed rows ready now, in order (each a fresh :class:`BatchOutputs`, rows for
        the slots ``done …``); ``final``: the forward pass has ended, smooth every held slot."""
        res = []
        while self.held >= self.span or (final and self.held > 0):
            n = min(self.held, self.span)
            if len(self._local) < n:
                self._local = new_smooth_outputs(n)
            self.failed += backward(self.cfg, self.rec, n, self._local)
            keep = n if (final and n == self.held) else min(self.window, n)
            res.append(BatchOutputs(*(a[:keep].copy() for a in self._local)))
            rest = self.held - keep
            self.rec[:rest] = self.rec[keep:self.held]
            self.held = rest
            self.done += keep
        return res


#: ``read(a, b)``: the readings ``(Δt, ω_g, a, m)`` of samples ``a … b − 1`` as C-contiguous
#: float64 arrays ((k,), (k, 3) × 3), as :meth:`AttitudeFilter.run` takes them.
Reader = Callable[[int, int], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def array_reader(dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray) -> Reader:
    """A :data:`Reader` of readings held in arrays."""
    arrays = tuple(np.ascontiguousarray(x, dtype=np.float64) for x in (dts, gyr, acc, mag))
    return lambda a, b: tuple(x[a:b] for x in arrays)  # type: ignore[return-value]


def smooth_stream(f: AttitudeFilter, n: int, read: Reader, window: int, overlap: int
                  ) -> Iterator[tuple[int, BatchOutputs, BatchOutputs]]:
    """The filter ``f`` (an MEKF or MUKF) forward over ``n`` samples read in pieces by ``read``
    (as :meth:`AttitudeFilter.run`, from its current state, which advances) and the backward
    pass in windows of ``window`` samples started ``overlap`` samples later (docs/math.md
    §11.4, :class:`Windows`); ``window ≥ n`` is the full-interval smoother. Yields, in order,
    ``(first sample, filtered rows, smoothed rows)`` (rows without an estimate keep the
    filter's): memory is that of ``window + overlap`` samples whatever ``n``."""
    arrays = f.kernel_arrays()
    c = record(arrays.cfg)
    if c.algorithm > ALGO_MUKF:
        raise ValueError(f"the smoother needs algorithm mekf or mukf, not {f.params.algorithm!r}")
    cap = min(window + overlap, max(n, 1))
    wins = Windows(arrays.cfg, window, overlap, cap)
    held = new_batch_outputs(cap)  # the held slots' filtered rows, as Windows holds the slots
    table = kernel_table(arrays.cfg)
    c.record_posterior = True
    try:
        fwd = 0  # first sample not yet filtered
        while fwd < n or wins.held:
            end = min(fwd + cap - wins.held, n)
            part = BatchOutputs(*(a[wins.held:wins.held + end - fwd] for a in held))
            forward_recorded(table, arrays.cfg, arrays.st, arrays.counters, arrays.work,
                             *read(fwd, end), part, wins.rec, wins.held)
            wins.held += end - fwd
            fwd = end
            pos, rest = wins.done, wins.held
            for rows in wins.smooth(fwd == n):
                k = len(rows.initialized)
                rest -= k  # rows still held after these
                filt = BatchOutputs(*(a[:k].copy() for a in held))
                for a in held:  # the rows move with their slots (Windows.smooth)
                    a[:rest] = a[k:k + rest]
                bad = ~rows.initialized
                for a, b in zip(rows[:5], filt[:5], strict=True):  # quat … bias_var
                    a[bad] = b[bad]
                yield pos, filt, rows
                pos += k
    finally:
        c.record_posterior = False


def smooth_run(f: AttitudeFilter, dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
               mag: np.ndarray, window: int | None = None,
               overlap: int | None = None) -> tuple[BatchOutputs, BatchOutputs]:
    """:func:`smooth_stream` over readings in arrays (readings as for
    :meth:`AttitudeFilter.run`; ``window``, ``overlap`` as :func:`window_sizes` resolves them
    at the steps' mean period): the filtered and the smoothed outputs, one row per sample."""
    n = len(dts)
    window, overlap = window_sizes(window, overlap, steps_period(dts))
    filt, sm = new_batch_outputs(n), new_smooth_outputs(n)
    for pos, fr, sr in smooth_stream(f, n, array_reader(dts, gyr, acc, mag), window, overlap):
        k = len(sr.initialized)
        for a, b in zip((*filt, *sm), (*fr, *sr), strict=True):
            a[pos:pos + k] = b
    return filt, sm


# --- both directions (docs/math.md §11.5) ----------------------------------------------------


def smooth_mode(smooth: bool | str) -> str | None:
    """``estimate``'s ``smooth`` as one of :data:`SMOOTH_MODES` (``True``: ``"rts"``), or None
    (``False``: the causal filter). ValueError for anything else."""
    if smooth is False:
        return None
    mode = "rts" if smooth is True else smooth
    if mode not in SMOOTH_MODES:
        raise ValueError(f"smooth must be False, True or one of {SMOOTH_MODES}, got {smooth!r}")
    return mode


def reversed_reader(read: Reader, n: int) -> Reader:
    """A :data:`Reader` of a recording of ``n`` samples (read forwards by ``read``) backwards
    in time (docs/math.md §11.5): sample ``j`` of the result is sample ``k = n − 1 − j``. A
    step's gyro reading and ``Δt`` describe the interval that *ends* at its sample, so
    backwards sample ``j`` takes those of sample ``k + 1`` (the interval from ``t_k`` to
    ``t_{k+1}``, turned the other way: ``−ω``); the first keeps its own. Accelerometer and
    magnetometer readings are instantaneous: reversed as they are. Each call reads the one
    forward block it needs."""
    def rev(a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        lo, hi = n - b, min(n + 1 - a, n)  # the forward samples of a … b − 1 and the next
        dts, gyr, acc, mag = read(lo, hi)
        k = n - 1 - lo - np.arange(a, b)  # the samples read, backwards, in the block
        k1 = np.minimum(k + 1, n - 1 - lo)  # the interval that ends at the next one
        return (np.ascontiguousarray(dts[k1], dtype=np.float64),
                -np.ascontiguousarray(gyr[k1], dtype=np.float64),
                np.ascontiguousarray(acc[k], dtype=np.float64),
                np.ascontiguousarray(mag[k], dtype=np.float64))
    return rev


def reversed_inputs(dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The whole recording backwards in time (:func:`reversed_reader`)."""
    n = len(dts)
    return reversed_reader(array_reader(dts, gyr, acc, mag), n)(0, n)


#: ``D = diag(√2, √2, 1)``: the congruence ``D P D`` widens the fused tilt to covariance
#: intersection's bound (ω = ½; docs/math.md §11.5).
_CI_SCALE = (np.sqrt(2.0), np.sqrt(2.0), 1.0)


@jit
def fuse_tilt_rows(e: np.ndarray, d: np.ndarray, q_f: np.ndarray, P_f: np.ndarray,
                   P_b: np.ndarray, q: np.ndarray, P: np.ndarray) -> None:
    """The per-sample arithmetic of :func:`fuse_tilt` (eq. 11.5a–d) into ``q``, ``P``: ``e``
    the world rotation between the estimates (N, 4), ``d`` its swing's inverse (N, 2)."""
    for n in range(q_f.shape[0]):
        finite = np.isfinite(d[n, 0]) and np.isfinite(d[n, 1])
        for i in range(4):
            finite &= np.isfinite(q_f[n, i]) and np.isfinite(e[n, i])
        for i in range(3):
            for j in range(3):
                finite &= np.isfinite(P_f[n, i, j]) and np.isfinite(P_b[n, i, j])
        Pf = t33(P_f[n])
        psi = 2.0 * np.arctan2(e[n, 3], e[n, 0])  # the heading between the two worlds
        c, sn = np.cos(psi), np.sin(psi)
        Pb = congruence33_t(((c, -sn, 0.0), (sn, c, 0.0), (0.0, 0.0, 1.0)), t33(P_b[n]))
        s00, s11 = Pf[0][0] + Pb[0][0], Pf[1][1] + Pb[1][1]  # S = H (P_f + P_b') Hᵀ
        s01 = 0.5 * (Pf[0][1] + Pf[1][0] + Pb[0][1] + Pb[1][0])
        det = s00 * s11 - s01 * s01
        if not (finite and det > 0.0):  # no usable second estimate: keep the first
            for i in range(4):
                q[n, i] = q_f[n, i]
            for i in range(3):
                for j in range(3):
                    P[n, i, j] = P_f[n, i, j]
            continue
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det  # S⁻¹
        K = ((Pf[0][0] * i00 + Pf[0][1] * i01, Pf[0][0] * i01 + Pf[0][1] * i11, 0.0),
             (Pf[1][0] * i00 + Pf[1][1] * i01, Pf[1][0] * i01 + Pf[1][1] * i11, 0.0),
             (Pf[2][0] * i00 + Pf[2][1] * i01, Pf[2][0] * i01 + Pf[2][1] * i11, 0.0))  # K Hᵀ
        dx = (K[0][0] * d[n, 0] + K[0][1] * d[n, 1], K[1][0] * d[n, 0] + K[1][1] * d[n, 1],
              K[2][0] * d[n, 0] + K[2][1] * d[n, 1])
        qn = qnormalize_t(qmul_t(q_omega_t(dx, 1.0), t4(q_f[n])))  # exp(K d) ⊗ q_f
        sg = -1.0 if qn[0] < 0.0 else 1.0
        for i in range(4):
            q[n, i] = sg * qn[i]
        # (I − KH) P_f (I − KH)ᵀ + K (H P_b' Hᵀ) Kᵀ (eq. 11.5b), then D · D (eq. 11.5c)
        G = ((1.0 - K[0][0], -K[0][1], 0.0), (-K[1][0], 1.0 - K[1][1], 0.0),
             (-K[2][0], -K[2][1], 1.0))
        X = congruence33_t(G, Pf)
        B = congruence33_t(K, ((Pb[0][0], Pb[0][1], 0.0), (Pb[1][0], Pb[1][1], 0.0),
                               (0.0, 0.0, 0.0)))
        for i in range(3):
            for j in range(i, 3):
                pij = 0.5 * ((X[i][j] + B[i][j]) + (X[j][i] + B[j][i])) * _CI_SCALE[i] * \
                    _CI_SCALE[j]
                P[n, i, j] = pij
                P[n, j, i] = pij
        # + the two estimates' spread about the fused tilt, as a mixture of equal weights
        # (eq. 11.5d): the forward at −K d, the reversed at d − K d
        b0, b1 = d[n, 0] - dx[0], d[n, 1] - dx[1]
        s01 = 0.5 * (dx[0] * dx[1] + b0 * b1)
        P[n, 0, 0] += 0.5 * (dx[0] * dx[0] + b0 * b0)
        P[n, 1, 1] += 0.5 * (dx[1] * dx[1] + b1 * b1)
        P[n, 0, 1] += s01
        P[n, 1, 0] += s01


def fuse_tilt(q_f: np.ndarray, P_f: np.ndarray, q_b: np.ndarray, P_b: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """The forward estimate ``(q_f, P_f)`` updated with the tilt of a second estimate
    ``(q_b, P_b)`` of the same samples (docs/math.md §11.5, eq. 11.5a–d); covariances about
    each estimate's world axes, (N, 3, 3). The second estimate's world frame may differ from
    the first's by a heading (a reversed 6D pass starts its own): only its vertical is used.
    The world rotation between the two, ``e = q_f ⊗ q_b⁻¹``, is a swing about a horizontal
    axis after a twist ``ψ`` about the vertical (:func:`~mkf_ros.core.frames.swing_rotvec`);
    the swing's inverse ``d`` (it takes the body's up seen by the second, ``R(e) z``, back to
    ``z``) is a measurement of the first's world error ``δ`` with ``H = [I₂ 0]`` and noise
    ``P_b`` turned by ``ψ`` into the first's world (both are vertical):
    ``K = P_f Hᵀ (H P_f Hᵀ + H P_b' Hᵀ)⁻¹``, ``q = exp(K d) ⊗ q_f``.
    The two estimates share their samples, so their errors are correlated by an unknown
    amount: the covariance is the Joseph form's ``(I − KH) P_f (I − KH)ᵀ + K H P_b' Hᵀ Kᵀ``
    (right for independent errors) with its tilt widened to covariance intersection's bound
    for any correlation (ω = ½: twice), ``D P D``, ``D = diag(√2, √2, 1)``; equal estimates
    then keep their covariance. Plus the spread of the two tilts about the fused one,
    ``½ (a aᵀ + b bᵀ)`` with ``a = H K d``, ``b = d − H K d`` (eq. 11.5d: the two estimates as
    a mixture of equal weights; a disagreement beyond their covariances is a model error,
    e.g. a gyro scale error turning the two passes' low-passes the opposite ways). Symmetric
    PSD by construction (a congruence of a sum of congruences, plus outer products). Samples
    where either is not finite keep the first."""
    q_f, P_f = np.ascontiguousarray(q_f, float), np.ascontiguousarray(P_f, float)
    e = qmul_np(q_f, qconj_np(q_b))  # the second's world → the first's: swing ⊗ twist about z
    with np.errstate(invalid="ignore"):
        d = -swing_rotvec(e)  # the horizontal rotation that takes v = R(e) z back to z
    q, P = np.empty_like(q_f), np.empty_like(P_f)
    fuse_tilt_rows(np.ascontiguousarray(e), np.ascontiguousarray(d), q_f, P_f,
                    np.ascontiguousarray(P_b, float), q, P)
    return q, P


def smooth_both_ways(f: AttitudeFilter, dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray,
                     mag: np.ndarray, window: int | None = None,
                     overlap: int | None = None) -> tuple[BatchOutputs, BatchOutputs]:
    """:func:`smooth_run` with ``f``, and a fresh filter of ``f``'s parameters smoothed over the
    recording reversed (:func:`smooth_reversed_into`), the two in parallel threads (the kernels
    release the GIL: on two cores the wall time of one); the forward smoother's tilt fused with
    the reversed one's where both have an estimate (:func:`fuse_tilt`, docs/math.md §11.5).
    Returns the filtered outputs and the smoothed ones with ``quat`` and ``cov`` fused (rate
    and bias the forward smoother's); ``window``, ``overlap`` as :func:`smooth_run`."""
    n = len(dts)
    window, overlap = window_sizes(window, overlap, steps_period(dts))
    q_b, P_b, ok_b = np.empty((n, 4)), np.empty((n, 3, 3)), np.zeros(n, dtype=np.bool_)

    def write(first: int, q: np.ndarray, P: np.ndarray, ok: np.ndarray) -> None:
        rows = slice(first, first + len(ok))
        q_b[rows], P_b[rows], ok_b[rows] = q, P, ok

    with ThreadPoolExecutor(max_workers=2) as pool:  # the kernels release the GIL
        fwd = pool.submit(smooth_run, f, dts, gyr, acc, mag, window, overlap)
        rev = pool.submit(smooth_reversed_into, f.params, n,
                          array_reader(dts, gyr, acc, mag), (), window, overlap, write)
        (filt, sm), _ = fwd.result(), rev.result()
    sm.quat[:], sm.cov[:] = fuse_two_way(sm.quat, sm.cov, filt.initialized, q_b, P_b, ok_b)
    return filt, sm


def fuse_two_way(q_f: np.ndarray, P_f: np.ndarray, ok_f: np.ndarray, q_b: np.ndarray,
                 P_b: np.ndarray, ok_b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The forward smoother's rows fused with the reversed one's of the same samples
    (:func:`fuse_tilt`) where both have an estimate (``ok_f``, ``ok_b``); elsewhere the
    forward rows."""
    q_b = np.where((ok_f & ok_b)[:, None], q_b, np.nan)  # no second estimate: keep the first
    return fuse_tilt(q_f, P_f, q_b, P_b)


def _shifted(read: Reader, s0: int, a: int, b: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``read`` of the samples ``s0 + a … s0 + b − 1``."""
    return read(s0 + a, s0 + b)


def smooth_reversed_into(params: Any, n: int, read: Reader, starts: Sequence[int],
                         window: int, overlap: int,
                         write: Callable[[int, np.ndarray, np.ndarray, np.ndarray], object],
                         progress: Callable[[int], object] | None = None) -> None:
    """The smoother over a recording reversed, streamed (``mkf process --smooth two-way``):
    ``read`` the readings of its ``n`` steps forwards (a :data:`Reader`; a bag's: a
    :data:`RECORD`'s ``u`` spilled to a file), ``starts`` the steps where the forward pass
    started anew (a reset: each segment between two is reversed with a fresh filter of
    ``params``, as a forward pass over it would start). Hands the reversed smoother's rows out
    in blocks of consecutive steps, ``write(first step, q (k, 4), P (k, 3, 3), ok (k,))``
    (``ok``: the step has an estimate), in forward order within a block; ``progress(k)``
    after each. Memory: one smoothing window + overlap."""
    bounds = sorted({0, *(int(s) for s in starts if 0 < s < n), n})
    for s0, s1 in itertools.pairwise(bounds):
        seg = reversed_reader(functools.partial(_shifted, read, s0), s1 - s0)
        for pos, fr, sr in smooth_stream(AttitudeFilter(params), s1 - s0, seg, window,
                                         overlap):
            k = len(sr.initialized)
            write(s1 - pos - k, sr.quat[::-1], sr.cov[::-1], fr.initialized[::-1])
            if progress is not None:
                progress(k)
