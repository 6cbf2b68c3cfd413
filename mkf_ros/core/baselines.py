"""Baseline attitude filters of the seed report: Euler-angle KF, Euler-angle UKF, Madgwick.

Report: M. Patil, C. Merrill, R. Lumba, "Non-stinky Unscented Kalman Filter for Attitude
Estimation" (class report, University of Maryland); equation numbers (1)–(39) are the report's.
Madgwick: S. O. H. Madgwick, "An efficient orientation filter for inertial and
inertial/magnetic sensor arrays", report, 2010; its equations are cited as (M25) etc.

Euler angles are ZYX (roll φ, pitch θ, yaw ψ), ``R(φ, θ, ψ) = R_z(ψ) R_y(θ) R_x(φ)``, body → ENU.
With this order the report's accelerometer model (33)–(35) is exact for our sensor convention
(+g along the world's up axis at rest, read in body axes): ``a/g = R(x)ᵀ ẑ =
(−sin θ, sin φ cos θ, cos φ cos θ)``. Kernels work on plain arrays; the sensor layer
(:mod:`mkf_ros.core.filter`) owns the state slots, the gates and the output.

What is plainly wrong in the report and fixed here (also noted where it is implemented):

1. Eq. (7): the third row of the Euler-rate matrix is (1, sφ secθ, cφ secθ); it is
   (0, sφ secθ, cφ secθ), as eq. (29) has it. It multiplies the body rates ω, not ω̇.
2. Eq. (12): roll ``atan(a_y / √(a_x² + a_z²))`` is the roll of the other rotation order (XYZ);
   for the ZYX angles of eqs. (7) and (33)–(35) roll is ``atan2(a_y, a_z)`` (quadrant-correct
   too: the report's ``atan`` cannot exceed ±90° of roll).
3. Eq. (14): ``atan(√(a_x² + a_y²) / a_z)`` is the tilt from the vertical, not yaw; an
   accelerometer does not observe yaw. The KF measures roll and pitch (6D); with a magnetometer
   a tilt-compensated heading is the third row (9D, our extension).
4. §II: Q_t "the covariance of the gyroscope" and R_t "the covariance of the accelerometer" have
   the units of rates (rad²/s²) and accelerations (m²/s⁴), not of angles. We propagate them:
   ``Q = Δt² W Σ_ω Wᵀ`` (gyro noise through eq. (6)–(7)) and ``R_φ = σ_a² / cos²θ``,
   ``R_θ = σ_a²`` (isotropic direction noise through eqs. (12)–(13), first order).
5. Angles wrap: innovations in roll and yaw are taken modulo 2π and the state is kept in
   ``θ ∈ [−π/2, π/2]`` with the identity ``(φ, θ, ψ) ≡ (φ + π, π − θ, ψ + π)``; otherwise a
   full turn makes a 2π innovation.
6. Eqs. (21)–(24): (23) and (24) are (21) and (22) again with *m* where the covariance weights
   *c* are meant; (22) has λ in the numerator. Standard scaled-UT weights:
   ``w0m = λ/(n+λ)``, ``wim = wic = 1/(2(n+λ))``, ``w0c = w0m + (1 − α² + β)`` (the report adds
   +α²). With the report's λ = 1 the numerator slip is harmless (λ = 1) and α only enters w0c;
   λ = 1 is used as given, not recomputed as ``α²(n + κ) − n`` (with α = 0.001 that would make
   ``n + λ = 6·10⁻⁶`` and ``w0m ≈ −10⁶``).
7. §III-D, §III-E: the update uses the accelerometer only, but the state contains the body rates
   (18) and R_t is 6×6: the gyroscope is the other three measurement rows, ``g(χ)(4:6) = χ(4:6)``
   (without it the rates would never be observed).
8. Eq. (32): ``Z_i = g(f(χ_{t−1,i}))`` reuses the propagated sigma points, which do not contain
   Q_t, so S_t (31) and Σ_xz (36) miss the process noise. The sigma points are redrawn from
   (μ̄_t, Σ̄_t) before the measurement (Thrun, Burgard, Fox, Probabilistic Robotics, Table 3.4).
9. Eqs. (33)–(35) print g as q (typesetting).

Near θ = ±90° the Euler-rate matrix (7) is singular (sec θ, tan θ → ∞) and roll and yaw become
one degree of freedom: that is gimbal lock. We evaluate sec θ and tan θ with |cos θ| clamped at
:data:`COS_MIN` so that nothing becomes infinite or NaN, and the sensor layer counts the samples
whose estimated pitch is near ±90° (counter ``gimbal_lock``). The failure itself is the method's
and is left as it is.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit, jit_inline
from mkf_ros.core.linalg import cho_solve, cholesky, congruence, copy_block, symmetrize_leading

#: Floor of |cos θ| in sec θ and tan θ (θ within 0.06° of ±90°): keeps eq. (7) finite.
COS_MIN = 1e-3
#: The report's sigma-point parameters (§III-B): λ, α, β; state size n (18).
UKF_LAMBDA, UKF_ALPHA, UKF_BETA, UKF_N = 1.0, 1e-3, 2.0, 6
UKF_NS = 2 * UKF_N + 1  # 13 sigma points
#: Measurement rows of the UKF update: accelerometer (3), gyroscope (3), heading (1).
UKF_M = 7


# ------------------------------------------------------------------------------ Euler angles
@jit
def wrap(a: float) -> float:
    """Angle modulo 2π in (−π, π]."""
    return np.arctan2(np.sin(a), np.cos(a))


@jit
def euler_to_quat(phi: float, theta: float, psi: float) -> np.ndarray:
    """Unit quaternion (q0 ≥ 0) of ``R_z(ψ) R_y(θ) R_x(φ)``."""
    cf, sf = np.cos(0.5 * phi), np.sin(0.5 * phi)
    ct, st = np.cos(0.5 * theta), np.sin(0.5 * theta)
    cp, sp = np.cos(0.5 * psi), np.sin(0.5 * psi)
    q = np.array((cf * ct * cp + sf * st * sp, sf * ct * cp - cf * st * sp,
                  cf * st * cp + sf * ct * sp, cf * ct * sp - sf * st * cp))
    if q[0] < 0.0:
        for i in range(4):
            q[i] = -q[i]
    return q


@jit
def quat_to_euler(q: np.ndarray) -> tuple[float, float, float]:
    """ZYX angles of a unit quaternion, ``θ ∈ [−π/2, π/2]``; at θ = ±90° (only φ ∓ ψ defined)
    roll is set to 0."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    r20 = 2.0 * (x * z - w * y)
    r21 = 2.0 * (y * z + w * x)
    r22 = 1.0 - 2.0 * (x * x + y * y)
    r00 = 1.0 - 2.0 * (y * y + z * z)
    r10 = 2.0 * (x * y + w * z)
    ch = np.sqrt(r00 * r00 + r10 * r10)
    theta = np.arctan2(-r20, ch)
    if np.sqrt(r21 * r21 + r22 * r22) < 1e-9:  # gimbal lock: φ = 0, ψ from the x-y block
        r01 = 2.0 * (x * y - w * z)
        r11 = 1.0 - 2.0 * (x * x + z * z)
        return 0.0, theta, np.arctan2(-r01, r11)
    return np.arctan2(r21, r22), theta, np.arctan2(r10, r00)


