"""The attitude filter for real sensors: the MEKF/MUKF of the paper behind a sensor layer.

The paper's filters (:mod:`~mkf_ros.core.mekf`, :mod:`~mkf_ros.core.mukf`) take abstract vector
measurements. This layer adds what a real IMU needs (spec §8 item 15):

* validation: a vector that is all NaN is *missing* (an asynchronous magnetometer, a dropped
  field); one that is partly non-finite or zero is *invalid*; either way only that sensor's
  update is skipped, and counted;
* references: the accelerometer reads +g "up" at rest, so its normalised reading measures the
  world up axis (0, 0, 1) in ENU; the magnetometer reference is given or learned (dip angle) from
  the first samples, horizontal part pointing north;
* initialisation: closed-form alignment (tilt from the accelerometer, heading from the first
  magnetometer sample), or the paper's identity with ``P0 = 100 I``;
* gaps: a step longer than ``max_dt`` re-aligns instead of integrating a stale rate;
* output in the chosen world frame with the orientation covariance about world axes.

Everything per sample runs in compiled kernels; :class:`AttitudeFilter` is the stateful Python
face used by the ROS node, and :func:`run_batch` the loop used by :func:`mkf_ros.estimate`.
"""

from __future__ import annotations

import contextlib

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.baselines import (
    body_cov_to_euler,
    euler_cov_to_body,
    euler_kf_acc_update,
    euler_kf_predict,
    euler_to_quat,
    euler_ukf_predict,
    euler_ukf_update,
    madgwick_step,
    quat_to_euler,
    yaw_update,
)
from mkf_ros.core.charts import chart_id, from_chart, from_chart_t, t_matrix, t_matrix_t
from mkf_ros.core.frames import FROM_ENU, align_tilt, heading_correction, keep_yaw
from mkf_ros.core.linalg import congruence, congruence33_t, eye, mm
from mkf_ros.core.mekf import (
    heading_residual,
    heading_residual_t,
    inv3_spd_t,
    mekf_apply_t,
    mekf_heading_update_t,
    mekf_predict_t,
    mekf_rate_update_t,
    mekf_scratch,
    mekf_vector_update_t,
    symmetrize_leading,
    transport_covariance,
)
from mkf_ros.core.mukf import B_HEADING, B_VEC0, B_VEC1, NOISE_MODES, mukf_scratch, mukf_step_t
from mkf_ros.core.params import ALGORITHMS, FilterParams
from mkf_ros.core.quaternion import (
    q_omega_t,
    qmul,
    qmul_t,
    qnormalize,
    qnormalize_t,
    rotate,
    rotate_inv,
    rotmat,
    rotmat_t,
    t3,
    t4,
    t33,
)

# --- layout of the configuration vector --------------------------------------------------------
C_ALGO, C_CHART, C_CU, C_USE_MAG, C_NX = 0, 1, 2, 3, 4
C_RW, C_RA, C_QA, C_RM, C_QM, C_QW, C_QB, C_B0 = 5, 6, 7, 8, 9, 10, 11, 12
C_W0, C_MUKF_NOISE, C_PAPER, C_MAXDT, C_MREF_GIVEN = 13, 14, 15, 16, 17
C_MREF = 18  # 3 values: given magnetic reference, ENU, unit
C_MAG_MODE, C_GRAVITY = 21, 22
C_ACC_TOL, C_ACC_GATE, C_ACC_RECOVER = 23, 24, 25
C_MAG_TOL, C_DIP_TOL, C_MAG_GATE, C_MAG_RECOVER = 26, 27, 28, 29
C_REST, C_REST_GYR, C_REST_ACC, C_REST_TIME, C_REST_VAR = 30, 31, 32, 33, 34
C_MAG_HI = 35  # 3 values: hard-iron offset, sensor units
C_MAG_SI = 38  # 9 values: soft-iron matrix, row-major
C_BETA, C_MADG_VAR, C_GIMBAL_COS = 47, 48, 49  # baselines (issue 7)
C_ACC_MODE = 50
C_ACC_TAU, C_ACC_DTIME, C_GYR_SCALE, C_GYR_GATE = 51, 52, 53, 54
C_MAG_TAU, C_MAG_CTOL, C_MAG_UNDIST, C_MAG_DTIME = 55, 56, 57, 58
C_ACC_ALIGN = 59
C_REST_SPLIT = 60  # 1: gyro and accelerometer come in separate samples (split input)
C_SIZE = 61
MAG_HEADING, MAG_VECTOR = 0, 1
ACC_TILT, ACC_VECTOR = 0, 1

# --- layout of the state vector ----------------------------------------------------------------
S_QC, S_E, S_W, S_B, S_MREF, S_MSUM = 0, 4, 7, 10, 13, 16  # q̄_c(4) ē(3) ω̄(3) b̄(3) m_ref m_sum
S_MNORM = 19  # learned magnitude of the (calibrated) field
# s since the last accepted acc; s a plausible field has disagreed (χ²); s at rest
S_T_ACC, S_T_MAG, S_T_REST = 20, 21, 22
# baselines (issue 7): Euler angles (φ, θ, ψ) of the Euler KF/UKF (the UKF's body rates are
# S_W); Madgwick's heading variance grown since alignment (6D), a held magnetometer sample
S_EUL, S_BL_YAWVAR, S_BL_MAG, S_BL_MHELD = 23, 26, 27, 30
# the accelerometer low-passed in an almost inertial frame: two first-order stages (body axes)
S_ALP = 31  # 6 values
S_T_MAGOK = 37  # s the field has been plausible and consistent without a break
S_MLP = 38  # 3: the calibrated field over its learned magnitude, inertial low-pass (body axes)
S_WLP = 41  # |ω| low-passed like the field
S_GLP, S_ALR = 42, 45  # 3 + 3: gyro and accelerometer low-passed for rest detection
S_GREJ = 48  # 1 after a gyro sample rejected by its gate
S_ALT, S_MLT = 49, 50  # s since the accelerometer / field low-pass started
S_AEX, S_AWLP = 51, 52  # low-passed (|a| − g)² and |ω|, over acc_time_constant
S_DTA, S_DTM = 53, 54  # s since the previous accelerometer / magnetometer sample
S_RDEV = 55  # 2: rest detection, low-passed squared deviations of the gyro and accelerometer
S_ALPHA = 57  # 4 × (Δt, τ, 1 − exp(−Δt/τ)): the last low-pass gains (acc, field, rest, |ω|)
S_RDT = 69  # 2: split input, s since the gyro / accelerometer last entered the rest test
S_SIZE = 71
NX_MAX = 9

