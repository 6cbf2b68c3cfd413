"""Compiled event loop of :class:`mkf_ros.stream.StreamAdapter`: every time and input rule.

The adapter's rules (see :mod:`mkf_ros.stream` for what they are) are implemented once, here,
as kernels over a merged sequence of IMU and magnetometer events. The per-message methods
(``on_imu``, ``on_mag``) run a one-event sequence through :func:`run_events`; the batch entry
(``process``) runs a whole recording through it. Only resets leave the compiled loop: the
kernel stops at the event that needs one, Python resets the filter (new state arrays) and the
loop resumes, so both paths share every rule, bit for bit.

Layouts: the adapter's time state ``ts`` (``T_*``), its node parameters ``npar`` (``P_*``), the
magnetometer samples held for the IMU stream ``pend`` (rows ``stamp, m``, in stamp order, equal
stamps in arrival order), its own
counters ``acnt`` (:data:`ADAPTER_COUNTERS`), events ``ev_f`` (``E_*``) and ``ev_i`` (kind,
output row), outputs ``out`` (``O_*``, one row per IMU message, flags ``OF_*``).
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.filter import (
    C_GRAVITY,
    C_MAXDT,
    C_NX,
    C_USE_MAG,
    F_HEADING,
    F_INIT,
    K_GAPS,
    MAX_ACC_G,
    MAX_GYRO_RATE,
    MAX_MAG,
    S_B,
    S_W,
    classify_reading,
    sensor_step,
    world_output,
)
from mkf_ros.core.quaternion import q_from_rotvec, qmul, rotate_inv, rotmat

#: Out-of-order IMU samples in a row after which the stream is taken to have jumped back.
MAX_BACKWARDS = 10
#: Magnetometer samples held while waiting for the IMU stream to reach their stamps.
MAX_PENDING_MAG = 32
#: Smallest time step of an internal magnetometer-only filter step (the MUKF cannot
#: factorise its sigma points with zero process noise at dt = 0).
MIN_STEP = 1e-9
#: A magnetometer stamp this close to an IMU stamp is fused in the same filter step.
SAME_STAMP = 1e-6
#: Published yaw variance (rad²) while the heading is unknown: after a gap the filter keeps
#: the heading it had, but the sensor may have turned by any angle meanwhile (uniform on ±π).
YAW_UNKNOWN_VAR = np.pi**2 / 3.0

#: The adapter's own counters (the filter's are synced separately), in ``acnt`` order.
ADAPTER_COUNTERS = (
    "imu_received", "imu_duplicate", "imu_out_of_order", "imu_bad_stamp",
    "gyr_missing", "gyr_invalid", "acc_missing", "acc_invalid", "acc_implausible",
    "mag_received", "mag_unused", "mag_missing", "mag_invalid", "mag_too_old", "mag_ahead",
    "mag_overflow", "mag_fused", "output_nonfinite", "resets", "resets_time_jump",
)
(A_IMU_RECEIVED, A_IMU_DUPLICATE, A_IMU_OUT_OF_ORDER, A_IMU_BAD_STAMP,
 A_GYR_MISSING, A_GYR_INVALID, A_ACC_MISSING, A_ACC_INVALID, A_ACC_IMPLAUSIBLE,
 A_MAG_RECEIVED, A_MAG_UNUSED, A_MAG_MISSING, A_MAG_INVALID, A_MAG_TOO_OLD, A_MAG_AHEAD,
 A_MAG_OVERFLOW, A_MAG_FUSED, A_OUTPUT_NONFINITE, A_RESETS, A_RESETS_TIME_JUMP) = range(20)
A_SIZE = len(ADAPTER_COUNTERS)

# time state: filter time and whether it is set, heading lost in a gap, out-of-order run,
# number of held samples (these five are cleared by a reset), latest magnitudes/offset/stamps,
# dt statistics
T_T, T_VALID, T_YAW_LOST, T_BACK, T_NPEND = 0, 1, 2, 3, 4
T_ACC_NORM, T_MAG_NORM, T_MAG_OFFSET, T_LAST_IMU, T_LAST_MAG = 5, 6, 7, 8, 9
T_DT_N, T_DT_MIN, T_DT_SUM, T_DT_MAX = 10, 11, 12, 13
T_SIZE = 14
#: Rows of ``pend``: one more than it keeps (a sample is inserted, then the oldest dropped).
PEND_ROWS = MAX_PENDING_MAG + 1

# node parameters (the filter's own are read from its configuration vector)
P_CONST_DT, P_JUMP, P_ACC_TOL, P_MAG_DELAY, P_HAS_OFF = 0, 1, 2, 3, 4
P_Q_OFF, P_R_OFF, P_UP_W = 5, 9, 18  # 4, 9 (row-major), 3 values
P_ORI_SD, P_AV_SRC, P_NO_GRAVITY = 21, 22, 23
P_SIZE = 24
#: ``angular_velocity_source`` choices, in ``npar[P_AV_SRC]`` code order.
AV_SOURCES = ("input", "bias_corrected", "estimate")
AV_INPUT, AV_BIAS_CORRECTED, AV_ESTIMATE = 0, 1, 2

# events: ev_f row = stamp, gyro or magnetometer vector, accelerometer; ev_i row = kind, row
E_STAMP, E_V, E_A, E_SIZE = 0, 1, 4, 7
EV_IMU, EV_MAG = 0, 1

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
def check_input(acnt: np.ndarray, v: np.ndarray, k_missing: int, is_vector: bool,
                limit: float) -> bool:
    """True if ``v`` is a usable reading; otherwise counted (``k_missing``, or the invalid
    counter right after it). The filter's own rule, :func:`~mkf_ros.core.filter.classify_reading`
    with its plausibility limits (``limit``: a gyro faster than
    :data:`~mkf_ros.core.filter.MAX_GYRO_RATE` is invalid, etc.)."""
    c = classify_reading((v[0], v[1], v[2]), is_vector, limit)
    if c:
        acnt[k_missing + c - 1] += 1
        return False
    return True


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
    :func:`mkf_ros.stream.covariance_out`); ``add`` has one row per row of ``c``, one for
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


# --- magnetometer samples held for the IMU stream -----------------------------------------------


@jit
def _pop_front(ts: np.ndarray, pend: np.ndarray, k: int) -> None:
    """Drop the ``k`` oldest held samples."""
    n = int(ts[T_NPEND])
    for i in range(n - k):
        for j in range(4):
            pend[i, j] = pend[i + k, j]
    ts[T_NPEND] = n - k


@jit
def hold(ts: np.ndarray, pend: np.ndarray, acnt: np.ndarray, stamp: float,
         m: np.ndarray) -> None:
    """Insert a sample in stamp order (after equal stamps); the oldest goes on overflow."""
    n = int(ts[T_NPEND])
    i = n
    while i > 0 and pend[i - 1, 0] > stamp:
        for j in range(4):
            pend[i, j] = pend[i - 1, j]
        i -= 1
    pend[i, 0] = stamp
    for j in range(3):
        pend[i, 1 + j] = m[j]
    ts[T_NPEND] = n + 1
    if n + 1 > MAX_PENDING_MAG:
        _pop_front(ts, pend, 1)
        acnt[A_MAG_OVERFLOW] += 1


@jit
def fuse_mag_now(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                 fl: np.ndarray, fcnt: np.ndarray, acnt: np.ndarray, m: np.ndarray,
                 age: float, nan3: np.ndarray) -> None:
    """Fuse at the filter's current time, ``m`` rotated forward over its ``age`` (s)."""
    if age > 0.0 and fl[F_INIT] > 0:
        w = np.empty(3)
        for i in range(3):
            w[i] = st[S_W + i] * age
        m = rotate_back(m, w)
    sensor_step(cfg, nz, st, P, fl, fcnt, MIN_STEP, nan3, nan3, m)
    acnt[A_MAG_FUSED] += 1