@jit
def _sec_tan(theta: float) -> tuple[float, float, bool]:
    """sec θ and tan θ with |cos θ| ≥ COS_MIN; ``clamped`` tells whether the floor acted."""
    c = np.cos(theta)
    clamped = abs(c) < COS_MIN
    if clamped:
        c = COS_MIN if c >= 0.0 else -COS_MIN
    return 1.0 / c, np.sin(theta) / c, clamped


@jit
def euler_rate_matrix(phi: float, theta: float) -> tuple[np.ndarray, bool]:
    """``W`` with ``(φ̇, θ̇, ψ̇) = W ω`` (eq. (7), third row fixed: 0, not 1; eq. (29))."""
    sec, tan, clamped = _sec_tan(theta)
    sf, cf = np.sin(phi), np.cos(phi)
    W = np.empty((3, 3))
    W[0, 0], W[0, 1], W[0, 2] = 1.0, sf * tan, cf * tan
    W[1, 0], W[1, 1], W[1, 2] = 0.0, cf, -sf
    W[2, 0], W[2, 1], W[2, 2] = 0.0, sf * sec, cf * sec
    return W, clamped


@jit
def body_jacobian(phi: float, theta: float) -> np.ndarray:
    """``E = W⁻¹``: the body rotation vector of a small Euler increment,
    ``R(x + dx) = R(x) exp([E dx]×)``; |cos θ| floored like :func:`euler_rate_matrix` so that a
    positive definite Euler covariance stays positive definite about body axes."""
    sec, tan, _ = _sec_tan(theta)
    c = 1.0 / sec
    s = tan * c
    sf, cf = np.sin(phi), np.cos(phi)
    E = np.zeros((3, 3))
    E[0, 0], E[0, 2] = 1.0, -s
    E[1, 1], E[1, 2] = cf, sf * c
    E[2, 1], E[2, 2] = -sf, cf * c
    return E


