"""Quaternion algebra (`docs/math.md` §1).

Quaternions are NumPy arrays ``(q0, q1, q2, q3)``, **scalar first**, Hamilton product. A unit
quaternion ``q`` maps body (sensor) coordinates to external (world) coordinates:
``v_E = R(q) v_B`` (§1.2). All functions are numba kernels and also run as plain Python.
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit
from mkf_ros.core.linalg import mtv, mv


# Tuple kernels (suffix ``_t``) are the single implementation of each operation: numba passes
# tuples by value, so the filters' inner loops run them without heap allocations. The array
# functions below wrap them for readable code elsewhere.
@jit
def qmul_t(p: tuple, q: tuple) -> tuple:
    """Hamilton product ``p * q`` (§1.1)."""
    return (
        p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3],
        p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2],
        p[0] * q[2] + p[2] * q[0] + p[3] * q[1] - p[1] * q[3],
        p[0] * q[3] + p[3] * q[0] + p[1] * q[2] - p[2] * q[1],
    )


@jit
def qconj_mul_t(p: tuple, q: tuple) -> tuple:
    """``p* * q``: the deviation of q from p (§2.3)."""
    return qmul_t((p[0], -p[1], -p[2], -p[3]), q)


@jit
def qnormalize_t(q: tuple) -> tuple:
    """``q / ‖q‖`` (§8 item 16)."""
    n = 1.0 / np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return (q[0] * n, q[1] * n, q[2] * n, q[3] * n)


@jit
def rotate_inv_t(q: tuple, v: tuple) -> tuple:
    """``R(q)ᵀ v`` for a unit quaternion: world vector to body coordinates (§1.2)."""
    # R(q)ᵀ v = v + 2 u × (u × v − q0 v)... written out: t = 2 (u × v), r = v − q0 t + u × t
    ux, uy, uz = -q[1], -q[2], -q[3]  # conjugate rotates the other way
    tx = 2.0 * (uy * v[2] - uz * v[1])
    ty = 2.0 * (uz * v[0] - ux * v[2])
    tz = 2.0 * (ux * v[1] - uy * v[0])
    return (
        v[0] + q[0] * tx + (uy * tz - uz * ty),
        v[1] + q[0] * ty + (uz * tx - ux * tz),
        v[2] + q[0] * tz + (ux * ty - uy * tx),
    )


# Below this θ² (θ = 0.1) the half angle's cos θ and sin θ/θ are evaluated as their Taylor series
# through θ⁸: the first omitted terms, θ¹⁰/10! ≤ 2.8e-17 and θ¹⁰/11! ≤ 2.6e-18, are below half
# an ulp of the results (≥ 0.99), so the series agree with libm's sin and cos to rounding; they
# need no square root, division or libm call.
_SERIES_TH2 = 0.01


@jit
def cos_sinc_t(th2: float) -> tuple[float, float]:
    """``(cos θ, sin θ / θ)`` from ``θ²`` for ``θ² < 0.01`` (Taylor series, see above)."""
    c = 1.0 + th2 * (-1.0 / 2.0 + th2 * (1.0 / 24.0 + th2 * (-1.0 / 720.0 + th2 * (1.0 / 40320.0))))
    s = 1.0 + th2 * (-1.0 / 6.0 + th2 * (1.0 / 120.0 + th2 * (-1.0 / 5040.0
                                                              + th2 * (1.0 / 362880.0))))
    return c, s


@jit
def q_omega_t(w: tuple, dt: float) -> tuple:
    """Increment for a constant body rate ``w`` over ``dt`` (§1.3, paper eq. A20).

    ``(cos(‖w‖dt/2), w · sin(‖w‖dt/2)/‖w‖)``, the bracket evaluated as a sinc so that it stays
    finite for ``w → 0``; for a small half angle (almost every step) by series (:func:`cos_sinc_t`).
    """
    n2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    half2 = 0.25 * n2 * dt * dt
    if half2 < _SERIES_TH2:
        c, sinc = cos_sinc_t(half2)
        s = 0.5 * dt * sinc  # sin(x)/‖w‖ = (dt/2) sin(x)/x
        return (c, w[0] * s, w[1] * s, w[2] * s)
    n = np.sqrt(n2)
    half = 0.5 * n * dt
    s = np.sin(half) / n
    return (np.cos(half), w[0] * s, w[1] * s, w[2] * s)


@jit
def t4(q: np.ndarray) -> tuple:
    """Array → 4-tuple."""
    return (q[0], q[1], q[2], q[3])


@jit
def t3(v: np.ndarray) -> tuple:
    """Array → 3-tuple."""
    return (v[0], v[1], v[2])


@jit
def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p * q`` (§1.1)."""
    return np.array(qmul_t(t4(p), t4(q)))


@jit
def qconj(q: np.ndarray) -> np.ndarray:
    """Conjugate ``q* = (q0, -q_v)``; the inverse of a unit quaternion (§1.1)."""
    return np.array((q[0], -q[1], -q[2], -q[3]))


