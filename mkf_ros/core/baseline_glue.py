"""Glue between the sensor layer (:mod:`mkf_ros.core.sensor`) and the baselines of
:mod:`mkf_ros.core.baselines` (Euler-angle KF/UKF, Madgwick): their estimate and covariance
about body axes, conversion to and from the MKF ("canonical") form of the state, their step
after the sensor layer's checks, and the Euler filters' tilt re-alignment.
"""

from __future__ import annotations

from collections import namedtuple

import numpy as np
from numba import types as nt

from mkf_ros.core._jit import jit, tuple_type, unit
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
from mkf_ros.core.frames import align_tilt, keep_yaw
from mkf_ros.core.linalg import copy_block, copy_into
from mkf_ros.core.mekf import heading_residual
from mkf_ros.core.quaternion import rotmat
from mkf_ros.core.state import (
    ALGO_EULER_KF,
    ALGO_EULER_UKF,
    ALGO_MADGWICK,
    CONFIG_T,
    NX_MAX,
    REALIGN_ACC_TOL,
    REALIGN_MAX_RATE,
    STATE_T,
    Fusion,
    mag_yaw_var,
    set_world_attitude_cov,
)

# --- glue between the sensor layer and mkf_ros.core.baselines ---------------------------------
# The sensor layer (alignment, heading initialisation, recovery) works on the MKF form of the
# state, "canonical" here: q̄ = q_c with ē = 0, P_ee about body axes, P_ωω, P_bb. The Euler
# filters keep their own state (euler, and P as the covariance of (φ, θ, ψ[, p, q, r])) and are
# converted only where the sensor layer resets something and on an algorithm switch, so that
# their gimbal-lock behaviour is theirs. Madgwick's state is q_c itself; it has no covariance.


@jit
def _euler_n(algo: int) -> int:
    return 3 if algo == ALGO_EULER_KF else 6


@jit
def baseline_estimate(c: np.record, s: np.record) -> tuple[np.ndarray, np.ndarray]:
    """Estimate and attitude covariance about body axes of a baseline: Euler filters
    ``E Σ_φθψ Eᵀ`` (E: body rotation vector per Euler increment, the inverse of eq. (7));
    Madgwick a fixed ``madgwick_stddev²`` about each world axis (heading in 6D growing with the
    integrated gyro noise)."""
    q = s.q_c.copy()
    if c.algorithm == ALGO_MADGWICK:
        v = c.madgwick_var
        vy = v if c.use_mag else v + s.madgwick_yaw_var
        R = rotmat(q)
        C = np.empty((3, 3))
        for i in range(3):
            for j in range(3):
                C[i, j] = v * (R[0, i] * R[0, j] + R[1, i] * R[1, j]) + vy * R[2, i] * R[2, j]
        return q, C
    return q, euler_cov_to_body(s.euler, s.P, 3)


@jit
def baseline_export(c: np.record, s: np.record) -> None:
    """Baseline state → canonical form (no-op for the MKFs); attitude-bias cross terms are
    zero (the baselines do not estimate the bias; a bias estimated before a switch is kept
    frozen and subtracted from the gyro)."""
    algo = c.algorithm
    if algo < ALGO_EULER_KF:
        return
    q, C = baseline_estimate(c, s)
    n = 3 if algo != ALGO_EULER_UKF else 6
    P = s.P
    if algo == ALGO_EULER_UKF:
        C = euler_cov_to_body(s.euler, P, 6)
    copy_into(s.q_c, q)
    s.e[:] = 0.0
    for i in range(NX_MAX):  # clear everything but the bias block ...
        for j in range(NX_MAX):
            if i < 6 or j < 6:
                P[i, j] = 0.0
    copy_block(P, 0, 0, C, False)  # ... then the attitude [and rate] block
    if n == 3:  # KF, Madgwick: the gyro reading is the rate estimate
        for i in range(3, 6):
            P[i, i] = c.gyro_var
    if c.nx == 9:  # ω̄ = g − b̄ (frozen bias): the rate inherits its uncertainty
        for i in range(3):
            for j in range(3):
                P[3 + i, 3 + j] += P[6 + i, 6 + j]
                P[3 + i, 6 + j] = -P[6 + i, 6 + j]
                P[6 + j, 3 + i] = -P[6 + i, 6 + j]


