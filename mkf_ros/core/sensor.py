"""The sensor layer: one sample of a real IMU through the paper's filters (docs/math.md §8 item 15).

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
  the magnetometer's consistency checks (see each function).

:func:`step` is the per-sample kernel, a sequence of named steps over the filter's records
(:mod:`mkf_ros.core.state`: configuration ``c``, state ``s``, counters ``k``, scratch ``w``);
:mod:`mkf_ros.core.filter` runs it over a recording or one sample at a time. Every step is a
separately compiled function (the records are passed by pointer, so a call costs no
reference counting).
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import types as nt

from mkf_ros.core._jit import jit, jit_inline, tuple_type, unit
from mkf_ros.core.baseline_glue import (
    CANONICAL_T,
    Canonical,
    baseline_realign,
    baseline_update,
)
from mkf_ros.core.frames import align_tilt, heading_correction, keep_yaw
from mkf_ros.core.linalg import (
    ZERO3,
    ZERO33,
    copy_block,
    copy_into,
    eye,
    largest_eigh33_t,
    none_above33_t,
    scale_direction,
    symmetrize_leading,
)
from mkf_ros.core.mekf import (
    heading_residual_t,
    inv3_spd_t,
    mekf_apply_t,
    mekf_heading_update_t,
    mekf_predict_t,
    mekf_rate_update_t,
    mekf_vector_update_t,
)
from mkf_ros.core.mukf import B_HEADING, B_VEC0, B_VEC1, MukfMeasurement, mukf_step_t
from mkf_ros.core.quaternion import (
    q_omega_t,
    qmul,
    qnormalize,
    rotate,
    rotate_inv,
    rotmat_t,
    t3,
    t4,
    up_in_body_t,
)
from mkf_ros.core.state import (
    ACC,
    ACC_CLIP_MIN_G,
    ACC_CLIP_SIGMAS,
    ACC_GATE,
    ACC_NORM_TOLERANCE,
    ACC_RECOVERY_TIME,
    ALGO_EULER_KF,
    ALGO_MEKF,
    ALGO_MUKF,
    CONFIG_T,
    COUNTERS_T,
    F3,
    F33,
    FUSION_T,
    GYR,
    GYRO_GATE,
    GYRO_SCALE_SWING,
    GYRO_SURPRISE_CHI2,
    LP_ACC,
    LP_MAG,
    LP_MAG_SLOW,
    LP_NET,
    LP_RATE,
    LP_REST,
    MAG,
    MAG_GATE,
    MAG_NEW_MIN_RATE,
    MAG_RECOVERY_TIME,
    MAG_REF_SAMPLES,
    MAG_SLOW_TIME,
    MAG_SLOW_TOLERANCE,
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    MISSING,
    P0_PAPER,
    REST_BIAS_RANGE,
    REST_CHI2,
    REST_LP_TAU,
    STATE_T,
    UP,
    VALID,
    WORK_T,
    YAW0_STDDEV,
    YAW_VAR_UNKNOWN,
    Fusion,
    classify_reading,
    count_reading,
    heading_fixed,
    heading_unobserved,
    inflate_world,
    iso33,
    mag_yaw_var,
    recentre,
    record_posterior,
    set_world_attitude_cov,
    step_dt,
)

#: How far (relative) an attitude variance may exceed the cap before it is scaled back to it
#: (:func:`_cap_attitude_variance`).
CAP_SLACK = 1e-6
MAG_SLOW_COS = float(np.cos(MAG_SLOW_TOLERANCE))  # the steadiness test's bound on the cosine
#: The largest heading variance the MUKF's sigma points are drawn with when nothing observes the
#: heading ((π/4)², σ 45°; :func:`_heading_spread`).
MUKF_HEADING_SPREAD_VAR = (np.pi / 4) ** 2
#: The per-sample steps: compiled once each and linked into :func:`step` (they take the
#: records, passed by pointer, so a call costs little).
hot = jit_inline
#: Signature of the filters' updates after the sensor layer: ``(ok, acc NIS, mag NIS)``.
_UPDATE_SIG = nt.Tuple((nt.boolean, nt.float64, nt.float64))


# --- small helpers ---------------------------------------------------------------------------
@hot
def _unit_t(v: tuple) -> tuple:
    n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return (v[0] / n, v[1] / n, v[2] / n)


@jit
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@hot
def _turn(v: np.ndarray, R: tuple) -> None:
    """A 3-vector kept in body axes follows the body over one step: ``v ← R(Δq)ᵀ v``."""
    x = (v[0], v[1], v[2])
    for i in range(3):
        v[i] = R[0][i] * x[0] + R[1][i] * x[1] + R[2][i] * x[2]


@hot
def _age_sensitivity(S: np.ndarray, R: tuple, dt: float) -> None:
    """The low-pass memory's rotation error per unit gyro bias error ages one step
    (docs/math.md §9.1): its content is turned by ``R(Δq)ᵀ`` with the bias-corrected gyro, so
    a bias error ``δb`` turns all of it by a further ``δb Δt`` in this sample's axes:
    ``S ← R(Δq)ᵀ S + I Δt``."""
    for j in range(3):
        x0, x1, x2 = S[0, j], S[1, j], S[2, j]
        for i in range(3):
            S[i, j] = R[0][i] * x0 + R[1][i] * x1 + R[2][i] * x2
        S[j, j] += dt


@hot
def _lowpass_sensitivity(s: np.record, a1: float, a2: float) -> None:
    """The sensitivities follow the two stages: a new sample has none (``S₁ ← (1 − α₁) S₁``),
    the second stage low-passes the first (``S₂ ← S₂ + α₂ (S₁ − S₂)``)."""
    S1, S2 = s.acc_sens, s.acc_sens2
    for i in range(3):
        for j in range(3):
            S1[i, j] *= 1.0 - a1
            S2[i, j] += a2 * (S1[i, j] - S2[i, j])


@hot
def _lowpass(x: np.ndarray, v: tuple, al: float) -> None:
    """First-order low-pass step of a 3-vector: ``x ← x + α (v − x)``."""
    for i in range(3):
        x[i] += al * (v[i] - x[i])


@hot
def _alpha(s: np.record, k: int, dt: float, tau: float) -> float:
    """``1 − exp(−Δt/τ)``, the gain of a first-order low-pass, kept in ``s.lp_gain[k]`` for the
    last (Δt, τ) of low-pass ``k`` (``LP_*``): at a fixed rate it is computed once (measured:
    the MEKF 9D loop spent ~8 % of its time in these exponentials)."""
    g = s.lp_gain
    if g[k, 0] != dt or g[k, 1] != tau:
        g[k, 0] = dt
        g[k, 1] = tau
        g[k, 2] = 1.0 - np.exp(-dt / tau)
    return g[k, 2]


@hot
def _lowpass_gain(s: np.record, k: int, t: float, dt: float, tau: float) -> tuple[float, bool]:
    """Gain of a first-order low-pass with time constant ``tau`` (gain slot ``k`` of
    :func:`_alpha`) that starts as the running mean: for the first ``tau`` seconds since its
    start (``t``, s, before this sample) it averages every sample equally, so that no single
    first sample dominates its memory (as VQF does). Also whether it is still in that start.

    ``Δt = 0`` (a sample at the same instant as the previous one) has no time to average over:
    the low-pass keeps its memory (gain 0), unless nothing is averaged yet (``t = 0``): then,
    as for any first sample, it starts from this one (gain 1)."""
    if not dt > 0.0:
        return (1.0, True) if t <= 0.0 else (0.0, t < tau)
    a = _alpha(s, k, dt, tau)
    m = dt / (t + dt)
    return (m, True) if m > a else (a, False)


@hot
def _correlated(T: float, dt: float) -> float:
    """``max(1, T/Δt)``: how much a disturbance correlated over ``T`` (s) widens the variance
    of samples ``Δt`` apart, so that their information per second does not grow with the rate.
    ``Δt = 0`` (readings at one instant, or the first since the start) has no rate: 1, the
    per-sample variance."""
    return T / dt if 0.0 < dt < T else 1.0


# --- 1. the sample's readings ----------------------------------------------------------------
@hot
def calibrate_mag(c: np.record, mag: tuple) -> tuple:
    """Hard- and soft-iron correction ``m = S (m_raw − h)`` (extension; sensor units)."""
    h, S = c.mag_hard_iron, c.mag_soft_iron
    v0, v1, v2 = mag[0] - h[0], mag[1] - h[1], mag[2] - h[2]
    return (S[0, 0] * v0 + S[0, 1] * v1 + S[0, 2] * v2,
            S[1, 0] * v0 + S[1, 1] * v1 + S[1, 2] * v2,
            S[2, 0] * v0 + S[2, 1] * v1 + S[2, 2] * v2)


@hot
def _read(c: np.record, k: np.record, gyr: tuple, acc: tuple, mag: tuple) -> tuple:
    """Classify the sample's three readings (:func:`~mkf_ros.core.state.classify_reading`,
    counted) and calibrate the field. Returns ``(gs, as_, ms, m_body, m_norm)``: the classes,
    the field's unit direction and magnitude (zero unless valid)."""
    gs = classify_reading(gyr, False, MAX_GYRO_RATE)
    as_ = classify_reading(acc, True, MAX_ACC_G * c.gravity)
    m_cal = calibrate_mag(c, mag) if c.use_mag else mag
    ms = classify_reading(m_cal, True, MAX_MAG) if c.use_mag else MISSING
    count_reading(k, gs, GYR)
    count_reading(k, as_, ACC)
    if c.use_mag:
        count_reading(k, ms, MAG)
    if ms != VALID:
        return gs, as_, ms, ZERO3, 0.0
    m_norm = np.sqrt(m_cal[0] ** 2 + m_cal[1] ** 2 + m_cal[2] ** 2)
    return gs, as_, ms, _unit_t(m_cal), m_norm


