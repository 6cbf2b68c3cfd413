"""World frames (REP-103 / REP-145) and closed-form alignment.

The filters work internally in ENU (x east, y north, z up; an accelerometer at rest reads +g
along the world's up axis, docs/math.md §8 item 15). The published orientation is
``q_W = q_{W←ENU} * q_ENU``, so ``R(q_W) = R_{W←ENU} R(q_ENU)`` (docs/math.md §1.2).
"""

from __future__ import annotations

import numpy as np

from mkf_ros.core._jit import jit
from mkf_ros.core.linalg import cross3
from mkf_ros.core.quaternion import qconj, qmul, qnormalize, rotate

_S = np.sqrt(0.5)
#: ``q_{W←ENU}`` for each world frame: NED swaps x/y and flips z (180° about (1,1,0)/√2);
#: NWU is ENU rotated by −90° about z (x north, y west).
FROM_ENU = {
    "enu": np.array([1.0, 0.0, 0.0, 0.0]),
    "ned": np.array([0.0, _S, _S, 0.0]),
    "nwu": np.array([_S, 0.0, 0.0, -_S]),
}


@jit
def quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (q0 ≥ 0) of a rotation matrix (Shepperd's method)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    q = np.empty(4)
    if tr > 0.0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q[0] = 0.25 * s
        q[1] = (r[2, 1] - r[1, 2]) / s
        q[2] = (r[0, 2] - r[2, 0]) / s
        q[3] = (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q[0] = (r[2, 1] - r[1, 2]) / s
        q[1] = 0.25 * s
        q[2] = (r[0, 1] + r[1, 0]) / s
        q[3] = (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q[0] = (r[0, 2] - r[2, 0]) / s
        q[1] = (r[0, 1] + r[1, 0]) / s
        q[2] = 0.25 * s
        q[3] = (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q[0] = (r[1, 0] - r[0, 1]) / s
        q[1] = (r[0, 2] + r[2, 0]) / s
        q[2] = (r[1, 2] + r[2, 1]) / s
        q[3] = 0.25 * s
    q = qnormalize(q)
    if q[0] < 0.0:
        q = -q
    return q


@jit
def align_tilt(acc: np.ndarray) -> np.ndarray:
    """Shortest rotation taking the body ``acc`` direction to world up (heading left at zero)."""
    a = acc / np.sqrt(acc[0] ** 2 + acc[1] ** 2 + acc[2] ** 2)
    # q with R(q) a = (0,0,1): axis a × z, half-angle form (a·z = a[2])
    q = np.array((1.0 + a[2], a[1], -a[0], 0.0))
    n = np.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2)
    if n < 1e-9:  # upside down: rotate 180° about body x
        return np.array((0.0, 1.0, 0.0, 0.0))
    return q / n


@jit
def align_triad(acc: np.ndarray, mag: np.ndarray) -> tuple[np.ndarray, bool]:
    """ENU attitude from an accelerometer (up) and magnetometer (north + down) reading (TRIAD).

    ``east = m × a``, ``north = up × east``; ``R = [east; north; up]`` as rows. Returns
    ``ok = False`` when the two vectors are (nearly) parallel (free fall, magnetic pole).
    """
    up = acc / np.sqrt(acc[0] ** 2 + acc[1] ** 2 + acc[2] ** 2)
    east = cross3(mag, up)
    ne = np.sqrt(east[0] ** 2 + east[1] ** 2 + east[2] ** 2)
    if ne < 1e-6 * np.sqrt(mag[0] ** 2 + mag[1] ** 2 + mag[2] ** 2):
        return align_tilt(acc), False
    east = east / ne
    north = cross3(up, east)
    r = np.empty((3, 3))
    r[0] = east
    r[1] = north
    r[2] = up
    return quat_from_matrix(r), True


@jit
def yaw_twist(q: np.ndarray) -> np.ndarray:
    """Twist of ``q`` about the world z axis (swing–twist decomposition), as a unit quaternion."""
    n = np.sqrt(q[0] * q[0] + q[3] * q[3])
    if n < 1e-9:
        return np.array((1.0, 0.0, 0.0, 0.0))
    return np.array((q[0] / n, 0.0, 0.0, q[3] / n))


def swing_rotvec(e: np.ndarray) -> np.ndarray:
    """Horizontal rotation vector (..., 2) [rad] of the swing of error quaternions ``e``
    (..., 4) [w, x, y, z] in the swing–twist decomposition about the world z axis,
    ``e = swing ⊗ twist_z``.

    With ``n = √(e_w² + e_z²)`` the twist is ``[e_w, 0, 0, e_z] / n`` and the swing
    ``e ⊗ twist⁻¹ = [n, (e_w e_x − e_y e_z)/n, (e_w e_y + e_x e_z)/n, 0]``: a rotation about a
    horizontal axis by ``2·atan2(√(e_x² + e_y²), n) = 2·acos n``, BROAD's inclination error.
    The result does not depend on the sign of ``e``. At ``n = 0`` (a half turn about a
    horizontal axis, where the decomposition is not unique) the axis ``(e_x, e_y)`` is used."""
    e = np.asarray(e, dtype=float)
    w, x, y, z = e[..., 0], e[..., 1], e[..., 2], e[..., 3]
    n = np.hypot(w, z)
    r = np.hypot(x, y)
    ang = 2.0 * np.arctan2(r, n)
    sx = w * x - y * z  # n · (swing vector part)
    sy = w * y + x * z
    rn = r * n
    with np.errstate(divide="ignore", invalid="ignore"):
        # |(sx, sy)| = r·n; as r → 0 the scale ang/(r·n) tends to 2/n²
        scale = np.where(rn > 0, ang / np.where(rn > 0, rn, 1.0),
                         2.0 / np.where(n > 0, n * n, 1.0))
        half_turn = np.pi / np.where(r > 0, r, 1.0)
    out = np.stack([sx * scale, sy * scale], axis=-1)
    deg = n == 0
    if np.any(deg):
        alt = np.stack([x * half_turn, y * half_turn], axis=-1)
        out = np.where(deg[..., None], alt, out)
    return out


@jit
def heading_correction(q: np.ndarray, mag_body: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Rotation about world z that turns the horizontal part of ``R(q) mag_body`` onto the
    horizontal part of the world reference ``ref`` (used to fix heading once a magnetometer
    sample is available)."""
    m = rotate(q, mag_body)
    a = np.arctan2(m[0] * ref[1] - m[1] * ref[0], m[0] * ref[0] + m[1] * ref[1])
    return np.array((np.cos(0.5 * a), 0.0, 0.0, np.sin(0.5 * a)))


@jit
def keep_yaw(q_new: np.ndarray, q_old: np.ndarray) -> np.ndarray:
    """``q_new`` turned about world z so that its heading matches ``q_old``'s."""
    return qnormalize(qmul(yaw_twist(qmul(q_old, qconj(q_new))), q_new))
