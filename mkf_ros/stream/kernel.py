"""Compiled event loop of :class:`mkf_ros.stream.adapter.StreamAdapter`: every time and input rule.

The adapter's rules (see :mod:`mkf_ros.stream` for what they are) are implemented once, here,
as kernels over a merged sequence of IMU and magnetometer events. The per-message methods
(``on_imu``, ``on_mag``) run a one-event sequence through :func:`run_events`; the batch entry
(``process``) runs a whole recording through it. Only resets leave the compiled loop: the
kernel stops at the event that needs one, Python resets the filter (new state arrays) and the
loop resumes, so both paths share every rule, bit for bit.

Layouts: the adapter's time state ``ts`` (``T_*``), its node parameters ``npar`` (``P_*``), the
magnetometer samples held for the IMU stream ``pend`` and, with split input, the accelerometer
samples held for the gyro stream ``pacc`` (rows ``stamp, v``, in stamp order, equal stamps in
arrival order), its own counters ``acnt`` (:data:`ADAPTER_COUNTERS`), events ``ev_f``
(``E_*``) and ``ev_i`` (kind, output row), outputs ``out`` (``O_*``, one row per IMU (gyro)
message, flags ``OF_*``).
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.filter import (
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    YAW_VAR_UNKNOWN,
    bias,
    bias_variance,
    classify_reading,
    gap_count,
    gravity,
    heading_fixed,
    is_initialized,
    max_dt,
    rate,
    rate_covariance,
    sensor_step,
    uses_mag,
    world_output,
)
from mkf_ros.core.quaternion import q_from_rotvec, qmul, rotate_inv, rotmat

#: Out-of-order IMU samples in a row after which the stream is taken to have jumped back.
MAX_BACKWARDS = 10
#: Magnetometer (and, split input, accelerometer) samples held while waiting for the IMU
#: (gyro) stream to reach their stamps, per sensor.
MAX_PENDING_MAG = 32
#: Smallest time step of an internal magnetometer-only filter step (the MUKF cannot
#: factorise its sigma points with zero process noise at dt = 0).
MIN_STEP = 1e-9
#: A magnetometer stamp this close to an IMU stamp is fused in the same filter step.
SAME_STAMP = 1e-6

#: The adapter's own counters (the filter's are synced separately), in ``acnt`` order.
ADAPTER_COUNTERS = (
    "imu_received", "imu_duplicate", "imu_out_of_order", "imu_bad_stamp",
    "gyr_missing", "gyr_invalid", "acc_missing", "acc_invalid", "acc_implausible",
    "mag_received", "mag_unused", "mag_missing", "mag_invalid", "mag_too_old", "mag_ahead",
    "mag_overflow", "mag_fused", "output_nonfinite", "resets", "resets_time_jump",
    "acc_received", "acc_too_old", "acc_ahead", "acc_overflow", "acc_fused",
)
(A_IMU_RECEIVED, A_IMU_DUPLICATE, A_IMU_OUT_OF_ORDER, A_IMU_BAD_STAMP,
 A_GYR_MISSING, A_GYR_INVALID, A_ACC_MISSING, A_ACC_INVALID, A_ACC_IMPLAUSIBLE,
 A_MAG_RECEIVED, A_MAG_UNUSED, A_MAG_MISSING, A_MAG_INVALID, A_MAG_TOO_OLD, A_MAG_AHEAD,
 A_MAG_OVERFLOW, A_MAG_FUSED, A_OUTPUT_NONFINITE, A_RESETS, A_RESETS_TIME_JUMP,
 A_ACC_RECEIVED, A_ACC_TOO_OLD, A_ACC_AHEAD, A_ACC_OVERFLOW, A_ACC_FUSED) = range(25)
A_SIZE = len(ADAPTER_COUNTERS)

# time state: filter time and whether it is set, heading lost in a gap, out-of-order run,
# number of held samples (these five, and the held accelerometer samples, are cleared by a
# reset), latest magnitudes/offset/stamps, dt statistics; whether a usable gyro reading that
# is not exactly zero, and a usable accelerometer reading, ever arrived (input checks)
T_T, T_VALID, T_YAW_LOST, T_BACK, T_NPEND = 0, 1, 2, 3, 4
T_ACC_NORM, T_MAG_NORM, T_MAG_OFFSET, T_LAST_IMU, T_LAST_MAG = 5, 6, 7, 8, 9
T_DT_N, T_DT_MIN, T_DT_SUM, T_DT_MAX = 10, 11, 12, 13
T_NPEND_ACC, T_GYR_SEEN, T_ACC_SEEN, T_LAST_ACC = 14, 15, 16, 17
T_SIZE = 18
#: Rows of ``pend``: one more than it keeps (a sample is inserted, then the oldest dropped).
PEND_ROWS = MAX_PENDING_MAG + 1

# node parameters (the filter's own are read from its configuration vector)
P_CONST_DT, P_JUMP, P_ACC_TOL, P_MAG_DELAY, P_HAS_OFF = 0, 1, 2, 3, 4
P_Q_OFF, P_R_OFF, P_UP_W = 5, 9, 18  # 4, 9 (row-major), 3 values
P_ORI_SD, P_AV_SRC, P_NO_GRAVITY = 21, 22, 23
P_SPLIT, P_ACC_DELAY = 24, 25  # input_mode split; acc_max_delay
P_SIZE = 26
#: ``angular_velocity_source`` choices, in ``npar[P_AV_SRC]`` code order.
AV_SOURCES = ("input", "bias_corrected", "estimate")
AV_INPUT, AV_BIAS_CORRECTED, AV_ESTIMATE = 0, 1, 2

# events: ev_f row = stamp, gyro or magnetometer vector, accelerometer; ev_i row = kind, row
E_STAMP, E_V, E_A, E_SIZE = 0, 1, 4, 7
EV_IMU, EV_MAG, EV_ACC = 0, 1, 2  # EV_ACC: split input, an accelerometer sample in E_V

# outputs per IMU message; flags: published, and which optional fields are present (an absent
# one is NaN)
O_FLAGS, O_Q, O_COV, O_W, O_WCOV, O_WADD, O_LIN, O_OMEGA, O_BIAS, O_BSTD = (
    0, 1, 5, 14, 17, 26, 29, 32, 35, 38)
O_SIZE = 41
OF_PUB, OF_W, OF_WCOV, OF_WADD, OF_LIN, OF_HEADING = 1, 2, 4, 8, 16, 32

# the outcome of one IMU event: nothing published, published, or a reset request; run_events
# returns R_DONE or the reset request with the index of the event it stopped at
_NONE, _OUT, R_TIME_JUMP, R_NONFINITE = 0, 1, 2, 3
R_DONE = 0


@jit
def norm3(v: np.ndarray) -> float:
    """Euclidean norm without overflow or underflow (like ``math.hypot``)."""
    m = max(abs(v[0]), abs(v[1]), abs(v[2]))
    if m == 0.0 or not np.isfinite(m):
        return m
    x, y, z = v[0] / m, v[1] / m, v[2] / m
    return m * np.sqrt(x * x + y * y + z * z)


@jit
def input_class(acnt: np.ndarray, v: np.ndarray, k_missing: int, is_vector: bool,
                limit: float) -> int:
    """0 if ``v`` is a usable reading, 1 missing (no reading), 2 invalid; counted
    (``k_missing``, or the invalid counter right after it). The filter's own rule,
    :func:`~mkf_ros.core.filter.classify_reading` with its plausibility limits (``limit``: a
    gyro faster than :data:`~mkf_ros.core.filter.MAX_GYRO_RATE` is invalid, etc.)."""
    c = classify_reading((v[0], v[1], v[2]), is_vector, limit)
    if c:
        acnt[k_missing + c - 1] += 1
    return c


@jit
def check_input(acnt: np.ndarray, v: np.ndarray, k_missing: int, is_vector: bool,
                limit: float) -> bool:
    """True if ``v`` is a usable reading (:func:`input_class`)."""
    return input_class(acnt, v, k_missing, is_vector, limit) == 0


@jit
def rotate_back(v: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """``Exp(−θ) v = R(q(θ))ᵀ v``: a world-fixed vector seen after the body turned by ``θ``."""
    th = norm3(rotvec)
    if not 1e-12 < th < 1e3:  # no rotation, or a diverged rate: leave the vector as it is
        return v
    return rotate_inv(q_from_rotvec(rotvec), v)


@jit
def covariance_rows(c: np.ndarray, stddev: float, add: np.ndarray) -> None:
    """Published covariances from the input's, in place (rows of 9, see
    :func:`mkf_ros.stream.adapter.covariance_out`); ``add`` has one row per row of ``c``, one for
    all, or none."""
    for i in range(c.shape[0]):
        row = c[i]
        if row[0] == -1.0 or not np.isfinite(row.sum()):
            row[:] = 0.0
        if not row.any():
            if stddev <= 0.0:
                continue
            row[0] = row[4] = row[8] = stddev * stddev
        if add.shape[0]:
            row += add[i if add.shape[0] > 1 else 0]


# --- magnetometer (split input: accelerometer) samples held for the IMU (gyro) stream --------
# ``pend`` holds magnetometer samples (count ``ts[T_NPEND]``), ``pacc`` accelerometer samples
# (count ``ts[T_NPEND_ACC]``); ``is_acc`` selects the sensor in the functions below.


@jit
def _pop_front(ts: np.ndarray, pend: np.ndarray, k: int, ni: int = T_NPEND) -> None:
    """Drop the ``k`` oldest held samples (count in ``ts[ni]``)."""
    n = int(ts[ni])
    for i in range(n - k):
        for j in range(4):
            pend[i, j] = pend[i + k, j]
    ts[ni] = n - k


@jit
def hold(ts: np.ndarray, pend: np.ndarray, acnt: np.ndarray, stamp: float,
         m: np.ndarray, is_acc: bool = False) -> None:
    """Insert a sample in stamp order (after equal stamps); the oldest goes on overflow."""
    ni = T_NPEND_ACC if is_acc else T_NPEND
    n = int(ts[ni])
    i = n
    while i > 0 and pend[i - 1, 0] > stamp:
        for j in range(4):
            pend[i, j] = pend[i - 1, j]
        i -= 1
    pend[i, 0] = stamp
    for j in range(3):
        pend[i, 1 + j] = m[j]
    ts[ni] = n + 1
    if n + 1 > MAX_PENDING_MAG:
        _pop_front(ts, pend, 1, ni)
        acnt[A_ACC_OVERFLOW if is_acc else A_MAG_OVERFLOW] += 1


@jit
def fuse_now(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
             fl: np.ndarray, fcnt: np.ndarray, acnt: np.ndarray, v: np.ndarray,
             age: float, nan3: np.ndarray, is_acc: bool = False) -> None:
    """Fuse a magnetometer (or accelerometer) sample at the filter's current time, rotated
    forward over its ``age`` (s): both measure a world-fixed vector in body axes."""
    if age > 0.0 and is_initialized(fl) and np.isfinite(v[0] + v[1] + v[2]):
        w = np.empty(3)
        for i in range(3):
            w[i] = rate(st, i) * age
        v = rotate_back(v, w)
    if is_acc:
        sensor_step(cfg, nz, st, P, fl, fcnt, MIN_STEP, nan3, v, nan3)
        acnt[A_ACC_FUSED] += 1
    else:
        sensor_step(cfg, nz, st, P, fl, fcnt, MIN_STEP, nan3, nan3, v)
        acnt[A_MAG_FUSED] += 1


@jit
def fuse_late(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
              fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray, acnt: np.ndarray,
              stamp: float, m: np.ndarray, nan3: np.ndarray, is_acc: bool = False) -> None:
    """A sample stamped at or before the filter time: fused now if recent enough
    (``mag_max_delay``, ``acc_max_delay``)."""
    age = ts[T_T] - stamp
    if age > npar[P_ACC_DELAY if is_acc else P_MAG_DELAY] + SAME_STAMP:
        acnt[A_ACC_TOO_OLD if is_acc else A_MAG_TOO_OLD] += 1
        return
    fuse_now(cfg, nz, st, P, fl, fcnt, acnt, m, max(age, 0.0), nan3, is_acc)


@jit
def _first_pending(ts: np.ndarray, pend: np.ndarray, acnt: np.ndarray, t_new: float,
                   tol: float, same: np.ndarray, is_acc: bool) -> bool:
    """On the first IMU sample: keep the held samples ahead of it, drop the older ones but the
    latest within ``tol``, which goes in ``same`` to be fused with it (True if so)."""
    ni = T_NPEND_ACC if is_acc else T_NPEND
    n = int(ts[ni])
    n_keep = 0
    n_near = 0
    for i in range(n):
        p = pend[i, 0]
        if p > t_new + SAME_STAMP:
            n_keep += 1
        elif abs(t_new - p) <= tol:
            n_near += 1
            for j in range(3):
                same[j] = pend[i, 1 + j]
    acnt[A_ACC_TOO_OLD if is_acc else A_MAG_TOO_OLD] += n - n_keep - min(n_near, 1)
    _pop_front(ts, pend, n - n_keep, ni)  # sorted: the kept ones are the newest
    return n_near > 0


@jit
def take_pending(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                 fl: np.ndarray, fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray,
                 pend: np.ndarray, acnt: np.ndarray, t_new: float, dt: float,
                 same: np.ndarray, nan3: np.ndarray, pacc: np.ndarray,
                 same_a: np.ndarray) -> int:
    """Fuse held samples stamped before ``t_new``, in stamp order (the magnetometer first at
    equal stamps), each at its own stamp; put one stamped at ``t_new`` (or, on the first IMU
    sample, the latest recent one) in ``same`` (magnetometer) / ``same_a`` (accelerometer) to
    fuse with the IMU (gyro) sample. Returns 1 if ``same`` is set, plus 2 if ``same_a`` is."""
    if ts[T_VALID] == 0:  # first sample: initialise with the latest recent samples
        r = 0
        if ts[T_NPEND] > 0 and _first_pending(ts, pend, acnt, t_new,
                                              max(npar[P_MAG_DELAY], SAME_STAMP), same, False):
            r |= 1
        if ts[T_NPEND_ACC] > 0 and _first_pending(ts, pacc, acnt, t_new,
                                                  max(npar[P_ACC_DELAY], SAME_STAMP), same_a,
                                                  True):
            r |= 2
        return r
    if dt > max_dt(cfg):  # a gap: the held samples cannot be placed
        for is_acc in (False, True):
            buf = pacc if is_acc else pend
            ni = T_NPEND_ACC if is_acc else T_NPEND
            x = t_new - npar[P_ACC_DELAY if is_acc else P_MAG_DELAY]
            n = int(ts[ni])
            old = 0
            while old < n and buf[old, 0] < x:
                old += 1
            acnt[A_ACC_TOO_OLD if is_acc else A_MAG_TOO_OLD] += old
            _pop_front(ts, buf, old, ni)
    r = 0
    while True:
        m_due = ts[T_NPEND] > 0 and pend[0, 0] <= t_new + SAME_STAMP
        a_due = ts[T_NPEND_ACC] > 0 and pacc[0, 0] <= t_new + SAME_STAMP
        if not (m_due or a_due):
            break
        is_acc = a_due and not (m_due and pend[0, 0] <= pacc[0, 0])
        buf = pacc if is_acc else pend
        tm = buf[0, 0]
        v = buf[0, 1:4].copy()
        _pop_front(ts, buf, 1, T_NPEND_ACC if is_acc else T_NPEND)
        if abs(tm - t_new) <= SAME_STAMP:
            bit = 2 if is_acc else 1
            sm = same_a if is_acc else same
            if r & bit:
                fuse_now(cfg, nz, st, P, fl, fcnt, acnt, sm.copy(), 0.0, nan3, is_acc)
            sm[:] = v
            r |= bit
        elif tm <= ts[T_T]:  # held before a reset moved the time: treat as late
            fuse_late(cfg, nz, st, P, fl, fcnt, npar, ts, acnt, tm, v, nan3, is_acc)
        else:
            if is_acc:
                sensor_step(cfg, nz, st, P, fl, fcnt, max(tm - ts[T_T], MIN_STEP), nan3, v,
                            nan3)
                acnt[A_ACC_FUSED] += 1
            else:
                sensor_step(cfg, nz, st, P, fl, fcnt, max(tm - ts[T_T], MIN_STEP), nan3, nan3,
                            v)
                acnt[A_MAG_FUSED] += 1
            ts[T_T] = tm
    return r


# --- events ---------------------------------------------------------------------------------


@jit_inline
def fuse_untimed(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                 fl: np.ndarray, fcnt: np.ndarray, ts: np.ndarray, buf: np.ndarray,
                 acnt: np.ndarray, v: np.ndarray, nan3: np.ndarray, is_acc: bool) -> None:
    """A magnetometer or (split input) accelerometer sample when stamps are not trusted
    (``use_constant_dt``): fused at the current time; before the first IMU sample kept as the
    one held sample."""
    if ts[T_VALID] == 0:
        buf[0, 0] = 0.0
        buf[0, 1:4] = v
        ts[T_NPEND_ACC if is_acc else T_NPEND] = 1
    else:
        fuse_now(cfg, nz, st, P, fl, fcnt, acnt, v, 0.0, nan3, is_acc)


@jit_inline
def place(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
          fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray, buf: np.ndarray,
          acnt: np.ndarray, stamp: float, v: np.ndarray, nan3: np.ndarray,
          is_acc: bool) -> None:
    """A checked, stamped magnetometer or (split input) accelerometer sample: held while ahead
    of the IMU (gyro) stream (before its first sample, the latest few), dropped when more than
    ``max_dt`` ahead, else fused now if recent enough (:func:`fuse_late`)."""
    if ts[T_VALID] == 0:  # before the first IMU sample: keep the latest few
        hold(ts, buf, acnt, stamp, v, is_acc)
        return
    d = stamp - ts[T_T]
    if d > max_dt(cfg):
        acnt[A_ACC_AHEAD if is_acc else A_MAG_AHEAD] += 1
    elif d > SAME_STAMP:
        hold(ts, buf, acnt, stamp, v, is_acc)
    else:
        fuse_late(cfg, nz, st, P, fl, fcnt, npar, ts, acnt, stamp, v, nan3, is_acc)


@jit_inline
def mag_event(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
              fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray, pend: np.ndarray,
              acnt: np.ndarray, stamp: float, mag: np.ndarray, nan3: np.ndarray) -> None:
    """One magnetometer sample: fused now (late), held (ahead of the IMU) or dropped."""
    acnt[A_MAG_RECEIVED] += 1
    if not uses_mag(cfg):
        acnt[A_MAG_UNUSED] += 1
        return
    if not check_input(acnt, mag, A_MAG_MISSING, True, MAX_MAG):
        return
    m = mag.copy()
    # hard/soft-iron calibration (mag_bias_*, mag_soft_iron) is applied by the core filter
    norm = norm3(m)
    ts[T_MAG_NORM] = norm
    if not 0.0 < norm < np.inf:
        acnt[A_MAG_INVALID] += 1
        return
    # the raw field goes to the filter: it calibrates it and checks magnitude and dip
    ts[T_LAST_MAG] = stamp
    if npar[P_CONST_DT] > 0.0:  # stamps are not trusted: fuse at the current time
        fuse_untimed(cfg, nz, st, P, fl, fcnt, ts, pend, acnt, m, nan3, False)
        return
    if not np.isfinite(stamp):
        acnt[A_MAG_INVALID] += 1
        return
    if ts[T_VALID] != 0:
        ts[T_MAG_OFFSET] = stamp - ts[T_T]
    place(cfg, nz, st, P, fl, fcnt, npar, ts, pend, acnt, stamp, m, nan3, False)


@jit_inline
def acc_event(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
              fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray, pacc: np.ndarray,
              acnt: np.ndarray, stamp: float, acc: np.ndarray, nan3: np.ndarray) -> None:
    """One accelerometer sample of split input (its own stream, ``input_mode`` split): like a
    magnetometer sample, held until the gyro stream reaches its stamp and fused there (with
    the gyro sample of the same stamp), fused at once if up to ``acc_max_delay`` late (rotated
    forward by the estimated rate), dropped if older. The same checks as the accelerometer of
    a combined message: a missing, invalid or implausible sample is counted and not fused."""
    acnt[A_ACC_RECEIVED] += 1
    if input_class(acnt, acc, A_ACC_MISSING, True, MAX_ACC_G * gravity(cfg)) != 0:
        return
    norm = norm3(acc)
    ts[T_ACC_NORM] = norm
    if abs(norm / gravity(cfg) - 1.0) > npar[P_ACC_TOL]:
        acnt[A_ACC_IMPLAUSIBLE] += 1
        return
    ts[T_ACC_SEEN] = 1.0
    a = acc.copy()
    if npar[P_CONST_DT] > 0.0:  # stamps are not trusted: fuse at the current time
        fuse_untimed(cfg, nz, st, P, fl, fcnt, ts, pacc, acnt, a, nan3, True)
        return
    if not np.isfinite(stamp) or stamp == 0.0:
        acnt[A_ACC_INVALID] += 1
        return
    ts[T_LAST_ACC] = stamp
    place(cfg, nz, st, P, fl, fcnt, npar, ts, pacc, acnt, stamp, a, nan3, True)


@jit_inline
def imu_event(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
              fcnt: np.ndarray, q_from_enu: np.ndarray, npar: np.ndarray, ts: np.ndarray,
              pend: np.ndarray, acnt: np.ndarray, stamp: float, gyr: np.ndarray,
              acc: np.ndarray, out: np.ndarray, resume: bool, nan3: np.ndarray,
              pacc: np.ndarray) -> int:
    """One IMU sample (split input: a gyro sample; its accelerometer field is ignored): time
    rules, input checks, held magnetometer (and accelerometer) samples, filter step, output.
    Returns ``_OUT`` (``out`` written), ``_NONE``, or a reset request ``R_*``; ``resume``: the
    same sample again after a time-jump reset (already counted). A reading that is not
    usable goes to the filter as missing (all NaN)."""
    out[O_FLAGS] = 0.0
    if not resume:
        acnt[A_IMU_RECEIVED] += 1
    valid = ts[T_VALID] > 0
    if npar[P_CONST_DT] > 0.0:
        dt = npar[P_CONST_DT] if valid else 0.0
        t_new = ts[T_T] + dt if valid else 0.0
    else:
        if not np.isfinite(stamp) or stamp == 0.0:
            acnt[A_IMU_BAD_STAMP] += 1
            return _NONE
        t_new = stamp
        dt = 0.0
        if valid:
            dt = stamp - ts[T_T]
            if dt <= 0.0:
                if dt == 0.0:
                    acnt[A_IMU_DUPLICATE] += 1
                    return _NONE
                ts[T_BACK] += 1
                if -dt <= npar[P_JUMP] and ts[T_BACK] < MAX_BACKWARDS:
                    acnt[A_IMU_OUT_OF_ORDER] += 1
                    return _NONE
                acnt[A_RESETS_TIME_JUMP] += 1
                return R_TIME_JUMP  # Python resets; the sample comes back with resume
    ts[T_BACK] = 0
    ts[T_LAST_IMU] = stamp
    g_cls = input_class(acnt, gyr, A_GYR_MISSING, False, MAX_GYRO_RATE)
    has_g = g_cls == 0
    if has_g and (gyr[0] != 0.0 or gyr[1] != 0.0 or gyr[2] != 0.0):
        ts[T_GYR_SEEN] = 1.0
    split = npar[P_SPLIT] > 0.0
    a_cls = 1 if split else input_class(acnt, acc, A_ACC_MISSING, True,
                                        MAX_ACC_G * gravity(cfg))
    has_a_in = a_cls == 0
    has_a = has_a_in
    if has_a:
        norm = norm3(acc)
        ts[T_ACC_NORM] = norm
        if abs(norm / gravity(cfg) - 1.0) > npar[P_ACC_TOL]:
            acnt[A_ACC_IMPLAUSIBLE] += 1
            has_a = False
        else:
            ts[T_ACC_SEEN] = 1.0
    if valid and dt > 0.0:
        ts[T_DT_N] += 1
        ts[T_DT_MIN] = min(ts[T_DT_MIN], dt)
        ts[T_DT_SUM] += dt
        ts[T_DT_MAX] = max(ts[T_DT_MAX], dt)
    mag = np.empty(3)
    a_in = acc if has_a else nan3
    # the call is skipped when nothing is held, as it mostly is (it costs ~0.4 µs)
    has_m = False
    a_held = False
    if ts[T_NPEND] > 0 or ts[T_NPEND_ACC] > 0:
        a_same = np.empty(3)
        r = take_pending(cfg, nz, st, P, fl, fcnt, npar, ts, pend, acnt, t_new, dt, mag, nan3,
                         pacc, a_same)
        has_m = (r & 1) > 0
        if r & 2:
            a_in = a_same
            a_held = True
    gaps = gap_count(fcnt)
    step = dt if not valid or npar[P_CONST_DT] > 0.0 else t_new - ts[T_T]
    sensor_step(cfg, nz, st, P, fl, fcnt, step,
                gyr if has_g else nan3, a_in,
                mag if has_m else nan3)
    if gap_count(fcnt) != gaps:
        ts[T_YAW_LOST] = 1.0
    if has_m:
        acnt[A_MAG_FUSED] += 1
    if a_held:
        acnt[A_ACC_FUSED] += 1
    ts[T_T] = t_new
    ts[T_VALID] = 1.0
    return output(cfg, st, P, fl, q_from_enu, npar, ts, acnt, gyr, has_g, acc, has_a_in, out)


@jit_inline
def output(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
           q_from_enu: np.ndarray, npar: np.ndarray, ts: np.ndarray, acnt: np.ndarray,
           g: np.ndarray, has_g: bool, a: np.ndarray, has_a: bool, out: np.ndarray) -> int:
    """The estimate as published (``out``, one ``O_*`` row): nothing before initialisation,
    never NaN (a non-finite estimate asks for a reset), then the output options."""
    if not is_initialized(fl):
        return _NONE
    q = np.empty(4)
    cov = np.empty((3, 3))
    world_output(cfg, st, P, q_from_enu, q, cov)
    tot = q.sum() + cov.sum()
    for i in range(3):
        tot += rate(st, i) + bias(st, i)
    if not np.isfinite(tot):
        acnt[A_OUTPUT_NONFINITE] += 1
        return R_NONFINITE
    if npar[P_HAS_OFF] > 0:
        q = qmul(npar[P_Q_OFF:P_Q_OFF + 4], q)
        R = npar[P_R_OFF:P_R_OFF + 9]
        rc = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                rc[i, j] = (R[3 * i] * cov[0, j] + R[3 * i + 1] * cov[1, j]
                            + R[3 * i + 2] * cov[2, j])
        for i in range(3):
            for j in range(3):
                cov[i, j] = (rc[i, 0] * R[3 * j] + rc[i, 1] * R[3 * j + 1]
                             + rc[i, 2] * R[3 * j + 2])
        if q[0] < 0.0:
            q = -q
    heading = heading_fixed(cfg, fl)
    if ts[T_YAW_LOST] > 0:
        if heading:
            ts[T_YAW_LOST] = 0.0
        elif cov[2, 2] < YAW_VAR_UNKNOWN:
            cov[2, 2] = YAW_VAR_UNKNOWN  # world z is vertical in ENU, NED and NWU
    sd = npar[P_ORI_SD]
    if sd > 0.0:
        cov[:, :] = 0.0
        for i in range(3):
            cov[i, i] = sd * sd
    flags = OF_PUB | (OF_HEADING if heading else 0)
    for i in range(4):
        out[O_Q + i] = q[i]
    for i in range(3):
        for j in range(3):
            out[O_COV + 3 * i + j] = cov[i, j]
    for i in range(3):
        out[O_OMEGA + i] = rate(st, i)
        out[O_BIAS + i] = bias(st, i)
        out[O_BSTD + i] = np.sqrt(bias_variance(cfg, P, i))
    out[O_W:O_LIN + 3] = np.nan  # the optional fields, absent unless written below
    src = int(npar[P_AV_SRC])
    if src == AV_ESTIMATE:
        flags |= OF_W | OF_WCOV
        for i in range(3):
            out[O_W + i] = rate(st, i)
            for j in range(3):
                out[O_WCOV + 3 * i + j] = rate_covariance(P, i, j)
    elif has_g:
        flags |= OF_W
        for i in range(3):
            out[O_W + i] = g[i] - bias(st, i) if src == AV_BIAS_CORRECTED else g[i]
        if src == AV_BIAS_CORRECTED:
            flags |= OF_WADD
            for i in range(3):
                out[O_WADD + i] = out[O_BSTD + i] * out[O_BSTD + i]
    if has_a:
        flags |= OF_LIN
        for i in range(3):
            out[O_LIN + i] = a[i]
        if npar[P_NO_GRAVITY] > 0:
            Rq = rotmat(q)
            up = npar[P_UP_W:P_UP_W + 3]
            for i in range(3):
                up_b = Rq[0, i] * up[0] + Rq[1, i] * up[1] + Rq[2, i] * up[2]
                out[O_LIN + i] = a[i] - gravity(cfg) * up_b
    out[O_FLAGS] = flags
    return _OUT


@jit
def run_events(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
               fl: np.ndarray, fcnt: np.ndarray, q_from_enu: np.ndarray, npar: np.ndarray,
               ts: np.ndarray, pend: np.ndarray, acnt: np.ndarray, ev_f: np.ndarray,
               ev_i: np.ndarray, out: np.ndarray, k0: int, k1: int,
               resume: bool, pacc: np.ndarray) -> tuple[int, int]:
    """Events ``k0 … k1-1`` in order; returns ``(k, R_DONE)`` at the end, or the index and
    reason of an event that needs a reset (``R_TIME_JUMP``: call again from ``k`` with
    ``resume``; ``R_NONFINITE``: the event is done, call again from ``k + 1``)."""
    nan3 = np.full(3, np.nan)
    for k in range(k0, k1):
        e = ev_f[k]
        kind = ev_i[k, 0]
        if kind == EV_MAG:
            mag_event(cfg, nz, st, P, fl, fcnt, npar, ts, pend, acnt, e[E_STAMP],
                      e[E_V:E_V + 3], nan3)
            continue
        if kind == EV_ACC:
            acc_event(cfg, nz, st, P, fl, fcnt, npar, ts, pacc, acnt, e[E_STAMP],
                      e[E_V:E_V + 3], nan3)
            continue
        r = imu_event(cfg, nz, st, P, fl, fcnt, q_from_enu, npar, ts, pend, acnt, e[E_STAMP],
                      e[E_V:E_V + 3], e[E_A:E_A + 3], out[ev_i[k, 1]], resume, nan3, pacc)
        resume = False
        if r >= R_TIME_JUMP:
            return k, r
    return k1, R_DONE