# --- 2. initialisation, gaps and the heading -------------------------------------------------
@jit
def _learn_mag_ref(c: np.record, s: np.record, m_body: np.ndarray, m_norm: float) -> None:
    """Learn the Earth field from the first accepted samples: the magnitude, and the dip from
    the average of ``R(q̂) m`` keeping its (north, up) components — north is *defined* by the
    field's horizontal part. A given ``mag_reference`` fixes the direction; the magnitude is
    still learned (any unit)."""
    if s.mag_count >= MAG_REF_SAMPLES:
        return
    n = s.mag_count
    s.mag_norm = (s.mag_norm * n + m_norm) / (n + 1)
    s.mag_count = n + 1
    if c.mag_ref_given:
        copy_into(s.mag_ref, c.mag_ref)
        return
    r = rotate(s.q_c, m_body)
    for i in range(3):
        s.mag_sum[i] += r[i]
    m = s.mag_sum
    copy_into(s.mag_ref, _unit(np.array((0.0, np.sqrt(m[0] * m[0] + m[1] * m[1]), m[2]))))


@jit
def _heading_init(c: np.record, s: np.record, m_body: np.ndarray, m_norm: float) -> None:
    """Closed-form heading from a magnetometer sample; the yaw variance then reflects it."""
    recentre(c, s)
    if c.mag_ref_given:
        ref = c.mag_ref.copy()
    else:
        m = rotate(s.q_c, m_body)
        ref = _unit(np.array((0.0, np.sqrt(m[0] * m[0] + m[1] * m[1]), m[2])))
    s.mag_sum[:] = 0.0
    s.mag_norm = 0.0
    s.mag_count = 0
    s.t_mag_cand = 0.0
    rot = heading_correction(s.q_c, m_body, ref)
    copy_into(s.q_c, qnormalize(qmul(rot, s.q_c)))
    copy_into(s.mag_ref, ref)
    set_world_attitude_cov(s, c.nx, 0.0, mag_yaw_var(c, ref), True)
    s.heading_fixed = True
    s.t_mag_disagree = 0.0
    s.t_mag_lp = 0.0
    for i in range(3):  # the field's low-passes start at this sample (unit magnitude)
        s.mag_lp[i] = m_body[i]
        s.mag_lp_slow[i] = m_body[i]
    s.t_mag_lp_slow = 0.0
    _learn_mag_ref(c, s, m_body, m_norm)


@jit
def _restart_memory(s: np.record, gyr: np.ndarray, has_g: bool, acc: np.ndarray) -> None:
    """After an alignment the timers, the gyro gate and the low-passes start again, the
    low-passes at this sample."""
    s.t_acc_refused = 0.0
    s.t_rest = 0.0
    for i in range(3):
        s.acc_lp[i] = acc[i]
        s.acc_lp2[i] = acc[i]
        s.rest_acc_lp[i] = acc[i]
        s.rest_gyr_lp[i] = gyr[i] if has_g else 0.0
        for j in range(3):
            s.acc_sens[i, j] = 0.0
            s.acc_sens2[i, j] = 0.0
    s.rest_gyr_dev = 0.0
    s.rest_acc_dev = 0.0
    s.rest_dt_gyr = 0.0
    s.rest_dt_acc = 0.0
    s.gyr_rejected = False
    s.t_acc_lp = 0.0
    s.dt_acc = 0.0
    s.acc_excess = 0.0
    s.acc_dev = 0.0
    for i in range(3):
        s.gyro_net[i] = 0.0


@jit
def _align(c: np.record, s: np.record, gyr: np.ndarray, has_g: bool, acc: np.ndarray) -> None:
    """Closed-form initialisation (or re-alignment after a gap) from one sample: tilt from the
    accelerometer, the heading kept (re-alignment) or the start-up heading, the rate from the
    gyro; the covariance of one sample's tilt."""
    nx = c.nx
    q = align_tilt(acc)
    if s.ever_initialized:  # re-alignment: keep the heading we had (of the estimate q̂)
        recentre(c, s)
        q = keep_yaw(q, s.q_c)
    copy_into(s.q_c, q)
    s.e[:] = 0.0
    for i in range(3):
        s.w[i] = gyr[i] - s.b[i] if has_g else 0.0
    P = s.P
    Pb = P[6:9, 6:9].copy()
    P[:, :] = 0.0
    for i in range(3):
        P[3 + i, 3 + i] = c.gyro_var if has_g else 1.0
    if nx == 9:
        copy_block(P, 6, 6, Pb if s.ever_initialized else eye(3, c.bias_var0), False)
        if has_g:  # ω̄ = g − b̄: the rate inherits the bias uncertainty, anti-correlated
            for i in range(3):
                for j in range(3):
                    P[3 + i, 3 + j] += P[6 + i, 6 + j]
                    P[3 + i, 6 + j] = -P[6 + i, 6 + j]
                    P[6 + i, 3 + j] = -P[6 + i, 6 + j]
    # heading: defined by the start-up heading at the first alignment; after a gap it is kept
    # but unknown (uniform over ±180°) until a magnetometer fixes it
    # (with use_mag: unknown until the first magnetometer sample fixes it)
    var_yaw = YAW_VAR_UNKNOWN if s.ever_initialized or c.use_mag else YAW0_STDDEV ** 2
    # one sample's tilt: wrong by whatever the body's acceleration is at that instant, up to
    # three times acc_disturbance (so that the first corrections go to the attitude, not to
    # the gyro bias)
    set_world_attitude_cov(s, nx, c.acc_var + 9.0 * c.acc_disturbance_var, var_yaw, False)
    s.initialized = True
    s.ever_initialized = True
    s.heading_fixed = False
    _restart_memory(s, gyr, has_g, acc)


@jit
def _paper_init(c: np.record, s: np.record) -> None:
    """The paper's start: ``q̄ = (1,0,0,0)``, ``P = 10² I₆``, ``ω̄ = 0`` (MEKF) or
    ``10⁻¹⁰(1,1,1)`` (MUKF, "breaks the symmetry") (§5, §6, §8 item 9)."""
    s.q_c[:] = 0.0
    s.q_c[0] = 1.0
    s.e[:] = 0.0
    s.w[:] = 1e-10 if c.algorithm == ALGO_MUKF else 0.0
    P = s.P
    P[:, :] = 0.0
    for i in range(6):
        P[i, i] = P0_PAPER
    if c.nx == 9:
        for i in range(6, 9):
            P[i, i] = c.bias_var0
    copy_into(s.mag_ref, c.mag_ref)
    s.t_acc_refused = 0.0
    s.t_mag_disagree = 0.0
    s.t_rest = 0.0
    s.initialized = True
    s.ever_initialized = True
    s.heading_fixed = True


#: What :func:`start` says of a sample: used up (it aligned the filter, or there is nothing
#: to align from), go on, or go on without its magnetometer reading (it fixed the heading).
USED, GO, GO_WITHOUT_MAG = 0, 1, 2


@unit(nt.int64(CONFIG_T, STATE_T, COUNTERS_T, CANONICAL_T, nt.float64, F3, nt.boolean, F3,
               nt.boolean, F3, nt.float64, nt.boolean), cost=3.0)
def start(c: np.record, s: np.record, k: np.record, cn: Canonical, dt: float, gyr: tuple,
          has_g: bool, acc: tuple, has_a: bool, m_body: tuple, m_norm: float,
          has_m: bool) -> int:
    """Gaps, initialisation and the heading: a step longer than ``max_dt`` re-aligns from this
    (or the next) accelerometer sample, keeping yaw; a filter without an estimate aligns from
    this sample (heading from its magnetometer reading), or takes the paper's start; the first
    magnetometer sample since then fixes the heading (a baseline's state goes through the
    canonical form, ``cn``). Returns :data:`USED`, :data:`GO` or :data:`GO_WITHOUT_MAG`."""
    if s.initialized and dt > c.max_dt:
        k.gaps += 1
        s.initialized = False
    if not s.initialized:
        if c.paper_init:
            _paper_init(c, s)
            cn.restore(c, s)
        elif not has_a:
            k.before_init += 1
            return USED
        else:
            _align(c, s, np.array(gyr if has_g else ZERO3), has_g, np.array(acc))
            if has_m:
                _heading_init(c, s, np.array(m_body), m_norm)
            cn.restore(c, s)
            return USED
    if has_m and not s.heading_fixed:
        cn.export(c, s)
        _heading_init(c, s, np.array(m_body), m_norm)
        cn.restore(c, s)
        return GO_WITHOUT_MAG
    return GO


# --- 3. the gyro -----------------------------------------------------------------------------
@hot
def _rate_jump(P: np.ndarray, r: tuple, dt: float) -> None:
    """The attitude's variance grows by ``Δt² r rᵀ``: a rate jump ``r`` over the step
    (:func:`_gyro_gate`), added symmetrically (each entry once)."""
    for i in range(3):
        for j in range(i, 3):
            v = P[i, j] + dt * dt * r[i] * r[j]
            P[i, j] = v
            P[j, i] = v


