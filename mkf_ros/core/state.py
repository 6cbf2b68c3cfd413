"""The filter's named records: the one definition of its configuration, state, counters and
scratch, the plausibility limits of a reading, and the operations every algorithm's state
shares.

The compiled kernels keep a filter in four NumPy record arrays of one element each (numba
passes a record by pointer: no reference counting at a call, so the steps of the sensor layer
can be separate compiled functions):

* :data:`CONFIG` — the parameters as the kernels use them (:func:`build_config`: units
  converted, choices as ids); a field named like a parameter holds that parameter as it is;
* :data:`STATE` — the estimate (chart centre ``q_c``, chart point ``e``, rate ``w``, bias
  ``b``), its covariance ``P`` of ``(e, ω[, b])`` (docs/math.md §5, §6), and the sensor
  layer's memory (references, low-passes, timers, flags);
* :data:`COUNTERS` — one count per :data:`COUNTER_NAMES` reason;
* :data:`WORK` — scratch of the filters' updates (contents never carried between samples).

Front ends outside ``core`` use :mod:`mkf_ros.core.filter`, not these fields.
"""

from __future__ import annotations

from collections import namedtuple

import numba
import numpy as np
from numba import types as nt

from mkf_ros.core._jit import JIT_DISABLED, jit
from mkf_ros.core.charts import chart_id, from_chart, from_chart_t, t_matrix, t_matrix_t
from mkf_ros.core.frames import FROM_ENU
from mkf_ros.core.linalg import ZERO33, congruence, copy_block, copy_into, mm
from mkf_ros.core.mekf import MEKF_SCRATCH_ROWS, transport_covariance, transport_covariance_t
from mkf_ros.core.mukf import MUKF_SCRATCH, NOISE_MODES
from mkf_ros.core.params import ALGORITHMS, REMOVED, FilterParams, mag_reference_direction
from mkf_ros.core.quaternion import qmul, qmul_t, qnormalize, qnormalize_t, rotmat, rotmat_t, t4

NX_MAX = 9  # states: attitude error e, rate ω, gyro bias b

#: Parameters the kernels use as they are: a :data:`CONFIG` field of the same name each.
COPIED_PARAMS = (
    "mukf_w0", "rate_process_noise", "max_dt", "gravity",
    "acc_time_constant", "acc_bias_excess",
    "mag_bias_gain", "acc_turn_speed",
    "acc_disturbance_time", "acc_alignment_error", "gyro_scale_error",
    "mag_time_constant", "mag_consistency_tolerance",
    "mag_disturbance_time", "mag_norm_tolerance",
    "mag_new_time", "mag_new_first_time", "rest_gyro_threshold",
    "rest_acc_threshold", "rest_time",
    "madgwick_beta",
)