@jit
def from_canonical(c: np.record, s: np.record) -> None:
    """Canonical form → the algorithm's own state (no-op for the MKFs): Euler angles of
    ``q̄`` and ``Σ = W P_ee Wᵀ`` (W of eq. (7), |cos θ| floored), rates block kept for the UKF."""
    algo = c.algorithm
    if algo < ALGO_EULER_KF:
        return
    if algo == ALGO_MADGWICK:
        s.madgwick_yaw_var = 0.0
        s.mag_held = False
        return
    n = _euler_n(algo)
    phi, theta, psi = quat_to_euler(s.q_c)
    s.euler[0], s.euler[1], s.euler[2] = phi, theta, psi
    P = s.P
    S = body_cov_to_euler(s.euler, P, n)
    for i in range(n):
        for j in range(n, NX_MAX):
            P[i, j] = 0.0
            P[j, i] = 0.0
    copy_block(P, 0, 0, S, False)
    copy_into(s.q_c, euler_to_quat(phi, theta, psi))


@unit(nt.void(CONFIG_T, STATE_T), cost=2.2)
def export(c: np.record, s: np.record) -> None:
    """:func:`baseline_export` compiled on its own (the sensor layer's rare paths call it; a
    no-op for the MKFs, whose kernel table holds :func:`mkf_canonical` instead: compiled on a
    baseline's first use, :func:`mkf_ros.core.filter.kernel_table`)."""
    baseline_export(c, s)


@unit(nt.void(CONFIG_T, STATE_T), cost=1.2)
def restore(c: np.record, s: np.record) -> None:
    """:func:`from_canonical` compiled on its own (as :func:`export`)."""
    from_canonical(c, s)


@unit(nt.void(CONFIG_T, STATE_T), cost=0.1)
def mkf_canonical(c: np.record, s: np.record) -> None:
    """:func:`export` and :func:`restore` for the MKFs, whose state is its canonical form:
    nothing to do."""


#: The conversions of a baseline's state to and from the canonical form, compiled once each
#: and handed to the sensor layer's rare paths.
Canonical = namedtuple("Canonical", ("export", "restore"))
CANONICAL_T = tuple_type([export.type, restore.type], Canonical)


@jit
def baseline_realign(c: np.record, s: np.record, a: tuple, w: tuple) -> bool:
    """Euler baselines only: when the accelerometer has been refused for
    :data:`~mkf_ros.core.state.ACC_RECOVERY_TIME` and this sample looks like gravity (magnitude
    within :data:`REALIGN_ACC_TOL` of ``gravity``, rate below :data:`REALIGN_MAX_RATE`),
    re-align the tilt from it, keeping yaw and its variance, as after a gap. Widening the prior
    alone does not bring them back: once the tilt is far off, the Euler UKF's sigma points span
    more than a turn and its χ² gate refuses gravity whatever the variance (measured: tilt
    variances of 20–90 rad² still refused). The tilt variance is one sample's (as in the
    alignment) plus the square of the tilt's jump: never narrower than the step taken. Works on
    the canonical form (between :func:`baseline_export` and :func:`from_canonical`). Returns
    whether it re-aligned (False: not a baseline that needs it, or not gravity)."""
    algo = c.algorithm
    if algo != ALGO_EULER_KF and algo != ALGO_EULER_UKF:
        return False
    n = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    if (abs(n / c.gravity - 1.0) > REALIGN_ACC_TOL
            or w[0] * w[0] + w[1] * w[1] + w[2] * w[2] > REALIGN_MAX_RATE ** 2):
        return False
    P = s.P
    R = rotmat(s.q_c)
    # the jump: between the estimate's up (R's last row, in body axes) and the accelerometer's
    cj = (R[2, 0] * a[0] + R[2, 1] * a[1] + R[2, 2] * a[2]) / n
    jump = np.arccos(max(-1.0, min(1.0, cj)))
    var_yaw = 0.0  # world-z variance of the attitude block, kept
    for i in range(3):
        for j in range(3):
            var_yaw += R[2, i] * R[2, j] * P[i, j]
    copy_into(s.q_c, keep_yaw(align_tilt(np.array(a)), s.q_c))
    set_world_attitude_cov(s, c.nx, c.acc_var + 9.0 * c.acc_disturbance_var + jump * jump,
                           var_yaw, False)
    return True


@jit
def _madgwick_update(c: np.record, s: np.record, dt: float, z: Fusion) -> None:
    """Madgwick's step (it needs the accelerometer and the field together: a field sample
    without an accelerometer one is held for the next IMU sample)."""
    m = np.array(z.m)
    use_m = z.has_m
    has_a = z.has_a_raw
    if z.has_m and not has_a:  # hold it for the next IMU sample
        copy_into(s.held_mag, m)
        s.mag_held = True
        use_m = False
    elif has_a and not z.has_m and s.mag_held:
        m = s.held_mag.copy()
        use_m = True
    if has_a:
        s.mag_held = False
    madgwick_step(s.q_c, s.w, dt, np.array(z.a_raw), has_a, m, use_m, _h_ref(s), c.madgwick_beta)
    s.madgwick_yaw_var += c.gyro_var * dt * dt