@hot
def _gyro_gate(c: np.record, s: np.record, k: np.record, g: tuple, dt: float) -> bool:
    """The gyro's innovation gate: the innovation ``g − ω̄ − b̄`` against
    ``S = H P Hᵀ + R_ω`` (``H = [0, I, I]``), χ² with :data:`~mkf_ros.core.state.GYRO_GATE`.
    One sample alone beyond it
    is an outlier (a corrupted message): it is skipped — it reaches neither the filter nor the
    inertial low-passes — and counted. A second one in a row says the rate did change that
    much: the rate's prior was too narrow by the innovation, so its variance grows by it
    (``P_ωω += diag(r²)``) and the sample is taken. A sample taken beyond
    :data:`~mkf_ros.core.state.GYRO_SURPRISE_CHI2` is a jump of the rate that the model did
    not expect, real (an impact) or not (a glitch below the gate): the rotation over the coming
    step is uncertain by ``r Δt``, so the attitude's variance grows by ``Δt² r rᵀ`` (PSD; a
    20° glitch is then as uncertain as it is wrong, and the accelerometer and magnetometer
    take it back in seconds instead of at the pace of a confident filter). Returns whether to
    use the sample."""
    bias = c.nx == 9
    w, b, P = s.w, s.b, s.P
    r = (g[0] - w[0] - (b[0] if bias else 0.0), g[1] - w[1] - (b[1] if bias else 0.0),
         g[2] - w[2] - (b[2] if bias else 0.0))
    rw = c.gyro_var
    if r[0] * r[0] + r[1] * r[1] + r[2] * r[2] <= min(GYRO_GATE, GYRO_SURPRISE_CHI2) * rw:
        s.gyr_rejected = False  # S ⪰ R_ω I, so rᵀ S⁻¹ r ≤ |r|²/R_ω: within, no inverse needed
        return True
    S = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    for i in range(3):
        for j in range(3):
            v = P[3 + i, 3 + j]
            if bias:
                v += P[3 + i, 6 + j] + P[6 + i, 3 + j] + P[6 + i, 6 + j]
            S[i][j] = v + (rw if i == j else 0.0)
    okinv, Si = inv3_spd_t((S[0][0], S[0][1], S[0][2], S[1][1], S[1][2], S[2][2]))
    nis = 0.0
    for i in range(3):
        for j in range(3):
            nis += r[i] * Si[i][j] * r[j]
    if okinv and not nis > GYRO_GATE:
        s.gyr_rejected = False
        if nis > GYRO_SURPRISE_CHI2:
            _rate_jump(P, r, dt)
        return True
    k.gyr_rejected_chi2 += 1
    if s.gyr_rejected:
        for i in range(3):
            P[3 + i, 3 + i] += r[i] * r[i]
        _rate_jump(P, r, dt)
        s.gyr_rejected = False
        return True
    s.gyr_rejected = True
    return False


@hot
def _gyro(c: np.record, s: np.record, k: np.record, g: tuple, has_g: bool,
          dt: float) -> tuple:
    """The gyro sample after its gate (MEKF and MUKF: :func:`_gyro_gate`), and the rate (bias
    removed) that turns the inertial low-passes over this step: the gyro's, or without one the
    estimate's. Returns ``(g, has_g, ω_l)``."""
    if has_g and c.algorithm <= ALGO_MUKF and not c.paper_init:
        has_g = _gyro_gate(c, s, k, g, dt)
        if not has_g:
            g = ZERO3
    b, w = s.b, s.w
    wl = (g[0] - b[0], g[1] - b[1], g[2] - b[2]) if has_g else (w[0], w[1], w[2])
    return g, has_g, wl


# --- 4. the accelerometer --------------------------------------------------------------------
@hot
def _acc_blend(c: np.record, s: np.record, kq: float, u_raw: tuple, ex: float, ex2: float,
               qc: float) -> tuple:
    """The low-pass view of gravity and its blend with the raw one (:func:`_acc_measurement`);
    returns ``(u, q, status, share)``, ``share`` the low-pass's weight in ``u``; ``qc`` the
    variance of an error common to both views, which the blend does not reduce. Status 0:
    blended; 1: the raw sample, :data:`~mkf_ros.core.state.ACC_NORM_TOLERANCE` or more off
    gravity (a shock, a running person's footfall), has no say; 2: the low-pass itself is that
    far off (a sustained acceleration, or a memory the gyro turned wrong, which its variance
    does not describe) and nothing is fused."""
    g0 = c.gravity
    lp = (s.acc_lp2[0], s.acc_lp2[1], s.acc_lp2[2])
    n_lp = np.sqrt(lp[0] * lp[0] + lp[1] * lp[1] + lp[2] * lp[2])
    ex_lp = n_lp / g0 - 1.0
    u_lp = (lp[0] / n_lp, lp[1] / n_lp, lp[2] / n_lp)
    rot = c.gyro_scale_error * 2.0 * c.acc_time_constant * s.acc_rate_lp
    # a slow acceleration (a push, a brake) is still passing while the stages disagree
    a1 = s.acc_lp
    d2 = ((a1[0] - lp[0]) ** 2 + (a1[1] - lp[1]) ** 2 + (a1[2] - lp[2]) ** 2) / (g0 * g0)
    q_lp = c.acc_disturbance_var + ex_lp * ex_lp + d2 + rot * rot
    if abs(ex_lp) > ACC_NORM_TOLERANCE:  # refused (the low-pass holds a sustained acceleration)
        return u_lp, kq * q_lp + qc, 2, 1.0
    if abs(ex) > ACC_NORM_TOLERANCE:  # an implausible raw sample has no say (the low-pass
        return u_lp, kq * q_lp + qc, 1, 1.0  # still takes it: shaking is symmetric about gravity)
    q_rw = _raw_var(c, ex2, s.acc_excess)
    w = q_rw / (q_rw + q_lp)
    u = (w * u_lp[0] + (1.0 - w) * u_raw[0], w * u_lp[1] + (1.0 - w) * u_raw[1],
         w * u_lp[2] + (1.0 - w) * u_raw[2])
    return _unit_t(u), kq * q_lp * q_rw / (q_lp + q_rw) + qc, 0, w


@hot
def _acc_robust(c: np.record, s: np.record, a: tuple, al: float, ex2: float) -> tuple:
    """The sample as the low-passes take it: its deviation ``d = a − acc_lp`` from the
    first stage clipped to the radius ``r = max(ACC_CLIP_MIN_G · g, ACC_CLIP_SIGMAS · σ)``,
    σ the RMS deviation of the recent samples (``acc_dev``, low-passed with the same gain
    ``al``, from the clipped deviations). Body acceleration stays inside that radius, however
    hard the shaking or the running (σ grows with it) and passes unchanged; one absurd
    sample that is still below the plausibility limit (a 500 g spike, a corrupted message)
    moves the low-pass by at most ``α r`` instead of ``α |d|`` and leaves no memory that
    points gravity elsewhere for seconds. Returns the sample to low-pass and its magnitude
    excess ``ex2`` (as :func:`_acc_measurement`'s, of the clipped sample)."""
    lp = s.acc_lp
    d = (a[0] - lp[0], a[1] - lp[1], a[2] - lp[2])
    d2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2]
    r = max(ACC_CLIP_MIN_G * c.gravity, ACC_CLIP_SIGMAS * np.sqrt(s.acc_dev))
    if d2 > r * r:
        f = r / np.sqrt(d2)
        a = (lp[0] + f * d[0], lp[1] + f * d[1], lp[2] + f * d[2])
        d2 = r * r
        ex = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) / c.gravity - 1.0
        ex2 = max(0.0, ex * ex - c.acc_var)
    s.acc_dev += al * (d2 - s.acc_dev)
    return a, ex2