@jit
def principal(x: np.ndarray, P: np.ndarray, n: int) -> None:
    """Keep ``θ ∈ [−π/2, π/2]`` and φ, ψ in (−π, π] (fix 5): ``(φ + π, π − θ, ψ + π)`` is the
    same rotation; ``dθ`` changes sign, so row and column 1 of ``P`` (n×n block) do too."""
    th = wrap(x[1])
    if abs(th) > 0.5 * np.pi:
        th = (np.pi if th > 0.0 else -np.pi) - th
        x[0] += np.pi
        x[2] += np.pi
        for i in range(n):
            if i != 1:
                P[1, i] = -P[1, i]
                P[i, 1] = -P[i, 1]
    x[1] = th
    x[0] = wrap(x[0])
    x[2] = wrap(x[2])


@jit
def accel_roll_pitch(a: np.ndarray) -> tuple[float, float]:
    """Roll and pitch of a normalised accelerometer reading: eq. (12) fixed (atan2(a_y, a_z),
    fix 2) and eq. (13)."""
    return np.arctan2(a[1], a[2]), np.arctan2(-a[0], np.sqrt(a[1] * a[1] + a[2] * a[2]))


@jit
def euler_cov_to_body(x: np.ndarray, S: np.ndarray, n: int) -> np.ndarray:
    """``A S Aᵀ`` with ``A = blockdiag(E, I)``: an (n×n, n = 3 or 6) covariance of (Euler angles
    [, body rates]) as one of (body rotation vector [, rates])."""
    return _attitude_congruence(body_jacobian(x[0], x[1]), S, n)


@jit
def body_cov_to_euler(x: np.ndarray, C: np.ndarray, n: int) -> np.ndarray:
    """Inverse of :func:`euler_cov_to_body`: ``A⁻¹ C A⁻ᵀ`` with ``A⁻¹ = blockdiag(W, I)``."""
    return _attitude_congruence(euler_rate_matrix(x[0], x[1])[0], C, n)


@jit
def _attitude_congruence(M: np.ndarray, S: np.ndarray, n: int) -> np.ndarray:
    """``A S Aᵀ`` (symmetrised) for the leading n×n block of ``S``, ``A = blockdiag(M, I)``
    with the 3×3 ``M`` on the attitude."""
    A = np.zeros((n, n))
    copy_block(A, 0, 0, M, False)
    for i in range(3, n):
        A[i, i] = 1.0
    out = congruence(A, S[0:n, 0:n])
    symmetrize_leading(out, n)
    return out