@jit
def _h_ref(s: np.record) -> np.ndarray:
    """The field reference's horizontal direction (north if it has none)."""
    ref = s.mag_ref
    h = np.sqrt(ref[0] * ref[0] + ref[1] * ref[1])
    return np.array((ref[0] / h, ref[1] / h, 0.0)) if h > 0.0 else np.array((0.0, 1.0, 0.0))


@jit
def _euler_kf_update(c: np.record, s: np.record, dt: float, z: Fusion) -> tuple:
    """The Euler KF's step: predict with the gyro, update with gravity and the heading."""
    x = s.euler
    var_a = c.acc_var + z.var_a_raw
    euler_kf_predict(x, s.P, s.w, dt, c.gyro_var)
    acc_nis = 0.0
    mag_nis = 0.0
    if z.has_a_raw:
        acc_nis = euler_kf_acc_update(x, s.P, np.array(z.a_raw), var_a, z.acc_gate)
    if z.has_m:
        resid, _ = heading_residual(rotmat(euler_to_quat(x[0], x[1], x[2])), np.array(z.m),
                                    _h_ref(s))
        mag_nis = yaw_update(x, s.P, 3, resid, mag_yaw_var(c, s.mag_ref), z.mag_gate)
    return True, acc_nis, mag_nis


@jit
def _euler_ukf_update(c: np.record, s: np.record, dt: float, z: Fusion) -> tuple:
    """The Euler UKF's step: state (φ, θ, ψ, p, q, r), predict, then the gravity, gyro and
    heading measurements through the sigma points."""
    x = s.euler
    w = s.w
    var_w = c.gyro_var
    var_a = c.acc_var + z.var_a_raw
    xx = np.empty(6)
    for i in range(3):
        xx[i] = x[i]
        xx[3 + i] = w[i]
    acc_nis = 0.0
    mag_nis = 0.0
    ok = euler_ukf_predict(xx, s.P, dt, c.rate_process_noise)
    if ok:
        b = s.b
        zz = np.zeros(7)
        for i in range(3):
            zz[i] = z.a_raw[i]
            zz[3 + i] = z.g[i] - b[i]
        if z.has_m:
            resid, _ = heading_residual(rotmat(euler_to_quat(xx[0], xx[1], xx[2])),
                                        np.array(z.m), _h_ref(s))
            zz[6] = resid
        use = np.array((z.has_a_raw, z.has_g, z.has_m))
        Rd = np.array((var_a, var_a, var_a, var_w, var_w, var_w, mag_yaw_var(c, s.mag_ref)))
        gates = np.array((z.acc_gate, np.inf, z.mag_gate))
        nis = np.zeros(3)
        ok = euler_ukf_update(xx, s.P, use, zz, Rd, gates, nis)
        acc_nis, mag_nis = nis[0], nis[2]
    for i in range(3):
        x[i] = xx[i]
        w[i] = xx[3 + i]
    return ok, acc_nis, mag_nis


@jit
def baseline_update(c: np.record, s: np.record, k: np.record, dt: float,
                    z: Fusion) -> tuple[bool, float, float]:
    """One step of a baseline after the sensor layer's checks (it fuses the raw accelerometer
    sample that passed the magnitude test). The gyro minus the (frozen) bias is the rate; a
    missing gyro sample repeats the last rate (KF, Madgwick). Returns ``(ok, acc NIS, mag
    NIS)`` like the MKF branches (Madgwick: NIS 0, it has no gate)."""
    algo = c.algorithm
    if z.has_g and algo != ALGO_EULER_UKF:
        for i in range(3):
            s.w[i] = z.g[i] - s.b[i]
    if algo == ALGO_MADGWICK:
        _madgwick_update(c, s, dt, z)
        return True, 0.0, 0.0
    if algo == ALGO_EULER_KF:
        ok, acc_nis, mag_nis = _euler_kf_update(c, s, dt, z)
    else:
        ok, acc_nis, mag_nis = _euler_ukf_update(c, s, dt, z)
    x = s.euler
    if abs(np.cos(x[1])) < c.gimbal_cos:
        k.gimbal_lock += 1
    copy_into(s.q_c, euler_to_quat(x[0], x[1], x[2]))
    return ok, acc_nis, mag_nis