@hot
def _acc_measurement(c: np.record, s: np.record, dt: float, wl: tuple, Rw: tuple, a: tuple,
                     has_a: bool) -> tuple:
    """The accelerometer as the filters fuse it (extension): the unit direction and the
    disturbance variance per sample ``Q_a`` (normalised units), the raw sample's direction and
    variance (the baselines fuse those, as in the report, whatever their magnitude), a status
    (:func:`_acc_blend`'s; 2 also without a sample) and the low-pass's weight in the fused
    direction. With the low-pass, a raw sample :data:`~mkf_ros.core.state.ACC_NORM_TOLERANCE`
    or more off gravity has no say, in the blend or alone while the low-pass forms its first
    average (refused then); without it (``acc_time_constant = 0``) the raw sample is all there
    is and is fused with the variance its distance from gravity gives it.

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

    A body moving at ``acc_turn_speed`` v adds the centripetal acceleration of its turns,
    ``(v Ω̄ / g)²``, ``Ω̄`` the vertical rate low-passed over ``acc_time_constant`` τ: the same
    error in both views (added to the blend's variance, which it does not reduce), correlated
    over τ (times ``max(1, τ/Δt_a)``; docs/math.md §9.3).

    Shaking and vibration make the raw view noisy and leave the low-pass right; a fast turn,
    a saturated or miscalibrated gyro spoil the low-pass's memory while the raw view holds.
    Both errors are correlated in time: the variance per sample is ``max(1, T/Δt_a)`` times
    the above, ``T = acc_disturbance_time``, ``Δt_a`` the time since the previous
    accelerometer sample (the information per second does not grow with the sample rate).
    The low-pass starts as a running mean and is used once that first average is complete.
    Without it (``acc_time_constant = 0``) the raw sample alone."""
    tau = c.acc_time_constant
    if tau > 0.0:
        _turn(s.acc_lp, Rw)
        _turn(s.acc_lp2, Rw)
        _age_sensitivity(s.acc_sens, Rw, dt)
        _age_sensitivity(s.acc_sens2, Rw, dt)
    s.dt_acc += dt
    if not has_a:
        return ZERO3, 0.0, ZERO3, 0.0, 2, 0.0
    dta = s.dt_acc
    s.dt_acc = 0.0
    n_raw = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    ex = n_raw / c.gravity - 1.0
    ex2 = max(0.0, ex * ex - c.acc_var)  # the excess beyond what white noise explains
    q_raw = c.acc_disturbance_var + ex * ex
    u_raw = (a[0] / n_raw, a[1] / n_raw, a[2] / n_raw)
    kq = _correlated(c.acc_disturbance_time, dta)
    if tau <= 0.0:  # the raw view alone: its excess power over the disturbance's time
        al = _acc_memory_gain(s, dta, c.acc_disturbance_time)[0]
        q = _raw_var(c, ex2, _learn_excess(s, al, ex2))
        return u_raw, kq * q, u_raw, q_raw, 0, 0.0
    al, start = _acc_memory_gain(s, dta, tau)  # start: still the first average
    a_lp, ex2_lp = _acc_robust(c, s, a, al, ex2)
    _lowpass(s.acc_lp, a_lp, al)
    _lowpass(s.acc_lp2, (s.acc_lp[0], s.acc_lp[1], s.acc_lp[2]), 1.0 if start else al)
    _lowpass_sensitivity(s, al, 1.0 if start else al)
    _learn_excess(s, al, ex2_lp)
    s.acc_rate_lp += al * (np.sqrt(wl[0] ** 2 + wl[1] ** 2 + wl[2] ** 2) - s.acc_rate_lp)
    # the vertical rate Ω̄, about the low-pass's gravity (kept whatever acc_turn_speed, so that
    # a speed set live starts from the present turn, not from when it was last set)
    up = s.acc_lp2
    n_up = np.sqrt(up[0] * up[0] + up[1] * up[1] + up[2] * up[2])
    if n_up > 0.0:
        s.acc_yaw_lp += al * ((wl[0] * up[0] + wl[1] * up[1] + wl[2] * up[2]) / n_up
                              - s.acc_yaw_lp)
    if start:  # the low-pass is still forming its first average: the raw sample alone, unless
        # it has no say (as in the blend)
        return u_raw, kq * q_raw, u_raw, q_raw, 2 if abs(ex) > ACC_NORM_TOLERANCE else 0, 0.0
    # a turn at speed: the centripetal acceleration v Ω̄ across gravity, in both views alike and
    # correlated over the low-pass's memory (docs/math.md §9.3)
    cen = c.acc_turn_speed * s.acc_yaw_lp / c.gravity
    u, q, status, share = _acc_blend(c, s, kq, u_raw, ex, ex2,
                                     _correlated(tau, dta) * cen * cen)
    return u, q, u_raw, q_raw, status, share


@hot
def _acc_memory_gain(s: np.record, dta: float, tau: float) -> tuple[float, bool]:
    """The accelerometer's memories one sample on (``dta`` s since the previous): the gain of a
    low-pass over ``tau`` that starts as the running mean (:func:`_lowpass_gain`), and whether
    it is still in that start; ``tau = 0``: no memory, gain 1."""
    t = s.t_acc_lp
    s.t_acc_lp = t + dta
    return _lowpass_gain(s, LP_ACC, t, dta, tau) if tau > 0.0 else (1.0, False)


@hot
def _learn_excess(s: np.record, al: float, ex2: float) -> float:
    """The recent excess power of the magnitude ``E`` (``acc_excess``) low-passed with gain
    ``al`` towards this sample's ``ex2``; returns it."""
    E = float(s.acc_excess)
    E += al * (ex2 - E)
    s.acc_excess = E
    return E


@hot
def _raw_var(c: np.record, ex2: float, E: float) -> float:
    """The raw view's variance (before the correlation factor): ``acc_disturbance²`` plus the
    sample's magnitude excess ``ex2`` and twice the recent excess power ``E`` (the two
    components across gravity that a norm cannot see, docs/math.md §9.3). Without the
    low-pass (``acc_time_constant = 0``) ``E`` is taken over ``acc_disturbance_time``; without
    it at all the raw sample's variance saw only the acceleration along gravity: under BROAD's
    fast shaking the tilt went 30–69° off, the gyro bias learning from it at full gain (§9.1's
    ``γ`` takes ``E`` too)."""
    return c.acc_disturbance_var + ex2 + 2.0 * E


@hot
def _acc_bias_coupling(c: np.record, s: np.record, f: float) -> tuple:
    """How the fused gravity direction depends on the gyro bias, and how much the bias may
    learn from it (docs/math.md §9.1): ``(S_b, γ)``, ``S_b`` the low-pass's rotation per unit
    bias error times ``f``, its weight in the fused direction, ``γ = 1/(1 + E/e²)`` the bias's
    share of the gain, ``E`` the recent excess power of the magnitude (``acc_excess``) and
    ``e`` ``acc_bias_excess``."""
    S = s.acc_sens2
    Sb = ((f * S[0, 0], f * S[0, 1], f * S[0, 2]), (f * S[1, 0], f * S[1, 1], f * S[1, 2]),
          (f * S[2, 0], f * S[2, 1], f * S[2, 2]))
    e = c.acc_bias_excess
    return Sb, (1.0 / (1.0 + s.acc_excess / (e * e)) if e > 0.0 else 1.0)


@unit(nt.void(CONFIG_T, STATE_T, CANONICAL_T, F3, F3, F3), cost=1.8)
def acc_recovery(c: np.record, s: np.record, cn: Canonical, a: tuple, a_body: tuple,
                 wl: tuple) -> None:
    """Gravity refused for :data:`~mkf_ros.core.state.ACC_RECOVERY_TIME`: the estimate may be
    what is wrong. Its tilt
    variance grows by the measured disagreement (no forced update: the gates then judge
    against the wider prior, and a sample still refused grows it again later); the Euler
    baselines re-align instead (:func:`~mkf_ros.core.baseline_glue.baseline_realign`)."""
    up = rotate_inv(s.q_c, np.array(UP))
    ang = np.arccos(max(-1.0, min(1.0, up[0] * a_body[0] + up[1] * a_body[1]
                                  + up[2] * a_body[2])))
    cn.export(c, s)
    if not baseline_realign(c, s, a, wl):
        inflate_world(s, ang * ang, 0.0)
    cn.restore(c, s)
    s.t_acc_refused = 0.0


@hot
def _accelerometer(c: np.record, s: np.record, k: np.record, u: Units, dt: float, wl: tuple,
                   Rw: tuple, a: tuple, has_a: bool) -> tuple:
    """The accelerometer's view of gravity (:func:`_acc_measurement`), the recovery of a
    long-refused tilt (:func:`acc_recovery`) and the magnitude's count. Returns
    ``(a_body, var_a, a_raw, var_a_raw, has_a, a_sens, a_bias_gain)``: ``has_a`` something is
    fused (the baselines fuse the raw sample whenever there is one), the last two as
    :func:`_acc_bias_coupling`'s."""
    a_body, qa, a_rawu, qa_raw, a_stat, share = _acc_measurement(c, s, dt, wl, Rw, a, has_a)
    a_sens, a_bias_gain = _acc_bias_coupling(c, s, share)
    if has_a:
        if s.t_acc_refused > ACC_RECOVERY_TIME:
            u.acc_recovery(c, s, u.canonical, a, a_body, wl)
        if a_stat > 0:
            k.acc_rejected_norm += 1
        if a_stat == 2:
            has_a = False
    return a_body, qa, a_rawu, qa_raw, has_a, a_sens, a_bias_gain


# --- 5. rest ---------------------------------------------------------------------------------
@hot
def _rest_steady(c: np.record, s: np.record, dtg: float) -> bool:
    """Whether the body looks still: the gyro's and accelerometer's mean squared deviations
    below their thresholds, and the low-passed rate, less the bias estimate, a possible gyro
    bias: χ² (3 degrees of freedom) per axis against the bias's current variance ``P_bb``
    (which grows by ``gyro_bias_noise²`` per second without rest; ``gyro_bias_stddev²`` until
    a bias is learned) plus the low-pass's own noise, ``(gyro_noise² + rest_rate_stddev²)
    Δt/2τ``, plus ``REST_BIAS_RANGE²`` until the bias has been fused at rest for
    ``rest_time`` (the Kalman prior is a calibrated gyro's; a still gyro may show a turn-on
    bias several times larger, and only a rest learns it quickly). A bias does not change
    faster than its random walk; a rate that would need it to is a slow turn, however steady
    (measured on a PhidgetSpatial: a 0.013 rad/s turn 15 s after a rest, taken for rest,
    moved the vertical bias from −0.0002 to +0.0076 rad/s). Without a bias estimate, against
    ``rest_rate_stddev²``."""
    steady = (s.rest_gyr_dev < c.rest_gyro_threshold ** 2
              and s.rest_acc_dev < c.rest_acc_threshold ** 2)
    if steady:
        v = (c.gyro_var + c.rest_rate_var) * dtg / (2.0 * REST_LP_TAU)
        lp = s.rest_gyr_lp
        if c.nx == 9:
            P = s.P
            vb = v + (REST_BIAS_RANGE ** 2 if s.t_rest_fused < c.rest_time else 0.0)
            chi2 = 0.0
            for i in range(3):
                chi2 += (lp[i] - s.b[i]) ** 2 / (vb + P[6 + i, 6 + i])
        else:
            chi2 = (lp[0] ** 2 + lp[1] ** 2 + lp[2] ** 2) / (v + c.rest_rate_var)
        steady = chi2 < REST_CHI2
    return steady