#: The configuration of one filter (:func:`build_config`).
CONFIG = np.dtype(
    [
        ("algorithm", np.int64),  # index in ALGORITHMS (ALGO_*)
        ("chart", np.int64),  # chart id (charts.O, RP, MRP, RV)
        ("chart_update", np.bool_),  # chart update (eq. 47b) or reset
        ("use_mag", np.bool_),
        ("nx", np.int64),  # 9 with gyro bias estimation, else 6
        ("mukf_noise", np.int64),  # index in mukf.NOISE_MODES
        ("paper_init", np.bool_),  # init_mode paper: identity, P0 = 100 I, no gates
        ("mag_heading", np.bool_),  # mag_mode heading (else vector)
        ("acc_tilt_only", np.bool_),  # acc_mode tilt (else vector)
        ("rest_detection", np.bool_),
        ("split_input", np.bool_),  # gyro and accelerometer in separate samples
        # the smoother's forward pass: record the posterior before each prediction into WORK's
        # rec_* (docs/math.md §11, mkf_ros.core.smoother)
        ("record_posterior", np.bool_),
        ("mag_ref_given", np.bool_),  # mag_reference given (else learned)
        ("gyro_var", np.float64),  # R_ω = gyro_noise² (rad²/s²)
        ("acc_var", np.float64),  # R_a = (acc_noise / g)²: normalised reading, unit g
        ("acc_disturbance_var", np.float64),  # Q_a = (acc_disturbance / g)²
        ("mag_var", np.float64),  # R_m = mag_noise² (normalised reading)
        ("mag_disturbance_var", np.float64),  # Q_m = mag_disturbance²
        ("bias_process_var", np.float64),  # Q_b = gyro_bias_noise² (rad²/s³)
        ("bias_var0", np.float64),  # gyro_bias_stddev²: the bias prior
        ("rest_rate_var", np.float64),  # rest_rate_stddev²: the zero-rate measurement
        ("madgwick_var", np.float64),  # madgwick_stddev²: Madgwick's published variance
        ("gimbal_cos", np.float64),  # cos(gimbal_lock_pitch)
        ("mag_ref", np.float64, 3),  # given reference: ENU, unit
        ("mag_hard_iron", np.float64, 3),  # mag_bias_x/y/z (sensor units)
        ("mag_soft_iron", np.float64, (3, 3)),  # mag_soft_iron (row-major)
        ("q_from_enu", np.float64, 4),  # ENU → world_frame
        *[(name, np.float64) for name in COPIED_PARAMS],
    ],
    align=True,
)

#: The state of one filter: the estimate, its covariance and the sensor layer's memory.
STATE = np.dtype(
    [
        # --- the estimate (docs/math.md §5, §6) and its covariance
        ("q_c", np.float64, 4),  # chart centre q̄_c (the estimate for the MEKF)
        ("e", np.float64, 3),  # MUKF: mean ē in the chart at q̄_c (estimate q̄_c * φ⁻¹(ē))
        ("w", np.float64, 3),  # rate ω̄ (body, rad/s)
        ("b", np.float64, 3),  # gyro bias b̄ (rad/s)
        ("P", np.float64, (NX_MAX, NX_MAX)),  # covariance of (e, ω[, b]); leading nx × nx
        ("initialized", np.bool_),  # has an estimate (aligned, or the paper's start)
        ("ever_initialized", np.bool_),  # initialised at least once (a re-alignment keeps yaw)
        ("heading_fixed", np.bool_),  # the magnetometer has fixed the heading
        # --- the magnetometer's reference
        ("mag_ref", np.float64, 3),  # Earth field direction, ENU, unit
        ("mag_sum", np.float64, 3),  # Σ R(q̂) m of the samples learned so far
        ("mag_norm", np.float64),  # learned magnitude of the calibrated field
        ("mag_count", np.int64),  # samples in the learned reference
        ("mag_cand_norm", np.float64),  # a candidate new reference: magnitude ...
        ("mag_cand_dip", np.float64),  # ... and dip (rad), low-passed
        ("t_mag_cand", np.float64),  # s the candidate has held while the body turned; 0: none
        ("mag_adopted", np.bool_),  # a candidate has become the reference since the start
        # --- timers (s)
        ("t_acc_refused", np.float64),  # since the last accepted accelerometer sample
        ("t_mag_disagree", np.float64),  # a plausible field has disagreed (χ²); 0: it agrees
        ("t_rest", np.float64),  # at rest without a break
        ("dt_acc", np.float64),  # since the previous accelerometer sample
        ("dt_mag", np.float64),  # since the previous magnetometer sample
        # --- the accelerometer in an almost inertial frame (two first-order stages, body axes)
        ("acc_lp", np.float64, 3),  # first stage
        ("acc_lp2", np.float64, 3),  # second stage (what is fused)
        ("t_acc_lp", np.float64),  # s since the low-pass started
        ("acc_excess", np.float64),  # low-passed (|a| − g)² (normalised), over its τ
        ("acc_dev", np.float64),  # low-passed |a − acc_lp|² (m²/s⁴): the samples' spread
        ("acc_rate_lp", np.float64),  # low-passed |ω|, over acc_time_constant
        # the gyro's rate low-passed over acc_time_constant (body axes): the net rotation of
        # its scale noise (docs/math.md §9.1)
        ("gyro_net", np.float64, 3),
        ("acc_yaw_lp", np.float64),  # low-passed vertical rate Ω̄ (signed), over acc_time_constant
        # the low-pass's rotation error per unit gyro bias error (rad per rad/s, body axes), per
        # stage (docs/math.md §9.1): its memory is turned by the bias-corrected gyro
        ("acc_sens", np.float64, (3, 3)),
        ("acc_sens2", np.float64, (3, 3)),
        # --- the field over its learned magnitude, low-passed likewise (body axes)
        ("mag_lp", np.float64, 3),
        ("t_mag_lp", np.float64),  # s since the low-pass started
        ("mag_lp_slow", np.float64, 3),  # the unit field over MAG_SLOW_TIME (body axes)
        ("t_mag_lp_slow", np.float64),  # s since that low-pass started
        ("mag_rate_lp", np.float64),  # low-passed |ω|, over mag_time_constant
        # --- rest detection
        ("rest_gyr_lp", np.float64, 3),  # gyro low-pass
        ("rest_acc_lp", np.float64, 3),  # accelerometer low-pass
        ("rest_gyr_dev", np.float64),  # low-passed squared deviation of the gyro
        ("rest_acc_dev", np.float64),  # ... of the accelerometer
        ("rest_dt_gyr", np.float64),  # split input: s since the gyro entered the test
        ("rest_dt_acc", np.float64),  # ... the accelerometer
        ("t_rest_fused", np.float64),  # s of zero-rate updates fused (REST_BIAS_RANGE)
        # --- the gyro gate
        ("gyr_rejected", np.bool_),  # the previous gyro sample was refused by its gate
        # --- low-pass gains 1 − exp(−Δt/τ) kept for the last (Δt, τ) (LP_* rows)
        ("lp_gain", np.float64, (6, 3)),
        # --- baselines (Euler KF/UKF, Madgwick)
        ("euler", np.float64, 3),  # Euler angles (φ, θ, ψ) of the Euler KF/UKF
        ("madgwick_yaw_var", np.float64),  # Madgwick 6D: heading variance since alignment
        ("held_mag", np.float64, 3),  # Madgwick: a magnetometer sample held for the IMU
        ("mag_held", np.bool_),
    ],
    align=True,
)