# --- noise matrices derived from the configuration (built once per parameter set) -------------
N_QW, N_QB, N_RW, N_RA, N_QA, N_RM, N_QM = 0, 1, 2, 3, 4, 5, 6
N_SIZE = 7

# --- flags and counters ------------------------------------------------------------------------
F_INIT, F_HEADING, F_EVER, F_MCOUNT = 0, 1, 2, 3
F_SIZE = 4
COUNTER_NAMES = (
    "samples",
    "gyr_missing", "gyr_invalid",
    "acc_missing", "acc_invalid",
    "mag_missing", "mag_invalid",
    "gaps", "update_failed", "before_init",
    "acc_rejected_norm", "acc_rejected_chi2", "mag_rejected_norm", "mag_rejected_dip",
    "mag_rejected_chi2", "rest_updates", "gimbal_lock", "mag_rejected_inconsistent",
    "gyr_rejected_chi2",
)
K_SAMPLES, K_GYR_MISSING, K_GYR_INVALID, K_ACC_MISSING, K_ACC_INVALID = 0, 1, 2, 3, 4
K_MAG_MISSING, K_MAG_INVALID, K_GAPS, K_UPDATE_FAILED, K_BEFORE_INIT = 5, 6, 7, 8, 9
K_ACC_REJ_NORM, K_ACC_REJ_CHI2, K_MAG_REJ_NORM, K_MAG_REJ_DIP, K_MAG_REJ_CHI2 = 10, 11, 12, 13, 14
K_REST, K_GIMBAL, K_MAG_REJ_INCONS, K_GYR_REJ_CHI2 = 15, 16, 17, 18
K_SIZE = len(COUNTER_NAMES)

# algorithm ids (index in ALGORITHMS): the paper's filters, then the baselines (issue 7)
ALGO_MEKF, ALGO_MUKF = ALGORITHMS.index("mekf"), ALGORITHMS.index("mukf")
ALGO_EULER_KF, ALGO_EULER_UKF = ALGORITHMS.index("euler_kf"), ALGORITHMS.index("euler_ukf")
ALGO_MADGWICK = ALGORITHMS.index("madgwick")

UP = np.array((0.0, 0.0, 1.0))  # world up in ENU: what a resting accelerometer measures
MAG_REF_SAMPLES = 100  # magnetometer samples averaged into a learned reference
P0_PAPER = 100.0  # §8 item 9
YAW0_STDDEV = 1e-3  # rad: heading is defined by the start-up heading when no magnetometer
YAW_VAR_UNKNOWN = np.pi ** 2 / 3.0  # rad²: variance of an angle uniform over ±180°
REST_LP_TAU = 0.5  # s: rest detection compares the gyro and accelerometer with their low-pass
REST_CHI2 = 16.27  # 3 degrees of freedom, 0.1 %: the low-passed rate agrees with the bias
# Euler baselines' tilt re-alignment (issue 14 item 5, :func:`_bl_realign`): the accelerometer
# "looks like gravity" when its magnitude is within this fraction of ``gravity`` ...
REALIGN_ACC_TOL = 0.05
# ... and the gyro (bias removed) is below this rate (rad/s), so little centripetal acceleration
REALIGN_MAX_RATE = 0.5


# --- plausibility of a reading (issue 14): the one definition, for the library and the node ----
#: A gyro reading faster than this (rad/s, ~9500 rpm) is beyond any MEMS gyro's range: invalid.
MAX_GYRO_RATE = 1000.0
#: An accelerometer reading larger than this many times ``gravity`` is invalid (no IMU's
#: accelerometer reads 10,000 g; the filter's own magnitude test, ``acc_norm_tolerance``, judges
#: the plausible ones).
MAX_ACC_G = 1e4
#: A (calibrated) magnetometer reading larger than this, in any unit, is invalid: no field in
#: tesla, gauss, µT or raw counts comes near it, and the square of a larger one can overflow.
MAX_MAG = 1e100
#: The smallest magnitude of an accelerometer or magnetometer vector: below it (a zero vector,
#: or one whose square underflows) the direction is undefined and the reading invalid.
MIN_VECTOR = 1e-150


@jit_inline
def classify_reading(v: tuple, is_vector: bool, limit: float) -> int:
    """One sensor reading, for the batch loop and the stream adapter alike: 0 valid, 1 missing
    (all NaN), 2 invalid (partly non-finite, a vector below :data:`MIN_VECTOR` or a reading
    whose magnitude exceeds ``limit``: :data:`MAX_GYRO_RATE`, :data:`MAX_ACC_G` times gravity,
    :data:`MAX_MAG`)."""
    nan = 0
    bad = False
    for i in range(3):
        if np.isnan(v[i]):
            nan += 1
        elif not np.isfinite(v[i]):
            bad = True
    if nan == 3:
        return 1
    if nan > 0 or bad:
        return 2
    s = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    if s > limit * limit or (is_vector and s < MIN_VECTOR * MIN_VECTOR):
        return 2
    return 0


@jit_inline
def _unit_t(v: tuple) -> tuple:
    n = np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    return (v[0] / n, v[1] / n, v[2] / n)