@hot
def _rest_test(c: np.record, s: np.record, dt: float, g: tuple, has_g: bool, a: tuple,
               has_a: bool, g_none: bool, a_none: bool) -> bool:
    """Rest detection (extension): for ``rest_time`` without a break, the gyro and the
    accelerometer stay within ``rest_gyro_threshold`` / ``rest_acc_threshold`` of their own
    low-pass, RMS over REST_LP_TAU (the body is steady; a vibrating or rolling body is not) and the
    low-passed rate, less the bias estimate, could be a gyro bias (:func:`_rest_steady`; a
    faster turn is not rest; the current ``P_bb`` would lock a wrongly learned bias out of its
    own correction). A steady slow turn within that cannot be told from a bias by an IMU
    alone; the zero-rate update therefore never moves the attitude (:func:`_rate_updates`).

    A sample with neither a gyro nor an accelerometer reading given (a magnetometer message of
    its own, as a node receives it) leaves the test as it was; a refused reading (invalid, or
    the gyro's gate) breaks it.

    Split input (``split_input``: gyro and accelerometer in separate samples): a step without
    a reading of one sensor (``g_none`` / ``a_none``: not given, as opposed to rejected) keeps
    that sensor's part of the test as its last sample left it, each low-pass steps over the
    time since its own previous sample, and only a step with a gyro reading is at rest. The
    accelerometer, often at a lower rate than the gyro, has its squared deviation scaled by
    ``(2 − α) / (2 (1 − α)²)``: a deviation from a low-pass that includes the sample
    underestimates the sample variance by that factor (white noise; 1 % at α = 0.008, a
    250 Hz sample, 5 % at α = 0.03, a quarter of that), so ``rest_acc_threshold`` means the
    same at any accelerometer rate."""
    split = c.split_input
    if split:
        s.rest_dt_gyr += dt
        s.rest_dt_acc += dt
    elif g_none and a_none and c.rest_detection:
        return False  # a magnetometer-only sample says nothing of rest: the test goes on
    if not c.rest_detection or not ((has_g or (split and g_none))
                                    and (has_a or (split and a_none))):
        s.t_rest = 0.0
        return False
    dtg = dt
    if split:
        dtg = s.rest_dt_gyr
        al = _alpha(s, LP_REST, dtg, REST_LP_TAU) if has_g else 0.0
        ala = 1.0 - np.exp(-s.rest_dt_acc / REST_LP_TAU) if has_a else 0.0
        if has_g:
            s.rest_dt_gyr = 0.0
        if has_a:
            s.rest_dt_acc = 0.0
    else:
        al = ala = _alpha(s, LP_REST, dt, REST_LP_TAU)
    # mean squared deviations: a single noisy sample does not end a rest
    if has_g:
        lp = s.rest_gyr_lp
        _lowpass(lp, g, al)
        dg = (g[0] - lp[0]) ** 2 + (g[1] - lp[1]) ** 2 + (g[2] - lp[2]) ** 2
        s.rest_gyr_dev += al * (dg - s.rest_gyr_dev)
    if has_a:
        lp = s.rest_acc_lp
        _lowpass(lp, a, ala)
        da = (a[0] - lp[0]) ** 2 + (a[1] - lp[1]) ** 2 + (a[2] - lp[2]) ** 2
        if split:  # unbiased at any rate (see above)
            da *= (2.0 - ala) / (2.0 * (1.0 - ala) ** 2)
        s.rest_acc_dev += ala * (da - s.rest_acc_dev)
    if _rest_steady(c, s, dtg):
        s.t_rest += dt
    else:
        s.t_rest = 0.0
    return has_g and s.t_rest >= c.rest_time


# --- 6. the magnetometer ---------------------------------------------------------------------
@hot
def _dip(R: tuple, m_body: tuple) -> float:
    """Dip of the unit field ``m_body`` (rad, negative below the horizon) in the world frame of
    ``R`` = R(q̂): the elevation of ``R m``."""
    mz = R[2][0] * m_body[0] + R[2][1] * m_body[1] + R[2][2] * m_body[2]
    return np.arcsin(max(-1.0, min(1.0, mz)))


@hot
def _mag_plausible(c: np.record, s: np.record, k: np.record, m_norm: float) -> bool:
    """Field magnitude against the learned reference (extension); counted if not. No test on
    the dip: indoors it differs from room to room as much as a disturbance's (docs/math.md
    §9.3), and the consistency test already refuses a field that turns with the body."""
    if s.mag_count < 10:
        return True  # reference still being learned
    if abs(m_norm / s.mag_norm - 1.0) > c.mag_norm_tolerance:
        k.mag_rejected_norm += 1
        return False
    return True


@hot
def _mag_consistent(c: np.record, s: np.record, k: np.record, m_body: tuple, m_norm: float,
                    alm: float) -> bool:
    """The field over its learned magnitude against its own low-pass in the almost inertial
    frame (``mag_consistency_tolerance``, plus the gyro's scale error over the rotation in that
    memory), the low-pass stepped by this sample; counted if not. True before a magnitude is
    learned."""
    if s.mag_count <= 0:
        return True
    f = m_norm / s.mag_norm
    mv = (m_body[0] * f, m_body[1] * f, m_body[2] * f)
    lp = s.mag_lp
    dev2 = (mv[0] - lp[0]) ** 2 + (mv[1] - lp[1]) ** 2 + (mv[2] - lp[2]) ** 2
    _lowpass(lp, mv, alm)
    tol2 = (c.mag_consistency_tolerance ** 2
            + (c.gyro_scale_error * c.mag_time_constant * s.mag_rate_lp) ** 2)
    if dev2 > tol2:
        k.mag_rejected_inconsistent += 1
        return False
    return True


@hot
def _mag_steady(s: np.record, k: np.record, m_body: tuple, dtm: float) -> bool:
    """The direction of a field that passed :func:`_mag_consistent` against its slow low-pass
    in the same almost inertial frame (:data:`~mkf_ros.core.state.MAG_SLOW_TIME`, from every
    such sample: this one steps it), within :data:`~mkf_ros.core.state.MAG_SLOW_TOLERANCE`
    (extension, docs/math.md §9.3): a disturbance that builds up over seconds (a phone carried
    past metal) passes the consistency test, whose memory follows it, and keeps the magnitude
    of a calibrated field that a phone's system normalises; a field fixed in the world keeps
    its direction. The low-pass starts as the running mean at the heading's start and is
    tested against only once it holds ``MAG_SLOW_TIME`` (a recording that starts in a
    disturbed field); a field that stays catches it up in about that time. Counted as
    inconsistent if not; such a field is a candidate new reference (:func:`_mag_candidate`)."""
    v = s.mag_lp_slow
    n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    cos = (v[0] * m_body[0] + v[1] * m_body[1] + v[2] * m_body[2]) / n if n > 0.3 else 1.0
    t = s.t_mag_lp_slow
    s.t_mag_lp_slow = t + dtm
    al, start = _lowpass_gain(s, LP_MAG_SLOW, t, dtm, MAG_SLOW_TIME)
    _lowpass(v, m_body, al)
    if not start and cos < MAG_SLOW_COS:
        k.mag_rejected_inconsistent += 1
        return False
    return True


@hot
def _mag_candidate(c: np.record, s: np.record, dtm: float, R: tuple, m_body: tuple,
                   m_norm: float, wl: tuple) -> bool:
    """A consistent field that fails the magnitude test (:func:`_mag_plausible`) is a
    candidate new reference (extension, after VQF's magnetic disturbance rejection): its
    magnitude and dip are low-passed (``mag_time_constant``) while each sample's magnitude
    agrees with the candidate's within ``mag_norm_tolerance`` (else the candidate starts
    again at this sample), and its time counts while the body turns at
    :data:`~mkf_ros.core.state.MAG_NEW_MIN_RATE` or faster: turning is what tells a field
    fixed in the world (consistent in the almost inertial frame however the body turns) from
    a magnet carried along. After ``mag_new_first_time`` (the first since the start: the
    reference learned from the first second is the least trusted) or ``mag_new_time`` it
    becomes the reference: magnitude and dip (the direction only if learned; north stays the
    horizontal part). Indoors the undisturbed field differs by 10–25 % from room to room.
    Returns whether this sample is now plausible."""
    T = c.mag_new_time if s.mag_adopted else c.mag_new_first_time
    if not T > 0.0:
        return False
    dip = _dip(R, m_body)
    if s.t_mag_cand > 0.0 and abs(m_norm / s.mag_cand_norm - 1.0) <= c.mag_norm_tolerance:
        a = min(1.0, dtm / c.mag_time_constant)
        s.mag_cand_norm += a * (m_norm - s.mag_cand_norm)
        s.mag_cand_dip += a * (dip - s.mag_cand_dip)
        if wl[0] * wl[0] + wl[1] * wl[1] + wl[2] * wl[2] >= MAG_NEW_MIN_RATE ** 2:
            s.t_mag_cand += dtm
    else:
        s.mag_cand_norm = m_norm
        s.mag_cand_dip = dip
        s.t_mag_cand = 1e-12  # a candidate, no time yet
    if s.t_mag_cand < T:
        return False
    s.mag_norm = s.mag_cand_norm
    s.mag_count = max(s.mag_count, MAG_REF_SAMPLES)
    if not c.mag_ref_given:
        s.mag_ref[0] = 0.0
        s.mag_ref[1] = np.cos(s.mag_cand_dip)
        s.mag_ref[2] = np.sin(s.mag_cand_dip)
    s.mag_adopted = True
    s.t_mag_cand = 0.0
    return True


