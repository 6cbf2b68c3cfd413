"""The filter's state and configuration: the one definition of their layouts, the
plausibility limits of a reading, and the operations every algorithm's state shares.

The compiled kernels keep a filter in plain arrays: the configuration vector ``cfg`` (``C_*``,
built from :class:`~mkf_ros.core.params.FilterParams` by :func:`build_cfg`, units converted
here), the state ``st`` (``S_*``: chart centre ``q̄_c``, chart point ``ē``, rate ``ω̄``, bias
``b̄`` and the sensor layer's memory), the covariance ``P`` of ``(e, ω[, b])`` (§5, §6), the
noise matrices ``nz`` (``N_*``), flags ``fl`` (``F_*``) and counters ``cnt`` (``K_*``). Front
ends outside ``core`` do not index these arrays: they use :mod:`mkf_ros.core.filter`.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.charts import chart_id, from_chart, t_matrix
from mkf_ros.core.frames import FROM_ENU
from mkf_ros.core.linalg import congruence, mm
from mkf_ros.core.mekf import (
    transport_covariance,
)
from mkf_ros.core.mukf import NOISE_MODES
from mkf_ros.core.params import ALGORITHMS, FilterParams
from mkf_ros.core.quaternion import (
    qmul,
    qnormalize,
    rotmat,
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
#: rad² about each axis: the published attitude covariance before the filter has an estimate
ATTITUDE_VAR_UNKNOWN = np.pi ** 2
REST_LP_TAU = 0.5  # s: rest detection compares the gyro and accelerometer with their low-pass
REST_CHI2 = 16.27  # 3 degrees of freedom, 0.1 %: the low-passed rate agrees with the bias
# Euler baselines' tilt re-alignment (issue 14 item 5, :func:`baseline_realign`): the accelerometer
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
def noise33(nz: np.ndarray, k: int) -> tuple:
    """Noise matrix ``k`` of :func:`build_noise` as a tuple of rows (no array view)."""
    return ((nz[k, 0, 0], nz[k, 0, 1], nz[k, 0, 2]), (nz[k, 1, 0], nz[k, 1, 1], nz[k, 1, 2]),
            (nz[k, 2, 0], nz[k, 2, 1], nz[k, 2, 2]))


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


#: Configuration slots that hold a parameter's value as it is (:func:`build_cfg` converts the
#: others).
_COPIED = (
    (C_W0, "mukf_w0"), (C_QW, "rate_process_noise"), (C_MAXDT, "max_dt"),
    (C_ACC_TAU, "acc_time_constant"), (C_ACC_DTIME, "acc_disturbance_time"),
    (C_GYR_SCALE, "gyro_scale_error"), (C_GYR_GATE, "gyro_gate"),
    (C_MAG_TAU, "mag_time_constant"), (C_MAG_CTOL, "mag_consistency_tolerance"),
    (C_MAG_UNDIST, "mag_undisturbed_time"), (C_MAG_DTIME, "mag_disturbance_time"),
    (C_ACC_ALIGN, "acc_alignment_error"), (C_ACC_TOL, "acc_norm_tolerance"),
    (C_ACC_GATE, "acc_gate"), (C_ACC_RECOVER, "acc_recovery_time"),
    (C_MAG_TOL, "mag_norm_tolerance"), (C_DIP_TOL, "mag_dip_tolerance"),
    (C_MAG_GATE, "mag_gate"), (C_MAG_RECOVER, "mag_recovery_time"),
    (C_REST_GYR, "rest_gyro_threshold"), (C_REST_ACC, "rest_acc_threshold"),
    (C_REST_TIME, "rest_time"), (C_BETA, "madgwick_beta"),
)


def build_cfg(p: FilterParams) -> np.ndarray:
    """Kernel configuration vector from validated parameters (units converted here; the
    cross-parameter rules are :class:`~mkf_ros.core.params.FilterParams`')."""
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
    cfg[C_QB] = p.gyro_bias_noise**2
    cfg[C_B0] = p.gyro_bias_stddev**2
    cfg[C_MUKF_NOISE] = NOISE_MODES.index(p.mukf_noise_scaling)
    cfg[C_PAPER] = float(p.init_mode == "paper")
    cfg[C_MAG_MODE] = MAG_HEADING if p.mag_mode == "heading" else MAG_VECTOR
    cfg[C_ACC_MODE] = ACC_TILT if p.acc_mode == "tilt" else ACC_VECTOR
    cfg[C_GRAVITY] = g
    cfg[C_REST] = float(p.rest_detection)
    cfg[C_REST_VAR] = p.rest_rate_stddev**2
    cfg[C_MADG_VAR] = p.madgwick_stddev**2
    cfg[C_GIMBAL_COS] = np.cos(p.gimbal_lock_pitch)
    for k, name in _COPIED:
        cfg[k] = p[name]
    cfg[C_MAG_HI:C_MAG_HI + 3] = (p.mag_bias_x, p.mag_bias_y, p.mag_bias_z)
    cfg[C_MAG_SI:C_MAG_SI + 9] = p.mag_soft_iron
    ref = np.asarray(p.mag_reference, dtype=float)
    n = float(np.linalg.norm(ref))
    if n > 0.0:
        q = FROM_ENU[p.world_frame]  # given in the world frame → ENU: R(q_{W←ENU})ᵀ ref
        cfg[C_MREF_GIVEN] = 1.0
        cfg[C_MREF:C_MREF + 3] = rotmat(q).T @ (ref / n)
    return cfg


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
def set_world_attitude_cov(st: np.ndarray, P: np.ndarray, nx: int, var_tilt: float,
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
def inflate_world(st: np.ndarray, P: np.ndarray, var_tilt: float, var_yaw: float) -> None:
    """Add uncertainty about the world axes (tilt about x and y, yaw about z) to ``P_ee``: used
    when a sensor has been rejected for so long that the estimate itself is suspect."""
    R = rotmat(st[S_QC:S_QC + 4])
    for i in range(3):
        for j in range(3):
            P[i, j] += (var_tilt * (R[0, i] * R[0, j] + R[1, i] * R[1, j])
                        + var_yaw * R[2, i] * R[2, j])


@jit
def mag_yaw_var(cfg: np.ndarray, ref: np.ndarray) -> float:
    h = max(np.sqrt(ref[0] * ref[0] + ref[1] * ref[1]), 0.05)  # horizontal share of the field
    return (cfg[C_RM] + cfg[C_QM]) / (h * h)