@jit
def fuse_late(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
              fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray, acnt: np.ndarray,
              stamp: float, m: np.ndarray, nan3: np.ndarray) -> None:
    """A sample stamped at or before the filter time: fused now if recent enough."""
    age = ts[T_T] - stamp
    if age > npar[P_MAG_DELAY] + SAME_STAMP:
        acnt[A_MAG_TOO_OLD] += 1
        return
    fuse_mag_now(cfg, nz, st, P, fl, fcnt, acnt, m, max(age, 0.0), nan3)


@jit
def take_pending(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
                 fl: np.ndarray, fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray,
                 pend: np.ndarray, acnt: np.ndarray, t_new: float, dt: float,
                 same: np.ndarray, nan3: np.ndarray) -> bool:
    """Fuse held samples stamped before ``t_new``; put one stamped at ``t_new`` (or, on the
    first IMU sample, the latest recent one) in ``same`` to fuse with the IMU: True if so."""
    n = int(ts[T_NPEND])
    if n == 0:
        return False
    if ts[T_VALID] == 0:  # first sample: initialise with the latest recent magnetometer
        tol = max(npar[P_MAG_DELAY], SAME_STAMP)
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
        acnt[A_MAG_TOO_OLD] += n - n_keep - min(n_near, 1)
        _pop_front(ts, pend, n - n_keep)  # sorted: the kept ones are the newest
        return n_near > 0
    if dt > cfg[C_MAXDT]:  # a gap: the held samples cannot be placed
        x = t_new - npar[P_MAG_DELAY]
        old = 0
        while old < n and pend[old, 0] < x:
            old += 1
        acnt[A_MAG_TOO_OLD] += old
        _pop_front(ts, pend, old)
    has_same = False
    while ts[T_NPEND] > 0 and pend[0, 0] <= t_new + SAME_STAMP:
        tm = pend[0, 0]
        m = pend[0, 1:4].copy()
        _pop_front(ts, pend, 1)
        if abs(tm - t_new) <= SAME_STAMP:
            if has_same:
                fuse_mag_now(cfg, nz, st, P, fl, fcnt, acnt, same.copy(), 0.0, nan3)
            same[:] = m
            has_same = True
        elif tm <= ts[T_T]:  # held before a reset moved the time: treat as late
            fuse_late(cfg, nz, st, P, fl, fcnt, npar, ts, acnt, tm, m, nan3)
        else:
            sensor_step(cfg, nz, st, P, fl, fcnt, max(tm - ts[T_T], MIN_STEP), nan3, nan3, m)
            acnt[A_MAG_FUSED] += 1
            ts[T_T] = tm
    return has_same