@unit(nt.void(CONFIG_T, STATE_T, CANONICAL_T, F33, F3), cost=0.4)
def mag_recovery(c: np.record, s: np.record, cn: Canonical, Rq: tuple, m_body: tuple) -> None:
    """A plausible, consistent field refused by the χ² gate for
    :data:`~mkf_ros.core.state.MAG_RECOVERY_TIME`: the
    heading is what is wrong. Its variance grows by the disagreement (no snap: the next
    updates pull it in)."""
    ref = s.mag_ref
    h = np.sqrt(ref[0] ** 2 + ref[1] ** 2)
    psi, _ = heading_residual_t(Rq, m_body, (ref[0] / h, ref[1] / h, 0.0))
    cn.export(c, s)
    inflate_world(s, 0.0, psi * psi)
    cn.restore(c, s)
    s.t_mag_disagree = 0.0


@hot
def _mag_checks(c: np.record, s: np.record, k: np.record, u: Units, dt: float, dtm: float,
                wl: tuple, Rw: tuple, m_body: tuple, m_norm: float, has_m: bool) -> bool:
    """Whether this magnetometer sample may be fused (extension), in this order:

    * consistency (:func:`_mag_consistent`): a field fixed in the world passes however the
      body turns; a magnet on the body turns with it, and a field that changes along the path
      changes;
    * steadiness (:func:`_mag_steady`): its direction against its own slow low-pass;
    * plausibility: magnitude against the learned reference (:func:`_mag_plausible`);
    * recovery (:func:`mag_recovery`) after :data:`~mkf_ros.core.state.MAG_RECOVERY_TIME` of
      χ² refusals.

    Counted when refused."""
    _turn(s.mag_lp, Rw)
    _turn(s.mag_lp_slow, Rw)
    alm = _alpha(s, LP_RATE, dt, c.mag_time_constant)
    s.mag_rate_lp += alm * (np.sqrt(wl[0] ** 2 + wl[1] ** 2 + wl[2] ** 2) - s.mag_rate_lp)
    if not has_m:
        return False
    t = s.t_mag_lp
    s.t_mag_lp = t + dtm
    alm, _ = _lowpass_gain(s, LP_MAG, t, dtm, c.mag_time_constant)
    Rq = rotmat_t(t4(s.q_c))
    ok = _mag_consistent(c, s, k, m_body, m_norm, alm)
    if ok and not (_mag_steady(s, k, m_body, dtm) and _mag_plausible(c, s, k, m_norm)):
        ok = _mag_candidate(c, s, dtm, Rq, m_body, m_norm, wl)
    elif ok:
        s.t_mag_cand = 0.0  # the reference holds: no candidate
    if not ok:
        s.t_mag_disagree = 0.0  # disturbance, not evidence of a wrong heading
        return False
    if s.t_mag_disagree > MAG_RECOVERY_TIME:
        u.mag_recovery(c, s, u.canonical, Rq, m_body)
    return True


@hot
def _magnetometer(c: np.record, s: np.record, k: np.record, u: Units, dt: float, wl: tuple,
                  Rw: tuple, m_body: tuple, m_norm: float, has_m: bool) -> tuple:
    """The magnetometer's checks (:func:`_mag_checks`, once the heading is fixed) and the time
    since its previous sample. Returns ``(has_m, Δt_m)``."""
    s.dt_mag += dt
    dtm = s.dt_mag  # time since the previous magnetometer sample
    if has_m:
        s.dt_mag = 0.0
    if heading_fixed(c, s) and not c.paper_init:
        has_m = _mag_checks(c, s, k, u, dt, dtm, wl, Rw, m_body, m_norm, has_m)
    return has_m, dtm


# --- 7. the updates --------------------------------------------------------------------------
@hot
def _gyro_scale_noise(c: np.record, s: np.record, w: np.record, dt: float, wl: tuple) -> None:
    """The gyro's scale and axis errors (docs/math.md §9.1): attitude noise
    ``σ_s² (‖ω̃‖² + κ (‖ω‖² − ‖ω̃‖²)⁺) Δt``, ``ω̃`` the rate low-passed over
    ``acc_time_constant`` (the net rotation, whose error accumulates), ``κ``
    :data:`~mkf_ros.core.state.GYRO_SCALE_SWING` the share a swing back and forth keeps;
    without the low-pass (``acc_time_constant = 0``) every rate counts. The variance added goes
    to ``w.rec_ws2`` (the smoother takes it out of the transition, §11.3)."""
    w.rec_ws2 = 0.0
    if c.algorithm <= ALGO_MUKF and c.gyro_scale_error > 0:
        v = s.gyro_net
        _lowpass(v, wl, _alpha(s, LP_NET, dt, c.acc_time_constant) if c.acc_time_constant > 0.0
                 else 1.0)
        n2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        w2 = wl[0] * wl[0] + wl[1] * wl[1] + wl[2] * wl[2]
        qs = c.gyro_scale_error ** 2 * (n2 + GYRO_SCALE_SWING * max(0.0, w2 - n2)) * dt
        w.rec_ws2 = qs
        for i in range(3):
            s.P[i, i] += qs


# the MEKF's blocks (docs/math.md §5) on the state's covariance and the scratch: compiled once each
# (the blocks of mkf_ros.core.mekf inlined), called with the records (by pointer)
@jit
def _mekf_predict(s: np.record, nx: int, dt: float, q: tuple, wt: tuple, Qw: tuple,
                  Qb: tuple) -> tuple:
    """:func:`~mkf_ros.core.mekf.mekf_predict_t` of ``s.P``; returns ``q̄⁻``."""
    return mekf_predict_t(q, wt, s.P, nx, dt, Qw, Qb)


@jit
def _mekf_rate(s: np.record, w: np.record, nx: int, wt: tuple, b: tuple, wm: tuple, Rw: tuple,
               with_bias: bool, frozen: int, gate: float) -> float:
    """:func:`~mkf_ros.core.mekf.mekf_rate_update_t` into ``w.dx``."""
    return mekf_rate_update_t(s.P, nx, w.dx, wt, b, wm, Rw, with_bias, gate, w.mekf, frozen)


@jit
def _mekf_vector(s: np.record, w: np.record, nx: int, R: tuple, vm: tuple, vref: tuple,
                 Rv: tuple, Qv: tuple, gate: float, tilt_only: bool, Sb: tuple,
                 bias_gain: float) -> float:
    """:func:`~mkf_ros.core.mekf.mekf_vector_update_t` into ``w.dx``."""
    return mekf_vector_update_t(s.P, nx, w.dx, R, vm, vref, (Rv, Qv), gate, tilt_only, w.mekf,
                                Sb, bias_gain)


@jit
def _mekf_heading(s: np.record, w: np.record, nx: int, R: tuple, m: tuple, ref: tuple,
                  var: float, gate: float, bias_gain: float) -> float:
    """:func:`~mkf_ros.core.mekf.mekf_heading_update_t` into ``w.dx``."""
    return mekf_heading_update_t(s.P, nx, w.dx, R, m, ref, var, gate, bias_gain)


@jit
def _mekf_apply(c: np.record, s: np.record, w: np.record, q: tuple, wt: tuple,
                b: tuple, z: Fusion) -> tuple:
    """:func:`~mkf_ros.core.mekf.mekf_apply_t` of ``w.dx``: ``(q̄⁺, ω̄⁺, b̄⁺)``; while nothing
    observes the heading (:func:`~mkf_ros.core.state.heading_unobserved`) the chart update
    carries the heading's variance to the new vertical (docs/math.md §9.3)."""
    return mekf_apply_t(c.chart, c.chart_update, q, wt, b, s.P, c.nx, w.dx,
                        heading_unobserved(c, s, z))