#: Rows of :data:`STATE`'s ``lp_gain``: the accelerometer, field, rest and |ω| low-passes, the
#: field's slow low-pass (``mag_lp_slow``) and the gyro's net rotation (``gyro_net``).
LP_ACC, LP_MAG, LP_REST, LP_RATE, LP_MAG_SLOW, LP_NET = 0, 1, 2, 3, 4, 5

COUNTER_NAMES = (
    "samples",
    "gyr_missing", "gyr_invalid",
    "acc_missing", "acc_invalid",
    "mag_missing", "mag_invalid",
    "gaps", "update_failed", "before_init",
    "acc_rejected_norm", "acc_rejected_chi2", "mag_rejected_norm",
    "mag_rejected_chi2", "rest_updates", "gimbal_lock", "mag_rejected_inconsistent",
    "gyr_rejected_chi2",
)
#: The filter's counters: one per reason, in :data:`COUNTER_NAMES` order.
COUNTERS = np.dtype([(name, np.int64) for name in COUNTER_NAMES])

#: Scratch of one sample's updates: ``dx`` (the MEKF's correction), ``mekf`` (its block
#: updates, :func:`~mkf_ros.core.mekf.mekf_scratch`), the MUKF's tables
#: (:data:`~mkf_ros.core.mukf.MUKF_SCRATCH`) and the smoother's record ``rec_*``
#: (:func:`record_posterior`).
WORK = np.dtype(
    [("dx", np.float64, NX_MAX), ("mekf", np.float64, (MEKF_SCRATCH_ROWS, 3)),
     *MUKF_SCRATCH,
     # the smoother's record of this sample (CONFIG.record_posterior): the posterior at the
     # previous sample's time just before the prediction (docs/math.md §11.1)
     ("rec_set", np.bool_), ("rec_q", np.float64, 4), ("rec_w", np.float64, 3),
     ("rec_b", np.float64, 3), ("rec_P", np.float64, (NX_MAX, NX_MAX)),
     ("rec_ws2", np.float64)],  # the gyro's scale noise added in this step (§9.1)
    align=True,
)