@jit
def qconj_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``p* * q`` without forming ``p*``: the deviation of q from p (§2.3)."""
    return np.array(qconj_mul_t(t4(p), t4(q)))


@jit
def qnormalize(q: np.ndarray) -> np.ndarray:
    """Return ``q / ‖q‖`` (§8 item 16: renormalise after every product)."""
    return np.array(qnormalize_t(t4(q)))


@jit
def rotmat_t(q: tuple) -> tuple:
    """Rotation matrix ``R(q)`` with ``v_E = R(q) v_B`` (§1.2), as a tuple of its rows:
    ``R[i][j]``."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    return ((1.0 - 2.0 * (q2 * q2 + q3 * q3), 2.0 * (q1 * q2 - q0 * q3),
             2.0 * (q1 * q3 + q0 * q2)),
            (2.0 * (q1 * q2 + q0 * q3), 1.0 - 2.0 * (q1 * q1 + q3 * q3),
             2.0 * (q2 * q3 - q0 * q1)),
            (2.0 * (q1 * q3 - q0 * q2), 2.0 * (q2 * q3 + q0 * q1),
             1.0 - 2.0 * (q1 * q1 + q2 * q2)))


@jit
def up_in_body_t(q: tuple) -> tuple:
    """The world vertical (world z) in the body's axes, ``R(q)ᵀ e_z``: the third row of
    :func:`rotmat_t` (the same expressions)."""
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    return (2.0 * (q1 * q3 - q0 * q2), 2.0 * (q2 * q3 + q0 * q1),
            1.0 - 2.0 * (q1 * q1 + q2 * q2))


@jit
def t33(a: np.ndarray) -> tuple:
    """3×3 array → tuple of its rows."""
    return ((a[0, 0], a[0, 1], a[0, 2]), (a[1, 0], a[1, 1], a[1, 2]),
            (a[2, 0], a[2, 1], a[2, 2]))


@jit
def a33(t: tuple) -> np.ndarray:
    """Tuple of three rows → 3×3 array."""
    r = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            r[i, j] = t[i][j]
    return r


@jit
def rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``R(q)`` with ``v_E = R(q) v_B`` (§1.2)."""
    return a33(rotmat_t(t4(q)))


@jit
def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R(q) v``: body vector to world coordinates (§1.2)."""
    return mv(rotmat(q), v)


@jit
def rotate_inv(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``R(q)ᵀ v``: world vector to body coordinates (§1.2)."""
    return mtv(rotmat(q), v)


@jit
def q_omega(w: np.ndarray, dt: float) -> np.ndarray:
    """Array form of :func:`q_omega_t` (§1.3, eq. A20)."""
    return np.array(q_omega_t(t3(w), dt))


@jit
def q_from_rotvec(r: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation vector ``r`` (angle × axis, rad)."""
    return q_omega(r, 1.0)


@jit
def skew(a: np.ndarray) -> np.ndarray:
    """``[a]×`` with ``[a]× b = a × b`` (§1.1)."""
    s = np.zeros((3, 3))
    s[0, 1] = -a[2]
    s[0, 2] = a[1]
    s[1, 0] = a[2]
    s[1, 2] = -a[0]
    s[2, 0] = -a[1]
    s[2, 1] = a[0]
    return s


@jit
def angle_between(p: np.ndarray, q: np.ndarray) -> float:
    """Rotation angle of ``p* * q`` in rad, in [0, π] (§7.3, eq. 72: ``2 arccos|p·q|``), computed
    as ``2 atan2(‖δ_v‖, |δ0|)``, which is the same value but exact for small angles too."""
    d = qconj_mul_t(t4(p), t4(q))
    return 2.0 * np.arctan2(np.sqrt(d[1] * d[1] + d[2] * d[2] + d[3] * d[3]), abs(d[0]))


def rotmat_np(q: np.ndarray) -> np.ndarray:
    """Vectorised ``R(q)`` for an array of quaternions of shape (..., 4)."""
    q = np.asarray(q, dtype=float)
    q0, q1, q2, q3 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (q2**2 + q3**2), 2 * (q1 * q2 - q0 * q3), 2 * (q1 * q3 + q0 * q2)],
        [2 * (q1 * q2 + q0 * q3), 1 - 2 * (q1**2 + q3**2), 2 * (q2 * q3 - q0 * q1)],
        [2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1), 1 - 2 * (q1**2 + q2**2)],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def qmul_np(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Vectorised Hamilton product over leading axes (broadcasting)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    p0, p1, p2, p3 = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    q0, q1, q2, q3 = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3,
            p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2,
            p0 * q2 + p2 * q0 + p3 * q1 - p1 * q3,
            p0 * q3 + p3 * q0 + p1 * q2 - p2 * q1,
        ],
        -1,
    )


def q_exp_np(rotvec: np.ndarray) -> np.ndarray:
    """Quaternions of rotation vectors (..., 3) → (..., 4): ``[cos(θ/2), sin(θ/2) u]``."""
    rotvec = np.asarray(rotvec, dtype=float)
    th = np.atleast_1d(np.sqrt(np.einsum("...i,...i->...", rotvec, rotvec)))
    out = np.empty((*th.shape, 4))
    out[..., 0] = np.cos(0.5 * th)
    # sin(θ/2)/θ, with its series near 0
    small = th < 1e-6
    k = np.sin(0.5 * th) / np.where(small, 1.0, th)
    k[small] = 0.5 - th[small] ** 2 / 48.0
    out[..., 1:] = k[..., None] * rotvec
    return out.reshape((*rotvec.shape[:-1], 4))


def qconj_np(q: np.ndarray) -> np.ndarray:
    """Vectorised conjugate."""
    q = np.array(q, dtype=float)
    q[..., 1:] *= -1.0
    return q