@hot
def _rate_updates(c: np.record, s: np.record, k: np.record, w: np.record, dt: float,
                  z: Fusion) -> bool:
    """The rate measurements first: a gyro sample is the rate over the interval that ends at
    its stamp (what a MEMS gyro reports), so it observes ω̄ at the start of the step and drives
    the prediction over it; then rest's zero-rate pseudo-measurement, whose gain on the
    attitude is frozen (it never moves the attitude). Both are linear in the state, so this
    Kalman update is exact for the MUKF too. Returns False if a factorisation failed.

    The zero-rate measurement has its χ² gate (REST_CHI2, 3 degrees of freedom, against
    ``S = P_ωω + rest_rate_stddev²``): at rest the rate left after the gyro's update is noise
    within the bias's uncertainty; a rate beyond it is the body moving, which the rest test's
    low-passes see only later (the start of a slow turn). That sample's zero-rate update is
    skipped, and not counted in ``rest_updates``; the bias it would have pulled towards the
    turn's rate stays (measured on a PhidgetSpatial turning from rest: the vertical bias went
    from −0.0010 to −0.0073 rad/s in the turn's first 40 ms, the still gyro's mean −0.0014).
    At the first rest the bias's variance is raised to ``REST_BIAS_RANGE²`` (on the diagonal:
    the added matrix is PSD): the prior is a calibrated gyro's, a still gyro may show a turn-on
    bias several times larger, and the gate then takes it; a few zero-rate updates learn it and
    the gate is as tight as before when the turn starts."""
    nx = c.nx
    P, dx = s.P, w.dx
    wt, b = t3(s.w), t3(s.b)
    for i in range(nx):
        dx[i] = 0.0
    ok = True
    if z.has_g:
        ok &= _mekf_rate(s, w, nx, wt, b, z.g, iso33(c.gyro_var), True, 0, np.inf) >= 0
    if z.rest:
        if s.t_rest_fused == 0.0 and nx == 9:  # the first rest: a turn-on bias, not the prior
            for i in range(6, 9):
                P[i, i] = max(P[i, i], REST_BIAS_RANGE ** 2)
        nis = _mekf_rate(s, w, nx, wt, b, ZERO3, iso33(c.rest_rate_var), False, 3, REST_CHI2)
        ok &= nis >= 0
        if 0 <= nis <= REST_CHI2:
            k.rest_updates += 1
            s.t_rest_fused += dt
    if c.algorithm == ALGO_MEKF:
        q, wt, b = _mekf_apply(c, s, w, t4(s.q_c), wt, b, z)
        for i in range(4):
            s.q_c[i] = q[i]
    else:
        for i in range(3):
            s.e[i] += dx[i]
        symmetrize_leading(P, nx)
        wt = (wt[0] + dx[3], wt[1] + dx[4], wt[2] + dx[5])
        if nx == 9:
            b = (b[0] + dx[6], b[1] + dx[7], b[2] + dx[8])
    for i in range(3):
        s.w[i] = wt[i]
        s.b[i] = b[i]
    return ok


@hot
def _mekf_update(c: np.record, s: np.record, w: np.record, dt: float,
                 z: Fusion) -> tuple[float, float]:
    """The MEKF (docs/math.md §5): prediction over the step, one block per sensor (gravity, the
    field as a vector or a heading), one move back to the manifold. Returns the NIS of the two."""
    nx = c.nx
    wt, b = t3(s.w), t3(s.b)
    q = _mekf_predict(s, nx, dt, t4(s.q_c), wt, iso33(c.rate_process_noise),
                      iso33(c.bias_process_var))
    R = rotmat_t(q)
    for i in range(nx):
        w.dx[i] = 0.0
    acc_nis = 0.0
    mag_nis = 0.0
    if z.has_a:
        acc_nis = _mekf_vector(s, w, nx, R, z.a, UP, iso33(c.acc_var), iso33(z.var_a),
                               z.acc_gate, c.acc_tilt_only, z.a_sens, z.a_bias_gain)
    if z.has_m:
        if c.mag_heading:
            mag_nis = _mekf_heading(s, w, nx, R, z.m, z.h_ref, z.var_h, z.mag_gate,
                                         c.mag_bias_gain)
        else:
            mag_nis = _mekf_vector(s, w, nx, R, z.m, z.m_ref, iso33(c.mag_var),
                                   iso33(c.mag_disturbance_var), z.mag_gate, False, ZERO33, 1.0)
    q, wt, b = _mekf_apply(c, s, w, q, wt, b, z)
    for i in range(4):
        s.q_c[i] = q[i]
    for i in range(3):
        s.w[i] = wt[i]
        s.b[i] = b[i]
    return acc_nis, mag_nis


@unit(_UPDATE_SIG(CONFIG_T, STATE_T, WORK_T, nt.float64, FUSION_T), cost=15)
def mukf_update(c: np.record, s: np.record, w: np.record, dt: float,
                z: Fusion) -> tuple[bool, float, float]:
    """The MUKF (docs/math.md §6): the stacked measurement through the sigma points
    (:func:`~mkf_ros.core.mukf.mukf_step_t`). Returns ``(ok, acc NIS, mag NIS)``; on a failed
    factorisation the estimate is still carried over ``Δt`` (the MEKF's linear prediction
    from the re-centred mean), so that no time is lost."""
    nx = c.nx
    heading_m = z.has_m and c.mag_heading
    use_vm = z.has_m and not c.mag_heading
    # an unobserved heading's spread, bounded for the sigma points (its variance back after)
    f = _bound_heading_spread(s, nx) if heading_unobserved(c, s, z) else 1.0
    x = (t4(s.q_c), t3(s.e), t3(s.w), t3(s.b))
    meas = MukfMeasurement(
        (z.a, z.m if z.has_m else ZERO3), (UP, z.m_ref if z.has_m else ZERO3),
        (iso33(c.acc_var), iso33(c.mag_var)), (iso33(z.var_a), iso33(c.mag_disturbance_var)),
        (z.has_a, use_vm), z.g, False, iso33(c.gyro_var), z.m if z.has_m else ZERO3,
        z.h_ref if z.has_m else ZERO3, heading_m, z.var_h, False, c.rest_rate_var,
        (z.acc_gate, z.mag_gate, z.mag_gate, np.inf), True, c.acc_tilt_only,
        z.a_sens if z.has_a else ZERO33, z.a_bias_gain if z.has_a else 1.0,
        c.mag_bias_gain if heading_m else 1.0)
    ok, q, e, wt, b, nis = mukf_step_t(
        c.chart, c.chart_update, c.mukf_noise, c.mukf_w0, x, s.P, nx, dt,
        iso33(c.rate_process_noise), iso33(c.bias_process_var), meas,
        (w.L, w.X, w.Pxy, w.Pyy, w.Ly, w.KPyy, w.Pxx, w.Kt))
    for i in range(4):  # (on failure as far as changed: the reset variant's re-centring)
        s.q_c[i] = q[i]
    for i in range(3):
        s.e[i] = e[i]
        s.w[i] = wt[i]
        s.b[i] = b[i]
    if not ok:
        recentre(c, s)
        q = _mekf_predict(s, nx, dt, t4(s.q_c), wt, iso33(c.rate_process_noise),
                          (ZERO3, ZERO3, ZERO3))
        for i in range(4):
            s.q_c[i] = q[i]
    if f < 1.0:
        back = 1.0 / f
        inflate_world(s, 0.0, max(0.0, _vertical_variance(s)[1] * (back * back - 1.0)))
    acc_nis = nis[B_VEC0] if z.has_a else 0.0
    mag_nis = nis[B_HEADING] if c.mag_heading else nis[B_VEC1]
    return ok, acc_nis, mag_nis


@hot
def _vertical_variance(s: np.record) -> tuple:
    """``(u, v)``: the world vertical in the body (the error state's frame) and the attitude
    variance about it, ``v = uᵀ P_θθ u`` (the heading's)."""
    u = up_in_body_t(t4(s.q_c))
    P = s.P
    v = 0.0
    for i in range(3):
        for j in range(3):
            v += u[i] * P[i, j] * u[j]
    return u, v


@hot
def _bound_heading_spread(s: np.record, nx: int) -> float:
    """The MUKF's sigma points with a heading that nothing observes (no magnetometer in this
    step, and none has fixed the heading: docs/math.md §9.3): the variance ``v`` about the
    world vertical ``u`` scaled down to :data:`MUKF_HEADING_SPREAD_VAR` if above (``P ← D P
    Dᵀ``, ``D = I + (f − 1) u uᵀ`` on the attitude rows, ``f = √(MUKF_HEADING_SPREAD_VAR /
    v)``); returns ``f`` (1: unchanged). After the step :func:`mukf_update` gives the variance
    back, ``v′ (f⁻² − 1)`` about the new vertical, as an independent rotation
    (:func:`~mkf_ros.core.state.inflate_world`: PSD, the correlations left as the points made
    them).

    Gravity does not depend on the heading, but a 6D heading at its cap (σ 104°) put the points
    ±3.5 σ about the vertical, where the RP chart's coordinates no longer compose as rotations:
    the tilt covariance they carried grew, 3.6 → 11° over 80 s of RepoIMU's reversed Test10
    where the MEKF kept 3° (docs/real_data.md). Scaling the correlations back up by ``1/f``
    with the variance amplified what the points' nonlinearity put into them: on
    ``ardrone_imu.bag`` the rate measurement after a 0.16 s gap then turned the heading 7°."""
    u, v = _vertical_variance(s)
    if not v > MUKF_HEADING_SPREAD_VAR:
        return 1.0
    f = np.sqrt(MUKF_HEADING_SPREAD_VAR / v)
    scale_direction(s.P, nx, u, f)
    return f