#: What one sample gives the filter's update, after the sensor layer's checks
#: (:func:`mkf_ros.core.sensor.step`): the gyro reading (bias included) and whether to fuse it;
#: rest (the zero-rate pseudo-measurement); gravity as the MKFs fuse it (unit direction ``a``,
#: disturbance variance ``var_a`` per sample, ``has_a``) and the raw sample the baselines fuse
#: (``a_raw``, ``var_a_raw``, ``has_a_raw``: whenever there is a sample); the field's unit
#: direction ``m`` and ``has_m``, its world reference ``m_ref``, horizontal reference ``h_ref``
#: and heading variance ``var_h`` per sample; the χ² gates; ``a_sens`` (3×3, rows): how the fused
#: gravity direction turns with the gyro bias error (``a ≈ v + [v]× a_sens δb``, docs/math.md
#: §9.1) and ``a_bias_gain``, the share of the Kalman gain the bias takes from it.
Fusion = namedtuple("Fusion", ("g", "has_g", "rest", "a", "var_a", "has_a", "a_raw", "var_a_raw",
                               "has_a_raw", "m", "has_m", "m_ref", "h_ref", "var_h", "acc_gate",
                               "mag_gate", "a_sens", "a_bias_gain"))

# --- the numba types of the records and tuples above (the signatures of compile units) ------
CONFIG_T, STATE_T, COUNTERS_T, WORK_T = (numba.from_dtype(d) for d in (CONFIG, STATE, COUNTERS,
                                                                        WORK))
F3 = nt.UniTuple(nt.float64, 3)  # a 3-vector
F4 = nt.UniTuple(nt.float64, 4)  # a quaternion
F33 = nt.UniTuple(F3, 3)  # a 3×3 matrix (rows)
_Z3 = (0.0, 0.0, 0.0)
FUSION_T = numba.typeof(Fusion(_Z3, False, False, _Z3, 0.0, False, _Z3, 0.0, False, _Z3, False,
                               _Z3, _Z3, 0.0, 0.0, 0.0, ZERO33, 1.0))

# algorithm ids (index in ALGORITHMS): the paper's filters, then the baselines
ALGO_MEKF, ALGO_MUKF = ALGORITHMS.index("mekf"), ALGORITHMS.index("mukf")
ALGO_EULER_KF, ALGO_EULER_UKF = ALGORITHMS.index("euler_kf"), ALGORITHMS.index("euler_ukf")
ALGO_MADGWICK = ALGORITHMS.index("madgwick")