@jit_inline
def _n33(nz: np.ndarray, k: int) -> tuple:
    """Noise matrix ``k`` of :func:`build_noise` as a tuple of rows (no array view)."""
    return ((nz[k, 0, 0], nz[k, 0, 1], nz[k, 0, 2]), (nz[k, 1, 0], nz[k, 1, 1], nz[k, 1, 2]),
            (nz[k, 2, 0], nz[k, 2, 1], nz[k, 2, 2]))


@jit
def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@jit
def recentre(cfg: np.ndarray, st: np.ndarray, P: np.ndarray) -> None:
    """Move the chart centre onto the estimate: ``q̄_c ← q̄_c * φ⁻¹(ē)``, ``ē ← 0``, and carry
    ``P`` with the T-matrix (§3.2). A no-op for the MEKF, whose ``ē`` is always zero."""
    chart = int(cfg[C_CHART])
    nx = int(cfg[C_NX])
    e = st[S_E:S_E + 3]
    if e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0:
        return
    d = from_chart(chart, e)
    st[S_QC:S_QC + 4] = qnormalize(qmul(st[S_QC:S_QC + 4], d))
    st[S_E:S_E + 3] = 0.0
    transport_covariance(P, nx, t_matrix(chart, d))


@jit
def estimate_enu(cfg: np.ndarray, st: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point estimate ``q̂`` (ENU) and the attitude covariance about **body** axes, transported
    from the ``q̄_c``-chart to ``q̂`` with the T-matrix (§3.2; first order, every chart agrees
    with the rotation vector at the origin, eq. 10)."""
    if int(cfg[C_ALGO]) >= ALGO_EULER_KF:
        return _baseline_estimate(cfg, st, P)
    chart = int(cfg[C_CHART])
    e = st[S_E:S_E + 3]
    if e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0:
        return st[S_QC:S_QC + 4].copy(), P[0:3, 0:3].copy()
    d = from_chart(chart, e)
    T = t_matrix(chart, d)
    return qnormalize(qmul(st[S_QC:S_QC + 4], d)), congruence(T, P[0:3, 0:3])


@jit
def _set_world_attitude_cov(st: np.ndarray, P: np.ndarray, nx: int, var_tilt: float,
                            var_yaw: float, keep_tilt: bool) -> None:
    """Set the attitude block of ``P`` from world-axis variances (tilt about x/y, yaw about z);
    with ``keep_tilt`` only the yaw row/column is replaced. Cross terms with yaw are cleared."""
    R = rotmat(st[S_QC:S_QC + 4])
    Sw = congruence(R, P[0:3, 0:3])  # body → world axes
    C = mm(R, P[0:3, 3:nx])
    if not keep_tilt:
        Sw[:, :] = 0.0
        Sw[0, 0] = var_tilt
        Sw[1, 1] = var_tilt
        C[:, :] = 0.0
    for i in range(3):
        Sw[2, i] = 0.0
        Sw[i, 2] = 0.0
    Sw[2, 2] = var_yaw
    C[2, :] = 0.0
    P[0:3, 0:3] = mm(R.T.copy(), mm(Sw, R))
    Ct = mm(R.T.copy(), C)
    P[0:3, 3:nx] = Ct
    P[3:nx, 0:3] = Ct.T


@jit
def _inflate_world(st: np.ndarray, P: np.ndarray, var_tilt: float, var_yaw: float) -> None:
    """Add uncertainty about the world axes (tilt about x and y, yaw about z) to ``P_ee``: used
    when a sensor has been rejected for so long that the estimate itself is suspect."""
    R = rotmat(st[S_QC:S_QC + 4])
    for i in range(3):
        for j in range(3):
            P[i, j] += (var_tilt * (R[0, i] * R[0, j] + R[1, i] * R[1, j])
                        + var_yaw * R[2, i] * R[2, j])


@jit
def _mag_yaw_var(cfg: np.ndarray, ref: np.ndarray) -> float:
    h = max(np.sqrt(ref[0] * ref[0] + ref[1] * ref[1]), 0.05)  # horizontal share of the field
    return (cfg[C_RM] + cfg[C_QM]) / (h * h)


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
    _set_world_attitude_cov(st, P, nx, 0.0, _mag_yaw_var(cfg, ref), True)
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
    _set_world_attitude_cov(st, P, nx, cfg[C_RA] + 9.0 * cfg[C_QA], var_yaw, False)
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


@jit
def build_noise(cfg: np.ndarray) -> np.ndarray:
    """The isotropic noise matrices of the configuration: Q_ω, Q_b, R_ω, R_acc, Q_acc, R_mag,
    Q_mag (normalised vector units for the accelerometer and magnetometer, §8 item 15)."""
    nz = np.zeros((N_SIZE, 3, 3))
    for k, c in ((N_QW, C_QW), (N_QB, C_QB), (N_RW, C_RW), (N_RA, C_RA), (N_QA, C_QA),
                 (N_RM, C_RM), (N_QM, C_QM)):
        for i in range(3):
            nz[k, i, i] = cfg[c]
    return nz


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
    moves the attitude (the rate updates in :func:`_sensor_step`).

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
        _bl_export(cfg, st, P)
        _inflate_world(st, P, 0.0, psi * psi)
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


# --- baselines (issue 7): glue between the sensor layer and mkf_ros.core.baselines ----------
# The sensor layer (alignment, heading initialisation, recovery) works on the MKF form of the
# state, "canonical" here: q̄ = S_QC with ē = 0, P_ee about body axes, P_ωω, P_bb. The Euler
# filters keep their own state (S_EUL, and P as the covariance of (φ, θ, ψ[, p, q, r])) and are
# converted only where the sensor layer resets something and on an algorithm switch, so that
# their gimbal-lock behaviour is theirs. Madgwick's state is S_QC itself; it has no covariance.


@jit
def _euler_n(algo: int) -> int:
    return 3 if algo == ALGO_EULER_KF else 6


@jit
def _baseline_estimate(cfg: np.ndarray, st: np.ndarray,
                       P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Estimate and attitude covariance about body axes of a baseline: Euler filters
    ``E Σ_φθψ Eᵀ`` (E: body rotation vector per Euler increment, the inverse of eq. (7));
    Madgwick a fixed ``madgwick_stddev²`` about each world axis (heading in 6D growing with the
    integrated gyro noise)."""
    q = st[S_QC:S_QC + 4].copy()
    if int(cfg[C_ALGO]) == ALGO_MADGWICK:
        v = cfg[C_MADG_VAR]
        vy = v if cfg[C_USE_MAG] > 0 else v + st[S_BL_YAWVAR]
        R = rotmat(q)
        C = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                C[i, j] = v * (R[0, i] * R[0, j] + R[1, i] * R[1, j]) + vy * R[2, i] * R[2, j]
        return q, C
    return q, euler_cov_to_body(st[S_EUL:S_EUL + 3], P, 3)


@jit
def _bl_export(cfg: np.ndarray, st: np.ndarray, P: np.ndarray) -> None:
    """Baseline state → canonical form (no-op for the MKFs); attitude-bias cross terms are
    zero (the baselines do not estimate the bias; a bias estimated before a switch is kept
    frozen and subtracted from the gyro)."""
    algo = int(cfg[C_ALGO])
    if algo < ALGO_EULER_KF:
        return
    q, C = _baseline_estimate(cfg, st, P)
    n = 3 if algo != ALGO_EULER_UKF else 6
    if algo == ALGO_EULER_UKF:
        C = euler_cov_to_body(st[S_EUL:S_EUL + 3], P, 6)
    st[S_QC:S_QC + 4] = q
    st[S_E:S_E + 3] = 0.0
    for i in range(NX_MAX):  # clear everything but the bias block ...
        for j in range(NX_MAX):
            if i < 6 or j < 6:
                P[i, j] = 0.0
    P[0:n, 0:n] = C  # ... then the attitude [and rate] block
    if n == 3:  # KF, Madgwick: the gyro reading is the rate estimate
        for i in range(3, 6):
            P[i, i] = cfg[C_RW]
    if int(cfg[C_NX]) == 9:  # ω̄ = g − b̄ (frozen bias): the rate inherits its uncertainty
        for i in range(3):
            for j in range(3):
                P[3 + i, 3 + j] += P[6 + i, 6 + j]
                P[3 + i, 6 + j] = -P[6 + i, 6 + j]
                P[6 + j, 3 + i] = -P[6 + i, 6 + j]


@jit
def to_canonical(cfg: np.ndarray, st: np.ndarray, P: np.ndarray) -> None:
    """Any algorithm's state in the canonical form: :func:`recentre` for the MKFs."""
    if int(cfg[C_ALGO]) < ALGO_EULER_KF:
        recentre(cfg, st, P)
    else:
        _bl_export(cfg, st, P)


@jit
def from_canonical(cfg: np.ndarray, st: np.ndarray, P: np.ndarray) -> None:
    """Canonical form → the algorithm's own state (no-op for the MKFs): Euler angles of
    ``q̄`` and ``Σ = W P_ee Wᵀ`` (W of eq. (7), |cos θ| floored), rates block kept for the UKF."""
    algo = int(cfg[C_ALGO])
    if algo < ALGO_EULER_KF:
        return
    if algo == ALGO_MADGWICK:
        st[S_BL_YAWVAR] = 0.0
        st[S_BL_MHELD] = 0.0
        return
    n = _euler_n(algo)
    phi, theta, psi = quat_to_euler(st[S_QC:S_QC + 4])
    st[S_EUL], st[S_EUL + 1], st[S_EUL + 2] = phi, theta, psi
    S = body_cov_to_euler(st[S_EUL:S_EUL + 3], P, n)
    for i in range(n):
        for j in range(n, NX_MAX):
            P[i, j] = 0.0
            P[j, i] = 0.0
    P[0:n, 0:n] = S
    st[S_QC:S_QC + 4] = euler_to_quat(phi, theta, psi)


@jit
def _bl_realign(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, a: tuple, w: tuple) -> bool:
    """Euler baselines only (issue 14 item 5): when the accelerometer has been refused for
    ``acc_recovery_time`` and this sample looks like gravity (magnitude within
    :data:`REALIGN_ACC_TOL` of ``gravity``, rate below :data:`REALIGN_MAX_RATE`), re-align the
    tilt from it, keeping yaw and its variance, as after a gap (:func:`_align`). Widening the
    prior alone does not bring them back: once the tilt is far off, the Euler UKF's sigma points
    span more than a turn and its χ² gate refuses gravity whatever the variance (measured: tilt
    variances of 20–90 rad² still refused). The tilt variance is one sample's (as in
    :func:`_align`) plus the square of the tilt's jump: never narrower than the step taken.
    Works on the canonical form (between :func:`_bl_export` and :func:`from_canonical`).
    Returns whether it re-aligned (False: not a baseline that needs it, or not gravity)."""
    algo = int(cfg[C_ALGO])
    if algo != ALGO_EULER_KF and algo != ALGO_EULER_UKF:
        return False
    n = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    if (abs(n / cfg[C_GRAVITY] - 1.0) > REALIGN_ACC_TOL
            or w[0] * w[0] + w[1] * w[1] + w[2] * w[2] > REALIGN_MAX_RATE ** 2):
        return False
    R = rotmat(st[S_QC:S_QC + 4])
    # the jump: between the estimate's up (R's last row, in body axes) and the accelerometer's
    c = (R[2, 0] * a[0] + R[2, 1] * a[1] + R[2, 2] * a[2]) / n
    jump = np.arccos(max(-1.0, min(1.0, c)))
    var_yaw = 0.0  # world-z variance of the attitude block, kept
    for i in range(3):
        for j in range(3):
            var_yaw += R[2, i] * R[2, j] * P[i, j]
    st[S_QC:S_QC + 4] = keep_yaw(align_tilt(np.array(a)), st[S_QC:S_QC + 4])
    _set_world_attitude_cov(st, P, int(cfg[C_NX]), cfg[C_RA] + 9.0 * cfg[C_QA] + jump * jump,
                            var_yaw, False)
    return True


@jit
def _baseline_update(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                     cnt: np.ndarray, dt: float, g: np.ndarray, has_g: bool, a_body: np.ndarray,
                     has_a: bool, var_a_extra: float, m_body: np.ndarray, has_m: bool,
                     acc_gate: float, mag_gate: float) -> tuple[bool, float, float]:
    """One step of a baseline after the sensor layer's checks. The gyro minus the (frozen)
    bias is the rate; a missing gyro sample repeats the last rate (KF, Madgwick). Returns
    ``(ok, acc NIS, mag NIS)`` like the MKF branches (Madgwick: NIS 0, it has no gate)."""
    algo = int(cfg[C_ALGO])
    b = st[S_B:S_B + 3]
    w = st[S_W:S_W + 3]
    if has_g and algo != ALGO_EULER_UKF:
        for i in range(3):
            w[i] = g[i] - b[i]
    var_w = cfg[C_RW]
    var_a = cfg[C_RA] + var_a_extra
    ref = st[S_MREF:S_MREF + 3]
    h = np.sqrt(ref[0] * ref[0] + ref[1] * ref[1])
    href = np.array((ref[0] / h, ref[1] / h, 0.0)) if h > 0.0 else np.array((0.0, 1.0, 0.0))
    if algo == ALGO_MADGWICK:
        m = m_body
        use_m = has_m
        if has_m and not has_a:  # Madgwick needs both: hold it for the next IMU sample
            st[S_BL_MAG:S_BL_MAG + 3] = m_body
            st[S_BL_MHELD] = 1.0
            use_m = False
        elif has_a and not has_m and st[S_BL_MHELD] > 0:
            m = st[S_BL_MAG:S_BL_MAG + 3].copy()
            use_m = True
        if has_a:
            st[S_BL_MHELD] = 0.0
        madgwick_step(st[S_QC:S_QC + 4], w, dt, a_body, has_a, m, use_m, href, cfg[C_BETA])
        st[S_BL_YAWVAR] += var_w * dt * dt
        return True, 0.0, 0.0
    x = st[S_EUL:S_EUL + 3]
    mag_var = _mag_yaw_var(cfg, ref)
    ok = True
    acc_nis = 0.0
    mag_nis = 0.0
    if algo == ALGO_EULER_KF:
        euler_kf_predict(x, P, w, dt, var_w)
        if has_a:
            acc_nis = euler_kf_acc_update(x, P, a_body, var_a, acc_gate)
        if has_m:
            resid, _ = heading_residual(rotmat(euler_to_quat(x[0], x[1], x[2])), m_body, href)
            mag_nis = yaw_update(x, P, 3, resid, mag_var, mag_gate)
    else:
        xx = np.empty(6)
        for i in range(3):
            xx[i] = x[i]
            xx[3 + i] = w[i]
        ok = euler_ukf_predict(xx, P, dt, cfg[C_QW])
        if ok:
            z = np.zeros(7)
            for i in range(3):
                z[i] = a_body[i]
                z[3 + i] = g[i] - b[i]
            if has_m:
                resid, _ = heading_residual(rotmat(euler_to_quat(xx[0], xx[1], xx[2])), m_body,
                                            href)
                z[6] = resid
            use = np.array((has_a, has_g, has_m))
            Rd = np.array((var_a, var_a, var_a, var_w, var_w, var_w, mag_var))
            gates = np.array((acc_gate, np.inf, mag_gate))
            nis = np.zeros(3)
            ok = euler_ukf_update(xx, P, use, z, Rd, gates, nis)
            acc_nis, mag_nis = nis[0], nis[2]
        for i in range(3):
            x[i] = xx[i]
            w[i] = xx[3 + i]
    if abs(np.cos(x[1])) < cfg[C_GIMBAL_COS]:
        cnt[K_GIMBAL] += 1
    st[S_QC:S_QC + 4] = euler_to_quat(x[0], x[1], x[2])
    return ok, acc_nis, mag_nis


@jit
def sensor_step(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                fl: np.ndarray, cnt: np.ndarray, dt: float, gyr: np.ndarray, acc: np.ndarray,
                mag: np.ndarray) -> None:
    """Process one sample: any of ``gyr`` (rad/s), ``acc`` (m/s², +g up at rest) and ``mag``
    (any unit) may be NaN (missing). ``dt`` is the time since the previous sample."""
    _sensor_step(cfg, nz, st, P, fl, cnt, dt, t3(gyr), t3(acc), t3(mag), np.empty(NX_MAX),
                 mekf_scratch(NX_MAX), mukf_scratch(int(cfg[C_NX])))


@jit_inline
def _sensor_step(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
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
        _bl_export(cfg, st, P)  # baselines: the sensor layer works on (q̄, P_ee, ...)
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
            _bl_export(cfg, st, P)
            if not _bl_realign(cfg, st, P, acc, wl):
                _inflate_world(st, P, ang * ang, 0.0)
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
    var_h = (_mag_yaw_var(cfg, np.array(mref)) * _correlated(cfg[C_MAG_DTIME], dtm) if has_m
             else 0.0)
    algo = int(cfg[C_ALGO])
    if algo <= ALGO_MUKF and cfg[C_GYR_SCALE] > 0:
        # the gyro's scale and axis errors: attitude noise growing with the rate turned
        qs = cfg[C_GYR_SCALE] ** 2 * (wl[0] ** 2 + wl[1] ** 2 + wl[2] ** 2) * dt
        for i in range(3):
            P[i, i] += qs
    if algo >= ALGO_EULER_KF:  # baselines: no rate/bias state to sharpen at rest
        rest = False
        ok, acc_nis, mag_nis = _baseline_update(cfg, nz, st, P, cnt, dt, np.array(g), has_g,
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
            ok &= mekf_rate_update_t(P, nx, dx, w, b, g, _n33(nz, N_RW), True, np.inf,
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
        q = mekf_predict_t(q, w, P, nx, dt, _n33(nz, N_QW), _n33(nz, N_QB))
        R = rotmat_t(q)
        for i in range(nx):
            dx[i] = 0.0
        if has_a:
            acc_nis = mekf_vector_update_t(P, nx, dx, R, a_body, (0.0, 0.0, 1.0),
                                           _n33(nz, N_RA), Qa, acc_gate,
                                           cfg[C_ACC_MODE] == ACC_TILT, work)
        if has_m:
            if heading:
                mag_nis = mekf_heading_update_t(P, nx, dx, R, m_body, href, var_h, mag_gate)
            else:
                mag_nis = mekf_vector_update_t(P, nx, dx, R, m_body, mref, _n33(nz, N_RM),
                                               _n33(nz, N_QM), mag_gate, False, work)
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
        _n33(nz, N_QW), _n33(nz, N_QB), (a_body, m_body if has_m else zero3),
        ((0.0, 0.0, 1.0), mref if has_m else zero3), (_n33(nz, N_RA), _n33(nz, N_RM)),
        (Qa, _n33(nz, N_QM)), (has_a, use_vm), g, has_g, _n33(nz, N_RW),
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
                           _n33(nz, N_QW), (zero3, zero3, zero3))
        for i in range(4):
            st[S_QC + i] = q[i]
    acc_nis = nis[B_VEC0] if has_a else 0.0
    mag_nis = nis[B_HEADING] if heading else nis[B_VEC1]
    return ok, acc_nis, mag_nis


@jit_inline
def _world_output_t(cfg: np.ndarray, st: np.ndarray, P: np.ndarray,
                    q_from_enu: np.ndarray) -> tuple[tuple, tuple]:
    """:func:`world_output` as tuples (the quaternion, the covariance's rows): reads ``st`` and
    ``P`` element by element, so that the per-sample output of :func:`run_batch` allocates
    nothing and creates no array views (each costs reference counting)."""
    if int(cfg[C_ALGO]) >= ALGO_EULER_KF:
        qa, Pa = _baseline_estimate(cfg, st, P)
        q, Pb = t4(qa), t33(Pa)
    else:  # estimate_enu: q̂ = q̄_c * φ⁻¹(ē), Σ_body = T P_ee Tᵀ (identity for ē = 0)
        q = (st[S_QC], st[S_QC + 1], st[S_QC + 2], st[S_QC + 3])
        Pb = ((P[0, 0], P[0, 1], P[0, 2]), (P[1, 0], P[1, 1], P[1, 2]),
              (P[2, 0], P[2, 1], P[2, 2]))
        e = (st[S_E], st[S_E + 1], st[S_E + 2])
        if not (e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0):
            chart = int(cfg[C_CHART])
            d = from_chart_t(chart, e)
            q = qnormalize_t(qmul_t(q, d))
            Pb = congruence33_t(t_matrix_t(chart, d), Pb)
    q = qmul_t(t4(q_from_enu), q)
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[0] < 0.0:
        n = -n
    q = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
    C = congruence33_t(rotmat_t(q), Pb)
    f2 = cfg[C_ACC_ALIGN] ** 2 if int(cfg[C_ALGO]) != ALGO_MADGWICK else 0.0
    # the accelerometer's own misalignment: a constant no filter averages out (published only,
    # by every filter but Madgwick, whose published value is a parameter; every world frame
    # here has its z vertical, so x and y are the tilt axes). Symmetric by construction: the
    # mean of the two triangles, which the congruence's rounding makes differ by ~1e-16 of
    # the largest element (bit-identical where they agree)
    c01, c02, c12 = 0.5 * (C[0][1] + C[1][0]), 0.5 * (C[0][2] + C[2][0]), 0.5 * (C[1][2] + C[2][1])
    return q, ((C[0][0] + f2, c01, c02), (c01, C[1][1] + f2, c12), (c02, c12, C[2][2]))


@jit
def world_output(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, q_from_enu: np.ndarray,
                 q_out: np.ndarray, cov_out: np.ndarray) -> None:
    """Orientation in the world frame (``q0 ≥ 0``) and its 3×3 covariance about world axes:
    ``Σ_W = R(q_W) Σ_body R(q_W)ᵀ`` (the error is body-side, ``q = q̂ * δ(e)``)."""
    q, cov = _world_output_t(cfg, st, P, q_from_enu)
    for i in range(4):
        q_out[i] = q[i]
    for i in range(3):
        for j in range(3):
            cov_out[i, j] = cov[i][j]


@jit
def run_batch(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray, cnt: np.ndarray,
              dts: np.ndarray, gyr: np.ndarray, acc: np.ndarray, mag: np.ndarray,
              q_from_enu: np.ndarray, out_q: np.ndarray, out_cov: np.ndarray,
              out_w: np.ndarray, out_b: np.ndarray, out_bvar: np.ndarray,
              out_init: np.ndarray) -> None:
    """:func:`sensor_step` over a whole recording, writing the outputs of every sample
    (element by element: no array views in the loop)."""
    nx = int(cfg[C_NX])
    nz = build_noise(cfg)
    dx = np.empty(NX_MAX)
    work = mekf_scratch(NX_MAX)
    mwork = mukf_scratch(nx)
    for n in range(dts.shape[0]):
        _sensor_step(cfg, nz, st, P, fl, cnt, dts[n], (gyr[n, 0], gyr[n, 1], gyr[n, 2]),
                     (acc[n, 0], acc[n, 1], acc[n, 2]), (mag[n, 0], mag[n, 1], mag[n, 2]), dx,
                     work, mwork)
        q, cov = _world_output_t(cfg, st, P, q_from_enu)
        init = fl[F_INIT] > 0
        out_init[n] = init
        for i in range(4):
            out_q[n, i] = q[i]
        for i in range(3):
            for j in range(3):
                out_cov[n, i, j] = cov[i][j]
            if not init:
                out_cov[n, i, i] = np.pi ** 2  # not initialised: attitude unknown
            out_w[n, i] = st[S_W + i]
            out_b[n, i] = st[S_B + i]
            out_bvar[n, i] = P[6 + i, 6 + i] if nx == 9 else 0.0


def build_cfg(p: FilterParams) -> np.ndarray:
    """Kernel configuration vector from validated parameters (units converted here)."""
    cfg = np.zeros(C_SIZE)
    cfg[C_ALGO] = ALGORITHMS.index(p.algorithm)
    cfg[C_CHART] = chart_id(p.chart)
    cfg[C_CU] = float(p.chart_update)
    cfg[C_USE_MAG] = float(p.use_mag)
    cfg[C_NX] = 9 if p.estimate_gyro_bias else 6
    g = p.gravity
    cfg[C_RW] = p.gyro_noise**2
    cfg[C_RA] = (p.acc_noise / g) ** 2  # normalised reading: unit "g" (§8 item 15)
    cfg[C_QA] = (p.acc_disturbance / g) ** 2
    cfg[C_RM] = p.mag_noise**2
    cfg[C_QM] = p.mag_disturbance**2
    cfg[C_QW] = p.rate_process_noise
    cfg[C_QB] = p.gyro_bias_noise**2
    cfg[C_B0] = p.gyro_bias_stddev**2
    cfg[C_W0] = p.mukf_w0
    cfg[C_MUKF_NOISE] = NOISE_MODES.index(p.mukf_noise_scaling)
    cfg[C_PAPER] = float(p.init_mode == "paper")
    cfg[C_MAXDT] = p.max_dt
    cfg[C_MAG_MODE] = MAG_HEADING if p.mag_mode == "heading" else MAG_VECTOR
    cfg[C_ACC_MODE] = ACC_TILT if p.acc_mode == "tilt" else ACC_VECTOR
    cfg[C_ACC_TAU] = p.acc_time_constant
    cfg[C_ACC_DTIME] = p.acc_disturbance_time
    cfg[C_GYR_SCALE] = p.gyro_scale_error
    cfg[C_GYR_GATE] = p.gyro_gate
    cfg[C_MAG_TAU] = p.mag_time_constant
    cfg[C_MAG_CTOL] = p.mag_consistency_tolerance
    cfg[C_MAG_UNDIST] = p.mag_undisturbed_time
    cfg[C_MAG_DTIME] = p.mag_disturbance_time
    cfg[C_ACC_ALIGN] = p.acc_alignment_error
    cfg[C_GRAVITY] = g
    cfg[C_ACC_TOL] = p.acc_norm_tolerance
    cfg[C_ACC_GATE] = p.acc_gate
    cfg[C_ACC_RECOVER] = p.acc_recovery_time
    cfg[C_MAG_TOL] = p.mag_norm_tolerance
    cfg[C_DIP_TOL] = p.mag_dip_tolerance
    cfg[C_MAG_GATE] = p.mag_gate
    cfg[C_MAG_RECOVER] = p.mag_recovery_time
    cfg[C_REST] = float(p.rest_detection)
    cfg[C_REST_GYR] = p.rest_gyro_threshold
    cfg[C_REST_ACC] = p.rest_acc_threshold
    cfg[C_REST_TIME] = p.rest_time
    cfg[C_REST_VAR] = p.rest_rate_stddev**2
    cfg[C_BETA] = p.madgwick_beta
    cfg[C_MADG_VAR] = p.madgwick_stddev**2
    cfg[C_GIMBAL_COS] = np.cos(p.gimbal_lock_pitch)
    cfg[C_MAG_HI:C_MAG_HI + 3] = (p.mag_bias_x, p.mag_bias_y, p.mag_bias_z)
    si = np.asarray(p.mag_soft_iron, dtype=float)
    if abs(np.linalg.det(si.reshape(3, 3))) < 1e-12:
        raise ValueError("mag_soft_iron must be an invertible 3x3 matrix (row-major, 9 numbers)")
    cfg[C_MAG_SI:C_MAG_SI + 9] = si
    ref = np.asarray(p.mag_reference, dtype=float)
    n = float(np.linalg.norm(ref))
    if n > 0.0:
        q = FROM_ENU[p.world_frame]  # given in the world frame → ENU: R(q_{W←ENU})ᵀ ref
        cfg[C_MREF_GIVEN] = 1.0
        cfg[C_MREF:C_MREF + 3] = rotmat(q).T @ (ref / n)
    elif p.use_mag and p.init_mode == "paper":
        raise ValueError("init_mode 'paper' with use_mag needs mag_reference (the paper's "
                         "filter has no alignment step to learn it)")
    return cfg


class AttitudeFilter:
    """Stateful single-step attitude filter (MEKF or MUKF, any chart, or a baseline of
    :mod:`mkf_ros.core.baselines`) for streaming use.

    >>> f = AttitudeFilter(algorithm="mekf", chart="rp")
    >>> f.step(0.01, gyr=[0, 0, 0], acc=[0, 0, 9.81])
    >>> f.quaternion  # [w, x, y, z], sensor → world
    array([1., 0., 0., 0.])
    """

    def __init__(self, params: FilterParams | None = None, **overrides: object) -> None:
        self._params = (params or FilterParams()).replace(**overrides)
        self._cfg = build_cfg(self._params)
        self._nz = build_noise(self._cfg)
        self._q_from_enu = FROM_ENU[self._params.world_frame].copy()
        self.counters = np.zeros(K_SIZE, dtype=np.int64)
        self.reset()

    # --- state ---------------------------------------------------------------------------
    def reset(self) -> None:
        """Forget the estimate: the next accelerometer sample re-initialises (bias kept at 0)."""
        self._st = np.zeros(S_SIZE)
        self._st[S_QC] = 1.0
        self._P = np.zeros((NX_MAX, NX_MAX))
        self._fl = np.zeros(F_SIZE, dtype=np.int64)

    @property
    def params(self) -> FilterParams:
        return self._params

    def set_params(self, **changes: object) -> FilterParams:
        """Validate and apply parameter changes atomically (ValueError: nothing changes).

        Switching ``algorithm``, ``chart`` or ``chart_update`` keeps the estimate: a MUKF mean
        ``ē ≠ 0`` is first moved onto the chart origin with the T-matrix (§3.2); at the origin
        every chart agrees with the rotation vector to first order (eq. 10), so ``P`` carries
        over unchanged. A switch to or from a baseline converts the state through that form:
        quaternion ↔ Euler angles, ``P_ee = E Σ Eᵀ`` ↔ ``Σ = W P_ee Wᵀ`` (:func:`to_canonical`,
        :func:`from_canonical`). Enabling bias estimation starts the bias at 0 with
        ``gyro_bias_stddev``; disabling it freezes the current bias.
        """
        new = self._params.replace(**changes)
        cfg = build_cfg(new)
        switch = new.algorithm != self._params.algorithm
        if switch or int(self._cfg[C_ALGO]) < ALGO_EULER_KF:
            to_canonical(self._cfg, self._st, self._P)
        old_nx, new_nx = int(self._cfg[C_NX]), int(cfg[C_NX])
        if new_nx > old_nx and self._fl[F_INIT]:
            self._P[6:9, :] = 0.0
            self._P[:, 6:9] = 0.0
            self._P[6:9, 6:9] = cfg[C_B0] * np.eye(3)
        if new.mag_reference != self._params.mag_reference or (
            new.use_mag and not self._params.use_mag
        ):
            self._fl[F_HEADING] = 0  # re-establish heading from the next magnetometer sample
        if switch:
            from_canonical(cfg, self._st, self._P)
        self._params, self._cfg, self._nz = new, cfg, build_noise(cfg)
        self._q_from_enu = FROM_ENU[new.world_frame].copy()
        return new

    def step(self, dt: float, gyr: object = None, acc: object = None, mag: object = None) -> None:
        """Process one sample; ``None`` means the sensor has no reading at this time.

        ``dt`` (s) is the time since the previous sample: finite and ``≥ 0``. ``dt = 0`` is a
        sample at the same instant: no prediction, its readings are fused as further
        measurements at that instant (Madgwick's correction is a rate: it has no effect over
        no time). Readings as for :func:`mkf_ros.estimate` (all NaN: missing; partly
        non-finite, a zero vector or beyond the plausibility limits: invalid, skipped and
        counted). An invalid ``dt`` or a sample of the wrong shape raises ValueError naming
        the argument and leaves the filter exactly as it was."""
        d = _dt(dt)
        g, a, m = _vec(gyr, "gyr"), _vec(acc, "acc"), _vec(mag, "mag")
        sensor_step(self._cfg, self._nz, self._st, self._P, self._fl, self.counters, d, g, a, m)

    @property
    def initialized(self) -> bool:
        return bool(self._fl[F_INIT])

    @property
    def heading_initialized(self) -> bool:
        """True once the magnetometer has fixed the heading (always False without it)."""
        return bool(self._fl[F_HEADING]) and self._params.use_mag

    @property
    def quaternion(self) -> np.ndarray:
        """Orientation ``[w, x, y, z]`` of the sensor in the world frame."""
        q, _ = self._output()
        return q

    @property
    def covariance(self) -> np.ndarray:
        """3×3 orientation covariance about the world frame's x, y, z axes (rad²)."""
        _, c = self._output()
        return c

    @property
    def omega(self) -> np.ndarray:
        """Estimated angular velocity, body frame (rad/s)."""
        return self._st[S_W:S_W + 3].copy()

    @property
    def bias(self) -> np.ndarray:
        """Estimated gyro bias (rad/s); zero unless ``estimate_gyro_bias``."""
        return self._st[S_B:S_B + 3].copy()

    @property
    def bias_stddev(self) -> np.ndarray:
        return np.sqrt(np.diag(self._P)[6:9]) if self._cfg[C_NX] == 9 else np.zeros(3)

    @property
    def state_covariance(self) -> np.ndarray:
        """The filter's covariance of ``(e, ω[, b])`` in its current chart."""
        n = int(self._cfg[C_NX])
        return self._P[:n, :n].copy()

    def counter_dict(self) -> dict[str, int]:
        return dict(zip(COUNTER_NAMES, (int(c) for c in self.counters), strict=True))

    def _output(self) -> tuple[np.ndarray, np.ndarray]:
        q = np.empty(4)
        c = np.empty((3, 3))
        world_output(self._cfg, self._st, self._P, self._q_from_enu, q, c)
        if not self._fl[F_INIT]:
            c = np.pi**2 * np.eye(3)
        return q, c


_NAN3 = np.full(3, np.nan)


def _dt(dt: object) -> float:
    """``dt`` of :meth:`AttitudeFilter.step` as a float; ValueError unless finite and ≥ 0."""
    d = np.nan
    if not isinstance(dt, (str, bytes, bool, np.bool_)):
        with contextlib.suppress(TypeError, ValueError):
            d = float(dt)  # type: ignore[arg-type]
    if not (np.isfinite(d) and d >= 0.0):
        raise ValueError(f"dt must be a finite number of seconds >= 0 (the time since the "
                         f"previous sample), got {dt!r}")
    return d


def _vec(v: object, name: str) -> np.ndarray:
    if v is None:
        return _NAN3
    # a fresh C-contiguous, writable float64 array: anything else would make numba compile a
    # new specialisation of the kernels in the middle of a stream
    try:
        a = np.array(v, dtype=np.float64, copy=True)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be 3 numbers or None, got {v!r}") from None
    if a.size != 3:
        raise ValueError(f"{name} must have 3 components, got shape {a.shape}")
    return a.reshape(-1)
