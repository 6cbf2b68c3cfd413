"""Orientation error metrics (the BROAD benchmark's; docs/real_data.md § "The metric") and
the roll/pitch/yaw angles the node's debug topic and the plots show."""

from __future__ import annotations

import numpy as np

from mkf_ros.core.quaternion import qconj_np, qmul_np


def orientation_errors(q_est: np.ndarray, q_ref: np.ndarray) -> dict[str, np.ndarray]:
    """Total, heading and inclination error (rad) of ``q_est`` against ``q_ref`` (both
    [w, x, y, z], sensor → world), from ``e = q_est ⊗ q_ref⁻¹`` in the world frame:
    total ``2 acos|e_w|``, heading ``2 atan|e_z/e_w|``, inclination ``2 acos √(e_w² + e_z²)``.
    """
    e = qmul_np(q_est, qconj_np(q_ref))
    w = np.abs(e[..., 0])
    z = np.abs(e[..., 3])
    total = 2.0 * np.arctan2(np.linalg.norm(e[..., 1:], axis=-1), w)  # = 2 acos|e_w|, exact
    heading = 2.0 * np.arctan2(z, w)
    incl = 2.0 * np.arccos(np.clip(np.sqrt(w * w + z * z), 0.0, 1.0))
    return {"total": total, "heading": heading, "inclination": incl}


def roll_pitch_yaw(q_wxyz: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (rad; fixed axes x-y-z, as tf2's getRPY) of ``[w, x, y, z]``
    quaternions (..., 4): (..., 3). ``R = R_z(yaw) R_y(pitch) R_x(roll)``; pitch in
    [-π/2, π/2]."""
    q = np.asarray(q_wxyz, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def rmse_deg(err_rad: np.ndarray) -> float:
    """Root-mean-square of an error series, in degrees."""
    return float(np.degrees(np.sqrt(np.mean(np.square(err_rad)))))


def step_angles(q: np.ndarray) -> np.ndarray:
    """Rotation angle (rad) between consecutive orientations of ``q`` (N, 4): (N−1,), sign of
    each quaternion ignored."""
    q = np.asarray(q, dtype=float)
    return orientation_errors(q[1:], q[:-1])["total"]


def unexplained_steps(q: np.ndarray, t: np.ndarray, gyr: np.ndarray) -> np.ndarray:
    """The part of each step between consecutive orientations that the gyro does not explain
    (rad), (N−1,), for ``q`` (N, 4), stamps ``t`` (N,) in s and body rates ``gyr`` (N, 3) in
    rad/s:

    ``angle(q[k−1], q[k]) − |ω_k| Δt_k − ½ |ω_k − ω_{k−1}| Δt_{k−1}``.

    A gyro reading is the rate over the interval that ends at its stamp (docs/math.md): the
    interval ``k`` turns by ``|ω_k| Δt_k``. The rate is continuous (the filters model it as a
    Wiener process), so a reading that differs from the previous one says the rate was
    already changing over the previous interval: by the trapezoid, that interval turned by
    ``½ |ω_k − ω_{k−1}| Δt_{k−1}`` more (or less) than its own reading said, and a filter
    that learns of it at reading ``k`` moves it into step ``k`` (through the correlation of
    the attitude with the rate). Measured on the ROS bags: readings 20.9 → 39.8 rad/s 15 ms
    apart, a 41.5° step = 33.2° of the interval's own reading + 7.9° of the previous
    interval's ramp. An interval longer than 1.5 times the median holds readings that are
    missing (a dropped message): its reading is the rate over the last sample period only,
    and over the rest the continuous rate went from the previous reading to this one, so the
    interval turned by at least the trapezoid's ``½ (|ω_{k−1}| + |ω_k|) Δt_k`` where that is
    more than ``|ω_k| Δt_k`` (the AR.Drone bag: 18.5 → 4.4 rad/s across 42 ms, a 27.3° step).
    Negative: the gyro explains the whole step. A gyro row with NaN explains nothing (rate 0;
    no ramp into or out of it)."""
    g = np.asarray(gyr, dtype=float)
    valid = ~np.isnan(g).any(axis=-1)
    rate = np.where(valid, np.linalg.norm(np.nan_to_num(g), axis=-1), 0.0)
    dt = np.diff(np.asarray(t, dtype=float))
    ramp = np.zeros_like(dt)
    both = valid[1:] & valid[:-1]
    ramp[1:] = 0.5 * np.linalg.norm(g[2:] - g[1:-1], axis=-1) * dt[:-1]
    ramp[~both] = 0.0
    own = rate[1:] * dt
    if dt.size:
        gap = both & (dt > 1.5 * np.median(dt))
        own[gap] = np.maximum(own[gap], 0.5 * (rate[:-1] + rate[1:])[gap] * dt[gap])
    return step_angles(q) - own - ramp
