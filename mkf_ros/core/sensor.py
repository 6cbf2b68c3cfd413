"""The sensor layer: one sample of a real IMU through the paper's filters (spec §8 item 15).

The paper's filters (:mod:`~mkf_ros.core.mekf`, :mod:`~mkf_ros.core.mukf`) take abstract vector
measurements. This layer adds what a real IMU needs:

* validation: a vector that is all NaN is *missing* (an asynchronous magnetometer, a dropped
  field); one that is partly non-finite or zero is *invalid*; either way only that sensor's
  update is skipped, and counted;
* references: the accelerometer reads +g "up" at rest, so its normalised reading measures the
  world up axis (0, 0, 1) in ENU; the magnetometer reference is given or learned (dip angle) from
  the first samples, horizontal part pointing north;
* initialisation: closed-form alignment (tilt from the accelerometer, heading from the first
  magnetometer sample), or the paper's identity with ``P0 = 100 I``;
* gaps: a step longer than ``max_dt`` re-aligns instead of integrating a stale rate;
* the accelerometer's blend of raw and low-passed directions, the gyro gate, rest detection and
  the magnetometer's consistency checks (issue 13; see each function).

:func:`sensor_step` is the per-sample kernel; :mod:`mkf_ros.core.filter` runs it over a
recording (:func:`~mkf_ros.core.filter.run_batch`) or one sample at a time
(:class:`~mkf_ros.core.filter.AttitudeFilter`).
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.baseline_glue import (
    baseline_export,
    baseline_realign,
    baseline_update,
    from_canonical,
)
from mkf_ros.core.frames import align_tilt, heading_correction, keep_yaw
from mkf_ros.core.linalg import eye
from mkf_ros.core.mekf import (
    heading_residual_t,
    inv3_spd_t,
    mekf_apply_t,
    mekf_heading_update_t,
    mekf_predict_t,
    mekf_rate_update_t,
    mekf_scratch,
    mekf_vector_update_t,
    symmetrize_leading,
)
from mkf_ros.core.mukf import B_HEADING, B_VEC0, B_VEC1, mukf_scratch, mukf_step_t
from mkf_ros.core.quaternion import (
    q_omega_t,
    qmul,
    qnormalize,
    rotate,
    rotate_inv,
    rotmat_t,
    t3,
)
from mkf_ros.core.state import (
    ACC_TILT,
    ALGO_EULER_KF,
    ALGO_MEKF,
    ALGO_MUKF,
    C_ACC_DTIME,
    C_ACC_GATE,
    C_ACC_MODE,
    C_ACC_RECOVER,
    C_ACC_TAU,
    C_ACC_TOL,
    C_ALGO,
    C_B0,
    C_CHART,
    C_CU,
    C_DIP_TOL,
    C_GRAVITY,
    C_GYR_GATE,
    C_GYR_SCALE,
    C_MAG_CTOL,
    C_MAG_DTIME,
    C_MAG_GATE,
    C_MAG_HI,
    C_MAG_MODE,
    C_MAG_RECOVER,
    C_MAG_SI,
    C_MAG_TAU,
    C_MAG_TOL,
    C_MAG_UNDIST,
    C_MAXDT,
    C_MREF,
    C_MREF_GIVEN,
    C_MUKF_NOISE,
    C_NX,
    C_PAPER,
    C_QA,
    C_RA,
    C_REST,
    C_REST_ACC,
    C_REST_GYR,
    C_REST_SPLIT,
    C_REST_TIME,
    C_REST_VAR,
    C_RW,
    C_USE_MAG,
    C_W0,
    F_EVER,
    F_HEADING,
    F_INIT,
    F_MCOUNT,
    K_ACC_INVALID,
    K_ACC_MISSING,
    K_ACC_REJ_CHI2,
    K_ACC_REJ_NORM,
    K_BEFORE_INIT,
    K_GAPS,
    K_GYR_INVALID,
    K_GYR_MISSING,
    K_GYR_REJ_CHI2,
    K_MAG_INVALID,
    K_MAG_MISSING,
    K_MAG_REJ_CHI2,
    K_MAG_REJ_DIP,
    K_MAG_REJ_INCONS,
    K_MAG_REJ_NORM,
    K_REST,
    K_SAMPLES,
    K_UPDATE_FAILED,
    MAG_HEADING,
    MAG_REF_SAMPLES,
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    N_QA,
    N_QB,
    N_QM,
    N_QW,
    N_RA,
    N_RM,
    N_RW,
    NX_MAX,
    P0_PAPER,
    REST_CHI2,
    REST_LP_TAU,
    S_AEX,
    S_ALP,
    S_ALPHA,
    S_ALR,
    S_ALT,
    S_AWLP,
    S_B,
    S_DTA,
    S_DTM,
    S_E,
    S_GLP,
    S_GREJ,
    S_MLP,
    S_MLT,
    S_MNORM,
    S_MREF,
    S_MSUM,
    S_QC,
    S_RDEV,
    S_RDT,
    S_T_ACC,
    S_T_MAG,
    S_T_MAGOK,
    S_T_REST,
    S_W,
    S_WLP,
    UP,
    YAW0_STDDEV,
    YAW_VAR_UNKNOWN,
    classify_reading,
    inflate_world,
    mag_yaw_var,
    noise33,
    recentre,
    set_world_attitude_cov,
)


@jit_inline
def _unit_t(v: tuple) -> tuple:
    n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return (v[0] / n, v[1] / n, v[2] / n)


@jit
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@jit
def _learn_mag_ref(cfg: np.ndarray, st: np.ndarray, fl: np.ndarray, m_body: np.ndarray,
                   m_norm: float) -> None:
    """Learn the Earth field from the first accepted samples: the magnitude, and the dip from
    the average of ``R(q̂) m`` keeping its (north, up) components — north is *defined* by the
    field's horizontal part. A given ``mag_reference`` fixes the direction; the magnitude is
    still learned (any unit)."""
    if fl[F_MCOUNT] >= MAG_REF_SAMPLES:
        return
    n = fl[F_MCOUNT]
    st[S_MNORM] = (st[S_MNORM] * n + m_norm) / (n + 1)
    fl[F_MCOUNT] = n + 1
    if cfg[C_MREF_GIVEN] > 0:
        st[S_MREF:S_MREF + 3] = cfg[C_MREF:C_MREF + 3]
        return
    st[S_MSUM:S_MSUM + 3] += rotate(st[S_QC:S_QC + 4], m_body)
    s = st[S_MSUM:S_MSUM + 3]
    st[S_MREF:S_MREF + 3] = _unit(np.array((0.0, np.sqrt(s[0] * s[0] + s[1] * s[1]), s[2])))


@jit
def _heading_init(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
                  m_body: np.ndarray, m_norm: float) -> None:
    """Closed-form heading from a magnetometer sample; the yaw variance then reflects it."""
    recentre(cfg, st, P)
    nx = int(cfg[C_NX])
    if cfg[C_MREF_GIVEN] > 0:
        ref = cfg[C_MREF:C_MREF + 3].copy()
    else:
        m = rotate(st[S_QC:S_QC + 4], m_body)
        ref = _unit(np.array((0.0, np.sqrt(m[0] * m[0] + m[1] * m[1]), m[2])))
    st[S_MSUM:S_MSUM + 3] = 0.0
    st[S_MNORM] = 0.0
    fl[F_MCOUNT] = 0
    rot = heading_correction(st[S_QC:S_QC + 4], m_body, ref)
    st[S_QC:S_QC + 4] = qnormalize(qmul(rot, st[S_QC:S_QC + 4]))
    st[S_MREF:S_MREF + 3] = ref
    set_world_attitude_cov(st, P, nx, 0.0, mag_yaw_var(cfg, ref), True)
    fl[F_HEADING] = 1
    st[S_T_MAG] = 0.0
    st[S_T_MAGOK] = 0.0
    st[S_MLT] = 0.0
    for i in range(3):  # the field's low-pass starts at this sample (unit magnitude)
        st[S_MLP + i] = m_body[i]
    _learn_mag_ref(cfg, st, fl, m_body, m_norm)


@jit
def _align(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
           gyr: np.ndarray, has_g: bool, acc: np.ndarray, m_body: np.ndarray,
           m_norm: float, has_m: bool) -> None:
    """Closed-form initialisation (or re-alignment after a gap) from one sample."""
    nx = int(cfg[C_NX])
    q = align_tilt(acc)
    if fl[F_EVER] > 0:  # re-alignment: keep the heading we had (of the estimate q̂)
        recentre(cfg, st, P)
        q = keep_yaw(q, st[S_QC:S_QC + 4])
    st[S_QC:S_QC + 4] = q
    st[S_E:S_E + 3] = 0.0
    st[S_W:S_W + 3] = gyr - st[S_B:S_B + 3] if has_g else np.zeros(3)
    Pb = P[6:9, 6:9].copy()
    P[:, :] = 0.0
    for i in range(3):
        P[3 + i, 3 + i] = cfg[C_RW] if has_g else 1.0
    if nx == 9:
        P[6:9, 6:9] = Pb if fl[F_EVER] > 0 else eye(3, cfg[C_B0])
        if has_g:  # ω̄ = g − b̄: the rate inherits the bias uncertainty, anti-correlated
            P[3:6, 3:6] += P[6:9, 6:9]
            P[3:6, 6:9] = -P[6:9, 6:9]
            P[6:9, 3:6] = -P[6:9, 6:9]
    # heading: defined by the start-up heading at the first alignment; after a gap it is kept
    # but unknown (uniform over ±180°) until a magnetometer fixes it
    # (with use_mag: unknown until the first magnetometer sample fixes it)
    var_yaw = (YAW_VAR_UNKNOWN if fl[F_EVER] > 0 or cfg[C_USE_MAG] > 0
               else YAW0_STDDEV ** 2)
    # one sample's tilt: wrong by whatever the body's acceleration is at that instant, up to
    # three times acc_disturbance (so that the first corrections go to the attitude, not to
    # the gyro bias)
    set_world_attitude_cov(st, P, nx, cfg[C_RA] + 9.0 * cfg[C_QA], var_yaw, False)
    fl[F_INIT] = 1
    fl[F_EVER] = 1
    fl[F_HEADING] = 0
    st[S_T_ACC] = 0.0
    st[S_T_REST] = 0.0
    for i in range(3):  # the low-passes start at this sample
        st[S_ALP + i] = acc[i]
        st[S_ALP + 3 + i] = acc[i]
        st[S_ALR + i] = acc[i]
        st[S_GLP + i] = gyr[i] if has_g else 0.0
    st[S_RDEV] = st[S_RDEV + 1] = 0.0
    st[S_RDT] = st[S_RDT + 1] = 0.0
    st[S_GREJ] = 0.0
    st[S_ALT] = 0.0
    st[S_DTA] = 0.0
    st[S_AEX] = 0.0
    if has_m:
        _heading_init(cfg, st, P, fl, m_body, m_norm)


@jit
def _paper_init(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray) -> None:
    """The paper's start: ``q̄ = (1,0,0,0)``, ``P = 10² I₆``, ``ω̄ = 0`` (MEKF) or
    ``10⁻¹⁰(1,1,1)`` (MUKF, "breaks the symmetry") (§5, §6, §8 item 9)."""
    nx = int(cfg[C_NX])
    st[S_QC:S_QC + 4] = np.array((1.0, 0.0, 0.0, 0.0))
    st[S_E:S_E + 3] = 0.0
    st[S_W:S_W + 3] = 1e-10 if int(cfg[C_ALGO]) == 1 else 0.0
    P[:, :] = 0.0
    for i in range(6):
        P[i, i] = P0_PAPER
    if nx == 9:
        for i in range(6, 9):
            P[i, i] = cfg[C_B0]
    st[S_MREF:S_MREF + 3] = cfg[C_MREF:C_MREF + 3]
    st[S_T_ACC] = st[S_T_MAG] = st[S_T_REST] = 0.0
    fl[F_INIT] = 1
    fl[F_EVER] = 1
    fl[F_HEADING] = 1


@jit_inline
def calibrate_mag(cfg: np.ndarray, mag: tuple) -> tuple:
    """Hard- and soft-iron correction ``m = S (m_raw − h)`` (extension; sensor units)."""
    v0, v1, v2 = mag[0] - cfg[C_MAG_HI], mag[1] - cfg[C_MAG_HI + 1], mag[2] - cfg[C_MAG_HI + 2]
    return (cfg[C_MAG_SI] * v0 + cfg[C_MAG_SI + 1] * v1 + cfg[C_MAG_SI + 2] * v2,
            cfg[C_MAG_SI + 3] * v0 + cfg[C_MAG_SI + 4] * v1 + cfg[C_MAG_SI + 5] * v2,
            cfg[C_MAG_SI + 6] * v0 + cfg[C_MAG_SI + 7] * v1 + cfg[C_MAG_SI + 8] * v2)


@jit_inline
def _rotate_state(st: np.ndarray, o: int, R: tuple) -> None:
    """A 3-vector of ``st`` kept in body axes follows the body over one step: ``v ← R(Δq)ᵀ v``."""
    x = (st[o], st[o + 1], st[o + 2])
    for i in range(3):
        st[o + i] = R[0][i] * x[0] + R[1][i] * x[1] + R[2][i] * x[2]


@jit_inline
def _acc_measurement(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, dt: float, wl: tuple,
                     Rw: tuple, a: tuple, has_a: bool) -> tuple[tuple, float, tuple, float, int]:
    """The accelerometer as the filters fuse it (extension, issue 13): the unit direction and
    the disturbance variance per sample ``Q_a`` (normalised units), the raw sample's direction
    and variance (the baselines fuse those, as in the report), and a status: 0 fused, 1 the raw
    sample failed the magnitude test (``acc_norm_tolerance``) and only the low-pass is fused,
    2 nothing is fused (no sample, or the low-pass itself fails the test).

    Two views of gravity, each with its own error model, blended by inverse variance:

    * the raw sample: wrong by the non-gravitational acceleration now. Its variance is
      ``acc_disturbance²`` plus the sample's own magnitude excess and twice the recent excess
      power (``E[(|a| − g)²]`` over ``acc_time_constant``, less the white noise's share: the
      two components across gravity that a norm cannot see);
    * the low-pass (two first-order stages, ``acc_time_constant``) in an almost inertial frame:
      its memory turns with the body by the gyro, so gravity passes however the body turns and
      a non-gravitational acceleration, the derivative of a bounded velocity, averages out. It
      is wrong by what is left of that: ``acc_disturbance²``, its own magnitude excess and the
      difference between its two stages (a slow push still passing through), and by the gyro's
      error over the rotation in its memory, ``(gyro_scale_error · 2τ |ω|)²``.

    Shaking and vibration make the raw view noisy and leave the low-pass right; a fast turn,
    a saturated or miscalibrated gyro spoil the low-pass's memory while the raw view holds.
    Both errors are correlated in time: the variance per sample is ``max(1, T/Δt_a)`` times
    the above, ``T = acc_disturbance_time``, ``Δt_a`` the time since the previous
    accelerometer sample (the information per second does not grow with the sample rate).
    The low-pass starts as a running mean and is used once that first average is complete.
    Without it (``acc_time_constant = 0``) the raw sample alone."""
    tau = cfg[C_ACC_TAU]
    if tau > 0.0:
        _rotate_state(st, S_ALP, Rw)
        _rotate_state(st, S_ALP + 3, Rw)
    st[S_DTA] += dt
    zero3 = (0.0, 0.0, 0.0)
    if not has_a:
        return zero3, 0.0, zero3, 0.0, 2
    dta = st[S_DTA]
    st[S_DTA] = 0.0
    g0 = cfg[C_GRAVITY]
    n_raw = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    ex = n_raw / g0 - 1.0
    ex2 = max(0.0, ex * ex - cfg[C_RA])  # the excess beyond what white noise explains
    q_raw = nz[N_QA, 0, 0] + ex * ex
    u_raw = (a[0] / n_raw, a[1] / n_raw, a[2] / n_raw)
    kq = _correlated(cfg[C_ACC_DTIME], dta)
    tol = cfg[C_ACC_TOL]
    if tau <= 0.0:
        return u_raw, kq * q_raw, u_raw, q_raw, 0 if abs(ex) <= tol else 2
    al, start = _lowpass_gain(st, S_ALT, 0, dta, tau)  # start: still the first average
    _lowpass_state(st, S_ALP, a, al)
    _lowpass_state(st, S_ALP + 3, (st[S_ALP], st[S_ALP + 1], st[S_ALP + 2]), 1.0 if start else al)
    st[S_AEX] += al * (ex2 - st[S_AEX])
    st[S_AWLP] += al * (np.sqrt(wl[0] ** 2 + wl[1] ** 2 + wl[2] ** 2) - st[S_AWLP])
    if start:  # the low-pass is still forming its first average: the raw sample alone
        return u_raw, kq * q_raw, u_raw, q_raw, 0 if abs(ex) <= tol else 2
    lp = (st[S_ALP + 3], st[S_ALP + 4], st[S_ALP + 5])
    n_lp = np.sqrt(lp[0] * lp[0] + lp[1] * lp[1] + lp[2] * lp[2])
    ex_lp = n_lp / g0 - 1.0
    u_lp = (lp[0] / n_lp, lp[1] / n_lp, lp[2] / n_lp)
    rot = cfg[C_GYR_SCALE] * 2.0 * tau * st[S_AWLP]
    # a slow acceleration (a push, a brake) is still passing while the stages disagree
    d2 = ((st[S_ALP] - lp[0]) ** 2 + (st[S_ALP + 1] - lp[1]) ** 2
          + (st[S_ALP + 2] - lp[2]) ** 2) / (g0 * g0)
    q_lp = nz[N_QA, 0, 0] + ex_lp * ex_lp + d2 + rot * rot
    if abs(ex_lp) > tol:  # refused (the low-pass holds a sustained acceleration)
        return u_lp, kq * q_lp, u_raw, q_raw, 2
    if abs(ex) > tol:  # an implausible raw sample has no say (the low-pass still takes it:
        return u_lp, kq * q_lp, u_raw, q_raw, 1  # shaking is symmetric about gravity)
    q_rw = nz[N_QA, 0, 0] + ex2 + 2.0 * st[S_AEX]
    w = q_rw / (q_rw + q_lp)
    u = (w * u_lp[0] + (1.0 - w) * u_raw[0], w * u_lp[1] + (1.0 - w) * u_raw[1],
         w * u_lp[2] + (1.0 - w) * u_raw[2])
    return _unit_t(u), kq * q_lp * q_rw / (q_lp + q_rw), u_raw, q_raw, 0


@jit_inline
def _alpha(st: np.ndarray, k: int, dt: float, tau: float) -> float:
    """``1 − exp(−Δt/τ)``, the gain of a first-order low-pass, kept in ``st`` for the last
    (Δt, τ) of low-pass ``k``: at a fixed rate it is computed once (measured: the MEKF 9D loop
    spent ~8 % of its time in these exponentials)."""
    o = S_ALPHA + 3 * k
    if st[o] != dt or st[o + 1] != tau:
        st[o] = dt
        st[o + 1] = tau
        st[o + 2] = 1.0 - np.exp(-dt / tau)
    return st[o + 2]


@jit_inline
def _lowpass_gain(st: np.ndarray, o: int, k: int, dt: float, tau: float) -> tuple[float, bool]:
    """Gain of a first-order low-pass with time constant ``tau`` (cache slot ``k`` of
    :func:`_alpha`) that starts as the running mean: for the first ``tau`` seconds since its
    start (``st[o]``, s) it averages every sample equally, so that no single first sample
    dominates its memory (as VQF does). Also whether it is still in that start.

    ``Δt = 0`` (a sample at the same instant as the previous one) has no time to average over:
    the low-pass keeps its memory (gain 0), unless nothing is averaged yet (``st[o] = 0``):
    then, as for any first sample, it starts from this one (gain 1)."""
    t = st[o]
    st[o] = t + dt
    if not dt > 0.0:
        return (1.0, True) if t <= 0.0 else (0.0, t < tau)
    a = _alpha(st, k, dt, tau)
    m = dt / (t + dt)
    return (m, True) if m > a else (a, False)


@jit_inline
def _correlated(T: float, dt: float) -> float:
    """``max(1, T/Δt)``: how much a disturbance correlated over ``T`` (s) widens the variance
    of samples ``Δt`` apart, so that their information per second does not grow with the rate.
    ``Δt = 0`` (readings at one instant, or the first since the start) has no rate: 1, the
    per-sample variance."""
    return T / dt if 0.0 < dt < T else 1.0


@jit_inline
def _lowpass_state(st: np.ndarray, o: int, v: tuple, al: float) -> None:
    """First-order low-pass step of a 3-vector of ``st``: ``x ← x + α (v − x)``."""
    for i in range(3):
        st[o + i] += al * (v[i] - st[o + i])


@jit_inline
def _gyro_gate(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, nx: int, cnt: np.ndarray,
               g: tuple) -> bool:
    """The gyro's innovation gate (issue 13): the innovation ``g − ω̄ − b̄`` against
    ``S = H P Hᵀ + R_ω`` (``H = [0, I, I]``), χ² with ``gyro_gate``. One sample alone beyond it
    is an outlier (a corrupted message): it is skipped — it reaches neither the filter nor the
    inertial low-passes — and counted. A second one in a row says the rate did change that
    much: the rate's prior was too narrow by the innovation, so its variance grows by it
    (``P_ωω += diag(r²)``) and the sample is taken. Returns whether to use the sample."""
    bias = nx == 9
    r = (g[0] - st[S_W] - (st[S_B] if bias else 0.0), g[1] - st[S_W + 1]
         - (st[S_B + 1] if bias else 0.0), g[2] - st[S_W + 2] - (st[S_B + 2] if bias else 0.0))
    rw = cfg[C_RW]
    if r[0] * r[0] + r[1] * r[1] + r[2] * r[2] <= cfg[C_GYR_GATE] * rw:
        st[S_GREJ] = 0.0  # S ⪰ R_ω I, so rᵀ S⁻¹ r ≤ |r|²/R_ω: within the gate, no inverse needed
        return True
    s = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    for i in range(3):
        for j in range(3):
            v = P[3 + i, 3 + j]
            if bias:
                v += P[3 + i, 6 + j] + P[6 + i, 3 + j] + P[6 + i, 6 + j]
            s[i][j] = v + (rw if i == j else 0.0)
    okinv, Si = inv3_spd_t((s[0][0], s[0][1], s[0][2], s[1][1], s[1][2], s[2][2]))
    nis = 0.0
    for i in range(3):
        for j in range(3):
            nis += r[i] * Si[i][j] * r[j]
    if okinv and not nis > cfg[C_GYR_GATE]:
        st[S_GREJ] = 0.0
        return True
    cnt[K_GYR_REJ_CHI2] += 1
    if st[S_GREJ] > 0:
        for i in range(3):
            P[3 + i, 3 + i] += r[i] * r[i]
        st[S_GREJ] = 0.0
        return True
    st[S_GREJ] = 1.0
    return False


@jit_inline
def _rest_test(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, nx: int, dt: float, g: tuple,
               has_g: bool, a: tuple, has_a: bool, g_none: bool, a_none: bool) -> bool:
    """Rest detection (extension): for ``rest_time`` without a break, the gyro and the
    accelerometer stay within ``rest_gyro_threshold`` / ``rest_acc_threshold`` of their own
    low-pass, RMS over REST_LP_TAU (the body is steady; a vibrating or rolling body is not) and the
    low-passed rate, less the bias estimate, could be a gyro bias: χ² against the prior
    ``gyro_bias_stddev²`` plus the rest noise (a faster turn is not rest; the current ``P_bb``
    would lock a wrongly learned bias out of its own correction). A steady slow turn within
    that cannot be told from a bias by an IMU alone; the zero-rate update therefore never
    moves the attitude (the rate updates in :func:`sensor_step_t`).

    Split input (``C_REST_SPLIT``: gyro and accelerometer in separate samples): a step without
    a reading of one sensor (``g_none`` / ``a_none``: not given, as opposed to rejected) keeps
    that sensor's part of the test as its last sample left it, each low-pass steps over the
    time since its own previous sample, and only a step with a gyro reading is at rest. The
    accelerometer, often at a lower rate than the gyro, has its squared deviation scaled by
    ``(2 − α) / (2 (1 − α)²)``: a deviation from a low-pass that includes the sample
    underestimates the sample variance by that factor (white noise; 1 % at α = 0.008, a
    250 Hz sample, 5 % at α = 0.03, a quarter of that), so ``rest_acc_threshold`` means the
    same at any accelerometer rate."""
    split = cfg[C_REST_SPLIT] > 0
    if split:
        st[S_RDT] += dt
        st[S_RDT + 1] += dt
    if cfg[C_REST] <= 0 or not ((has_g or (split and g_none))
                                and (has_a or (split and a_none))):
        st[S_T_REST] = 0.0
        return False
    dtg = dt
    if split:
        dtg = st[S_RDT]
        al = _alpha(st, 2, dtg, REST_LP_TAU) if has_g else 0.0
        ala = 1.0 - np.exp(-st[S_RDT + 1] / REST_LP_TAU) if has_a else 0.0
        if has_g:
            st[S_RDT] = 0.0
        if has_a:
            st[S_RDT + 1] = 0.0
    else:
        al = ala = _alpha(st, 2, dt, REST_LP_TAU)
    # mean squared deviations: a single noisy sample does not end a rest
    if has_g:
        _lowpass_state(st, S_GLP, g, al)
        dg = (g[0] - st[S_GLP]) ** 2 + (g[1] - st[S_GLP + 1]) ** 2 + (g[2] - st[S_GLP + 2]) ** 2
        st[S_RDEV] += al * (dg - st[S_RDEV])
    if has_a:
        _lowpass_state(st, S_ALR, a, ala)
        da = (a[0] - st[S_ALR]) ** 2 + (a[1] - st[S_ALR + 1]) ** 2 + (a[2] - st[S_ALR + 2]) ** 2
        if split:  # unbiased at any rate (see above)
            da *= (2.0 - ala) / (2.0 * (1.0 - ala) ** 2)
        st[S_RDEV + 1] += ala * (da - st[S_RDEV + 1])
    steady = st[S_RDEV] < cfg[C_REST_GYR] ** 2 and st[S_RDEV + 1] < cfg[C_REST_ACC] ** 2
    if steady:
        v = cfg[C_REST_VAR] + cfg[C_RW] * dtg / (2.0 * REST_LP_TAU)
        if nx == 9:
            v += cfg[C_B0]
            b = (st[S_B], st[S_B + 1], st[S_B + 2])
        else:
            b = (0.0, 0.0, 0.0)
        r = (st[S_GLP] - b[0], st[S_GLP + 1] - b[1], st[S_GLP + 2] - b[2])
        steady = (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]) / v < REST_CHI2
    if steady:
        st[S_T_REST] += dt
    else:
        st[S_T_REST] = 0.0
    return has_g and st[S_T_REST] >= cfg[C_REST_TIME]


@jit_inline
def _mag_checks(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
                cnt: np.ndarray, dt: float, dtm: float, wl: tuple, Rw: tuple, m_body: tuple,
                m_norm: float, has_m: bool) -> bool:
    """Whether this magnetometer sample may be fused (extension, issue 13), in this order:

    * consistency: the field over its learned magnitude, low-passed in the same almost
      inertial frame as the accelerometer (``mag_time_constant``), must stay within
      ``mag_consistency_tolerance`` of each new sample (plus the gyro's own scale error over
      the rotation in that memory). A field fixed in the world passes however the body turns;
      a magnet on the body turns with it, and a field that changes along the path changes;
    * plausibility: magnitude and dip against the learned reference (:func:`_mag_plausible`);
    * both held for ``mag_undisturbed_time`` without a break;
    * recovery: a plausible, consistent field that the χ² gate has refused for
      ``mag_recovery_time`` says that the heading is what is wrong: its variance grows by the
      disagreement (no snap: the next updates pull it in).

    Counted when refused."""
    _rotate_state(st, S_MLP, Rw)
    alm = _alpha(st, 3, dt, cfg[C_MAG_TAU])
    st[S_WLP] += alm * (np.sqrt(wl[0] ** 2 + wl[1] ** 2 + wl[2] ** 2) - st[S_WLP])
    if not has_m:
        return False
    alm, _ = _lowpass_gain(st, S_MLT, 1, dtm, cfg[C_MAG_TAU])
    ok = True
    if fl[F_MCOUNT] > 0:
        k = m_norm / st[S_MNORM]
        mv = (m_body[0] * k, m_body[1] * k, m_body[2] * k)
        dev2 = ((mv[0] - st[S_MLP]) ** 2 + (mv[1] - st[S_MLP + 1]) ** 2
                + (mv[2] - st[S_MLP + 2]) ** 2)
        _lowpass_state(st, S_MLP, mv, alm)
        tol2 = cfg[C_MAG_CTOL] ** 2 + (cfg[C_GYR_SCALE] * cfg[C_MAG_TAU] * st[S_WLP]) ** 2
        if dev2 > tol2:
            cnt[K_MAG_REJ_INCONS] += 1
            ok = False
    Rq = rotmat_t((st[S_QC], st[S_QC + 1], st[S_QC + 2], st[S_QC + 3]))
    if ok and not _mag_plausible(cfg, st, fl, cnt, Rq, m_body, m_norm):
        ok = False
    if not ok:
        st[S_T_MAGOK] = 0.0
        st[S_T_MAG] = 0.0  # disturbance, not evidence of a wrong heading
        return False
    st[S_T_MAGOK] += dtm
    if st[S_T_MAGOK] < cfg[C_MAG_UNDIST]:
        return False
    if st[S_T_MAG] > cfg[C_MAG_RECOVER]:
        h = np.sqrt(st[S_MREF] ** 2 + st[S_MREF + 1] ** 2)
        psi, _ = heading_residual_t(Rq, m_body, (st[S_MREF] / h, st[S_MREF + 1] / h, 0.0))
        baseline_export(cfg, st, P)
        inflate_world(st, P, 0.0, psi * psi)
        from_canonical(cfg, st, P)
        st[S_T_MAG] = 0.0
    return True


@jit_inline
def _cap_yaw_variance(st: np.ndarray, P: np.ndarray, nx: int) -> None:
    """An angle uniform over ±180° has variance π²/3 (YAW_VAR_UNKNOWN); a Gaussian heading
    variance beyond that (6D: the unobservable vertical bias integrated for long) means
    nothing and spreads the MUKF's sigma points past the charts' domains. Scale the attitude
    error along the world vertical ``u`` so that its variance is the cap: ``P ← D P Dᵀ`` with
    ``D = I + (s − 1) u uᵀ`` on the attitude rows (a congruence: P stays PSD)."""
    R = rotmat_t((st[S_QC], st[S_QC + 1], st[S_QC + 2], st[S_QC + 3]))
    u = R[2]
    v = 0.0
    for i in range(3):
        for j in range(3):
            v += u[i] * P[i, j] * u[j]
    if not v > YAW_VAR_UNKNOWN:
        return
    c = np.sqrt(YAW_VAR_UNKNOWN / v) - 1.0
    for j in range(nx):  # rows: P[0:3, j] += c u (uᵀ P[0:3, j])
        t = c * (u[0] * P[0, j] + u[1] * P[1, j] + u[2] * P[2, j])
        for i in range(3):
            P[i, j] += u[i] * t
    for i in range(nx):  # columns
        t = c * (u[0] * P[i, 0] + u[1] * P[i, 1] + u[2] * P[i, 2])
        for j in range(3):
            P[i, j] += t * u[j]


@jit_inline
def _mag_plausible(cfg: np.ndarray, st: np.ndarray, fl: np.ndarray, cnt: np.ndarray,
                   R: tuple, m_body: tuple, m_norm: float) -> bool:
    """Field magnitude and dip against the learned reference (extension); counted if not."""
    if fl[F_MCOUNT] < 10:
        return True  # reference still being learned
    if abs(m_norm / st[S_MNORM] - 1.0) > cfg[C_MAG_TOL]:
        cnt[K_MAG_REJ_NORM] += 1
        return False
    mz = R[2][0] * m_body[0] + R[2][1] * m_body[1] + R[2][2] * m_body[2]
    dip = np.arcsin(max(-1.0, min(1.0, mz)))
    dip_ref = np.arcsin(max(-1.0, min(1.0, st[S_MREF + 2])))
    if abs(dip - dip_ref) > cfg[C_DIP_TOL]:
        cnt[K_MAG_REJ_DIP] += 1
        return False
    return True


@jit
def sensor_step(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                fl: np.ndarray, cnt: np.ndarray, dt: float, gyr: np.ndarray, acc: np.ndarray,
                mag: np.ndarray) -> None:
    """Process one sample: any of ``gyr`` (rad/s), ``acc`` (m/s², +g up at rest) and ``mag``
    (any unit) may be NaN (missing). ``dt`` is the time since the previous sample."""
    sensor_step_t(cfg, nz, st, P, fl, cnt, dt, t3(gyr), t3(acc), t3(mag), np.empty(NX_MAX),
                 mekf_scratch(NX_MAX), mukf_scratch(int(cfg[C_NX])))


@jit_inline
def sensor_step_t(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                 fl: np.ndarray, cnt: np.ndarray, dt: float, gyr: tuple, acc: tuple,
                 mag: tuple, dx: np.ndarray, work: np.ndarray, mwork: tuple) -> None:
    """:func:`sensor_step` with the readings as 3-tuples and the filters' scratch given (``dx``:
    9 values, ``work``: ``mekf_scratch(9)``, ``mwork``: ``mukf_scratch(nx)``). Speed: the
    common path (MEKF or MUKF, every sensor valid) works on tuples and elements of ``st``,
    ``nz`` and ``P``: no allocation, no array views (each costs reference counting, atomic
    operations that outweigh a small filter's arithmetic); the rare paths build arrays."""
    cnt[K_SAMPLES] += 1
    use_mag = cfg[C_USE_MAG] > 0
    gs = classify_reading(gyr, False, MAX_GYRO_RATE)
    as_ = classify_reading(acc, True, MAX_ACC_G * cfg[C_GRAVITY])
    m_cal = calibrate_mag(cfg, mag) if use_mag else mag
    ms = classify_reading(m_cal, True, MAX_MAG) if use_mag else 1
    if gs > 0:
        cnt[K_GYR_MISSING if gs == 1 else K_GYR_INVALID] += 1
    if as_ > 0:
        cnt[K_ACC_MISSING if as_ == 1 else K_ACC_INVALID] += 1
    if use_mag and ms > 0:
        cnt[K_MAG_MISSING if ms == 1 else K_MAG_INVALID] += 1
    has_g, has_a, has_m = gs == 0, as_ == 0, ms == 0
    zero3 = (0.0, 0.0, 0.0)
    g = gyr if has_g else zero3
    m_norm = np.sqrt(m_cal[0] ** 2 + m_cal[1] ** 2 + m_cal[2] ** 2) if has_m else 0.0
    m_body = _unit_t(m_cal) if has_m else zero3

    if fl[F_INIT] > 0 and dt > cfg[C_MAXDT]:
        cnt[K_GAPS] += 1
        fl[F_INIT] = 0  # re-align from this (or the next) accelerometer sample, keeping yaw
    if fl[F_INIT] == 0:
        if cfg[C_PAPER] > 0:
            _paper_init(cfg, st, P, fl)
            from_canonical(cfg, st, P)
        elif has_a:
            _align(cfg, st, P, fl, np.array(g), has_g, np.array(acc), np.array(m_body), m_norm,
                   has_m)
            from_canonical(cfg, st, P)
            return
        else:
            cnt[K_BEFORE_INIT] += 1
            return

    nx = int(cfg[C_NX])
    chart = int(cfg[C_CHART])
    algo_ = int(cfg[C_ALGO])
    if has_m and fl[F_HEADING] == 0:
        baseline_export(cfg, st, P)  # baselines: the sensor layer works on (q̄, P_ee, ...)
        _heading_init(cfg, st, P, fl, np.array(m_body), m_norm)
        from_canonical(cfg, st, P)
        has_m = False  # this sample set the heading; do not count it twice
    st[S_T_ACC] += dt
    if st[S_T_MAG] > 0.0:  # inside a period of disagreement with a plausible field
        st[S_T_MAG] += dt

    if has_g and algo_ <= ALGO_MUKF and cfg[C_GYR_GATE] > 0 and cfg[C_PAPER] <= 0:
        has_g = _gyro_gate(cfg, st, P, nx, cnt, g)
        if not has_g:
            g = zero3
    # the gyro's rate (bias removed) over this step, for the inertial low-passes below
    wl = ((g[0] - st[S_B], g[1] - st[S_B + 1], g[2] - st[S_B + 2]) if has_g
          else (st[S_W], st[S_W + 1], st[S_W + 2]))
    Rw = rotmat_t(q_omega_t(wl, dt))  # R(Δq): body axes of the previous sample → this one
    a_raw = acc
    # accelerometer: the raw sample and its low-pass in an almost inertial frame
    # (acc_time_constant > 0), blended by their variances; then the magnitude test
    a_body, qa, a_rawu, qa_raw, a_stat = _acc_measurement(cfg, nz, st, dt, wl, Rw, acc, has_a)
    acc_gate = cfg[C_ACC_GATE] if cfg[C_ACC_GATE] > 0 else np.inf
    if has_a:
        if st[S_T_ACC] > cfg[C_ACC_RECOVER]:
            # rejected for this long: the estimate may be what is wrong. Its tilt variance
            # grows by the measured disagreement (no forced update: the gates then judge
            # against the wider prior, and a sample still refused grows it again later)
            up = rotate_inv(st[S_QC:S_QC + 4], UP)
            ang = np.arccos(max(-1.0, min(1.0, up[0] * a_body[0] + up[1] * a_body[1]
                                          + up[2] * a_body[2])))
            baseline_export(cfg, st, P)
            if not baseline_realign(cfg, st, P, acc, wl):
                inflate_world(st, P, ang * ang, 0.0)
            from_canonical(cfg, st, P)
            st[S_T_ACC] = 0.0
        if a_stat > 0:
            cnt[K_ACC_REJ_NORM] += 1
        if a_stat == 2:
            has_a = False
    Qa = ((qa, 0.0, 0.0), (0.0, qa, 0.0), (0.0, 0.0, qa))
    rest = _rest_test(cfg, st, P, nx, dt, g, has_g, a_raw, has_a, gs > 0, as_ > 0)
    heading = int(cfg[C_MAG_MODE]) == MAG_HEADING
    mag_gate = cfg[C_MAG_GATE] if cfg[C_MAG_GATE] > 0 else np.inf
    if cfg[C_PAPER] > 0:  # the paper's start has no prior to gate against
        acc_gate = mag_gate = np.inf
    st[S_DTM] += dt
    dtm = st[S_DTM]  # time since the previous magnetometer sample
    if has_m:
        st[S_DTM] = 0.0
    if use_mag and fl[F_HEADING] > 0 and cfg[C_PAPER] <= 0:
        has_m = _mag_checks(cfg, st, P, fl, cnt, dt, dtm, wl, Rw, m_body, m_norm, has_m)
    ok = True
    acc_nis = 0.0
    mag_nis = 0.0
    mref = (st[S_MREF], st[S_MREF + 1], st[S_MREF + 2])
    h = np.sqrt(st[S_MREF] ** 2 + st[S_MREF + 1] ** 2)
    href = (st[S_MREF] / h, st[S_MREF + 1] / h, 0.0) if has_m and heading else zero3
    var_h = (mag_yaw_var(cfg, np.array(mref)) * _correlated(cfg[C_MAG_DTIME], dtm) if has_m
             else 0.0)
    algo = int(cfg[C_ALGO])
    if algo <= ALGO_MUKF and cfg[C_GYR_SCALE] > 0:
        # the gyro's scale and axis errors: attitude noise growing with the rate turned
        qs = cfg[C_GYR_SCALE] ** 2 * (wl[0] ** 2 + wl[1] ** 2 + wl[2] ** 2) * dt
        for i in range(3):
            P[i, i] += qs
    if algo >= ALGO_EULER_KF:  # baselines: no rate/bias state to sharpen at rest
        rest = False
        ok, acc_nis, mag_nis = baseline_update(cfg, nz, st, P, cnt, dt, np.array(g), has_g,
                                                np.array(a_rawu), has_a and a_stat == 0,
                                                qa_raw,
                                                np.array(m_body), has_m, acc_gate, mag_gate)
    else:
        # The rate measurements first: a gyro sample is the rate over the interval that ends
        # at its stamp (what a MEMS gyro reports), so it observes ω̄ at the start of the step
        # and drives the prediction over it. Both are linear in the state, so this Kalman
        # update is exact for the MUKF too; the zero-rate update never moves the attitude.
        w = (st[S_W], st[S_W + 1], st[S_W + 2])
        b = (st[S_B], st[S_B + 1], st[S_B + 2])
        for i in range(nx):
            dx[i] = 0.0
        if has_g:
            ok &= mekf_rate_update_t(P, nx, dx, w, b, g, noise33(nz, N_RW), True, np.inf,
                                     work) >= 0
        if rest:
            vz = cfg[C_REST_VAR]
            ok &= mekf_rate_update_t(P, nx, dx, w, b, zero3, ((vz, 0.0, 0.0), (0.0, vz, 0.0),
                                                             (0.0, 0.0, vz)), False, np.inf,
                                     work, 3) >= 0
        if algo == ALGO_MEKF:
            q, w, b = mekf_apply_t(chart, cfg[C_CU] > 0, (st[S_QC], st[S_QC + 1], st[S_QC + 2],
                                                          st[S_QC + 3]), w, b, P, nx, dx)
            for i in range(4):
                st[S_QC + i] = q[i]
        else:
            for i in range(3):
                st[S_E + i] += dx[i]
            symmetrize_leading(P, nx)
            w = (w[0] + dx[3], w[1] + dx[4], w[2] + dx[5])
            if nx == 9:
                b = (b[0] + dx[6], b[1] + dx[7], b[2] + dx[8])
        for i in range(3):
            st[S_W + i] = w[i]
            st[S_B + i] = b[i]
    if algo == ALGO_MEKF:  # predict, one block per sensor, one move to the manifold
        q = (st[S_QC], st[S_QC + 1], st[S_QC + 2], st[S_QC + 3])
        w = (st[S_W], st[S_W + 1], st[S_W + 2])
        b = (st[S_B], st[S_B + 1], st[S_B + 2])
        q = mekf_predict_t(q, w, P, nx, dt, noise33(nz, N_QW), noise33(nz, N_QB))
        R = rotmat_t(q)
        for i in range(nx):
            dx[i] = 0.0
        if has_a:
            acc_nis = mekf_vector_update_t(P, nx, dx, R, a_body, (0.0, 0.0, 1.0),
                                           noise33(nz, N_RA), Qa, acc_gate,
                                           cfg[C_ACC_MODE] == ACC_TILT, work)
        if has_m:
            if heading:
                mag_nis = mekf_heading_update_t(P, nx, dx, R, m_body, href, var_h, mag_gate)
            else:
                mag_nis = mekf_vector_update_t(P, nx, dx, R, m_body, mref, noise33(nz, N_RM),
                                               noise33(nz, N_QM), mag_gate, False, work)
        q, w, b = mekf_apply_t(chart, cfg[C_CU] > 0, q, w, b, P, nx, dx)
        for i in range(4):
            st[S_QC + i] = q[i]
        for i in range(3):
            st[S_W + i] = w[i]
            st[S_B + i] = b[i]
    elif algo == ALGO_MUKF:  # MUKF: stacked measurement through the sigma points
        ok_u, acc_nis, mag_nis = _mukf_sensor_update(cfg, nz, st, P, nx, chart, dt, g, False,
                                                     a_body, has_a, Qa, m_body, has_m, heading,
                                                     mref, href, var_h, acc_gate, mag_gate,
                                                     mwork)
        ok &= ok_u
    if algo <= ALGO_MUKF:
        _cap_yaw_variance(st, P, nx)
    if not ok or acc_nis < 0 or mag_nis < 0:
        cnt[K_UPDATE_FAILED] += 1
        for i in range(nx):  # regularise so that the next step can factorise again
            P[i, i] += 1e-9
        return
    if rest:
        cnt[K_REST] += 1
    if has_a:
        if acc_nis > acc_gate:
            cnt[K_ACC_REJ_CHI2] += 1
        else:
            st[S_T_ACC] = 0.0
    if has_m:
        if mag_nis > mag_gate:
            cnt[K_MAG_REJ_CHI2] += 1
            st[S_T_MAG] = max(st[S_T_MAG], 1e-12)  # start (or continue) the disagreement clock
        else:
            st[S_T_MAG] = 0.0
            if fl[F_MCOUNT] < MAG_REF_SAMPLES:
                _learn_mag_ref(cfg, st, fl, np.array(m_body), m_norm)


@jit_inline
def _mukf_sensor_update(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                        nx: int, chart: int, dt: float, g: tuple, has_g: bool, a_body: tuple,
                        has_a: bool, Qa: tuple, m_body: tuple, has_m: bool, heading: bool,
                        mref: tuple, href: tuple, var_h: float, acc_gate: float,
                        mag_gate: float, mwork: tuple) -> tuple[bool, float, float]:
    """The MUKF step of :func:`sensor_step`: the stacked measurement through the sigma points
    (:func:`~mkf_ros.core.mukf.mukf_step_t`, scratch ``mwork``). Returns ``(ok, acc NIS,
    mag NIS)``. Reads and writes ``st`` element by element: no allocation, no array views."""
    heading_m = has_m and heading
    use_vm = has_m and not heading
    x = ((st[S_QC], st[S_QC + 1], st[S_QC + 2], st[S_QC + 3]),
         (st[S_E], st[S_E + 1], st[S_E + 2]), (st[S_W], st[S_W + 1], st[S_W + 2]),
         (st[S_B], st[S_B + 1], st[S_B + 2]))
    zero3 = (0.0, 0.0, 0.0)
    ok, q, e, w, b, nis = mukf_step_t(
        chart, cfg[C_CU] > 0, int(cfg[C_MUKF_NOISE]), cfg[C_W0], x, P, nx, dt,
        noise33(nz, N_QW), noise33(nz, N_QB), (a_body, m_body if has_m else zero3),
        ((0.0, 0.0, 1.0), mref if has_m else zero3), (noise33(nz, N_RA), noise33(nz, N_RM)),
        (Qa, noise33(nz, N_QM)), (has_a, use_vm), g, has_g, noise33(nz, N_RW),
        m_body if has_m else zero3, href if has_m else zero3, heading_m, var_h, False,
        cfg[C_REST_VAR], (acc_gate, mag_gate, mag_gate, np.inf), True,
        cfg[C_ACC_MODE] == ACC_TILT, mwork)
    for i in range(4):  # (on failure as far as changed: the reset variant's re-centring)
        st[S_QC + i] = q[i]
    for i in range(3):
        st[S_E + i] = e[i]
        st[S_W + i] = w[i]
        st[S_B + i] = b[i]
    if not ok:
        # a factorisation failed before the prediction: still carry the estimate over Δt
        # (the MEKF's linear prediction from the re-centred mean), so that no time is lost
        recentre(cfg, st, P)
        q = mekf_predict_t((st[S_QC], st[S_QC + 1], st[S_QC + 2], st[S_QC + 3]), w, P, nx, dt,
                           noise33(nz, N_QW), (zero3, zero3, zero3))
        for i in range(4):
            st[S_QC + i] = q[i]
    acc_nis = nis[B_VEC0] if has_a else 0.0
    mag_nis = nis[B_HEADING] if heading else nis[B_VEC1]
    return ok, acc_nis, mag_nis