UP = (0.0, 0.0, 1.0)  # world up in ENU: what a resting accelerometer measures
MAG_REF_SAMPLES = 100  # magnetometer samples averaged into a learned reference
P0_PAPER = 100.0  # docs/math.md §8 item 9 (the paper's initial covariance)
YAW0_STDDEV = 1e-3  # rad: heading is defined by the start-up heading when no magnetometer
YAW_VAR_UNKNOWN = np.pi ** 2 / 3.0  # rad²: variance of an angle uniform over ±180°
#: rad² about each axis: the published attitude covariance before the filter has an estimate
ATTITUDE_VAR_UNKNOWN = np.pi ** 2
#: The accelerometer low-pass's robust input (:func:`~mkf_ros.core.sensor._acc_robust`): a
#: sample's deviation from the low-pass counts in full up to this many g ...
ACC_CLIP_MIN_G = 2.0
#: ... or this many RMS deviations of the recent samples (``acc_dev``), whichever is larger
ACC_CLIP_SIGMAS = 4.0
#: The share of the gyro's scale noise that an oscillating rate keeps (docs/math.md §9.1): the
#: rate's net part (low-passed over ``acc_time_constant``) turns the attitude by
#: ``gyro_scale_error`` times the angle turned, which accumulates; a swing back and forth turns
#: it one way and back, and only this share of its power is counted (a clipped or lagging gyro
#: still loses some of each swing).
GYRO_SCALE_SWING = 0.3
#: A candidate magnetic reference's time counts only while the body turns at least this fast
#: (rad/s, VQF's 20°/s): a still body sees any field, a magnet on it included, as consistent.
MAG_NEW_MIN_RATE = 0.35
#: The magnetometer's steadiness test (docs/math.md §9.3): the unit field low-passed over this
#: long (s) in the same almost inertial frame as ``mag_lp``, from every sample the consistency
#: test passes (tested against once it holds this long); a sample whose direction differs from
#: it by more than :data:`MAG_SLOW_TOLERANCE` is refused. A disturbance that builds up over
#: seconds (a phone carried past metal) passes the consistency test, whose memory follows it; a
#: field fixed in the world keeps its direction.
MAG_SLOW_TIME = 30.0
#: rad (≈34°): above what a gyro bias error turns that memory (0.01 rad/s over 30 s: 0.3 rad)
#: and the consistency tolerance; measured on tyrex, BROAD and RepoIMU (docs/math.md §9.3).
MAG_SLOW_TOLERANCE = 0.6
REST_LP_TAU = 0.5  # s: rest detection compares the gyro and accelerometer with their low-pass
REST_CHI2 = 16.27  # 3 degrees of freedom, 0.1 %: the low-passed rate agrees with the bias
#: A gyro sample whose innovation against the rate model is beyond this χ² (3 degrees of
#: freedom; 1000 is a rate change ~30 σ of the rate model's prior: at 100 Hz and the default
#: ``rate_process_noise``, ~14 rad/s within one sample) is a jump no motion of the model explains
#: — a glitch, or an impact that saturates the gyro: the attitude over the step is then uncertain
#: by the jump times the step (docs/math.md §9.3). Lower (the 0.1 % level, 16.3) took the jerks
#: of a phone in a running person's pocket for jumps: tyrex 6D +0.04°.
GYRO_SURPRISE_CHI2 = 1000.0
# The gates and recoveries of docs/math.md §9.3 and the rest test's turn-on range (§9.4): fixed
# levels, defined in mkf_ros.core.params.REMOVED (they were parameters; none of them moves a
# figure of the real-data benchmark, docs/real_data.md).
#: χ² gate on the accelerometer's innovation (3 degrees of freedom: 0.1 % false rejection).
ACC_GATE = REMOVED["acc_gate"][0]
#: χ² gate on the magnetometer's innovation (vector mode, 3 degrees of freedom: 1.3 % false
#: rejection; heading mode, 1: 3.3 σ).
MAG_GATE = REMOVED["mag_gate"][0]
#: χ² gate on the gyro's innovation against the rate model (3 degrees of freedom): a lone
#: sample beyond it is a corrupted message and is skipped; a second in a row is taken.
GYRO_GATE = REMOVED["gyro_gate"][0]
#: s of refused accelerometer samples after which the tilt variance grows by the disagreement.
ACC_RECOVERY_TIME = REMOVED["acc_recovery_time"][0]
#: s of a plausible, consistent field refused by :data:`MAG_GATE` after which the heading
#: variance grows by the disagreement.
MAG_RECOVERY_TIME = REMOVED["mag_recovery_time"][0]
#: rad/s per axis: until the bias has been fused at rest for ``rest_time``, a steady rate this
#: large is taken for a gyro's turn-on bias (a MEMS gyro's, up to a few °/s), and the first rest
#: raises the bias variance to its square; afterwards the bias changes by its random walk only.
REST_BIAS_RANGE = REMOVED["rest_bias_range"][0]
#: With the accelerometer's low-pass (:func:`mkf_ros.core.sensor._acc_measurement`), a raw sample
#: whose magnitude is this far from gravity (a fraction of g) has no say: left out of the blend
#: (the low-pass still takes it, clipped), refused while the low-pass forms its first average;
#: a low-pass that far off is refused. Without the low-pass (``acc_time_constant = 0``) nothing
#: is refused for its magnitude: the sample is fused with the variance its excess gives it.
ACC_NORM_TOLERANCE = REMOVED["acc_norm_tolerance"][0]
# Euler baselines' tilt re-alignment (:func:`baseline_realign`): the accelerometer "looks like
# gravity" when its magnitude is within this fraction of ``gravity`` ...
REALIGN_ACC_TOL = 0.05
# ... and the gyro (bias removed) is below this rate (rad/s), so little centripetal acceleration
REALIGN_MAX_RATE = 0.5