@hot
def _cap_attitude_variance(s: np.record, nx: int) -> None:
    """An angle uniform over ±180° has variance π²/3 (YAW_VAR_UNKNOWN); a Gaussian attitude
    variance beyond that about any axis means nothing ("unknown" is all it can say) and
    spreads the MUKF's sigma points past the charts' domains. First the heading (6D: the
    unobservable vertical bias integrated for long; an extreme ``rate_process_noise``): the
    attitude error along the world vertical ``u`` is scaled so that its variance is the cap;
    then any other direction still above it (an extreme ``rate_process_noise`` leaves the
    tilt unknown between two accelerometer samples), along the largest eigenvector. Each a
    congruence ``P ← D P Dᵀ`` with ``D = I + (s − 1) v vᵀ`` on the attitude rows
    (:func:`~mkf_ros.core.linalg.scale_direction`): P stays symmetric PSD.

    Each is scaled back to the cap once it exceeds it by more than :data:`CAP_SLACK`
    (relative; the published covariance is capped exactly by
    :func:`mkf_ros.core.filter.output`), and the eigenvalue is computed only when
    :func:`~mkf_ros.core.linalg.none_above33_t` cannot rule it out: a 6D heading sits at the
    cap for good, and scaling it back and computing the largest eigenvalue at every step cost
    ~14 % of every 6D step once the heading was unknown (MEKF 6D, 1000 s at 200 Hz, three
    alternating runs: 1.73–1.83 µs per sample before, 1.52–1.59 with the slack; 9D, whose
    heading is known, unchanged). Outputs move by ≤ 2e-6 (MUKF 6D), 3e-8 (MEKF 6D)."""
    P = s.P
    u, v = _vertical_variance(s)
    top = YAW_VAR_UNKNOWN * (1.0 + CAP_SLACK)
    if v > top:
        scale_direction(P, nx, u, np.sqrt(YAW_VAR_UNKNOWN / v))
    for _ in range(3):
        A = ((P[0, 0], P[0, 1], P[0, 2]), (P[1, 0], P[1, 1], P[1, 2]), (P[2, 0], P[2, 1], P[2, 2]))
        if none_above33_t(A, top):
            return
        lam, e = largest_eigh33_t(A)
        if not lam > top:
            return
        scale_direction(P, nx, e, np.sqrt(YAW_VAR_UNKNOWN / lam))


@hot
def _update(c: np.record, s: np.record, k: np.record, w: np.record, u: Units, dt: float,
            z: Fusion) -> tuple[bool, float, float]:
    """The filter's own step with this sample's measurements: a baseline's
    (:func:`baseline_step`), or the MKFs' rate updates then the MEKF's or the MUKF's
    (:func:`mukf_update`) prediction and update. Returns ``(ok, acc NIS, mag NIS)``."""
    if c.algorithm >= ALGO_EULER_KF:
        return u.baseline_update(c, s, k, dt, z)
    ok = _rate_updates(c, s, k, w, dt, z)
    if c.record_posterior:  # the smoother's forward pass (docs/math.md §11.1)
        record_posterior(c, s, w)
    if c.algorithm == ALGO_MEKF:
        acc_nis, mag_nis = _mekf_update(c, s, w, dt, z)
    else:
        ok_u, acc_nis, mag_nis = u.mukf_update(c, s, w, dt, z)
        ok &= ok_u
    _cap_attitude_variance(s, c.nx)
    return ok, acc_nis, mag_nis


# --- 8. bookkeeping --------------------------------------------------------------------------
@hot
def _bookkeeping(c: np.record, s: np.record, k: np.record, z: Fusion, ok: bool,
                 acc_nis: float, mag_nis: float, m_norm: float) -> None:
    """After the update: a failed factorisation regularises ``P`` (so that the next step can
    factorise again); otherwise count the gates' refusals and the rest updates, run the
    refusal timers and learn the field's reference from accepted samples."""
    if not ok or acc_nis < 0 or mag_nis < 0:
        k.update_failed += 1
        for i in range(c.nx):
            s.P[i, i] += 1e-9
        return
    if z.has_a:
        if acc_nis > z.acc_gate:
            k.acc_rejected_chi2 += 1
        else:
            s.t_acc_refused = 0.0
    if z.has_m:
        if mag_nis > z.mag_gate:
            k.mag_rejected_chi2 += 1
            s.t_mag_disagree = max(s.t_mag_disagree, 1e-12)  # start (or continue) its clock
        else:
            s.t_mag_disagree = 0.0
            if s.mag_count < MAG_REF_SAMPLES:
                _learn_mag_ref(c, s, np.array(z.m), m_norm)


@hot
def _fusion(c: np.record, s: np.record, has_m: bool, dtm: float) -> tuple:
    """The field's world reference, horizontal reference and heading variance per sample,
    and the gates (none for the paper's start): the last fields of
    :data:`~mkf_ros.core.state.Fusion`."""
    acc_gate, mag_gate = ACC_GATE, MAG_GATE
    if c.paper_init:  # the paper's start has no prior to gate against
        acc_gate = mag_gate = np.inf
    mr = s.mag_ref
    m_ref = (mr[0], mr[1], mr[2])
    h = np.sqrt(mr[0] ** 2 + mr[1] ** 2)
    h_ref = (mr[0] / h, mr[1] / h, 0.0) if has_m and c.mag_heading else ZERO3
    var_h = (mag_yaw_var(c, s.mag_ref) * _correlated(c.mag_disturbance_time, dtm) if has_m
             else 0.0)
    return m_ref, h_ref, var_h, acc_gate, mag_gate


@unit(_UPDATE_SIG(CONFIG_T, STATE_T, COUNTERS_T, nt.float64, FUSION_T), cost=9.0)
def baseline_step(c: np.record, s: np.record, k: np.record, dt: float,
                  z: Fusion) -> tuple[bool, float, float]:
    """The baselines' update (:func:`~mkf_ros.core.baseline_glue.baseline_update`). Compiled
    on first use, not at install time: only the comparison filters (``euler_kf``,
    ``euler_ukf``, ``madgwick``) call it (:func:`mkf_ros.core.filter.kernel_table`)."""
    return baseline_update(c, s, k, dt, z)


@unit(_UPDATE_SIG(CONFIG_T, STATE_T, WORK_T, nt.float64, FUSION_T), cost=0.1)
def no_mukf(c: np.record, s: np.record, w: np.record, dt: float,
            z: Fusion) -> tuple[bool, float, float]:
    """:func:`mukf_update`'s place in the kernel table of every algorithm but the MUKF, which
    alone calls it (:func:`_update`): nothing fused. :func:`mukf_update` is compiled on the
    MUKF's first use, not at install time (:func:`mkf_ros.core.filter.kernel_table`)."""
    return False, -1.0, -1.0


@unit(_UPDATE_SIG(CONFIG_T, STATE_T, COUNTERS_T, nt.float64, FUSION_T), cost=0.1)
def no_baseline(c: np.record, s: np.record, k: np.record, dt: float,
                z: Fusion) -> tuple[bool, float, float]:
    """:func:`baseline_step`'s place in the kernel table of the MKFs, which never call it
    (:func:`step` calls it for the baselines only): nothing fused."""
    return False, -1.0, -1.0


#: The steps of :func:`step` compiled as units of their own (the rare paths and the large
#: updates), in the form :func:`step` takes them (:func:`mkf_ros.core.filter.kernels_at`).
Units = namedtuple("Units", ("canonical", "start", "acc_recovery", "mag_recovery",
                             "mukf_update", "baseline_update"))
UNITS_T = tuple_type([CANONICAL_T] + [x.type for x in (start, acc_recovery, mag_recovery,
                                                        mukf_update, baseline_step)], Units)


# --- the step --------------------------------------------------------------------------------
@unit(nt.void(CONFIG_T, STATE_T, COUNTERS_T, WORK_T, UNITS_T, nt.float64, F3, F3, F3),
      cost=14)
def step(c: np.record, s: np.record, k: np.record, w: np.record, u: Units, dt: float,
         gyr: tuple, acc: tuple, mag: tuple) -> None:
    """One sample: any of ``gyr`` (rad/s), ``acc`` (m/s², +g up at rest) and ``mag`` (any unit)
    may be NaN (missing). ``dt`` is the time since the previous sample; ``u`` the compiled
    :data:`Units`. The steps: the readings; gaps and initialisation; the
    heading; the gyro; the accelerometer; rest; the magnetometer; the filter's update;
    bookkeeping. A ``dt`` below :data:`~mkf_ros.core.state.DT_MIN` is 0
    (:func:`~mkf_ros.core.state.step_dt`, docs/math.md §9.5)."""
    dt = step_dt(dt)
    k.samples += 1
    gs, as_, ms, m, m_norm = _read(c, k, gyr, acc, mag)
    has_g, has_a, has_m = gs == VALID, as_ == VALID, ms == VALID
    if not s.initialized or dt > c.max_dt or (has_m and not s.heading_fixed):
        go = u.start(c, s, k, u.canonical, dt, gyr, has_g, acc, has_a, m, m_norm, has_m)
        if go == USED:
            return
        has_m = has_m and go == GO  # a sample that set the heading is not fused again
    s.t_acc_refused += dt
    if s.t_mag_disagree > 0.0:  # inside a period of disagreement with a plausible field
        s.t_mag_disagree += dt
    g, has_g, wl = _gyro(c, s, k, gyr if has_g else ZERO3, has_g, dt)
    Rw = rotmat_t(q_omega_t(wl, dt))  # R(Δq): body axes of the previous sample → this one
    a_body, var_a, a_raw, var_a_raw, has_a_fused, a_sens, a_bias_gain = _accelerometer(
        c, s, k, u, dt, wl, Rw, acc, has_a)
    rest = _rest_test(c, s, dt, g, has_g, acc, has_a_fused, gs == MISSING, as_ == MISSING)
    has_m, dtm = _magnetometer(c, s, k, u, dt, wl, Rw, m, m_norm, has_m)
    _gyro_scale_noise(c, s, w, dt, wl)
    m_ref, h_ref, var_h, acc_gate, mag_gate = _fusion(c, s, has_m, dtm)
    z = Fusion(g, has_g, rest and c.algorithm < ALGO_EULER_KF, a_body, var_a, has_a_fused,
               a_raw, var_a_raw, has_a, m, has_m, m_ref, h_ref, var_h, acc_gate, mag_gate, a_sens,
               a_bias_gain)
    ok, acc_nis, mag_nis = _update(c, s, k, w, u, dt, z)
    _bookkeeping(c, s, k, z, ok, acc_nis, mag_nis, m_norm)