@jit
def gain_update(x: np.ndarray, P: np.ndarray, n: int, C: np.ndarray, S: np.ndarray,
                r: np.ndarray, gate: float) -> float:
    """``K = C S⁻¹``, ``x += K r``, ``P −= K Cᵀ`` (= ``K S Kᵀ``): eqs. (15)–(17) with
    ``C = Σ̄ Cᵀ_t``, eqs. (37)–(39) with ``C = Σ_xz``. Returns the NIS ``rᵀ S⁻¹ r``; −1 if ``S``
    is not positive definite; nothing changes if the NIS exceeds ``gate``."""
    m = r.shape[0]
    ok, L, sr, nis = _solve_nis(S, r)
    if not ok:
        return -1.0
    if nis > gate:
        return nis
    Ct = np.empty((m, n))
    for k in range(m):
        for j in range(n):
            Ct[k, j] = C[j, k]
    SiCt = cho_solve(L, Ct)
    for i in range(n):
        s = 0.0
        for k in range(m):
            s += C[i, k] * sr[k, 0]
        x[i] += s
    for i in range(n):
        for j in range(n):
            s = 0.0
            for k in range(m):
                s += C[i, k] * SiCt[k, j]
            P[i, j] -= s
    symmetrize_leading(P, n)
    return nis


# ------------------------------------------------------------------------------ Euler KF (§II)
@jit
def euler_kf_predict(x: np.ndarray, P: np.ndarray, w: np.ndarray, dt: float,
                     var_w: float) -> None:
    """Process update, eqs. (5)–(9): ``A = I``, ``B u = Δt W(φ, θ) ω`` with the gyro rates ω
    through the Euler-rate matrix (7) (third row fixed), ``Σ̄ = Σ + Q`` with
    ``Q = Δt² W σ_ω² Wᵀ`` (fix 4). ``x = (φ, θ, ψ)``, ``P`` its 3×3 covariance."""
    W, _ = euler_rate_matrix(x[0], x[1])
    for i in range(3):
        x[i] += dt * (W[i, 0] * w[0] + W[i, 1] * w[1] + W[i, 2] * w[2])
    q = var_w * dt * dt
    for i in range(3):
        for j in range(3):
            P[i, j] += q * (W[i, 0] * W[j, 0] + W[i, 1] * W[j, 1] + W[i, 2] * W[j, 2])
    principal(x, P, 3)


@jit
def euler_kf_acc_update(x: np.ndarray, P: np.ndarray, a: np.ndarray, var: float,
                        gate: float) -> float:
    """Measurement update, eqs. (10)–(17), with ``z = (φ_m, θ_m)`` from the normalised
    accelerometer (eq. (12) fixed, (13); the report's (14) is not yaw, fix 3), ``C_t`` the first
    two rows of I, ``R = diag(σ²/cos²θ_m, σ²)`` (fix 4; ``σ²`` = ``var``, direction variance).
    Roll innovation wrapped (fix 5). Returns the NIS (−1: not positive definite)."""
    phi_m, th_m = accel_roll_pitch(a)
    c = max(np.cos(th_m), COS_MIN)
    r = np.array((wrap(phi_m - x[0]), th_m - x[1]))
    S = np.empty((2, 2))
    C = np.empty((3, 2))
    for i in range(3):
        C[i, 0] = P[i, 0]
        C[i, 1] = P[i, 1]
    S[0, 0] = P[0, 0] + var / (c * c)
    S[0, 1] = S[1, 0] = P[0, 1]
    S[1, 1] = P[1, 1] + var
    nis = gain_update(x, P, 3, C, S, r, gate)
    principal(x, P, 3)
    return nis