# --- events ---------------------------------------------------------------------------------


@jit_inline
def mag_event(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
              fcnt: np.ndarray, npar: np.ndarray, ts: np.ndarray, pend: np.ndarray,
              acnt: np.ndarray, stamp: float, mag: np.ndarray, nan3: np.ndarray) -> None:
    """One magnetometer sample: fused now (late), held (ahead of the IMU) or dropped."""
    acnt[A_MAG_RECEIVED] += 1
    if cfg[C_USE_MAG] <= 0:
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
        if ts[T_VALID] == 0:
            pend[0, 0] = 0.0
            pend[0, 1:4] = m
            ts[T_NPEND] = 1
        else:
            fuse_mag_now(cfg, nz, st, P, fl, fcnt, acnt, m, 0.0, nan3)
        return
    if not np.isfinite(stamp):
        acnt[A_MAG_INVALID] += 1
        return
    if ts[T_VALID] == 0:  # before the first IMU sample: keep the latest few
        hold(ts, pend, acnt, stamp, m)
        return
    d = stamp - ts[T_T]
    ts[T_MAG_OFFSET] = d
    if d > cfg[C_MAXDT]:
        acnt[A_MAG_AHEAD] += 1
    elif d > SAME_STAMP:
        hold(ts, pend, acnt, stamp, m)
    else:
        fuse_late(cfg, nz, st, P, fl, fcnt, npar, ts, acnt, stamp, m, nan3)


@jit_inline
def imu_event(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
              fcnt: np.ndarray, q_from_enu: np.ndarray, npar: np.ndarray, ts: np.ndarray,
              pend: np.ndarray, acnt: np.ndarray, stamp: float, gyr: np.ndarray,
              acc: np.ndarray, out: np.ndarray, resume: bool, nan3: np.ndarray) -> int:
    """One IMU sample: time rules, input checks, held magnetometer samples, filter step,
    output. Returns ``_OUT`` (``out`` written), ``_NONE``, or a reset request ``R_*``;
    ``resume``: the same sample again after a time-jump reset (already counted)."""
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
    has_g = check_input(acnt, gyr, A_GYR_MISSING, False, MAX_GYRO_RATE)
    has_a_in = check_input(acnt, acc, A_ACC_MISSING, True, MAX_ACC_G * cfg[C_GRAVITY])
    has_a = has_a_in
    if has_a:
        norm = norm3(acc)
        ts[T_ACC_NORM] = norm
        if abs(norm / cfg[C_GRAVITY] - 1.0) > npar[P_ACC_TOL]:
            acnt[A_ACC_IMPLAUSIBLE] += 1
            has_a = False
    if valid and dt > 0.0:
        ts[T_DT_N] += 1
        ts[T_DT_MIN] = min(ts[T_DT_MIN], dt)
        ts[T_DT_SUM] += dt
        ts[T_DT_MAX] = max(ts[T_DT_MAX], dt)
    mag = np.empty(3)
    # the call is skipped when nothing is held, as it mostly is (it costs ~0.4 µs)
    has_m = ts[T_NPEND] > 0 and take_pending(cfg, nz, st, P, fl, fcnt, npar, ts, pend, acnt,
                                             t_new, dt, mag, nan3)
    gaps = fcnt[K_GAPS]
    step = dt if not valid or npar[P_CONST_DT] > 0.0 else t_new - ts[T_T]
    sensor_step(cfg, nz, st, P, fl, fcnt, step, gyr if has_g else nan3,
                acc if has_a else nan3, mag if has_m else nan3)
    if fcnt[K_GAPS] != gaps:
        ts[T_YAW_LOST] = 1.0
    if has_m:
        acnt[A_MAG_FUSED] += 1
    ts[T_T] = t_new
    ts[T_VALID] = 1.0
    return output(cfg, st, P, fl, q_from_enu, npar, ts, acnt, gyr, has_g, acc, has_a_in, out)