# --- plausibility of a reading: the one definition, for the library and the node -------------
#: A gyro reading faster than this (rad/s, ~9500 rpm) is beyond any MEMS gyro's range: invalid.
MAX_GYRO_RATE = 1000.0
#: An accelerometer reading larger than this many times ``gravity`` is invalid (no IMU's
#: accelerometer reads 10,000 g; the filter weighs the plausible ones by their magnitude's
#: distance from gravity).
MAX_ACC_G = 1e4
#: A (calibrated) magnetometer reading larger than this, in any unit, is invalid: no field in
#: tesla, gauss, µT or raw counts comes near it, and the square of a larger one can overflow.
MAX_MAG = 1e100
#: The smallest magnitude of an accelerometer or magnetometer vector: below it (a zero vector,
#: or one whose square underflows) the direction is undefined and the reading invalid.
MIN_VECTOR = 1e-150
#: The shortest time step (s) the filter integrates: a ``dt`` below it (1 ns, the resolution of a
#: ROS stamp) is treated as 0, a sample at the same instant (docs/math.md §9.5). Shorter steps
#: have no physical meaning, and the correlation factors ``T/Δt`` of a denormal or 1e-200 s step
#: overflow the variances they scale.
DT_MIN = 1e-9


@jit
def step_dt(dt: float) -> float:
    """The time step the filter integrates for a given ``dt ≥ 0``: 0 below :data:`DT_MIN`
    (docs/math.md §9.5), else ``dt``."""
    return dt if dt >= DT_MIN else 0.0


#: :func:`classify_reading`'s classes.
VALID, MISSING, INVALID = 0, 1, 2


@jit
def classify_reading(v: tuple, is_vector: bool, limit: float) -> int:
    """One sensor reading, for the batch loop and the stream adapter alike: :data:`VALID`,
    :data:`MISSING` (all NaN) or :data:`INVALID` (partly non-finite, a vector below
    :data:`MIN_VECTOR` or a reading whose magnitude exceeds ``limit``: :data:`MAX_GYRO_RATE`,
    :data:`MAX_ACC_G` times gravity, :data:`MAX_MAG`)."""
    nan = 0
    bad = False
    for i in range(3):
        if np.isnan(v[i]):
            nan += 1
        elif not np.isfinite(v[i]):
            bad = True
    if nan == 3:
        return MISSING
    if nan > 0 or bad:
        return INVALID
    s = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    if s > limit * limit or (is_vector and s < MIN_VECTOR * MIN_VECTOR):
        return INVALID
    return VALID


#: Sensors, for :func:`count_reading`.
GYR, ACC, MAG = 0, 1, 2