@jit
def yaw_update(x: np.ndarray, P: np.ndarray, n: int, resid: float, var: float,
               gate: float) -> float:
    """Heading from the magnetometer (extension, 9D): ``z = ψ + n`` with ``z − ψ̂`` the
    tilt-compensated heading residual ``resid`` (a rotation about the world vertical changes ψ
    only: ``R_z(a) R(φ, θ, ψ) = R(φ, θ, ψ + a)``); ``C_t = (0, 0, 1, 0…)``."""
    C = np.empty((n, 1))
    for i in range(n):
        C[i, 0] = P[i, 2]
    S = np.empty((1, 1))
    S[0, 0] = P[2, 2] + var
    r = np.array((wrap(resid),))
    nis = gain_update(x, P, n, C, S, r, gate)
    principal(x, P, n)
    return nis


# ------------------------------------------------------------------------------ Euler UKF (§III)
@jit
def ukf_weights() -> tuple[np.ndarray, np.ndarray]:
    """Mean and covariance weights, eqs. (21)–(24) corrected (fix 6)."""
    n, lam = UKF_N, UKF_LAMBDA
    wm = np.full(UKF_NS, 1.0 / (2.0 * (n + lam)))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = wm[0] + (1.0 - UKF_ALPHA * UKF_ALPHA + UKF_BETA)
    return wm, wc


@jit
def sigma_points(mu: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, bool]:
    """Eqs. (19)–(20): ``χ_0 = μ``, ``χ_i = μ ± (√((n+λ)Σ))_i`` with the Cholesky factor."""
    n = UKF_N
    A = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            A[i, j] = (n + UKF_LAMBDA) * P[i, j]
    L, ok = cholesky(A)
    X = np.empty((UKF_NS, n))
    for s in range(UKF_NS):
        for i in range(n):
            X[s, i] = mu[i]
    for j in range(n):
        for i in range(n):
            X[1 + j, i] += L[i, j]
            X[1 + n + j, i] -= L[i, j]
    return X, ok