@jit_inline
def output(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, fl: np.ndarray,
           q_from_enu: np.ndarray, npar: np.ndarray, ts: np.ndarray, acnt: np.ndarray,
           g: np.ndarray, has_g: bool, a: np.ndarray, has_a: bool, out: np.ndarray) -> int:
    """The estimate as published (``out``, one ``O_*`` row): nothing before initialisation,
    never NaN (a non-finite estimate asks for a reset), then the output options."""
    if fl[F_INIT] == 0:
        return _NONE
    q = np.empty(4)
    cov = np.empty((3, 3))
    world_output(cfg, st, P, q_from_enu, q, cov)
    tot = q.sum() + cov.sum() + st[S_W:S_W + 3].sum() + st[S_B:S_B + 3].sum()
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
    heading = fl[F_HEADING] > 0 and cfg[C_USE_MAG] > 0
    if ts[T_YAW_LOST] > 0:
        if heading:
            ts[T_YAW_LOST] = 0.0
        elif cov[2, 2] < YAW_UNKNOWN_VAR:
            cov[2, 2] = YAW_UNKNOWN_VAR  # world z is vertical in ENU, NED and NWU
    sd = npar[P_ORI_SD]
    if sd > 0.0:
        cov[:, :] = 0.0
        for i in range(3):
            cov[i, i] = sd * sd
    nx = int(cfg[C_NX])
    flags = OF_PUB | (OF_HEADING if heading else 0)
    for i in range(4):
        out[O_Q + i] = q[i]
    for i in range(3):
        for j in range(3):
            out[O_COV + 3 * i + j] = cov[i, j]
    for i in range(3):
        out[O_OMEGA + i] = st[S_W + i]
        out[O_BIAS + i] = st[S_B + i]
        out[O_BSTD + i] = np.sqrt(P[6 + i, 6 + i]) if nx == 9 else 0.0
    out[O_W:O_LIN + 3] = np.nan  # the optional fields, absent unless written below
    src = int(npar[P_AV_SRC])
    if src == AV_ESTIMATE:
        flags |= OF_W | OF_WCOV
        for i in range(3):
            out[O_W + i] = st[S_W + i]
            for j in range(3):
                out[O_WCOV + 3 * i + j] = P[3 + i, 3 + j]
    elif has_g:
        flags |= OF_W
        for i in range(3):
            out[O_W + i] = g[i] - st[S_B + i] if src == AV_BIAS_CORRECTED else g[i]
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
                out[O_LIN + i] = a[i] - cfg[C_GRAVITY] * up_b
    out[O_FLAGS] = flags
    return _OUT


@jit
def run_events(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
               fl: np.ndarray, fcnt: np.ndarray, q_from_enu: np.ndarray, npar: np.ndarray,
               ts: np.ndarray, pend: np.ndarray, acnt: np.ndarray, ev_f: np.ndarray,
               ev_i: np.ndarray, out: np.ndarray, k0: int, k1: int,
               resume: bool) -> tuple[int, int]:
    """Events ``k0 … k1-1`` in order; returns ``(k, R_DONE)`` at the end, or the index and
    reason of an event that needs a reset (``R_TIME_JUMP``: call again from ``k`` with
    ``resume``; ``R_NONFINITE``: the event is done, call again from ``k + 1``)."""
    nan3 = np.full(3, np.nan)
    for k in range(k0, k1):
        e = ev_f[k]
        if ev_i[k, 0] == EV_MAG:
            mag_event(cfg, nz, st, P, fl, fcnt, npar, ts, pend, acnt, e[E_STAMP],
                      e[E_V:E_V + 3], nan3)
            continue
        r = imu_event(cfg, nz, st, P, fl, fcnt, q_from_enu, npar, ts, pend, acnt, e[E_STAMP],
                      e[E_V:E_V + 3], e[E_A:E_A + 3], out[ev_i[k, 1]], resume, nan3)
        resume = False
        if r >= R_TIME_JUMP:
            return k, r
    return k1, R_DONE