@jit
def count_reading(k: np.record, cls: int, sensor: int) -> None:
    """Count a :data:`MISSING` or :data:`INVALID` reading of ``sensor`` (:data:`GYR`,
    :data:`ACC`, :data:`MAG`) in ``k``: the filter's counters or the stream adapter's (both
    name them ``gyr_missing`` … ``mag_invalid``)."""
    if cls == MISSING:
        if sensor == GYR:
            k.gyr_missing += 1
        elif sensor == ACC:
            k.acc_missing += 1
        else:
            k.mag_missing += 1
    elif cls == INVALID:
        if sensor == GYR:
            k.gyr_invalid += 1
        elif sensor == ACC:
            k.acc_invalid += 1
        else:
            k.mag_invalid += 1


@jit
def iso33(v: float) -> tuple:
    """The isotropic noise matrix ``v I`` as a tuple of rows."""
    return ((v, 0.0, 0.0), (0.0, v, 0.0), (0.0, 0.0, v))


def new_records(dtype: np.dtype, n: int = 1) -> np.ndarray:
    """``n`` zeroed records of ``dtype`` (by default one, in an array of length 1: what the
    kernels take, its element ``[0]`` is the record, passed by pointer). A plain structured
    array: numba types a ``recarray`` argument by attribute look-ups that cost microseconds at
    every call; with ``NUMBA_DISABLE_JIT=1`` a ``recarray``, whose element has the attribute
    access the kernels use. Python code reads and writes fields with :func:`record`."""
    arr = np.zeros(n, dtype)
    return arr.view(np.recarray) if JIT_DISABLED else arr


def record(arr: np.ndarray) -> np.record:
    """The record of a one-element record array (:func:`new_records`) with attribute access
    (``record(cfg).nx``), a view: assignments write into ``arr``."""
    return arr.view(np.recarray)[0]


def build_config(p: FilterParams, split_input: bool = False) -> np.ndarray:
    """The kernels' configuration (:data:`CONFIG`) from validated parameters (units converted
    here; the cross-parameter rules are :class:`~mkf_ros.core.params.FilterParams`')."""
    rec = new_records(CONFIG)
    c = record(rec)
    c.algorithm = ALGORITHMS.index(p.algorithm)
    c.chart = chart_id(p.chart)
    c.chart_update = p.chart_update
    c.use_mag = p.use_mag
    c.nx = 9 if p.estimate_gyro_bias else 6
    c.mukf_noise = NOISE_MODES.index(p.mukf_noise_scaling)
    c.paper_init = p.init_mode == "paper"
    c.mag_heading = p.mag_mode == "heading"
    c.acc_tilt_only = p.acc_mode == "tilt"
    c.rest_detection = p.rest_detection
    c.split_input = split_input
    g = p.gravity
    c.gyro_var = p.gyro_noise**2
    c.acc_var = (p.acc_noise / g) ** 2  # normalised reading: unit "g" (docs/math.md §8 item 15)
    c.acc_disturbance_var = (p.acc_disturbance / g) ** 2
    c.mag_var = p.mag_noise**2
    c.mag_disturbance_var = p.mag_disturbance**2
    c.bias_process_var = p.gyro_bias_noise**2
    c.bias_var0 = p.gyro_bias_stddev**2
    c.rest_rate_var = p.rest_rate_stddev**2
    c.madgwick_var = p.madgwick_stddev**2
    c.gimbal_cos = np.cos(p.gimbal_lock_pitch)
    for name in COPIED_PARAMS:
        c[name] = p[name]
    c.mag_hard_iron[:] = (p.mag_bias_x, p.mag_bias_y, p.mag_bias_z)
    c.mag_soft_iron[:] = np.reshape(p.mag_soft_iron, (3, 3))
    c.q_from_enu[:] = FROM_ENU[p.world_frame]
    ref = mag_reference_direction(p.mag_reference)
    if ref is not None:
        q = FROM_ENU[p.world_frame]  # given in the world frame → ENU: R(q_{W←ENU})ᵀ ref
        c.mag_ref_given = True
        c.mag_ref[:] = rotmat(q).T @ ref
    return rec