@jit
def _mean_cov(Y: np.ndarray, wm: np.ndarray, wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ns, n = Y.shape
    mu = np.zeros(n)
    for s in range(ns):
        for i in range(n):
            mu[i] += wm[s] * Y[s, i]
    S = np.zeros((n, n))
    for s in range(ns):
        for i in range(n):
            di = Y[s, i] - mu[i]
            for j in range(n):
                S[i, j] += wc[s] * di * (Y[s, j] - mu[j])
    return mu, S


@jit
def euler_ukf_predict(x: np.ndarray, P: np.ndarray, dt: float, q_w: float) -> bool:
    """Prediction, eqs. (25)–(29): each sigma point moves by ``f(χ)(1:3) = χ(1:3) +
    W(χ) χ(4:6) Δt`` (eq. (27), W of eq. (29)) with constant rates (28); ``μ̄ = Σ w_m f``,
    ``Σ̄ = Σ w_c (f − μ̄)(f − μ̄)ᵀ + Q``. ``Q`` (the report tunes it by hand, §III-E) is the
    discretised white angular acceleration of PSD ``q_w`` with W frozen at the mean:
    ``[[W Wᵀ q Δt³/3, W q Δt²/2], [·ᵀ, q Δt I]]``. ``x = (φ, θ, ψ, p, q, r)``, ``P`` 6×6.
    Returns False (nothing changed) if ``Σ`` has no Cholesky factor."""
    X, ok = sigma_points(x, P)
    if not ok:
        return False
    wm, wc = ukf_weights()
    Y = X.copy()
    for s in range(UKF_NS):
        W, _ = euler_rate_matrix(X[s, 0], X[s, 1])
        for i in range(3):
            Y[s, i] += dt * (W[i, 0] * X[s, 3] + W[i, 1] * X[s, 4] + W[i, 2] * X[s, 5])
    mu, S = _mean_cov(Y, wm, wc)
    W, _ = euler_rate_matrix(x[0], x[1])
    a, b, c = q_w * dt * dt * dt / 3.0, q_w * dt * dt / 2.0, q_w * dt
    for i in range(3):
        for j in range(3):
            S[i, j] += a * (W[i, 0] * W[j, 0] + W[i, 1] * W[j, 1] + W[i, 2] * W[j, 2])
            S[i, 3 + j] += b * W[i, j]
            S[3 + j, i] += b * W[i, j]
        S[3 + i, 3 + i] += c
    for i in range(6):
        x[i] = mu[i]
        for j in range(6):
            P[i, j] = S[i, j]
    principal(x, P, 6)
    return True


@jit
def _ukf_innovation(X: np.ndarray, x: np.ndarray, z: np.ndarray,
                    Rd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. (33)–(37) over the sigma points ``X``: ``Z_i = g(χ̄_i)``, the cross covariance
    ``C_xz``, ``S = S_zz + R_t`` and the innovation ``r`` (heading wrapped)."""
    wm, wc = ukf_weights()
    Z = np.empty((UKF_NS, UKF_M))
    for s in range(UKF_NS):
        sf, cf = np.sin(X[s, 0]), np.cos(X[s, 0])
        sth, cth = np.sin(X[s, 1]), np.cos(X[s, 1])
        Z[s, 0], Z[s, 1], Z[s, 2] = -sth, sf * cth, cf * cth
        Z[s, 3], Z[s, 4], Z[s, 5] = X[s, 3], X[s, 4], X[s, 5]
        Z[s, 6] = X[s, 2]
    zh, Szz = _mean_cov(Z, wm, wc)
    mu = np.zeros(UKF_N)
    for s in range(UKF_NS):
        for i in range(UKF_N):
            mu[i] += wm[s] * X[s, i]
    Cxz = np.zeros((UKF_N, UKF_M))
    for s in range(UKF_NS):
        for i in range(UKF_N):
            di = X[s, i] - mu[i]
            for j in range(UKF_M):
                Cxz[i, j] += wc[s] * di * (Z[s, j] - zh[j])
    for j in range(UKF_M):
        Szz[j, j] += Rd[j]
    r = np.empty(UKF_M)
    for j in range(6):
        r[j] = z[j] - zh[j]
    r[6] = wrap(z[6] + x[2] - zh[6])
    return Cxz, Szz, r


@jit
def _ukf_gated_rows(Szz: np.ndarray, r: np.ndarray, use: np.ndarray, gates: np.ndarray,
                    nis: np.ndarray) -> tuple[np.ndarray, int, bool]:
    """The rows of the blocks (accelerometer, gyroscope, heading) in use that pass their χ²
    gate (each block's NIS into ``nis``); returns ``(rows, m, good)``: the rows, their number,
    False if a block's ``S`` was not positive definite."""
    first = (0, 3, 6)
    size = (3, 3, 1)
    rows = np.zeros(UKF_M, dtype=np.int64)
    m = 0
    good = True
    for b in range(3):
        if not use[b]:
            continue
        f0, nb = first[b], size[b]
        Sb = Szz[f0:f0 + nb, f0:f0 + nb].copy()
        rb = r[f0:f0 + nb].copy()
        nb_nis = gain_nis(Sb, rb)
        nis[b] = nb_nis
        if nb_nis < 0.0:
            good = False
            continue
        if nb_nis > gates[b]:
            continue
        for k in range(nb):
            rows[m] = f0 + k
            m += 1
    return rows, m, good


@jit
def euler_ukf_update(x: np.ndarray, P: np.ndarray, use: np.ndarray, z: np.ndarray,
                     Rd: np.ndarray, gates: np.ndarray, nis: np.ndarray) -> bool:
    """Update, eqs. (30)–(39), over the measurement blocks ``use`` = (accelerometer,
    gyroscope, heading): sigma points redrawn from (μ̄, Σ̄) (fix 8); ``Z_i = g(χ̄_i)`` with
    ``g(1:3) = R(χ)ᵀ ẑ`` (eqs. (33)–(35), normalised by g), ``g(4:6) = χ(4:6)`` (the gyro,
    fix 7) and ``g(7) = ψ`` (heading, extension; ``z[6]`` is the residual ψ_m − ψ̄).
    ``z`` (7) holds the readings, ``Rd`` (7) the diagonal of R_t. Each block's NIS
    ``r_bᵀ S_bb⁻¹ r_b`` goes to ``nis``; a block above its gate is left out, the others are
    fused jointly. Returns False if a factorisation failed (``nis`` of the block −1)."""
    X, ok = sigma_points(x, P)
    if not ok:
        return False
    Cxz, Szz, r = _ukf_innovation(X, x, z, Rd)
    rows, m, good = _ukf_gated_rows(Szz, r, use, gates, nis)
    if m == 0:
        return good
    Ss = np.empty((m, m))
    Cs = np.empty((UKF_N, m))
    rs = np.empty(m)
    for a in range(m):
        rs[a] = r[rows[a]]
        for i in range(UKF_N):
            Cs[i, a] = Cxz[i, rows[a]]
        for b in range(m):
            Ss[a, b] = Szz[rows[a], rows[b]]
    if gain_update(x, P, UKF_N, Cs, Ss, rs, np.inf) < 0.0:
        return False
    principal(x, P, UKF_N)
    return good


@jit
def gain_nis(S: np.ndarray, r: np.ndarray) -> float:
    """``rᵀ S⁻¹ r``; −1 if ``S`` is not positive definite."""
    ok, _, _, nis = _solve_nis(S, r)
    return nis if ok else -1.0


@jit_inline
def _solve_nis(S: np.ndarray, r: np.ndarray) -> tuple[bool, np.ndarray, np.ndarray, float]:
    """``(ok, L, S⁻¹ r, rᵀ S⁻¹ r)`` with ``S = L Lᵀ`` (``S⁻¹ r`` as an m×1 column); ``ok`` is
    False if ``S`` is not positive definite (the rest then not computed)."""
    m = r.shape[0]
    L, ok = cholesky(S)
    rr = np.empty((m, 1))
    if not ok:
        return False, L, rr, 0.0
    for k in range(m):
        rr[k, 0] = r[k]
    sr = cho_solve(L, rr)
    s = 0.0
    for k in range(m):
        s += r[k] * sr[k, 0]
    return True, L, sr, s


# ------------------------------------------------------------------------------ Madgwick
@jit
def _grad_add(q: np.ndarray, d: np.ndarray, s: np.ndarray, g: np.ndarray) -> None:
    """``g += J(q)ᵀ f(q)`` for the objective ``f = q* ⊗ d ⊗ q − s = R(q)ᵀ d − s`` (M19–M21),
    with R written as Madgwick does (``1 − 2(…)`` on the diagonal) so that ``d = (0, 0, 1)``
    gives his J_g, f_g (M25–M26) exactly."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    dx, dy, dz = d[0], d[1], d[2]
    f1 = dx * (1.0 - 2.0 * (y * y + z * z)) + 2.0 * dy * (x * y + w * z) \
        + 2.0 * dz * (x * z - w * y) - s[0]
    f2 = 2.0 * dx * (x * y - w * z) + dy * (1.0 - 2.0 * (x * x + z * z)) \
        + 2.0 * dz * (y * z + w * x) - s[1]
    f3 = 2.0 * dx * (x * z + w * y) + 2.0 * dy * (y * z - w * x) \
        + dz * (1.0 - 2.0 * (x * x + y * y)) - s[2]
    # rows of J: ∂f_k/∂(w, x, y, z)
    g[0] += f1 * (2 * dy * z - 2 * dz * y) + f2 * (-2 * dx * z + 2 * dz * x) \
        + f3 * (2 * dx * y - 2 * dy * x)
    g[1] += f1 * (2 * dy * y + 2 * dz * z) + f2 * (2 * dx * y - 4 * dy * x + 2 * dz * w) \
        + f3 * (2 * dx * z - 2 * dy * w - 4 * dz * x)
    g[2] += f1 * (-4 * dx * y + 2 * dy * x - 2 * dz * w) + f2 * (2 * dx * x + 2 * dz * z) \
        + f3 * (2 * dx * w + 2 * dy * z - 4 * dz * y)
    g[3] += f1 * (-4 * dx * z + 2 * dy * w + 2 * dz * x) \
        + f2 * (-2 * dx * w - 4 * dy * z + 2 * dz * y) + f3 * (2 * dx * x + 2 * dy * y)


@jit
def madgwick_gradient(q: np.ndarray, a: np.ndarray, m: np.ndarray, use_m: bool,
                      href: np.ndarray) -> np.ndarray:
    """``∇f = J_gᵀ f_g`` (M25–M26, gravity up: d = (0, 0, 1)) plus, with a magnetometer,
    ``J_bᵀ f_b`` with the Earth field re-estimated from the estimate itself (M45–M46):
    ``h = q ⊗ m ⊗ q*``, ``b = (‖h_xy‖ n̂, h_z)`` — Madgwick's ``(0, b_x, 0, b_z)`` with north
    ``n̂`` along the horizontal reference ``href`` (ENU: y = north by default) instead of x."""
    g = np.zeros(4)
    _grad_add(q, np.array((0.0, 0.0, 1.0)), a, g)
    if use_m:
        w, x, y, z = q[0], q[1], q[2], q[3]
        hx = (1 - 2 * (y * y + z * z)) * m[0] + 2 * (x * y - w * z) * m[1] \
            + 2 * (x * z + w * y) * m[2]
        hy = 2 * (x * y + w * z) * m[0] + (1 - 2 * (x * x + z * z)) * m[1] \
            + 2 * (y * z - w * x) * m[2]
        hz = 2 * (x * z - w * y) * m[0] + 2 * (y * z + w * x) * m[1] \
            + (1 - 2 * (x * x + y * y)) * m[2]
        hh = np.sqrt(hx * hx + hy * hy)
        _grad_add(q, np.array((hh * href[0], hh * href[1], hz)), m, g)
    return g


@jit
def madgwick_step(q: np.ndarray, w: np.ndarray, dt: float, a: np.ndarray, use_a: bool,
                  m: np.ndarray, use_m: bool, href: np.ndarray, beta: float) -> None:
    """One step of the standard Madgwick filter (M42–M44), in place:
    ``q̇ = ½ q ⊗ (0, ω) − β ∇f/‖∇f‖``, ``q ← (q + q̇ Δt)/‖·‖``. ``a``, ``m`` normalised body
    readings; without an accelerometer reading the step is gyro-only (as in Madgwick's code,
    which also needs the accelerometer for the magnetometer)."""
    qd = np.empty(4)
    qd[0] = 0.5 * (-q[1] * w[0] - q[2] * w[1] - q[3] * w[2])
    qd[1] = 0.5 * (q[0] * w[0] + q[2] * w[2] - q[3] * w[1])
    qd[2] = 0.5 * (q[0] * w[1] - q[1] * w[2] + q[3] * w[0])
    qd[3] = 0.5 * (q[0] * w[2] + q[1] * w[1] - q[2] * w[0])
    if use_a:
        g = madgwick_gradient(q, a, m, use_m, href)
        n = np.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2] + g[3] * g[3])
        if n > 0.0:
            for i in range(4):
                qd[i] -= beta * g[i] / n
    s = 0.0
    for i in range(4):
        q[i] += qd[i] * dt
        s += q[i] * q[i]
    s = 1.0 / np.sqrt(s)
    for i in range(4):
        q[i] *= s
