"""Glue between the sensor layer (:mod:`mkf_ros.core.sensor`) and the baselines of
:mod:`mkf_ros.core.baselines` (Euler-angle KF/UKF, Madgwick; issue 7): their estimate and
covariance about body axes, conversion to and from the MKF ("canonical") form of the state,
their step after the sensor layer's checks, and the Euler filters' tilt re-alignment.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit
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
from mkf_ros.core.mekf import (
    heading_residual,
)
from mkf_ros.core.quaternion import (
    rotmat,
)
from mkf_ros.core.state import (
    ALGO_EULER_KF,
    ALGO_EULER_UKF,
    ALGO_MADGWICK,
    C_ALGO,
    C_BETA,
    C_GIMBAL_COS,
    C_GRAVITY,
    C_MADG_VAR,
    C_NX,
    C_QA,
    C_QW,
    C_RA,
    C_RW,
    C_USE_MAG,
    K_GIMBAL,
    NX_MAX,
    REALIGN_ACC_TOL,
    REALIGN_MAX_RATE,
    S_B,
    S_BL_MAG,
    S_BL_MHELD,
    S_BL_YAWVAR,
    S_E,
    S_EUL,
    S_MREF,
    S_QC,
    S_W,
    mag_yaw_var,
    recentre,
    set_world_attitude_cov,
)

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
def baseline_estimate(cfg: np.ndarray, st: np.ndarray,
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
def baseline_export(cfg: np.ndarray, st: np.ndarray, P: np.ndarray) -> None:
    """Baseline state → canonical form (no-op for the MKFs); attitude-bias cross terms are
    zero (the baselines do not estimate the bias; a bias estimated before a switch is kept
    frozen and subtracted from the gyro)."""
    algo = int(cfg[C_ALGO])
    if algo < ALGO_EULER_KF:
        return
    q, C = baseline_estimate(cfg, st, P)
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
        baseline_export(cfg, st, P)


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
def baseline_realign(cfg: np.ndarray, st: np.ndarray, P: np.ndarray, a: tuple, w: tuple) -> bool:
    """Euler baselines only (issue 14 item 5): when the accelerometer has been refused for
    ``acc_recovery_time`` and this sample looks like gravity (magnitude within
    :data:`REALIGN_ACC_TOL` of ``gravity``, rate below :data:`REALIGN_MAX_RATE`), re-align the
    tilt from it, keeping yaw and its variance, as after a gap (:func:`_align`). Widening the
    prior alone does not bring them back: once the tilt is far off, the Euler UKF's sigma points
    span more than a turn and its χ² gate refuses gravity whatever the variance (measured: tilt
    variances of 20–90 rad² still refused). The tilt variance is one sample's (as in
    :func:`_align`) plus the square of the tilt's jump: never narrower than the step taken.
    Works on the canonical form (between :func:`baseline_export` and :func:`from_canonical`).
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
    set_world_attitude_cov(st, P, int(cfg[C_NX]), cfg[C_RA] + 9.0 * cfg[C_QA] + jump * jump,
                            var_yaw, False)
    return True


@jit
def baseline_update(cfg: np.ndarray, nz: np.ndarray, st: np.ndarray, P: np.ndarray,
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
    mag_var = mag_yaw_var(cfg, ref)
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
