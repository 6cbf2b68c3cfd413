"""Synthetic IMU recordings with ground truth.

A scenario produces the true attitude ``q`` (body → ENU) and body rate ``ω`` on a fine time
grid; :func:`simulate` then samples ideal sensors at the requested rate and adds noise:

* gyro ``ω_m = ω + b + n_g``;
* accelerometer ``a_m = R(q)ᵀ (g·up + a_lin) + n_a`` (specific force, +g up at rest, REP-145);
* magnetometer ``m_m = R(q)ᵀ m_E + n_m`` in tesla.

The attitude is integrated exactly for a piecewise-constant rate (spec §1.3) on ``substeps``
sub-intervals per sample, as in the paper's study (§7.2: rate updated first, then used).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mkf_ros.core._jit import jit
from mkf_ros.core.quaternion import q_omega, qmul, qnormalize, rotmat_np

GRAVITY = 9.80665
#: Earth field used by default: 50 µT with a 60° dip (north and down), ENU, tesla.
MAG_FIELD_ENU = 50e-6 * np.array([0.0, np.cos(np.radians(60)), -np.sin(np.radians(60))])


@dataclass
class SimData:
    """A synthetic recording: sensor arrays and the ground truth, one row per sample."""

    t: np.ndarray  #: (N,) s
    gyr: np.ndarray  #: (N, 3) rad/s
    acc: np.ndarray  #: (N, 3) m/s²
    mag: np.ndarray  #: (N, 3) T (NaN rows where the magnetometer has no sample)
    quat: np.ndarray  #: (N, 4) true orientation, body → ENU, [w, x, y, z]
    omega: np.ndarray  #: (N, 3) true body rate, rad/s
    bias: np.ndarray  #: (N, 3) true gyro bias, rad/s
    meta: dict = field(default_factory=dict)


@jit
def integrate(q0: np.ndarray, omega: np.ndarray, dt: float) -> np.ndarray:
    """Attitudes on a grid: ``q_{k+1} = q_k * q_ω(ω_k, dt)`` (exact for piecewise-constant ω)."""
    n = omega.shape[0]
    out = np.empty((n + 1, 4))
    q = q0.copy()
    out[0] = q
    for k in range(n):
        q = qnormalize(qmul(q, q_omega(omega[k], dt)))
        out[k + 1] = q
    return out


def _wiener(rng: np.random.Generator, n: int, dt: float, q_omega_psd: float) -> np.ndarray:
    """Body rate as a Wiener process with PSD ``Q_ω`` (rad²/s³), starting at rest (§7.2)."""
    steps = rng.normal(0.0, np.sqrt(q_omega_psd * dt), size=(n, 3))
    return np.cumsum(steps, axis=0)


def _static(rng: np.random.Generator, t: np.ndarray, **kw: float) -> np.ndarray:
    return np.zeros((t.size, 3))


def _slow_rotation(rng: np.random.Generator, t: np.ndarray, **kw: float) -> np.ndarray:
    """Smooth rotation about all three axes (≤ ~0.6 rad/s), reaching large tilts."""
    f = np.array([0.05, 0.07, 0.09])
    a = np.array([0.5, 0.4, 0.6])
    ph = rng.uniform(0, 2 * np.pi, 3)
    return a * np.sin(2 * np.pi * f * t[:, None] + ph)


def _wiener_motion(rng: np.random.Generator, t: np.ndarray, q_omega_psd: float = 1.0,
                   **kw: float) -> np.ndarray:
    return _wiener(rng, t.size, t[1] - t[0], q_omega_psd)


SCENARIOS: dict[str, Callable[..., np.ndarray]] = {
    "static": _static,
    "slow_rotation": _slow_rotation,
    "wiener": _wiener_motion,
}


def simulate(
    scenario: str = "slow_rotation",
    *,
    duration: float = 20.0,
    rate: float = 100.0,
    seed: int = 0,
    substeps: int = 100,
    gyro_noise: float = 0.01,
    acc_noise: float = 0.05,
    mag_noise: float = 0.5e-6,
    gyro_bias: object = (0.0, 0.0, 0.0),
    mag_field: np.ndarray = MAG_FIELD_ENU,
    mag_rate: float | None = None,
    q0: np.ndarray | None = None,
    **scenario_args: float,
) -> SimData:
    """Synthesise a recording of ``duration`` s at ``rate`` Hz (see module doc).

    ``q0`` is the initial attitude (default: random, uniform on S³); ``mag_rate`` (Hz) makes the
    magnetometer slower (NaN rows between its samples).
    """
    if scenario not in SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; known: {', '.join(SCENARIOS)}")
    if not (rate > 0 and duration > 0 and substeps >= 1):
        raise ValueError("rate, duration and substeps must be positive")
    rng = np.random.default_rng(seed)
    n = round(duration * rate) + 1
    dt = 1.0 / rate
    fine_dt = dt / substeps
    t_fine = np.arange((n - 1) * substeps) * fine_dt
    if q0 is None:
        q0 = rng.normal(size=4)
    q0 = np.asarray(q0, dtype=float) / np.linalg.norm(q0)
    w_fine = SCENARIOS[scenario](rng, t_fine if t_fine.size > 1 else np.array([0.0, fine_dt]),
                                 **scenario_args)[: t_fine.size]
    q_fine = integrate(q0, np.ascontiguousarray(w_fine), fine_dt)
    quat = q_fine[::substeps]
    # the rate that was active at (just before) each sample; at t=0 the first one
    omega = np.vstack([w_fine[:1], w_fine[substeps - 1::substeps]]) if w_fine.size else \
        np.zeros((n, 3))
    R = rotmat_np(quat)
    bias = np.broadcast_to(np.asarray(gyro_bias, dtype=float), (n, 3)).copy()
    gyr = omega + bias + rng.normal(0, gyro_noise, (n, 3))
    up = np.array([0.0, 0.0, GRAVITY])
    acc = np.einsum("nji,j->ni", R, up) + rng.normal(0, acc_noise, (n, 3))
    mag = np.einsum("nji,j->ni", R, mag_field) + rng.normal(0, mag_noise, (n, 3))
    t = np.arange(n) * dt
    if mag_rate is not None:
        keep = np.zeros(n, dtype=bool)
        keep[np.unique(np.round(np.arange(0, duration, 1.0 / mag_rate) * rate).astype(int))] = True
        mag[~keep[: n]] = np.nan
    return SimData(t=t, gyr=gyr, acc=acc, mag=mag, quat=quat, omega=omega, bias=bias,
                   meta=dict(scenario=scenario, rate=rate, seed=seed, mag_field=mag_field))