@jit
def recentre(c: np.record, s: np.record) -> None:
    """Move the chart centre onto the estimate: ``q̄_c ← q̄_c * φ⁻¹(ē)``, ``ē ← 0``, and carry
    ``P`` with the T-matrix (docs/math.md §3.2). A no-op for the MEKF, whose ``ē`` is always
    zero."""
    e = s.e
    if e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0:
        return
    d = from_chart(c.chart, e)
    copy_into(s.q_c, qnormalize(qmul(s.q_c, d)))
    s.e[:] = 0.0
    transport_covariance(s.P, c.nx, t_matrix(c.chart, d))


@jit
def set_world_attitude_cov(s: np.record, nx: int, var_tilt: float, var_yaw: float,
                           keep_tilt: bool) -> None:
    """Set the attitude block of ``P`` from world-axis variances (tilt about x/y, yaw about z);
    with ``keep_tilt`` only the yaw row/column is replaced. Cross terms with yaw are cleared."""
    P = s.P
    R = rotmat(s.q_c)
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
    copy_block(P, 0, 0, mm(R.T.copy(), mm(Sw, R)), False)
    Ct = mm(R.T.copy(), C)
    copy_block(P, 0, 3, Ct, False)
    copy_block(P, 3, 0, Ct, True)


@jit
def heading_fixed(c: np.record, s: np.record) -> bool:
    """Whether the magnetometer has fixed the heading (never without ``use_mag``)."""
    return s.heading_fixed and c.use_mag


@jit
def heading_unobserved(c: np.record, s: np.record, z: Fusion) -> bool:
    """Whether nothing observes the heading in this step: no magnetometer sample now, and
    none has fixed it (6D, or 9D before the first field). The MEKF's chart update then carries
    the vertical exactly, the MUKF bounds its sigma points' heading spread (docs/math.md
    §9.3)."""
    return not (z.has_m or heading_fixed(c, s))


@jit
def inflate_world(s: np.record, var_tilt: float, var_yaw: float) -> None:
    """Add uncertainty about the world axes (tilt about x and y, yaw about z) to ``P_ee``: an
    independent rotation (used when a sensor has been rejected for so long that the estimate
    itself is suspect, and to give the MUKF's bounded heading spread its variance back)."""
    P = s.P
    R = rotmat_t(t4(s.q_c))
    for i in range(3):
        for j in range(3):
            P[i, j] += (var_tilt * (R[0][i] * R[0][j] + R[1][i] * R[1][j])
                        + var_yaw * R[2][i] * R[2][j])


@jit
def mag_yaw_var(c: np.record, ref: np.ndarray) -> float:
    """The heading variance of one magnetometer sample: its noise and disturbance over the
    square of the field's horizontal share (floored at 0.05)."""
    h = max(np.sqrt(ref[0] * ref[0] + ref[1] * ref[1]), 0.05)
    return (c.mag_var + c.mag_disturbance_var) / (h * h)


@jit
def record_posterior(c: np.record, s: np.record, w: np.record) -> None:
    """The smoother's recording hook (docs/math.md §11.1): the posterior at the previous
    sample's time after this sample's rate updates, just before the prediction, into ``w.rec_*``
    (``w.rec_set``). The estimate ``q̂ = q̄_c * φ⁻¹(ē)`` and ``P`` moved to the chart at ``q̂``
    (§3.2; the MEKF's ``ē`` is zero); ``s`` is unchanged."""
    nx = c.nx
    P = w.rec_P
    for i in range(nx):
        for j in range(nx):
            P[i, j] = s.P[i, j]
    q = (s.q_c[0], s.q_c[1], s.q_c[2], s.q_c[3])
    e = s.e
    if not (e[0] == 0.0 and e[1] == 0.0 and e[2] == 0.0):
        d = from_chart_t(c.chart, (e[0], e[1], e[2]))
        q = qnormalize_t(qmul_t(q, d))
        transport_covariance_t(P, nx, t_matrix_t(c.chart, d))
    for i in range(4):
        w.rec_q[i] = q[i]
    for i in range(3):
        w.rec_w[i] = s.w[i]
        w.rec_b[i] = s.b[i]
    w.rec_set = True
